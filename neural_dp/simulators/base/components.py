"""Effect components for the base model: one per name of the vocabulary (``dp5k_common.effects``).

Each component is a small physical extension of :class:`neural_dp.simulators.base.BaseModel` with a few
parameters that :func:`neural_dp.simulators.base.fit_parameters` fits on training pairs. Parameter names
carry units and follow the physical definitions of docs/studio.md, so fitted values compare with planted
ones; field coordinates ``x, y`` are in [-1, 1], ``r^2 = (x^2 + y^2) / 2`` (corner = 1).

===================== ================================================================================
effect                model change (parameters)
===================== ================================================================================
lr_gain_imbalance     L/R ratio rho: ln rho = a0 + ax x + ay y + axx x^2 + ayy y^2 + axy x y; left x 2 rho/(1+rho),
                      right x 2/(1+rho) (``lr_ratio_center`` = exp(a0))
field_varying_psf     CoC x (1 + ``coc_growth_at_corner`` r^2); off-axis photodiode leak: the left view
                      receives ``edge_leak`` max(0, -x) of the right view's light, mirrored on the right;
                      cat's-eye vignetting: at field (x, y) the pupil cut by a unit circle centred ``vignetting``
                      (x, y a) pupil radii, a = (H - 1) / (W - 1), along the field vector (each view's brightness
                      corrected back); the split line moved to pupil x = ``split_shift`` x (each view's PSF and
                      share of the light change, :func:`split_share`)
chromatic_defocus     per-channel thin-lens focal length f + ``focal_shift_r_mm`` / f + ``focal_shift_b_mm``
                      with the sensor set for green (per-channel CoC from the depth map)
disparity_scale       symmetric photodiode crosstalk kappa: L' = (1-kappa) L + kappa R (and mirrored);
                      ``disparity_scale`` = 1 - 2 kappa (L/R separation / ideal half-aperture one), in
                      [-0.5, 1]: crosstalk >= 0 only shrinks it; < 0 means swapped views
focus_offset          CoC recomputed (Eq. 6) at focus distance F' with 1/F' = 1/(``focus_factor`` F) - ``focus_shift_dpt``
                      (a relative error and one in dioptres; ``focus_offset_mm`` reported)
psf_profile           radial weight 1 + ``rim_gain2`` (rho/R)^2 + ``rim_gain`` (rho/R)^4 (> 0 bright rim, < 0 bright
                      centre; a ring near the rim, a quadratic or a quartic rim)
front_back_asymmetry  behind focus weight 1 + ``back_rim_gain`` (rho/R)^2, in front 1 + ``front_center_gain``
                      (1 - (rho/R)^2) and diameter x ``front_size_factor``; and spherical aberration: pupil zone rho
                      lands as if the CoC were c - ``spherical_mm_f1`` / N^3 (rho^2 - 3/5) (mm on the sensor)
misregistration       each view shifted by (``left_dx_px``, ``left_dy_px``), (``right_dx_px``, ``right_dy_px``)
noise                 signal-dependent white noise var = ``shot_var`` I + ``read_sigma``^2 in the views
                      (estimated from the residual; the prediction itself, an expectation, is unchanged)
===================== ================================================================================
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dp5k_learn.batch import DPBatch

from .field import field_r2
from .model import Component
from .psf import PSFShape, split_share


class LRGainImbalance(Component):
    """L/R brightness ratio varying smoothly across the field (vignetting of each half aperture)."""

    name = "lr_gain_imbalance"
    post_only = True
    stage = 1
    KEYS = ("a0", "ax", "ay", "axx", "ayy", "axy")

    def __init__(self) -> None:
        super().__init__()
        self.params = {k: 0.0 for k in self.KEYS}
        self.fit_names = list(self.KEYS)
        self.bounds = {k: (-2.0, 2.0) for k in self.KEYS}
        self.steps = {k: 0.01 for k in self.KEYS}

    def log_ratio(self, field: Tensor) -> Tensor:
        """(B, 1, H, W) ln(L/R gain ratio) at field coordinates (B, 2, H, W): every quadratic in x and y (a
        renderer's or a sensor's ramp may tilt along any direction and curve along either axis)."""
        x, y = field[:, :1], field[:, 1:2]
        p = self.params
        return p["a0"] + p["ax"] * x + p["ay"] * y + p["axx"] * x * x + p["ayy"] * y * y + p.get("axy", 0.0) * x * y

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        rho = torch.exp(self.log_ratio(field))
        return left * (2 * rho / (1 + rho)), right * (2 / (1 + rho))

    def describe(self) -> dict[str, float]:
        """The fitted coefficients, the ratio at the field centre, and the ratio's mean, min and max over the
        field the fit data covered (:attr:`field_box`, reported as ``field_x0`` .. ``field_y1``), not over
        [-1, 1]^2: the quadratic extrapolated to the corners of a field the pairs did not reach printed
        0.705..2.605 for a measured 1.01-1.42 (real Pixel 4 data)."""
        p = dict(self.params)
        x0, x1, y0, y1 = self.field_box
        f = torch.stack(torch.meshgrid(torch.linspace(x0, x1, 9), torch.linspace(y0, y1, 9), indexing="xy"))[None]
        rho = torch.exp(self.log_ratio(f))
        p["lr_ratio_center"] = float(np.exp(self.params["a0"]))
        p["lr_ratio_mean"] = float(rho.mean())
        p["lr_ratio_min"] = float(rho.min())
        p["lr_ratio_max"] = float(rho.max())
        p.update(field_x0=x0, field_x1=x1, field_y0=y0, field_y1=y1)
        return p


def crosstalk(left: Tensor, right: Tensor, k_rl: Tensor | float, k_lr: Tensor | float) -> tuple[Tensor, Tensor]:
    """Move a fraction ``k_rl`` of R's light to L and ``k_lr`` of L's to R (keeps L + R)."""
    return left * (1 - k_lr) + right * k_rl, right * (1 - k_rl) + left * k_lr


class FieldVaryingPSF(Component):
    """The blur changes across the field, three ways a real lens and sensor do it:

    * ``coc_growth_at_corner``: the blur grows off axis, CoC x (1 + g r^2);
    * ``edge_leak``: the photodiodes' split shifts off axis (the chief ray's angle), so one view receives
      ``edge_leak`` max(0, -x) of the other view's light (mirrored on the right);
    * ``vignetting``: a lens element other than the stop clips the pupil off axis (a cat's-eye pupil): at field
      (x, y) the pupil is cut by a circle of radius 1 centred ``vignetting`` (x, y a) pupil radii, along the
      field vector on the sensor (``a`` the frame's half-height over its half-width, so the cut is the same at
      the same distance from the centre in any direction), each view's brightness corrected back (its PSF, not
      its light, changes: off axis in x the clipped half's blur narrows and its disparity shrinks; off axis in y
      both halves lose their top or bottom). Its sign says which side the clipping element sits on. Until
      2026-12-06 the cut moved along x only: on ``aperture_dp``'s cat's-eye, whose stop moves along the field
      vector, 43 % of the effect's signal was out of its reach (the cut's y part; fitted, it left half) and the
      effect sat at its detection limit.
    * ``split_shift``: the photodiodes' split line itself moves off axis (the microlens offset against the chief
      ray's angle): at field x it crosses the pupil at :math:`u_x = ` ``split_shift`` x pupil radii (the left
      photodiode takes :math:`u_x <` it). Each view's PSF is the part of the disc on its side of the line, and
      its light is its share of the pupil (:func:`split_share`: the left view brightens where the line moves
      right), not corrected back. ``edge_leak`` is the same cause seen as a mixing of the views' light; which
      of the two a sensor follows shows in the PSFs' shapes at the edges.
    """

    name = "field_varying_psf"
    post_params = ("edge_leak",)
    """Parameters only the :meth:`post` hook reads (a fit's Jacobian reuses one layered render for them)."""

    def __init__(self) -> None:
        super().__init__()
        self.params = {"coc_growth_at_corner": 0.0, "edge_leak": 0.0, "vignetting": 0.0, "split_shift": 0.0}
        self.fit_names = list(self.params)
        self.bounds = {"coc_growth_at_corner": (-0.9, 3.0), "edge_leak": (-0.5, 0.5), "vignetting": (-1.2, 1.2), "split_shift": (-0.9, 0.9)}
        self.steps = {"coc_growth_at_corner": 0.03, "edge_leak": 0.02, "vignetting": 0.05, "split_shift": 0.03}

    @property
    def field_x_dependent(self) -> bool:  # type: ignore[override]
        return self.params.get("vignetting", 0.0) != 0.0 or self.params.get("split_shift", 0.0) != 0.0

    @property
    def field_y_dependent(self) -> bool:  # type: ignore[override]
        return self.params.get("vignetting", 0.0) != 0.0

    @property
    def changes_psf(self) -> bool:  # type: ignore[override]
        return self.field_x_dependent

    def coc(self, coc_px: Tensor, batch: DPBatch, field: Tensor) -> Tensor:
        return coc_px * (1.0 + self.params["coc_growth_at_corner"] * field_r2(field))

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        v = self.params.get("vignetting", 0.0)
        s = self.params.get("split_shift", 0.0)
        if v:
            shape = replace(shape, clip_dx=shape.clip_dx + v * self.field_x, clip_dy=shape.clip_dy + v * self.field_y)
        if s:
            shape = replace(shape, split_dx=shape.split_dx + s * self.field_x)
        return shape

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        x = field[:, :1]
        s = self.params.get("split_shift", 0.0)
        if s:  # each view's share of the pupil's light (the kernels sum to 1)
            left, right = left * split_share(s * x), right * split_share(-s * x)
        b = self.params["edge_leak"]
        return crosstalk(left, right, b * (-x).clamp(min=0), b * x.clamp(min=0))


class ChromaticDefocus(Component):
    """Longitudinal chromatic aberration: red and blue have their own focal length (sensor set for green)."""

    name = "chromatic_defocus"
    needs_colour = True
    KEYS = ("focal_shift_r_mm", "focal_shift_b_mm")

    def __init__(self) -> None:
        super().__init__()
        self.params = {k: 0.0 for k in self.KEYS}
        self.fit_names = list(self.KEYS)
        self.bounds = {k: (-2.0, 2.0) for k in self.KEYS}
        self.steps = {k: 0.05 for k in self.KEYS}

    @staticmethod
    def coc_shift_px(batch: DPBatch, focal_shift_mm: float) -> Tensor:
        r"""(B, 1, H, W) change of the signed CoC (px) when the focal length is ``f + focal_shift_mm``.

        Thin lens with the sensor at :math:`v = 1/(1/f - 1/F)`: :math:`C_c = (f/N)(v - v_c)/v_c`,
        :math:`v_c = 1/(1/f_c - 1/z)`; for :math:`f_c = f` this is Eq. 6.
        """
        z = batch.depth_mm.double()
        f = batch.focal_length_mm.double().view(-1, 1, 1, 1)
        Fd = batch.focus_distance_mm.double().view(-1, 1, 1, 1)
        N = batch.f_number.double().view(-1, 1, 1, 1)
        pitch = batch.pixel_pitch_mm.double().view(-1, 1, 1, 1)
        zz = torch.where(batch.valid, z, Fd.expand_as(z))
        v = 1.0 / (1.0 / f - 1.0 / Fd)

        def coc(fc: Tensor) -> Tensor:
            vz = 1.0 / (1.0 / fc - 1.0 / zz)
            return (f / N) * (v - vz) / vz / pitch

        d = coc(f + focal_shift_mm) - coc(f)
        return torch.where(batch.valid, d, torch.zeros_like(d)).float()

    def coc(self, coc_px: Tensor, batch: DPBatch, field: Tensor) -> Tensor:
        c = coc_px[:, :1]
        return torch.cat([c + self.coc_shift_px(batch, self.params["focal_shift_r_mm"]), c,
                          c + self.coc_shift_px(batch, self.params["focal_shift_b_mm"])], dim=1)


class DisparityScale(Component):
    """Symmetric photodiode crosstalk: disparity is a fraction of the ideal half-aperture one, L + R kept."""

    name = "disparity_scale"
    post_only = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"disparity_scale": 1.0}
        self.fit_names = ["disparity_scale"]
        # crosstalk mixes the halves, so it can only shrink disparity: at most 1 (crosstalk >= 0); below 0
        # the views are swapped (a sign or labelling error). Above 1 it would be a rim-heavy aperture, which
        # psf_profile and front_back_asymmetry model: unbounded, it took 0.22 of the systematic error on a
        # front_back_asymmetry set at 1.08 and was named instead.
        self.bounds = {"disparity_scale": (-0.5, 1.0)}
        self.steps = {"disparity_scale": 0.05}

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        k = (1.0 - self.params["disparity_scale"]) / 2.0
        return crosstalk(left, right, k, k)

    def describe(self) -> dict[str, float]:
        return {**self.params, "crosstalk": (1.0 - self.params["disparity_scale"]) / 2.0}


