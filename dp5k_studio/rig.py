"""The virtual rig: two Canon EOS 5D Mark IV bodies with EF 85 mm f/1.8 lenses and an EPSON EB-U42 projector.

Geometry follows OpenCV: ``X_cam = R @ X_world + t`` (metres), camera x right, y down, z forward.
World frame: origin midway between the two cameras' centres, x to the right, y down, z forward
(so the floor of a room lies at ``y = +camera height``).

Sizes are RAW sensor pixels at the chosen downscale of the 6720 x 4480 full sensor (36 x 24 mm).
The studio's lenses are distortion free (``dist`` is zeros) and the pinhole focal length is the
thin-lens image distance for the rig's reference focus distance (2.7 m, the paper's median depth);
focus breathing is not modelled (K does not change with focus).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError

SENSOR_SIZE_MM: tuple[float, float] = (36.0, 24.0)
"""Canon EOS 5D Mark IV sensor (width, height) in mm."""
FULL_SENSOR_PX: tuple[int, int] = (6720, 4480)
"""Full-resolution sensor (width, height) in pixels."""
FOCAL_LENGTH_MM = 85.0
"""EF 85 mm f/1.8 USM, thin-lens focal length in mm."""
REFERENCE_FOCUS_M = 2.7
"""Focus distance (m) at which the pinhole intrinsics are defined (image distance v = 1/(1/f - 1/F))."""
PROJECTOR_SIZE_PX: tuple[int, int] = (1920, 1200)
"""EPSON EB-U42 native resolution (width, height)."""
PROJECTOR_THROW_RATIO = 1.5
"""EB-U42 throw ratio (distance / image width), middle of its 1.38..1.68 zoom range."""

SCALES: dict[str, float] = {"small": 20.0, "medium": 5.0, "paper": 2.0}
"""Named downscale factors of the 6720 x 4480 sensor: small 336x224, medium 1344x896, paper 3360x2240 raw
(the paper's processed output, 1680x1120, is half of that)."""


def _rot_y(angle_rad: float) -> NDArray[np.float64]:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(angle_rad: float) -> NDArray[np.float64]:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@dataclass(frozen=True)
class CameraModel:
    """One simulated camera body + lens.

    Attributes:
        name: ``"cam0"`` (left body) or ``"cam1"`` (right body).
        serial: a fake body serial number.
        width, height: RAW sensor size in pixels at this scale.
        K: (3, 3) intrinsics in px (pinhole focal length = image distance at REFERENCE_FOCUS_M).
        dist: (5,) OpenCV distortion (zeros: the studio's lens is distortion free).
        R: (3, 3) world-to-camera rotation.
        t: (3,) world-to-camera translation in metres.
        pixel_pitch_mm: sensor pixel pitch in mm (36 / width).
        focal_length_mm: thin-lens focal length in mm (85).
        sensor_size_mm: (36, 24).
    """

    name: str
    serial: str
    width: int
    height: int
    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    pixel_pitch_mm: float
    focal_length_mm: float = FOCAL_LENGTH_MM
    sensor_size_mm: tuple[float, float] = SENSOR_SIZE_MM
    model: str = "Canon EOS 5D Mark IV"
    lens: str = "Canon EF 85mm f/1.8 USM"

    @property
    def center_m(self) -> NDArray[np.float64]:
        """(3,) camera centre in world coordinates, metres (``-R^T t``)."""
        return -self.R.T @ self.t

    def scaled(self, width: int, height: int) -> CameraModel:
        """The same body rendered at another pixel size (K scaled, pitch = 36 / width)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        # pixel centres at integer coordinates: scale about the pixel-edge origin
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(self.name, self.serial, width, height, K, self.dist.copy(), self.R, self.t,
                           SENSOR_SIZE_MM[0] / width, self.focal_length_mm, self.sensor_size_mm, self.model, self.lens)


@dataclass(frozen=True)
class ProjectorModel:
    """The simulated EPSON EB-U42 (a pinhole 'inverse camera').

    Attributes:
        width, height: projector image size in px (1920 x 1200 unless scaled).
        K: (3, 3) intrinsics in px.
        R, t: world-to-projector rotation and translation (metres).
        lumens_rel: projector irradiance at 2 m on a surface facing it, relative to the studio's ambient (1.0).
    """

    width: int
    height: int
    K: NDArray[np.float64]
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    lumens_rel: float = 1.6
    model: str = "EPSON EB-U42"

    @property
    def center_m(self) -> NDArray[np.float64]:
        return -self.R.T @ self.t


@dataclass(frozen=True)
class Rig:
    """Two cameras and a projector, all ground truth.

    Attributes:
        cameras: (cam0, cam1).
        projector: the projector.
        scale: the downscale factor of the 6720 x 4480 sensor.
        baseline_m: distance between the camera centres.
    """

    cameras: tuple[CameraModel, CameraModel]
    projector: ProjectorModel
    scale: float
    baseline_m: float
    extra: dict = field(default_factory=dict)

    def stereo_RT(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Stereo extrinsics cam0 -> cam1 (``X1 = R X0 + T``, T in metres)."""
        c0, c1 = self.cameras
        R = c1.R @ c0.R.T
        T = c1.t - R @ c0.t
        return R, T


def _resolve_scale(scale: float | str) -> float:
    if isinstance(scale, str):
        if scale not in SCALES:
            raise BadInputError(f"unknown rig scale {scale!r} (use {', '.join(SCALES)} or a number >= 1)")
        return SCALES[scale]
    s = float(scale)
    if not (np.isfinite(s) and s >= 1.0):
        raise BadInputError(f"rig scale must be a downscale factor >= 1, got {scale}")
    return s


def make_rig(
    scale: float | str = "small",
    baseline_m: float = 0.30,
    seed: int = 0,
    convergence_m: float = 3.0,
    projector_size: tuple[int, int] | None = None,
) -> Rig:
    """Build the studio rig.

    Args:
        scale: ``"small"`` (raw 336x224), ``"medium"`` (1344x896), ``"paper"`` (3360x2240) or a downscale
            factor of the 6720 x 4480 sensor (raw size = round(6720 / factor), rounded to even numbers).
        baseline_m: distance between the two camera centres in metres.
        seed: perturbs the mounting (toe-in +-0.3 deg, roll +-0.2 deg, principal point +-0.5 % of size) so
            calibration has something real to find; seed 0 is deterministic like every other seed.
        convergence_m: the two bodies are toed in to converge at this distance (metres).
        projector_size: (width, height) of the projector image; default 1920 x 1200.

    Returns:
        The :class:`Rig`.
    """
    s = _resolve_scale(scale)
    W = max(2, int(round(FULL_SENSOR_PX[0] / s / 2.0)) * 2)
    H = max(2, int(round(FULL_SENSOR_PX[1] / s / 2.0)) * 2)
    if not baseline_m > 0:
        raise BadInputError(f"baseline must be > 0 m, got {baseline_m}")
    rng = np.random.default_rng(seed)
    pitch_mm = SENSOR_SIZE_MM[0] / W
    v_mm = 1.0 / (1.0 / FOCAL_LENGTH_MM - 1.0 / (REFERENCE_FOCUS_M * 1000.0))
    f_px = v_mm / pitch_mm
    cams = []
    toe = np.arctan2(baseline_m / 2.0, convergence_m)
    serials = ("012021000417", "012021000533")
    for i, side in enumerate((-1.0, 1.0)):
        jitter = rng.normal(0.0, 1.0, 4) if seed else np.zeros(4)
        # camera looks toward the rig centre line: cam0 (left, x<0) turns right (+yaw about y)
        yaw = -side * toe + np.deg2rad(0.3) * jitter[0]
        roll = np.deg2rad(0.2) * jitter[1]
        R_cw = _rot_y(yaw) @ _rot_x(0.0)
        c, sn = np.cos(roll), np.sin(roll)
        R_roll = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        R_wc = R_cw @ R_roll  # camera axes in world coordinates (columns)
        R = R_wc.T
        center = np.array([side * baseline_m / 2.0, 0.0, 0.0])
        t = -R @ center
        cx = (W - 1) / 2.0 + 0.005 * W * jitter[2]
        cy = (H - 1) / 2.0 + 0.005 * H * jitter[3]
        K = np.array([[f_px, 0.0, cx], [0.0, f_px, cy], [0.0, 0.0, 1.0]])
        cams.append(CameraModel(f"cam{i}", serials[i], W, H, K, np.zeros(5), R, t, pitch_mm))
    Wp, Hp = projector_size or PROJECTOR_SIZE_PX
    fp = PROJECTOR_THROW_RATIO * Wp
    Kp = np.array([[fp, 0.0, (Wp - 1) / 2.0], [0.0, fp, (Hp - 1) / 2.0 + 0.05 * Hp], [0.0, 0.0, 1.0]])
    # projector above the cameras (y up is negative), tilted slightly down toward the scene
    Rp_wc = _rot_x(-np.deg2rad(2.0))
    Rp = Rp_wc.T
    center_p = np.array([0.0, -0.12, 0.02])
    tp = -Rp @ center_p
    projector = ProjectorModel(Wp, Hp, Kp, Rp, tp)
    return Rig((cams[0], cams[1]), projector, s, float(baseline_m))
