"""The virtual studio: a scene, the rig, optional board and projector pattern, and exposures of them.

``Studio.expose`` renders what a camera would record: pinhole radiance by ray casting (render.py), the
DP optics at the requested f-number and focus (dp_optics.py, every planted effect included), diffraction,
then the sensor (sensor.py) into a 14-bit Dual Pixel RAW. ``ground_truth`` returns what no real rig can
give: exact depth, intrinsics, extrinsics and the projector correspondence.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.board import DEFAULT_BOARD, BoardSpec
from dp5k_common.errors import BadInputError

from .dp_optics import DPPlan, DPRender, LensSetting, plan_dp
from .effects import EffectSet, effect_parameters
from .geometry import Quad, cast
from .pattern_views import PatternViews
from .render import ViewGeometry, pixel_rays, view_geometry
from .rig import Rig
from .scenes import Scene
from .sensor import DEFAULT_SENSOR, RawExposure, SensorModel, expose_raw
from .textures import TextureSpec

MISREG_MAX_F_NUMBER = 8.0
"""Exposures at this f-number or above (sharp f/22, structured light, ChArUco at f/8) are not misregistered."""

WAVELENGTH_MM = 0.00055
"""Green wavelength for diffraction (mm)."""


def diffraction_sigma_px(f_number: float, pixel_pitch_mm: float) -> float:
    """Gaussian sigma (px) approximating the Airy core: ``0.42 * lambda * N / pitch``."""
    return 0.42 * WAVELENGTH_MM * f_number / pixel_pitch_mm


def board_quad(board: BoardSpec, R: NDArray[np.float64], t: NDArray[np.float64], px_per_square: int = 48) -> Quad:
    """The board as a textured quad (print + a half-square white margin), posed board -> world by (R, t)."""
    img = board.image(px_per_square).astype(np.float32) / 255.0
    albedo = 0.03 + 0.82 * img  # black ink 0.03, paper 0.85
    W_m, H_m = board.size_m
    margin = 0.5 * board.square_m
    tex = TextureSpec("image", image=albedo, size_m=(W_m, H_m))
    # the texture is addressed in board coordinates: shift the quad origin by the margin
    origin = t + R @ np.array([-margin, -margin, 0.0])
    return _ShiftedQuad(origin, R[:, 0], R[:, 1], (W_m + 2 * margin, H_m + 2 * margin), tex, "board", margin)


class _ShiftedQuad(Quad):
    """A quad whose surface coordinates are offset by ``-margin`` (so they are board coordinates)."""

    def __init__(self, origin, u, v, size, tex, name, margin):  # noqa: D107
        object.__setattr__(self, "origin", np.asarray(origin, float))
        object.__setattr__(self, "u_axis", np.asarray(u, float))
        object.__setattr__(self, "v_axis", np.asarray(v, float))
        object.__setattr__(self, "size_m", size)
        object.__setattr__(self, "texture", tex)
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "_margin", margin)

    def surface(self, p):
        u, v, n = super().surface(p)
        return u - self._margin, v - self._margin, n


def _pose_to_Rt(pose: Any) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Accept (R (3,3) | rvec (3,), t (3,)) or a 4x4 matrix; board -> world, metres."""
    if isinstance(pose, np.ndarray) and pose.shape == (4, 4):
        return pose[:3, :3].astype(float), pose[:3, 3].astype(float)
    try:
        r, t = pose
    except Exception as exc:
        raise BadInputError("board pose must be (R or rvec, t) or a 4x4 matrix") from exc
    r = np.asarray(r, dtype=float)
    t = np.asarray(t, dtype=float).reshape(3)
    if r.shape == (3, 3):
        return r, t
    if r.size == 3:
        R, _ = cv2.Rodrigues(r.reshape(3, 1))
        return R, t
    raise BadInputError(f"board rotation must be 3x3 or a Rodrigues vector, got shape {r.shape}")