MIN_FOCUS_OVER_FOCAL = 1.05
"""A fitted focus distance is kept at least this many focal lengths from the lens (Eq. 6 diverges at F = f)."""


class FocusOffset(Component):
    """The lens focuses at :math:`F'` with :math:`1/F' = 1/(k F) - \\delta` instead of the recorded :math:`F` (Eq. 6
    recomputed at :math:`F'`).

    Two forms of focus error: ``focus_factor`` k, a relative one (a focus-by-wire error that scales with the
    distance), and ``focus_shift_dpt`` delta, one in dioptres (1/m: a sensor or autofocus offset in image
    space, the same blur at every distance). Pairs focused at one distance cannot tell them apart (their
    intervals then say so); pairs at several distances can. The report also gives the offset in mm at the mean
    recorded focus distance of the fit data.
    """

    name = "focus_offset"
    stage = -1

    def __init__(self) -> None:
        super().__init__()
        self.params = {"focus_factor": 1.0, "focus_shift_dpt": 0.0}
        self.fit_names = ["focus_factor", "focus_shift_dpt"]
        self.bounds = {"focus_factor": (0.5, 2.0), "focus_shift_dpt": (-1.0, 1.0)}
        self.steps = {"focus_factor": 0.01, "focus_shift_dpt": 0.005}
        self.mean_focus_mm = float("nan")

    def initial_guess(self, model, batch: DPBatch, field: Tensor) -> None:
        """Remember the mean recorded focus distance (mm) to report the offset in mm."""
        self.mean_focus_mm = float(batch.focus_distance_mm.mean())

    MIN_FOCUS_DISTANCES = 4
    """Distinct recorded focus distances the fit data needs before ``focus_shift_dpt`` is fitted beside
    ``focus_factor``."""
    MIN_FOCUS_RATIO = 2.0
    """... spanning at least this ratio (farthest / nearest)."""

    def supported_names(self, samples: Sequence[Any]) -> list[str]:
        """``focus_factor`` always; ``focus_shift_dpt`` only where the fit data was focused at several distances
        far enough apart to tell a relative error from one in dioptres (:data:`MIN_FOCUS_DISTANCES`,
        :data:`MIN_FOCUS_RATIO`). At a few nearby distances the two trade off: fitted together on 3 focus
        distances of another renderer's set with a planted relative offset, they drifted to 1.175 and -0.026 dpt
        and predicted the detection pairs, focused elsewhere, worse than the base model."""
        F = sorted({round(float(f), 3) for s in samples for f in s.batch.focus_distance_mm.tolist()})
        wide = len(F) >= self.MIN_FOCUS_DISTANCES and F[-1] >= self.MIN_FOCUS_RATIO * max(F[0], 1e-9)
        return ["focus_factor", "focus_shift_dpt"] if wide else ["focus_factor"]

    def true_focus_mm(self, F_mm: Tensor | float, f_mm: Tensor | float) -> Tensor:
        """:math:`F' = 1 / (1/(k F) - \\delta / 1000)` (mm), at least 1.05 f (infinity or beyond: 1e9 mm)."""
        k, dpt = self.params["focus_factor"], self.params.get("focus_shift_dpt", 0.0)
        F = torch.as_tensor(F_mm, dtype=torch.float64)
        inv = 1.0 / (F * k) - dpt / 1000.0
        F_new = torch.where(inv > 1e-9, 1.0 / inv.clamp(min=1e-9), torch.full_like(F, 1e9))
        return torch.maximum(F_new, torch.as_tensor(f_mm, dtype=torch.float64) * MIN_FOCUS_OVER_FOCAL)

    def coc(self, coc_px: Tensor, batch: DPBatch, field: Tensor) -> Tensor:
        r"""The CoC (px) at the true focus distance :math:`F'` (:meth:`true_focus_mm`), from the CoC itself, not
        the depth.

        Eq. 6 is :math:`C = K(F) (1 - F/d)` with :math:`K(F) = f^2 / (N (F - f))` (mm on the sensor), so at the
        same depth :math:`C' = K(F') (1 - (F'/F)(1 - C/K(F)))`, affine in :math:`C`: exact for coc.tif's float
        CoC, where recomputing from depth.png's whole millimetres moved it by 0.25-0.9 px per mm at a 70 mm
        phone focus and made the CoC jump between ``k = 1`` and any other ``k``. Applied per channel to the
        CoC the components before it produced.
        """
        if self.params["focus_factor"] == 1.0 and self.params.get("focus_shift_dpt", 0.0) == 0.0:
            return coc_px
        view = lambda t: t.double().view(-1, 1, 1, 1)  # noqa: E731
        f, N, pitch = view(batch.focal_length_mm), view(batch.f_number), view(batch.pixel_pitch_mm)
        F = view(batch.focus_distance_mm)
        F_new = self.true_focus_mm(F, f)
        K, K_new = f * f / (N * (F - f)), f * f / (N * (F_new - f))
        c_mm = coc_px.double() * pitch
        new = (K_new * (1.0 - (F_new / F) * (1.0 - c_mm / K)) / pitch).to(coc_px.dtype)
        return torch.where(batch.valid, new, coc_px)

    def describe(self) -> dict[str, float]:
        p = dict(self.params)
        if np.isfinite(self.mean_focus_mm):
            F = self.mean_focus_mm
            p["focus_offset_mm"] = float(self.true_focus_mm(F, 0.0)) - F
        else:
            p["focus_offset_mm"] = float("nan")
        return p


