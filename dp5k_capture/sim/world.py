"""The simulated rig: two simulated EOS bodies on a simulated USB bus, a simulated EB-U42 on a pty, a
headless pattern window feeding the projector's HDMI input, and the world they photograph.

The world is a :class:`~dp5k_capture.sim.eos_body.BodyOptics`: :class:`StudioOptics` renders through the
virtual studio (``dp5k_studio``); :class:`FlatOptics` is a tiny textured plane used by the
protocol and fault tests (fast, no studio). Both write each exposure as a two-frame Dual Pixel DNG with
``dp5k_common.rawfile.write_dual_pixel_dng`` (or one frame when the body's DPRAW setting is off).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile
from numpy.typing import NDArray

from dp5k_common.io import new_file_mode
from dp5k_common.rawfile import write_dual_pixel_dng

from ..display import PatternWindow
from ..rig import RigConfig
from .eos_body import BodyFaults, ExposureSettings, SimulatedEOS
from .fault_spec import parse_sim_faults
from .projector import SimulatedEBU42
from .usb_backend import SimUsbBackend
from .usb_device import SimUsbPtpDevice

SIM_SERIALS = ("SIM5D4000001", "SIM5D4000002")
GROUND_TRUTH_TMP_PREFIX = "ground_truth.partial."


def dng_bytes(main: NDArray[np.uint16], aux: NDArray[np.uint16] | None, black: int, white: int,
              wb: tuple[float, float, float], metadata: dict[str, Any]) -> bytes:
    """Encode one exposure as DNG bytes: two frames (Dual Pixel) or, if ``aux`` is None, one frame."""
    with tempfile.TemporaryDirectory(prefix="dp5k-sim-") as tmp:
        path = Path(tmp) / "shot.dng"
        if aux is None:
            _write_single_frame_dng(path, main, black, white, metadata)
        else:
            write_dual_pixel_dng(path, main, aux, black, white, wb, metadata)
        return path.read_bytes()


def _write_single_frame_dng(path: Path, main: NDArray[np.uint16], black: int, white: int, metadata: dict[str, Any]) -> None:
    """A plain one-frame Bayer DNG: what a body with Dual Pixel RAW switched off would deliver."""
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True), (271, "s", 0, "Canon", True), (272, "s", 0, "Canon EOS 5D Mark IV", True),
        (50708, "s", 0, "Canon EOS 5D Mark IV", True), (33421, "H", 2, (2, 2), False), (33422, "B", 4, (0, 1, 1, 2), False),
        (50714, "I", 1, int(black), False), (50717, "I", 1, int(white), False),
    ]
    tifffile.imwrite(path, main, photometric=32803, subfiletype=0, metadata=None,
                     description=json.dumps(metadata), extratags=tags)


class FlatOptics:
    """A tiny world: a textured plane 1.397-1.403 m away (tilted along x), lit by ambient light and the projector,
    seen through an 85 mm lens by a W x H crop of a 5D Mark IV sensor (5.36 um pixels), so a focus change of a
    fraction of a percent shows as it would on the real body.

    Defocus follows Eq. 6 (docs/conventions.md): the signed blur-circle diameter C = f^2 (d - F) / (N d (F - f))
    (mm on the sensor, C > 0 behind the focal plane) per column; each DP view is the scene blurred by a Gaussian
    of sigma = |C| / 4 px (a disc's) and displaced by half the DP disparity 4 C / (3 pi), the right view to +x
    behind focus. The frames are main = left + right and aux = left. The ChArUco stand-in is a checkerboard
    patch that lands a few px elsewhere at every placement (a hand-held board is never put back exactly),
    seeded by ``seed``, ``run`` and the placement count.

    Args:
        raw_size_px: (W, H) of the raw frames (even).
        lit_image: returns what the projector throws on the scene (uint8 grey at any size) or None.
        seed: texture and board-placement seed.
        run: how many runs of the scene came before this world was made (in-process ``--sim``).
    """

    FOCAL_LENGTH_MM = 85.0
    PIXEL_PITCH_MM = 0.00536
    BLUR_LEVELS = 6  # Gaussian blurs blended per column (sigma varies along the tilted plane)

    def __init__(self, raw_size_px: tuple[int, int] = (96, 64), lit_image: Callable[[], NDArray[np.uint8] | None] | None = None,
                 seed: int = 0, run: int = 0) -> None:
        self.w, self.h = raw_size_px
        self.lit_image = lit_image or (lambda: None)
        rng = np.random.default_rng(seed)
        self.albedo = cv2.resize(rng.uniform(0.2, 0.9, (self.h // 4, self.w // 4)), (self.w, self.h), interpolation=cv2.INTER_LINEAR)
        yy, xx = np.mgrid[0 : self.h, 0 : self.w]
        self.depth_m = 1.397 + 0.006 * xx / max(self.w - 1, 1)  # (H, W) slightly tilted plane, metres
        self.seed, self.run = seed, run
        self.board: int | None = None
        self.board_offset_px = (0, 0)
        self.placements = 0
        self.exposures: list[ExposureSettings] = []

    def place(self, view: int) -> None:
        rng = np.random.default_rng([self.seed, self.run, view, self.placements])
        self.placements += 1
        self.board = view
        self.board_offset_px = (int(rng.integers(-3, 4)), int(rng.integers(-2, 3)))

    def clear(self) -> None:
        self.board = None

    def autofocus_m(self, serial: str, point_px: tuple[float, float]) -> float:
        x = int(np.clip(point_px[0], 0, self.w - 1))
        y = int(np.clip(point_px[1], 0, self.h - 1))
        return float(self.depth_m[y, x])

    def coc_px(self, f_number: float, focus_m: float) -> NDArray[np.float64]:
        """Signed CoC diameter (raw px) of each column of the plane (W,), Eq. 6."""
        f, F, d = self.FOCAL_LENGTH_MM, focus_m * 1000.0, self.depth_m[0] * 1000.0
        return f * f * (d - F) / (f_number * d * (F - f)) / self.PIXEL_PITCH_MM

    def _views(self, scene: NDArray[np.float64], coc_px: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Left and right views (H, W), each carrying half the light, of ``scene`` at per-column CoC ``coc_px``."""
        sigma = np.abs(coc_px) / 4.0
        levels = np.linspace(0.0, max(float(sigma.max()), 1e-6), self.BLUR_LEVELS)
        stack = np.stack([scene if s == 0 else cv2.GaussianBlur(scene, (0, 0), s, borderType=cv2.BORDER_REFLECT) for s in levels])
        t = np.clip(sigma / levels[1], 0, self.BLUR_LEVELS - 1 - 1e-9)
        i0 = np.floor(t).astype(int)
        w = t - i0
        cols = np.arange(self.w)
        blurred = stack[i0, :, cols].T * (1 - w) + stack[i0 + 1, :, cols].T * w  # (H, W)
        half_disp = (2.0 / (3.0 * np.pi)) * coc_px  # half of 4 C / (3 pi), px
        xx, yy = np.meshgrid(np.arange(self.w, dtype=np.float32), np.arange(self.h, dtype=np.float32))
        src = blurred.astype(np.float32)

        def moved(dx: NDArray[np.float64]) -> NDArray[np.float64]:  # content displaced by dx (px) along x
            return cv2.remap(src, xx - dx[None, :].astype(np.float32), yy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.float64)

        return 0.5 * moved(-half_disp), 0.5 * moved(half_disp)

    def expose(self, s: ExposureSettings) -> bytes:
        self.exposures.append(s)
        light = np.full((self.h, self.w), 0.3)
        lit = self.lit_image()
        if lit is not None:
            light = light + cv2.resize(lit.astype(np.float64) / 255.0, (self.w, self.h), interpolation=cv2.INTER_NEAREST)
        scene = self.albedo * light
        if self.board is not None:  # a checkerboard patch standing in for the ChArUco board
            ox, oy = self.board_offset_px
            y0, x0, bh, bw = max(self.h // 4 + oy, 0), max(self.w // 4 + 4 * self.board + ox, 0), self.h // 2, self.w // 3
            yy, xx = np.indices((bh, bw))
            patch = ((yy // 4 + xx // 4) % 2).astype(np.float64)
            region = scene[y0 : y0 + bh, x0 : x0 + bw]
            region[...] = patch[: region.shape[0], : region.shape[1]]
        gain = s.shutter_s * s.iso / 100.0 / s.f_number**2 * 2000.0
        black, white = 512, 16383
        focus = s.focus_distance_m or float(self.depth_m.mean())
        left, right = self._views(scene * gain * (white - black), self.coc_px(s.f_number, focus))
        main = np.clip(black + left + right, 0, white).astype(np.uint16)
        aux = np.clip(black + left, 0, white).astype(np.uint16)
        meta = {"serial": s.serial, "f_number": s.f_number, "shutter_s": s.shutter_s, "iso": s.iso,
                "focus_distance_m": s.focus_distance_m, "sequence": s.sequence,
                **({"board": {"view": self.board, "placement": self.placements}} if self.board is not None else {})}
        return dng_bytes(main, aux if s.dual_pixel_raw else None, black, white, (2.0, 1.0, 1.5), meta)

    def write_ground_truth(self, folder: Path) -> list[Path]:
        """``ground_truth/`` of the flat world: ``camN_depth_mm.png`` (16-bit, mm; both bodies see the same
        plane) and ``truth.json`` (scene ``flat``, raw size in px)."""
        from dp5k_common.io import write_json_atomic, write_png16

        folder = Path(folder)
        depth_mm = np.rint(self.depth_m * 1000.0).astype(np.uint16)
        written = []
        for i in range(2):
            write_png16(folder / f"cam{i}_depth_mm.png", depth_mm)
            written.append(folder / f"cam{i}_depth_mm.png")
        write_json_atomic(folder / "truth.json", {"scene": "flat", "raw_size_px": [self.w, self.h]})
        return [*written, folder / "truth.json"]


def focus_point(studio: Any, srig: Any, camera: int) -> tuple[int, int, int]:
    """Where body ``camera`` of ``srig`` focuses in ``studio``: on the scene's focus target, as an operator places the AF point.

    The target's surface is the primitive whose surface the ray to the target meets at the target's depth
    (within 2 %). The AF point must lie where the structured light can measure the focus distance (Eq. 5
    averages depth over DP5K's 30 x 20 window at the 1680-wide output, here scaled to this raw size): the
    window, plus a 2 px margin (processing loses a 1-3 px rim at depth edges), all on the target's surface
    and lit by the rig's projector. The target projected into the view is kept when it qualifies;
    otherwise (the target hidden by something nearer, in a nearer object's projector shadow, or only a
    sliver of it showing at an occluding edge) the point moves to the nearest pixel that does, else on
    any surface at the target's depth (the same focus distance), then to the nearest pixel whose window
    is at least half lit target (or lit at its depth), then the nearest lit pixel of either, last the
    nearest pixel at that depth. Both bodies thus focus on the same surface, or at the same distance.

    Returns:
        ``(x, y, choice)``: the pixel and which rule gave it: 0 the target itself, 1 .. 7 the fallbacks in the
        order above, 8 none (the projected target).
    """
    from dp5k_studio.geometry import cast

    x, y = (int(v) for v in studio.focus_point_px(camera))
    cam = srig.cameras[camera]
    target = np.asarray(studio.scene.focus_target_m, dtype=np.float64)
    z_target = float((cam.R @ target + cam.t)[2])
    geo = studio.geometry(camera)
    depth = np.asarray(geo.depth_m, dtype=np.float64)
    d = target - cam.center_m
    d = (d / np.linalg.norm(d))[None]
    zc = float((cam.R @ d[0])[2])
    prims = list(studio.scene.prims)
    z_hit = np.array([float(cast([p], cam.center_m, d)[0][0]) * zc for p in prims])
    k = int(np.argmin(np.abs(z_hit - z_target)))
    surface = (geo.prim == k) if abs(z_hit[k] - z_target) <= 0.02 * z_target else np.zeros(depth.shape, bool)
    lit = np.isfinite(np.asarray(geo.proj_xy)[..., 0])
    with np.errstate(invalid="ignore"):
        at_depth = np.abs(depth - z_target) <= 0.02 * z_target
    win = tuple(2 * max(3, int(round(n * cam.width / 2 / 1680))) for n in (30, 20))  # raw px (half-size output)
    on = [surface & lit, at_depth & lit]

    def inside(m: NDArray[np.bool_], size: tuple[int, int], frac: float) -> NDArray[np.bool_]:
        return m & (cv2.boxFilter(m.astype(np.float32), -1, size, borderType=cv2.BORDER_CONSTANT) >= frac)

    margin = (win[0] + 4, win[1] + 4)  # clear of the surface's edges by 2 px (depth edges lose a rim)
    clear = [inside(m, margin, 0.999) for m in on]
    good = [inside(m, win, 0.5) for m in on]
    if clear[0][y, x]:
        return x, y, 0
    for choice, cand in enumerate((clear[0], clear[1], good[0], good[1], on[0], on[1], at_depth), start=1):
        ys, xs = np.nonzero(cand)
        if xs.size:
            j = int(np.argmin((xs - x) ** 2 + (ys - y) ** 2))
            return int(xs[j]), int(ys[j]), choice
    return x, y, 8


class StudioOptics:
    """The virtual studio as the bodies' world (``dp5k_studio``).

    Each exposure shows the projector's current output (``projector.lit_image()``: the pattern window's
    framebuffer while the projector is on, unmuted and on HDMI) in the studio and renders camera ``i``
    (the body whose serial is the studio camera's serial) at the body's aperture, shutter, ISO and focus.
    The ChArUco views are the recalibration shots an operator takes at the scene's focus setting: the board
    is held 2.0-2.3 m from the rig in 3 tilted poses in front of a plain far wall (a separate calibration
    studio with the same rig and focus), because in a furnished scene nearer objects would hide it.

    Args:
        scene: studio scene name or seed.
        projector: the simulated projector (its lit image lights the scene).
        scale: studio rig scale (``"small"``, or a sensor downscale factor; larger = smaller images).
        seed: rig / noise seed.
        run: how many runs of the scene came before this world was made (in-process ``--sim``: board placements differ).
    """

    def __init__(self, scene: str | int, projector: SimulatedEBU42, scale: float | str = 60, seed: int = 0,
                 effects: Any = None, run: int = 0) -> None:
        from dp5k_studio import Studio, make_rig, make_scene

        from dp5k_studio import plane_scene

        self.srig = make_rig(scale, seed=seed)
        self.scene_studio = Studio(make_scene(scene, self.srig), self.srig, effects, seed=seed)
        self.calib_studio = Studio(plane_scene(8.0), self.srig, effects, seed=seed + 1)
        self.studio = self.scene_studio  # the scene: focus, ground truth, DP and structured-light shots
        if self.scene_studio.scene.name == "wall":
            # the depth-validation scene: the printed board is pasted on the wall for every shot
            from calib.board import WALL_BOARD

            from dp5k_studio import wall_board_pose

            self.scene_studio.set_board_pose(wall_board_pose(self.scene_studio.scene, WALL_BOARD.size_m), WALL_BOARD)
        self._active = self.scene_studio
        self.projector = projector
        self.seed, self.run = seed, run
        self.placements: dict[int, int] = {}
        self.board_view: tuple[int, int] | None = None  # (view, placement) while the board is held
        cams = self.srig.cameras
        self.serials = [c.serial for c in cams]
        self.raw_sizes_px = [(c.width, c.height) for c in cams]
        # the simulated bodies' factory intrinsics prior (what a one-time many-view calibration would give)
        self.intrinsics = [(tuple(tuple(float(v) for v in row) for row in np.asarray(c.K)), tuple(float(v) for v in np.ravel(c.dist)))
                           for c in cams]
        self.focus_points_px = [self._focus_point_px(i) for i in range(2)]
        self._shown: bytes | None = b"unset"
        self.board_poses: dict[int, tuple[list[list[float]], list[float]]] = {}
        self.focus_m: dict[int, float] = {}

    def _focus_point_px(self, camera: int) -> tuple[int, int]:
        """Where body ``camera`` focuses: :func:`focus_point` in this world's scene."""
        x, y, _ = focus_point(self.studio, self.srig, camera)
        return x, y

    def _index(self, serial: str) -> int:
        return self.serials.index(serial)

    def autofocus_m(self, serial: str, point_px: tuple[float, float]) -> float:
        i = self._index(serial)
        self.focus_m[i] = float(self.studio.focus_distance_m(i, point_px))
        return self.focus_m[i]

    def board_pose(self, view: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Board -> world pose of ChArUco view ``view`` (metres), as an operator would hold it.

        The board centre is held 2.0-2.3 m in front of the rig, tilted differently per view (yaw, pitch,
        roll of 5-20 degrees: varied poses constrain R, T). At 85 mm on a 36 x 24 mm sensor the view is
        0.42 z wide and 0.28 z high, so the 0.72 x 0.54 m board fills most of both toed-in views, with its
        ~60 mm squares several pixels wide even at the small studio scale.
        """
        from calib.board import DEFAULT_BOARD

        (cx, cy_, cz), yaw_deg, pitch_deg, roll_deg = [((0.0, 0.0, 2.1), 18.0, 8.0, 3.0),
                                                      ((0.03, 0.02, 2.3), -20.0, -10.0, -4.0),
                                                      ((-0.03, -0.02, 2.0), 5.0, 15.0, 8.0)][view % 3]
        R = (cv2.Rodrigues(np.radians([0.0, yaw_deg, 0.0]))[0] @ cv2.Rodrigues(np.radians([pitch_deg, 0.0, 0.0]))[0]
             @ cv2.Rodrigues(np.radians([0.0, 0.0, roll_deg]))[0])
        w, h = DEFAULT_BOARD.size_m
        t = np.array([cx, cy_, cz]) - R @ np.array([w / 2, h / 2, 0.0])
        return R, t

    def place(self, view: int) -> None:
        """Hold the board in pose ``view``: the following exposures are the calibration shots.

        A hand-held board is never put back exactly: every placement of a view after its first in this world
        (and every placement in a later in-process run) is off the nominal pose by up to 2 cm and 1.5 degrees,
        seeded by seed, run, view and the placement count."""
        R, t = self.board_pose(view)
        n = self.placements.get(view, 0)
        self.placements[view] = n + 1
        if n > 0 or self.run > 0:
            rng = np.random.default_rng([self.seed, self.run, view, n])
            R = cv2.Rodrigues(np.radians(rng.uniform(-1.5, 1.5, 3)))[0] @ R
            t = t + rng.uniform(-0.02, 0.02, 3)
        self.board_poses[view] = (R.tolist(), t.tolist())
        self.board_view = (view, n + 1)
        self.calib_studio.set_board_pose((R, t))
        self._active = self.calib_studio
        self._shown = b"unset"

    def clear(self) -> None:
        """Board away: the following exposures show the scene again."""
        self.board_view = None
        self.calib_studio.set_board_pose(None)
        self._active = self.scene_studio
        self._shown = b"unset"

    def expose(self, s: ExposureSettings) -> bytes:
        i = self._index(s.serial)
        studio = self._active
        lit = self.projector.lit_image()
        key = None if lit is None else hashlib.sha1(np.ascontiguousarray(lit).tobytes()).digest()
        if key != self._shown:
            studio.set_projector_image(lit)
            self._shown = key
        # the body keeps the scene's focus setting for every shot, the calibration views included
        focus = s.focus_distance_m if s.focus_distance_m is not None else self.studio.focus_distance_m(i, self.focus_points_px[i])
        rng = np.random.default_rng([self.seed, i, s.sequence])
        raw = studio.expose(i, s.f_number, focus, s.shutter_s, s.iso, rng)
        if studio is self.scene_studio:
            self.focus_m[i] = float(focus)  # the focus of the scene's frames (an AF after this run's first moves it)
        meta = {**raw.metadata, "sequence": s.sequence,
                **({"board": {"view": self.board_view[0], "placement": self.board_view[1]}} if self.board_view else {})}
        return dng_bytes(raw.main, raw.aux if s.dual_pixel_raw else None, raw.black_level, raw.white_level, raw.wb_gains, meta)

    def write_ground_truth(self, folder: Path) -> list[Path]:
        """``ground_truth/``: per camera depth (16-bit PNG, mm, 0 = no surface) and projector correspondence
        (``camN_proj_xy.npy`` float32 (H, W, 2), NaN = unlit), plus ``truth.json`` (intrinsics K/dist,
        extrinsics R/t world -> camera, stereo R/T, projector, pixel pitch, focal length, recorded and true
        focus distance, focus point, the ChArUco board poses used, effects)."""
        from dp5k_common.io import write_json_atomic, write_png16

        folder = Path(folder)
        written = []
        self.clear()
        self.studio.set_projector_image(None)
        self._shown = None
        truth: dict[str, Any] = {"scene": str(self.studio.scene.name) if hasattr(self.studio.scene, "name") else None,
                                 "cameras": {}, "board_poses": {str(k): v for k, v in self.board_poses.items()}}
        for i in range(2):
            gt = self.studio.ground_truth(i)
            depth_mm = np.where(np.isfinite(gt["depth_m"]), np.rint(gt["depth_m"] * 1000.0), 0)
            path = folder / f"cam{i}_depth_mm.png"
            write_png16(path, np.clip(depth_mm, 0, 65535).astype(np.uint16))
            written.append(path)
            npy = folder / f"cam{i}_proj_xy.npy"
            from dp5k_common.io import atomic_path

            with atomic_path(npy, suffix=".npy") as tmp:
                np.save(tmp, np.asarray(gt["proj_xy"], dtype=np.float32))
            written.append(npy)
            rec = self.focus_m.get(i)
            if rec is None:  # a resumed session whose shots were all taken before: the bodies did not refocus
                rec = self.autofocus_m(self.serials[i], self.focus_points_px[i])
            truth["cameras"][f"cam{i}"] = {
                "serial": self.serials[i], "K": gt["K"].tolist(), "dist": gt["dist"].tolist(), "R": gt["R"].tolist(),
                "t": gt["t"].tolist(), "width": gt["width"], "height": gt["height"],
                "pixel_pitch_mm": gt["pixel_pitch_mm"], "focal_length_mm": gt["focal_length_mm"],
                "focus_point_px": list(self.focus_points_px[i]),
                "focus_distance_recorded_m": rec,
                "focus_distance_true_m": None if rec is None else self.studio.true_focus_mm(rec) / 1000.0,
            }
            if i == 0:
                p = gt["projector"]
                truth["projector"] = {"K": p["K"].tolist(), "R": p["R"].tolist(), "t": p["t"].tolist(),
                                      "width": p["width"], "height": p["height"]}
                truth["stereo_R"] = np.asarray(gt["stereo_R"]).tolist()
                truth["stereo_T"] = np.asarray(gt["stereo_T"]).tolist()
                truth["effects"] = gt["effects"]
        write_json_atomic(folder / "truth.json", truth)
        written.append(folder / "truth.json")
        return written


@dataclass
class SimRig:
    """Everything a ``--sim`` capture connects to (the client code opens it exactly like the real rig).

    Attributes:
        rig: the rig configuration (serials of the simulated bodies, the pty as projector port).
        backend: the pyusb backend that enumerates the simulated bodies.
        bodies: the bodies' PTP cores, by camera id.
        usb_devices: their USB framings (fault injection), by camera id.
        projector: the simulated EB-U42.
        window: the headless pattern window (its framebuffer is the projector's HDMI input); None when the
            window lives in the capture client's process (sim-rig server).
        optics: the world (also the ChArUco board positioner).
    """

    rig: RigConfig
    backend: SimUsbBackend
    bodies: dict[str, SimulatedEOS]
    usb_devices: dict[str, SimUsbPtpDevice]
    projector: SimulatedEBU42
    window: PatternWindow | None
    optics: Any

    def close(self) -> None:
        self.projector.stop()


CALIBRATABLE_FOCUS_M = (1.2, 4.5)
"""Focus distances (m) at which a named random ``--sim`` scene is captured. The ChArUco shots are taken at the
scene's focus (f/22) with the board held 2.0-2.3 m away (:meth:`StudioOptics.board_pose`); focused much nearer,
the board's markers blur past detection (a body focused at 0.31 m or 0.83 m: 'only 0 (2) of 3 ChArUco pairs
share >= 12 corners'), and processing cannot calibrate."""


def calibratable(scene: str | int) -> bool:
    """Whether the studio scene ``scene`` (a preset or a seed) can be captured and processed on the rig: both bodies find their AF
    point (:func:`focus_point`) on a lit window of the target or at its depth (not a last-resort fallback, whose
    window the structured light cannot measure: 'the focus window has no valid depth'), focus at the same
    distance (within 5 %), and that distance lies in :data:`CALIBRATABLE_FOCUS_M`. Judged on the small rig of seed
    0, so a name means the same scene at every scale."""
    from dp5k_studio import Studio, make_rig, make_scene

    rig = make_rig("small")
    studio = Studio(make_scene(scene, rig), rig)
    focus = []
    for camera in range(2):
        x, y, choice = focus_point(studio, rig, camera)
        if choice > 4:
            return False
        focus.append(float(studio.focus_distance_m(camera, (x, y))))
    lo, hi = CALIBRATABLE_FOCUS_M
    return all(lo <= f <= hi for f in focus) and abs(focus[0] - focus[1]) <= 0.05 * max(focus)


def sim_studio_scene(scene: str) -> str | int:
    """The studio scene for a ``--sim`` capture: a preset of the same name (``dp5k_studio.PRESETS``), a seed given as
    digits or ``rand<seed>``; any other name seeds a random scene the rig can calibrate in: the first of the seeds
    ``crc32(name) % 100000``, + 1, + 2, ... that is :func:`calibratable` (the same name, the same scene).

    >>> sim_studio_scene("demo01"), sim_studio_scene("17"), sim_studio_scene("rand3")
    ('demo01', '17', 'rand3')
    """
    from dp5k_studio import PRESETS

    if scene in PRESETS or scene.isdigit() or (scene.startswith("rand") and scene[4:].isdigit()):
        return scene
    seed = zlib.crc32(scene.encode()) % 100000
    while not calibratable(seed):
        seed = (seed + 1) % 100000
    return seed


def write_ground_truth_once(optics: Any, session_dir: Path, file_mode: int | None = None) -> Path:
    """``session_dir/ground_truth/`` from the simulated world, as one atomic folder rename (kept if present).

    Written into a hidden temporary folder beside it and renamed, so an interruption leaves either no
    ``ground_truth/`` or a whole one; leftovers of an interrupted write are removed on the next call.
    ``file_mode`` is the mode new files get under the capture client's umask (a sim-rig server writes for a
    client with another umask); default: this process's.
    """
    final = Path(session_dir) / "ground_truth"
    for stale in Path(session_dir).glob(f".{GROUND_TRUTH_TMP_PREFIX}*"):
        shutil.rmtree(stale, ignore_errors=True)
    if final.is_dir():
        return final
    tmp = Path(tempfile.mkdtemp(prefix=f".{GROUND_TRUTH_TMP_PREFIX}", dir=session_dir))
    try:
        optics.write_ground_truth(tmp)
        mode = new_file_mode() if file_mode is None else file_mode & 0o666
        for path in tmp.iterdir():
            os.chmod(path, mode)
        os.chmod(tmp, mode | (mode & 0o444) >> 2)  # a folder: x wherever r (0o755 under umask 022)
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def make_sim_rig(base: RigConfig | None = None, *, optics_factory: Callable[[SimulatedEBU42, PatternWindow | None], Any] | None = None,
                 raw_size_px: tuple[int, int] = (96, 64), warmup_s: float = 0.2, seed: int = 0, faults: str = "",
                 hdmi: Callable[[], NDArray[np.uint8]] | None = None, run: int = 0, blocking: bool = False) -> SimRig:
    """Build the simulated rig. ``optics_factory(projector, window)`` makes the world (default :class:`FlatOptics`).

    ``faults`` is a ``--sim-faults`` text (:mod:`dp5k_capture.sim.fault_spec`). ``hdmi`` is the projector's
    HDMI input when the pattern window lives in another process (a sim-rig server); then ``window`` is None.
    ``run`` counts the runs of this scene before this one (new bodies each in-process run: their lenses sit
    where an earlier run's AF left them, see :mod:`~dp5k_capture.sim.eos_body`). ``blocking``: bulk-IN reads
    with nothing to return wait out their timeout (as libusb does).
    """
    base = base or RigConfig()
    p = base.projector
    window = None if hdmi is not None else PatternWindow(p.width, p.height, display_index=0, settle_s=0.0, headless=True)
    projector = SimulatedEBU42(warmup_s=warmup_s, hdmi=hdmi if window is None else window.frame)
    port = projector.serve_pty()
    if optics_factory is None:
        optics: Any = FlatOptics(raw_size_px, projector.lit_image, seed, run)
        sizes = [raw_size_px, raw_size_px]
    else:
        optics = optics_factory(projector, window)
        sizes = list(getattr(optics, "raw_sizes_px", [raw_size_px, raw_size_px]))
    serials = list(getattr(optics, "serials", SIM_SERIALS))
    points = list(getattr(optics, "focus_points_px", [(w // 2, h // 2) for (w, h) in sizes]))
    intrinsics = list(getattr(optics, "intrinsics", [(b.K, b.dist) for b in base.bodies]))
    bodies_cfg = tuple(
        replace(b, serial=serials[i], raw_size_px=tuple(sizes[i]), focus_point_px=tuple(points[i]),
                K=intrinsics[i][0], dist=intrinsics[i][1])
        for i, b in enumerate(base.bodies)
    )
    rig = replace(base, bodies=bodies_cfg, projector=replace(p, port=port))
    bodies, devs = {}, {}
    for i, b in enumerate(rig.bodies):
        core = SimulatedEOS(b.serial, optics, faults=BodyFaults(), af_seed=seed, run=run, lens_point_px=b.focus_point_px)
        bodies[b.id] = core
        devs[b.id] = SimUsbPtpDevice(core, address=10 + i, blocking=blocking)
    for cam_id, plan in parse_sim_faults(faults, tuple(devs)).items():
        devs[cam_id].arm(plan)
    backend = SimUsbBackend(list(devs.values()))
    return SimRig(rig, backend, bodies, devs, projector, window, optics)


__all__ = ["SimRig", "make_sim_rig", "FlatOptics", "StudioOptics", "dng_bytes", "SIM_SERIALS", "sim_studio_scene",
           "write_ground_truth_once"]