class Studio:
    """A scene in front of the rig, ready to be exposed.

    Args:
        scene: the :class:`~.scenes.Scene`.
        rig: the :class:`~.rig.Rig`.
        effects: planted optical effects (None = ideal lens).
        seed: noise seed used when ``expose`` gets no ``rng``.
        supersample: rays per pixel side for radiance; default 2 for raw widths up to 800 px (small
            rigs, where ChArUco bits are a few pixels wide), else 1.
        sensor: sensor constants.
    """

    def __init__(self, scene: Scene, rig: Rig, effects: EffectSet | None = None, seed: int = 0,
                 supersample: int | None = None, sensor: SensorModel = DEFAULT_SENSOR) -> None:
        self.scene = scene
        self.rig = rig
        self.effects = effects or EffectSet()
        self.supersample = int(supersample) if supersample else (2 if rig.cameras[0].width <= 800 else 1)
        self.sensor = sensor
        self._rng = np.random.default_rng(seed)
        self._pattern: NDArray[np.float32] | None = None
        self._board: Quad | None = None
        self._board_pose: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self._geom: dict[int, ViewGeometry] = {}
        self._rad: dict[int, NDArray[np.float32]] = {}
        self._plans: dict[int, tuple[tuple, DPPlan]] = {}
        self._views: dict[int, PatternViews] = {}

    # ---------------------------------------------------------------- scene state
    def set_projector_image(self, image: NDArray[Any] | None) -> None:
        """Show an image on the projector: (Hp, Wp) or (Hp, Wp, 3), float in [0, 1] or uint8; None = dark."""
        if image is None:
            self._pattern = None
        else:
            img = np.asarray(image)
            p = self.rig.projector
            if img.shape[:2] != (p.height, p.width) or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
                raise BadInputError(f"projector image must be ({p.height}, {p.width}[, 3]), got {img.shape}")
            img = img.astype(np.float32) / 255.0 if img.dtype == np.uint8 else np.clip(img.astype(np.float32), 0.0, 1.0)
            self._pattern = img
        self._rad.clear()

    def set_board_pose(self, pose: Any | None, board: BoardSpec = DEFAULT_BOARD) -> None:
        """Place the ChArUco board (board -> world pose ``(R | rvec, t)`` or 4x4, metres); None removes it."""
        if pose is None:
            self._board = None
            self._board_pose = None
        else:
            R, t = _pose_to_Rt(pose)
            self._board = board_quad(board, R, t)
            self._board_pose = (R, t)
        self._geom.clear()
        self._rad.clear()
        self._plans.clear()
        self._views.clear()

    def _extra(self) -> tuple:
        return (self._board,) if self._board is not None else ()

    def geometry(self, camera: int) -> ViewGeometry:
        """The ray-cast geometry of ``camera`` with the current board (cached; independent of the pattern)."""
        cam = self._camera(camera)
        if camera not in self._geom:
            self._geom[camera] = view_geometry(self.scene, cam, self.rig.projector, self._extra(), self.supersample)
        return self._geom[camera]

    def radiance(self, camera: int) -> NDArray[np.float32]:
        """(H, W, 3) sharp pinhole radiance of ``camera`` under the current pattern and board (cached)."""
        if camera not in self._rad:
            self._rad[camera] = self.geometry(camera).radiance(self._pattern)
        return self._rad[camera]

    def _camera(self, camera: int):
        if camera not in (0, 1):
            raise BadInputError(f"camera must be 0 or 1, got {camera}")
        return self.rig.cameras[camera]

    # ---------------------------------------------------------------- optics
    def true_focus_mm(self, focus_distance_m: float) -> float:
        """Where the lens truly focuses (mm) when the recorded focus distance is ``focus_distance_m``."""
        fac = effect_parameters("focus_offset", self.effects.s("focus_offset"))["focus_factor"]
        return float(focus_distance_m) * 1000.0 * fac

    def effects_at(self, f_number: float) -> EffectSet:
        """The effects acting on an exposure at ``f_number``: ``misregistration`` moves only the DP captures
        (f-numbers below MISREG_MAX_F_NUMBER) against the sharp, structured-light and ChArUco frames, which
        define the depth geometry."""
        if f_number >= MISREG_MAX_F_NUMBER and self.effects.s("misregistration") > 0:
            return EffectSet({k: v for k, v in self.effects.strengths.items() if k != "misregistration"})
        return self.effects

    def dp_plan(self, camera: int, f_number: float, focus_distance_m: float) -> DPPlan:
        """The depth-dependent part of ``camera``'s DP render at this aperture and recorded focus (cached: the
        last plan per camera is kept until the geometry changes, so the 92 structured-light frames, the f/22
        sharp frame and every pattern share one plan)."""
        cam = self._camera(camera)
        lens = LensSetting(cam.focal_length_mm, float(f_number), self.true_focus_mm(focus_distance_m), cam.pixel_pitch_mm)
        effects = self.effects_at(f_number)
        key = (lens, tuple(sorted(effects.strengths.items())))
        cached = self._plans.get(camera)
        if cached is None or cached[0] != key:
            geom = self.geometry(camera)
            hidden_mm = None if geom.hidden is None else geom.hidden["depth_m"] * 1000.0
            self._plans[camera] = (key, plan_dp(geom.depth_m * 1000.0, lens, effects, hidden_mm))
        return self._plans[camera][1]

    def render_views(self, camera: int, f_number: float, focus_distance_m: float, full: bool = False) -> DPRender:
        """Noise-free linear DP views (H, W, 3) of ``camera`` at raw resolution (diffraction included)."""
        cam = self._camera(camera)
        plan = self.dp_plan(camera, f_number, focus_distance_m)
        geom = self.geometry(camera)
        if full:
            hidden = None if geom.hidden is None else geom.hidden_radiance(self._pattern)
            out = plan.render(self.radiance(camera), hidden, full=True)
        else:  # the projector images share the dark and full-light views (pattern_views.py)
            if camera not in self._views or self._views[camera].plan is not plan:
                self._views[camera] = PatternViews(plan, geom)
            left, right = self._views[camera].views(self._pattern)
            out = DPRender(left, right, None, plan.coc_px)
        sig = diffraction_sigma_px(f_number, cam.pixel_pitch_mm)
        if sig > 0.05:
            blur = lambda a: cv2.GaussianBlur(a, (0, 0), sig, borderType=cv2.BORDER_REFLECT)  # noqa: E731
            out.left, out.right = blur(out.left), blur(out.right)
            if out.full is not None:
                out.full = blur(out.full)
        return out

    def expose(self, camera: int, f_number: float, focus_distance_m: float, shutter_s: float, iso: int,
               rng: np.random.Generator | None = None) -> RawExposure:
        """Take a Dual Pixel RAW.

        Args:
            camera: 0 or 1.
            f_number: aperture (1.8 .. 22; f/22 is the near-pinhole sharp frame).
            focus_distance_m: the focus distance the camera records (the lens truly focuses there unless
                the ``focus_offset`` effect is planted).
            shutter_s: exposure time in seconds.
            iso: ISO speed.
            rng: noise generator (default: the studio's own, seeded).

        Returns:
            :class:`RawExposure` (main = both photodiodes, aux = LEFT photodiode, 14-bit RGGB).
        """
        if not (math.isfinite(focus_distance_m) and focus_distance_m * 1000.0 > self.rig.cameras[0].focal_length_mm):
            raise BadInputError(f"focus distance must exceed the focal length, got {focus_distance_m} m")
        dp = self.render_views(camera, f_number, focus_distance_m)
        nz = effect_parameters("noise", self.effects.s("noise"))
        main, aux = expose_raw(dp.left, dp.right, f_number, shutter_s, iso, rng or self._rng, self.sensor,
                               nz["shot_var_factor"], nz["read_sigma_factor"])
        cam = self._camera(camera)
        meta = {
            "camera": cam.name, "serial": cam.serial, "model": cam.model, "lens": cam.lens,
            "f_number": float(f_number), "focus_distance_m": float(focus_distance_m),
            "shutter_s": float(shutter_s), "iso": int(iso), "aux_view": "left", "cfa": "RGGB",
            "focal_length_mm": cam.focal_length_mm, "effects": self.effects_at(f_number).to_json((cam.width, cam.height)),
        }
        return RawExposure(main, aux, self.sensor.black_level, self.sensor.white_level, self.sensor.wb_gains, meta)

    # ---------------------------------------------------------------- truth
    def ground_truth(self, camera: int) -> dict[str, Any]:
        """Everything true about ``camera`` now.

        Returns:
            dict with ``depth_m`` (H, W) z-depth at pixel centres (inf = no surface), ``K``, ``dist``, ``R``,
            ``t`` (world -> camera), ``pixel_pitch_mm``, ``focal_length_mm``, ``width``, ``height``,
            ``proj_xy`` (H, W, 2) projector pixel seen at each pixel centre (NaN = unlit or shadowed),
            ``projector`` {K, R, t, width, height}, ``stereo_R``, ``stereo_T`` (cam0 -> cam1),
            ``board_pose`` (R, t) board -> world or None, ``effects``.
        """
        cam = self._camera(camera)
        v = self.geometry(camera)
        p = self.rig.projector
        sR, sT = self.rig.stereo_RT()
        return {
            "depth_m": v.depth_m, "K": cam.K.copy(), "dist": cam.dist.copy(), "R": cam.R.copy(), "t": cam.t.copy(),
            "pixel_pitch_mm": cam.pixel_pitch_mm, "focal_length_mm": cam.focal_length_mm,
            "width": cam.width, "height": cam.height, "proj_xy": v.proj_xy,
            "projector": {"K": p.K.copy(), "R": p.R.copy(), "t": p.t.copy(), "width": p.width, "height": p.height},
            "stereo_R": sR, "stereo_T": sT, "board_pose": self._board_pose,
            "effects": self.effects.to_json((cam.width, cam.height)),
        }

    def focus_distance_m(self, camera: int, focus_point_px: tuple[float, float]) -> float:
        """True z-depth (m) of the surface seen exactly at raw pixel ``(x, y)`` of ``camera``."""
        cam = self._camera(camera)
        d, zc = pixel_rays(cam, np.array([float(focus_point_px[0])]), np.array([float(focus_point_px[1])]))
        t, idx = cast(list(self.scene.prims) + list(self._extra()), cam.center_m, d)
        if idx[0] < 0:
            raise BadInputError(f"no surface at focus point {focus_point_px} of {cam.name}")
        return float(t[0] * zc[0])

    def focus_point_px(self, camera: int) -> tuple[float, float]:
        """The scene's focus target projected into ``camera`` (raw px), clipped into the image."""
        cam = self._camera(camera)
        Xc = cam.R @ self.scene.focus_target_m + cam.t
        uv = cam.K @ (Xc / Xc[2])
        x = float(np.clip(np.rint(uv[0]), 0, cam.width - 1))
        y = float(np.clip(np.rint(uv[1]), 0, cam.height - 1))
        return x, y