class PSFProfile(Component):
    """The disc is not uniform: weight 1 + rim_gain2 (rho/R)^2 + rim_gain (rho/R)^4 (a bright rim, "soap bubble",
    < 0 a bright centre). Two terms, since a real lens's (or another renderer's) profile has no set power: a
    quadratic rim, a quartic one, or a ring just inside the rim (their difference)."""

    name = "psf_profile"
    changes_psf = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"rim_gain": 0.0, "rim_gain2": 0.0}
        self.fit_names = ["rim_gain", "rim_gain2"]
        self.bounds = {"rim_gain": (-0.95, 10.0), "rim_gain2": (-0.95, 10.0)}
        self.steps = {"rim_gain": 0.2, "rim_gain2": 0.2}

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        return replace(shape, rim2=shape.rim2 + self.params.get("rim_gain2", 0.0), rim4=shape.rim4 + self.params["rim_gain"])


class FrontBackAsymmetry(Component):
    """Blur in front of focus differs from blur behind it: rim-heavy behind, centre-heavy and larger in front.

    Two descriptions, fitted together: the blur's shape on each side as such (``back_rim_gain``,
    ``front_center_gain``, ``front_size_factor``: the same shape at every CoC), and its physical cause,
    spherical aberration (``spherical_mm_f1``): a ray through normalized pupil radius rho lands as if the CoC
    were ``c - S (rho^2 - 3/5)`` with ``S = spherical_mm_f1 / N^3`` mm on the sensor (third-order aberration
    grows with the aperture cubed; > 0 over-corrected), so the PSF's shape depends on the CoC (strong near focus,
    fading for large discs) and on the f-number (f/4 has a tenth of f/1.8's), which a fixed shape cannot follow.
    """

    name = "front_back_asymmetry"
    changes_psf = True

    @property
    def shape_needs_optics(self) -> bool:  # type: ignore[override]
        """Only spherical aberration depends on the f-number and pitch (pairs then render per f-number)."""
        return self.params.get("spherical_mm_f1", 0.0) != 0.0

    def __init__(self) -> None:
        super().__init__()
        self.params = {"back_rim_gain": 0.0, "front_center_gain": 0.0, "front_size_factor": 1.0, "spherical_mm_f1": 0.0}
        self.fit_names = list(self.params)
        # in front the disc can be centre-heavy or flat, not rim-heavy: a rim on both sides is no asymmetry
        # but psf_profile (with front_center_gain down to -0.45 it fitted a quadratic rim planted on both
        # sides better than psf_profile's quartic one, and was named in its place)
        self.bounds = {"back_rim_gain": (-0.95, 6.0), "front_center_gain": (0.0, 6.0), "front_size_factor": (0.5, 2.0),
                       "spherical_mm_f1": (-20.0, 20.0)}
        self.steps = {"back_rim_gain": 0.15, "front_center_gain": 0.15, "front_size_factor": 0.03, "spherical_mm_f1": 0.2}

    SIDE_MIN_COC_PX = 1.5
    """A pixel tells the blur's shape on its side of focus from this |CoC| (px) on."""
    SIDE_MIN_SHARE = 0.02
    """The share of the fit's scored pixels a side needs before its parameters are fitted."""

    def supported_names(self, samples: Sequence[Any]) -> list[str]:
        """The parameters the fit samples constrain: the front ones only with enough scored pixels in front of
        focus (``coc < -1.5 px``), the back one only with enough behind. Without them the fit moved the front
        size factor to 0.6 and the centre gain to its bound to sharpen near-focus pixels (a 4-pair fit set
        with no front content), and that extension raised the front error of the detection pairs several-fold."""
        front = back = total = 0
        for s in samples:
            c, m = s.batch.coc_px, s.score
            front += int(((c < -self.SIDE_MIN_COC_PX) & m).sum())
            back += int(((c > self.SIDE_MIN_COC_PX) & m).sum())
            total += int(m.sum())
        names = []
        if back >= self.SIDE_MIN_SHARE * max(total, 1):
            names.append("back_rim_gain")
        if front >= self.SIDE_MIN_SHARE * max(total, 1):
            names += ["front_center_gain", "front_size_factor"]
        if names:  # spherical aberration acts on both sides and near focus: any blur shows it
            names.append("spherical_mm_f1")
        return names

    def coc(self, coc_px: Tensor, batch: DPBatch, field: Tensor) -> Tensor:
        return torch.where(coc_px < 0, coc_px * self.params["front_size_factor"], coc_px)

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        front = (shape.coc_px < 0).float()
        g = self.params["front_center_gain"]
        # 1 + g (1 - q) is proportional to 1 - g/(1+g) q
        a2 = (1 - front) * self.params["back_rim_gain"] + front * (-g / (1 + g))
        sa_mm = self.params.get("spherical_mm_f1", 0.0)
        sa_px = sa_mm / shape.f_number**3 / shape.pixel_pitch_mm if sa_mm and shape.f_number > 0 and shape.pixel_pitch_mm > 0 else 0.0
        return replace(shape, rim2=shape.rim2 + a2, sa_px=shape.sa_px + sa_px)


