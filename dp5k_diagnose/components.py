"""Effect components for the base model: one per name of the vocabulary (``dp5k_common.effects``).

Each component is a small physical extension of :class:`neural_dp.simulators.base.BaseModel` with a few
parameters that :func:`neural_dp.simulators.base.fit_parameters` fits on training pairs. Parameter names
carry units; the sign conventions are those of docs/conventions.md.

===================== ================================================================================
effect                model change (parameters)
===================== ================================================================================
lr_gain_imbalance     left *= exp(q/2), right *= exp(-q/2), q = a0 + ax x + ay y + axx x^2 + ayy y^2
                      (``gain_ratio`` = exp(a0), the L/R ratio at the centre; field coords in [-1, 1])
field_varying_psf     disc diameter x (1 + ``coc_scale_r2`` r^2) and split x (1 + ``split_r2`` r^2),
                      r = field radius (corner = 1)
chromatic_defocus     per-channel CoC offset: c_R = c + ``coc_offset_r_px``, c_B = c + ``coc_offset_b_px``
disparity_scale       split weight ``disparity_scale`` (L/R centroid separation / ideal)
focus_offset          CoC recomputed (Eq. 6) at focus distance F + ``focus_offset_mm``
psf_profile           radial weight 1 + ``profile`` (2 rho^2/R^2 - 1) (> 0 brighter rim, < 0 brighter centre)
front_back_asymmetry  diameter x ``front_scale`` and profile ``front_profile`` for c < 0 only
misregistration       each view shifted by (``left_dx_px``, ``left_dy_px``), (``right_dx_px``, ``right_dy_px``)
noise                 the sharp input is denoised with a Gaussian of ``input_blur_sigma_px``; the views'
                      white noise (``noise_sigma``, linear units) is estimated from the residual
===================== ================================================================================
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dp5k_common.optics import coc_diameter_px
from neural_dp.batch import DPBatch
from neural_dp.simulators.base import Component, PSFShape, field_r2


class LRGainImbalance(Component):
    """L/R brightness ratio varying smoothly across the field (vignetting of each half aperture)."""

    name = "lr_gain_imbalance"
    post_only = True
    KEYS = ("a0", "ax", "ay", "axx", "ayy")

    def __init__(self) -> None:
        super().__init__()
        self.params = {k: 0.0 for k in self.KEYS}
        self.fit_names = list(self.KEYS)
        self.bounds = {k: (-2.0, 2.0) for k in self.KEYS}
        self.steps = {k: 0.01 for k in self.KEYS}

    def log_ratio(self, field: Tensor) -> Tensor:
        x, y = field[:, :1], field[:, 1:2]
        p = self.params
        return p["a0"] + p["ax"] * x + p["ay"] * y + p["axx"] * x * x + p["ayy"] * y * y

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        q = self.log_ratio(field)
        return left * torch.exp(q / 2), right * torch.exp(-q / 2)

    def describe(self) -> dict[str, float]:
        p = dict(self.params)
        xs = torch.linspace(-1, 1, 9)
        f = torch.stack(torch.meshgrid(xs, xs, indexing="xy"))[None]
        q = self.log_ratio(f)
        p["gain_ratio"] = float(np.exp(self.params["a0"]))
        p["gain_ratio_mean"] = float(torch.exp(q).mean())
        p["gain_ratio_min"] = float(torch.exp(q).min())
        p["gain_ratio_max"] = float(torch.exp(q).max())
        return p


class FieldVaryingPSF(Component):
    """PSF size and L/R split change with the field radius (off-axis vignetting of the half apertures)."""

    name = "field_varying_psf"
    field_dependent = True
    changes_psf = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"coc_scale_r2": 0.0, "split_r2": 0.0}
        self.fit_names = list(self.params)
        self.bounds = {"coc_scale_r2": (-0.9, 3.0), "split_r2": (-1.0, 1.5)}
        self.steps = {"coc_scale_r2": 0.05, "split_r2": 0.05}

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        return PSFShape(
            shape.coc_px,
            shape.scale * (1.0 + self.params["coc_scale_r2"] * field_r2),
            shape.softness_px,
            shape.profile,
            shape.split * (1.0 + self.params["split_r2"] * field_r2),
        )

    def describe(self) -> dict[str, float]:
        p = dict(self.params)
        p["coc_scale_at_corner"] = 1.0 + p["coc_scale_r2"]
        p["disparity_scale_at_corner"] = 1.0 + p["split_r2"]
        return p


class ChromaticDefocus(Component):
    """Longitudinal chromatic aberration: red and blue focus elsewhere than green (CoC offset per channel)."""

    name = "chromatic_defocus"
    channel_dependent = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"coc_offset_r_px": 0.0, "coc_offset_b_px": 0.0}
        self.fit_names = list(self.params)
        self.bounds = {k: (-20.0, 20.0) for k in self.params}
        self.steps = {k: 0.25 for k in self.params}

    def coc(self, coc_px: Tensor, batch: DPBatch) -> Tensor:
        c = coc_px[:, :1]
        return torch.cat([c + self.params["coc_offset_r_px"], c, c + self.params["coc_offset_b_px"]], dim=1)


class DisparityScale(Component):
    """Soft L/R split (sub-pixel crosstalk): disparity is a fraction of the ideal half-aperture one."""

    name = "disparity_scale"
    changes_psf = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"disparity_scale": 1.0}
        self.fit_names = ["disparity_scale"]
        self.bounds = {"disparity_scale": (0.0, 2.0)}
        self.steps = {"disparity_scale": 0.05}

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        return PSFShape(shape.coc_px, shape.scale, shape.softness_px, shape.profile, shape.split * self.params["disparity_scale"])


class FocusOffset(Component):
    """The true focus distance differs from the recorded one (Eq. 6 at F + offset)."""

    name = "focus_offset"

    def __init__(self) -> None:
        super().__init__()
        self.params = {"focus_offset_mm": 0.0}
        self.fit_names = ["focus_offset_mm"]
        self.bounds = {"focus_offset_mm": (-1e6, 1e6)}
        self.steps = {"focus_offset_mm": 10.0}

    def initial_guess(self, model, batch: DPBatch, field: Tensor) -> None:
        """Scale the finite-difference step and bounds to the focus distances in the data."""
        F_mm = float(batch.focus_distance_mm.mean())
        self.steps["focus_offset_mm"] = 0.01 * F_mm
        self.bounds["focus_offset_mm"] = (-0.5 * F_mm, 0.5 * F_mm)

    def coc(self, coc_px: Tensor, batch: DPBatch) -> Tensor:
        off = self.params["focus_offset_mm"]
        if off == 0.0:
            return coc_px
        out = []
        depth = batch.depth_mm[:, 0].detach().cpu().numpy()
        for i in range(depth.shape[0]):
            F_mm = float(batch.focus_distance_mm[i])
            f_mm = float(batch.focal_length_mm[i])
            F_new = max(F_mm + off, f_mm * 1.05)
            c = coc_diameter_px(depth[i], F_new, f_mm, float(batch.f_number[i]), float(batch.pixel_pitch_mm[i]))
            out.append(torch.from_numpy(np.nan_to_num(c, nan=0.0).astype(np.float32)))
        new = torch.stack(out)[:, None].to(coc_px.device)
        new = torch.where(batch.valid, new, coc_px[:, :1])
        return new.expand_as(coc_px) if coc_px.shape[1] > 1 else new


class PSFProfile(Component):
    """The disc is not uniform: brighter rim (> 0, e.g. Butterworth ring) or brighter centre (< 0)."""

    name = "psf_profile"
    changes_psf = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"profile": 0.0}
        self.fit_names = ["profile"]
        self.bounds = {"profile": (-1.0, 1.0)}
        self.steps = {"profile": 0.1}

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        return PSFShape(shape.coc_px, shape.scale, shape.softness_px, shape.profile + self.params["profile"], shape.split)


class FrontBackAsymmetry(Component):
    """Blur in front of focus differs from blur behind it (spherical aberration): size and profile."""

    name = "front_back_asymmetry"
    changes_psf = True

    def __init__(self) -> None:
        super().__init__()
        self.params = {"front_scale": 1.0, "front_profile": 0.0}
        self.fit_names = list(self.params)
        self.bounds = {"front_scale": (0.2, 3.0), "front_profile": (-1.0, 1.0)}
        self.steps = {"front_scale": 0.05, "front_profile": 0.1}

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        front = (shape.coc_px < 0).float()
        scale = shape.scale * (1.0 + front * (self.params["front_scale"] - 1.0))
        profile = shape.profile + front * self.params["front_profile"]
        return PSFShape(shape.coc_px, scale, shape.softness_px, profile, shape.split)


def shift_image(img: Tensor, dx_px: float, dy_px: float) -> Tensor:
    """(B, C, H, W) image translated by (dx, dy) px (content moves +x right, +y down), bilinear, border clamp."""
    if dx_px == 0.0 and dy_px == 0.0:
        return img
    B, C, H, W = img.shape
    ys = torch.arange(H, dtype=img.dtype, device=img.device) - dy_px
    xs = torch.arange(W, dtype=img.dtype, device=img.device) - dx_px
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    grid = torch.stack([gx / max(W - 1, 1) * 2 - 1, gy / max(H - 1, 1) * 2 - 1], dim=-1)[None].expand(B, H, W, 2)
    return F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)


class Misregistration(Component):
    """The views are not registered to the sharp image (and to each other): a global shift per view."""

    name = "misregistration"
    post_only = True
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
        p["shift_dx_px"] = p["right_dx_px"] - p["left_dx_px"]
        p["shift_dy_px"] = p["right_dy_px"] - p["left_dy_px"]
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


def gaussian_blur(img: Tensor, sigma_px: float) -> Tensor:
    """(B, C, H, W) separable Gaussian blur with standard deviation ``sigma_px`` (reflect padding)."""
    if sigma_px <= 0.05:
        return img
    r = int(np.ceil(3 * sigma_px))
    x = torch.arange(-r, r + 1, dtype=img.dtype, device=img.device)
    k = torch.exp(-0.5 * (x / sigma_px) ** 2)
    k = k / k.sum()
    C = img.shape[1]
    out = F.conv2d(F.pad(img, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    return F.conv2d(F.pad(out, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


class Noise(Component):
    """Sensor noise: the views carry white noise the model does not predict; a noisy sharp input is denoised."""

    name = "noise"

    def __init__(self) -> None:
        super().__init__()
        self.params = {"input_blur_sigma_px": 0.0}
        self.fit_names = ["input_blur_sigma_px"]
        self.bounds = {"input_blur_sigma_px": (0.0, 2.0)}
        self.steps = {"input_blur_sigma_px": 0.15}
        self.estimates: dict[str, float] = {}

    def sharp(self, sharp: Tensor, batch: DPBatch) -> Tensor:
        return gaussian_blur(sharp, self.params["input_blur_sigma_px"])

    def describe(self) -> dict[str, float]:
        return {**self.params, **self.estimates}


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