def fittable_names(comp: Component, samples: Sequence[Any]) -> list[str]:
    """``comp``'s parameters that ``samples`` (diagnose ``Sample``s) can constrain (its ``supported_names``,
    within ``fit_names``); the rest stay at their neutral values."""
    return [n for n in comp.supported_names(samples) if n in comp.fit_names]


def shift_image(img: Tensor, dx_px: float, dy_px: float) -> Tensor:
    """(B, C, H, W) image translated by (dx, dy) px (content moves +x right, +y down), bicubic, border clamp."""
    if dx_px == 0.0 and dy_px == 0.0:
        return img
    B, C, H, W = img.shape
    ys = torch.arange(H, dtype=img.dtype, device=img.device) - dy_px
    xs = torch.arange(W, dtype=img.dtype, device=img.device) - dx_px
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    grid = torch.stack([gx / max(W - 1, 1) * 2 - 1, gy / max(H - 1, 1) * 2 - 1], dim=-1)[None].expand(B, H, W, 2)
    return F.grid_sample(img, grid, mode="bicubic", padding_mode="border", align_corners=True)


class Misregistration(Component):
    """The views are not registered to the sharp image (and to each other): a global shift per view."""

    name = "misregistration"
    post_only = True
    stage = 2
    KEYS = ("left_dx_px", "left_dy_px", "right_dx_px", "right_dy_px")

    def __init__(self) -> None:
        super().__init__()
        self.params = {k: 0.0 for k in self.KEYS}
        self.fit_names = list(self.KEYS)
        self.bounds = {k: (-8.0, 8.0) for k in self.KEYS}
        self.steps = {k: 0.05 for k in self.KEYS}

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        p = self.params
        return shift_image(left, p["left_dx_px"], p["left_dy_px"]), shift_image(right, p["right_dx_px"], p["right_dy_px"])

    def initial_guess(self, model, batch: DPBatch, field: Tensor) -> None:
        """Lucas-Kanade estimate of each view's global shift against the model's prediction."""
        left, right = model.render(batch, field)
        m = batch.valid.float()
        for view, pred, meas in (("left", left, batch.left), ("right", right, batch.right)):
            dx, dy = global_shift_lk(pred, meas, m)
            self.params[f"{view}_dx_px"] = float(np.clip(dx, -8, 8))
            self.params[f"{view}_dy_px"] = float(np.clip(dy, -8, 8))

    def describe(self) -> dict[str, float]:
        p = dict(self.params)
        p["shift_px"] = [(p["left_dx_px"] + p["right_dx_px"]) / 2, (p["left_dy_px"] + p["right_dy_px"]) / 2]
        p["lr_shift_px"] = [p["right_dx_px"] - p["left_dx_px"], p["right_dy_px"] - p["left_dy_px"]]
        return p


def global_shift_lk(ref: Tensor, moved: Tensor, mask: Tensor, iters: int = 3) -> tuple[float, float]:
    r"""Global translation (dx, dy) px with ``moved ~ shift(ref, dx, dy)`` by iterated Lucas-Kanade.

    Solves :math:`\min_d \sum m (\mathrm{shift}(ref, d) - moved)^2` with the Gauss-Newton normal equations
    on image gradients (all channels and pairs pooled).
    """
    dx = dy = 0.0
    for _ in range(iters):
        cur = shift_image(ref, dx, dy)
        gx = (cur[..., :, 2:] - cur[..., :, :-2])[..., 1:-1, :] / 2
        gy = (cur[..., 2:, :] - cur[..., :-2, :])[..., :, 1:-1] / 2
        e = (moved - cur)[..., 1:-1, 1:-1]
        w = mask[..., 1:-1, 1:-1]
        # shifting content by +d changes the image by -d . grad
        a11 = float((w * gx * gx).sum()); a22 = float((w * gy * gy).sum()); a12 = float((w * gx * gy).sum())
        b1 = float((w * gx * -e).sum()); b2 = float((w * gy * -e).sum())
        det = a11 * a22 - a12 * a12
        if abs(det) < 1e-12:
            break
        ddx = (a22 * b1 - a12 * b2) / det
        ddy = (a11 * b2 - a12 * b1) / det
        dx += ddx
        dy += ddy
        if abs(ddx) + abs(ddy) < 1e-3:
            break
    return dx, dy


class Noise(Component):
    """Sensor noise in the views: white, signal dependent, var = shot_var * I + read_sigma^2 (linear units).

    A simulator's prediction is the noise-free expectation, so the component leaves the views unchanged;
    its parameters (estimated from the residual by :func:`dp5k_diagnose.noise.test_noise`) let a
    simulator add calibrated noise when it synthesises data.
    """

    name = "noise"
    post_only = True
    stage = 3

    def __init__(self) -> None:
        super().__init__()
        self.params = {"shot_var": 0.0, "read_sigma": 0.0}

    def sample(self, view: Tensor, rng: torch.Generator | None = None) -> Tensor:
        """A noisy sample of a (B, 3, H, W) view under the fitted noise model."""
        var = self.params["shot_var"] * view.clamp(min=0) + self.params["read_sigma"] ** 2
        return view + torch.randn(view.shape, generator=rng, device=view.device) * var.sqrt()


COMPONENTS: dict[str, type[Component]] = {
    c.name: c
    for c in (
        LRGainImbalance,
        FieldVaryingPSF,
        ChromaticDefocus,
        DisparityScale,
        FocusOffset,
        PSFProfile,
        FrontBackAsymmetry,
        Misregistration,
        Noise,
    )
}
"""Component class per effect name (every name of ``EFFECT_NAMES``)."""
