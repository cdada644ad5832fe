"""Did a body's focus move since its kept frames? A re-shot frame against a kept one, in the focus window.

Both frames are Dual Pixel raws shot with the same settings (the kept DP frame at the widest aperture, where
defocus shows most). In the focus window around the body's AF point, on the raw frames binned 2 x 2 (one
value per Bayer quad, black subtracted), vectorised with numpy and OpenCV. Views are aligned after a
high-pass (the frame divided by its mean, minus its Gaussian blur of sigma 3 binned px): shading and
vignetting ramps, which differ between the two photodiodes, would otherwise pass for a shift. Each alignment
also gives its own uncertainty, the Cramer-Rao bound of a translation estimate: sigma^2 = var(residual after
alignment) / sum(g^2) over the template's gradient g along the shift. It counts only if ECC converges with a
correlation of at least 0.6 (texture, not noise). Where the focus window holds too little texture (a plain
wall) to measure the DP disparity change to a third of its limit and the shift to a third of its limit, the
window grows (x2, x4, ... up to the whole frame) until it does, and the record says which window was used:

* **DP disparity** (raw px): the shift along x of the right photodiode view (main - aux) against the left
  (aux), found by OpenCV's ECC alignment (``cv2.findTransformECC``, translation). It is signed and grows with
  defocus (about 4 C / (3 pi) for a blur-circle diameter C, docs/conventions.md), so its change between the
  kept and the new frame measures how far the focus moved, and in which direction.
* **sharpness**: the mean squared Sobel gradient of the main frame over its squared mean (so exposure and
  light level cancel); the ratio new / kept drops when focus left the subject.
* **image shift** (raw px): the translation of the new main frame against the kept one (ECC): the body, lens
  or scene moved, which re-shooting one body cannot repair.

Thresholds (:class:`FocusThresholds`, why in docs/capture.md): focus moved if the DP disparity changed by more
than 0.25 raw px or the sharpness by more than 15 %; the view moved if it shifted by more than 0.5 raw px.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.rawfile import DualPixelFrames

EQ5_WINDOW_OUT_PX = (30, 20)  # DP5K's focus window (Eq. 5) at the 1680-px output ...
EQ5_OUTPUT_WIDTH_PX = 1680  # ... of a 6720-px raw: 120 x 80 raw px
WINDOW_SCALE = 2  # the check measures in twice that window (240 x 160 raw px): more texture, steadier numbers
MIN_WINDOW_PX = 32  # raw px (16 binned px), the least ECC aligns reliably
GROWTH = (1, 2, 4, 8, 16, 32)  # window scales tried in turn until the views align (the last covers any frame)
ECC_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
MIN_ALIGN_CC = 0.6  # ECC correlation of the high-passed views below which an alignment is noise
HIGHPASS_SIGMA_PX = 3.0  # binned px


@dataclass(frozen=True)
class FocusThresholds:
    """When a re-shot frame says the focus (or the view) moved.

    Attributes:
        dp_disparity_px: largest accepted change of DP disparity, raw px (0.25: a CoC change of ~0.6 raw px,
            0.15 px at the paper's 1680-px output).
        sharpness_rel: largest accepted relative change of the sharpness (0.15 = 15 %).
        shift_px: largest accepted image shift of the main frame, raw px.
    """

    dp_disparity_px: float = 0.25
    sharpness_rel: float = 0.15
    shift_px: float = 0.5


@dataclass(frozen=True)
class FocusComparison:
    """A new frame against the kept one. ``moved``: the focus moved; ``view_moved``: the picture shifted."""

    window_px: tuple[int, int, int, int]
    dp_disparity_kept_px: float
    dp_disparity_new_px: float
    dp_disparity_change_sigma_px: float
    sharpness_ratio: float
    shift_px: tuple[float, float]
    moved: bool
    view_moved: bool
    reason: str

    @property
    def dp_disparity_change_px(self) -> float:
        return self.dp_disparity_new_px - self.dp_disparity_kept_px

    def to_json(self) -> dict[str, object]:
        """The comparison as JSON values (a measure that could not be made is null, never NaN)."""
        out = asdict(self)
        out["dp_disparity_change_px"] = self.dp_disparity_change_px
        return {k: _finite(v) for k, v in out.items()}


def _finite(v: object) -> object:
    if isinstance(v, float):
        return v if np.isfinite(v) else None
    if isinstance(v, (tuple, list)):
        return [_finite(x) for x in v]
    return v


def focus_window(point_px: tuple[float, float], raw_size_px: tuple[int, int], grow: int = 1) -> tuple[int, int, int, int]:
    """``(x0, y0, w, h)`` in raw px (even, inside the frame) centred on the AF point: the Eq. 5 window scaled to
    this raw width, doubled, at least ``MIN_WINDOW_PX`` square, times ``grow`` (clipped to the frame)."""
    W, H = raw_size_px
    scale = W / (4 * EQ5_OUTPUT_WIDTH_PX)  # raw px per 6720-wide raw px
    w = min(W, grow * max(MIN_WINDOW_PX, int(round(EQ5_WINDOW_OUT_PX[0] * 4 * scale * WINDOW_SCALE))))
    h = min(H, grow * max(MIN_WINDOW_PX, int(round(EQ5_WINDOW_OUT_PX[1] * 4 * scale * WINDOW_SCALE))))
    w, h = w - w % 2, h - h % 2
    x0 = int(np.clip(round(point_px[0] - w / 2), 0, W - w)) & ~1
    y0 = int(np.clip(round(point_px[1] - h / 2), 0, H - h)) & ~1
    return x0, y0, w, h


def _binned(frame: NDArray[np.uint16] | NDArray[np.float32], window: tuple[int, int, int, int], black: float) -> NDArray[np.float32]:
    """Sum of each 2 x 2 Bayer quad in the window, black subtracted: (h/2, w/2) float32 in raw counts."""
    x0, y0, w, h = window
    a = np.asarray(frame, dtype=np.float32)[y0 : y0 + h, x0 : x0 + w] - np.float32(black)
    return a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]


def _highpass(a: NDArray[np.float32]) -> NDArray[np.float32]:
    """``a`` over its mean, minus its Gaussian blur: texture without shading ramps (float32)."""
    a = a / max(float(np.mean(a, dtype=np.float64)), 1e-6)
    return (a - cv2.GaussianBlur(a, (0, 0), HIGHPASS_SIGMA_PX, borderType=cv2.BORDER_REFLECT)).astype(np.float32)


@dataclass(frozen=True)
class Shift:
    """A translation between two images (their pixels) and its 1-sigma uncertainty along x and y."""

    dx: float
    dy: float
    sigma_x: float
    sigma_y: float


def _ecc_shift(template: NDArray[np.float32], image: NDArray[np.float32]) -> Shift | None:
    """Translation of ``image`` against ``template`` (ECC on the high-passed images) with its uncertainty; None if
    it does not converge, correlates below ``MIN_ALIGN_CC`` or runs off a quarter of the window."""
    a, b = _highpass(template), _highpass(image)
    warp = np.eye(2, 3, dtype=np.float32)
    try:
        cc, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_TRANSLATION, ECC_CRITERIA, None, 1)
    except cv2.error:
        return None
    h, w = a.shape
    dx, dy = float(warp[0, 2]), float(warp[1, 2])
    if not (cc >= MIN_ALIGN_CC and abs(dx) < w / 4 and abs(dy) < h / 4):
        return None
    back = cv2.warpAffine(b, warp, (w, h), flags=cv2.INTER_LINEAR + cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
    inner = (slice(2, h - 2), slice(2, w - 2))
    a_in, b_in = a[inner].astype(np.float64), back[inner].astype(np.float64)
    gain = float((a_in * b_in).sum() / max((a_in * a_in).sum(), 1e-12))  # ECC is blind to gain: so is the residual
    resid_var = float(np.var(b_in - gain * a_in))
    gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3)[inner].astype(np.float64) / 8.0
    gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3)[inner].astype(np.float64) / 8.0
    return Shift(dx, dy, float(np.sqrt(resid_var / max(float((gx * gx).sum()), 1e-12))),
                 float(np.sqrt(resid_var / max(float((gy * gy).sum()), 1e-12))))


def _dp_shift(frames: DualPixelFrames, window: tuple[int, int, int, int], aux_view: str) -> Shift | None:
    aux = _binned(frames.aux, window, frames.black_level)
    other = _binned(frames.main, window, frames.black_level) - aux
    left, right = (aux, other) if aux_view == "left" else (other, aux)
    return _ecc_shift(left, right)


def dp_disparity_px(frames: DualPixelFrames, window: tuple[int, int, int, int], aux_view: str = "left") -> float | None:
    """DP disparity in the window (raw px): the right view's shift against the left along x, + behind focus."""
    shift = _dp_shift(frames, window, aux_view)
    return None if shift is None else 2.0 * shift.dx


def sharpness(frames: DualPixelFrames, window: tuple[int, int, int, int]) -> float:
    """Mean squared Sobel gradient of the binned main frame over its squared mean (dimensionless)."""
    g = _binned(frames.main, window, frames.black_level)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    energy = float(np.mean(gx[1:-1, 1:-1].astype(np.float64) ** 2 + gy[1:-1, 1:-1].astype(np.float64) ** 2))
    return energy / max(float(np.mean(g, dtype=np.float64)) ** 2, 1e-12)


def compare_focus(kept: DualPixelFrames, new: DualPixelFrames, point_px: tuple[float, float],
                  thresholds: FocusThresholds | None = None, aux_view: str = "left") -> FocusComparison:
    """Compare a new frame of a body with its kept one around the AF point ``point_px`` (raw px), in the focus
    window or, where that holds too little texture, the smallest grown window in which both frames align."""
    t = thresholds or FocusThresholds()
    H, W = kept.main.shape
    for grow in GROWTH:
        window = focus_window(point_px, (W, H), grow)
        dk, dn = _dp_shift(kept, window, aux_view), _dp_shift(new, window, aux_view)
        shift = _ecc_shift(_binned(kept.main, window, kept.black_level), _binned(new.main, window, new.black_level))
        if dk is not None and dn is not None and shift is not None \
                and 2.0 * float(np.hypot(dk.sigma_x, dn.sigma_x)) <= t.dp_disparity_px / 3 \
                and 2.0 * max(shift.sigma_x, shift.sigma_y) <= t.shift_px / 3:
            break
        if window[2:] == (W - W % 2, H - H % 2):
            dk = dn = shift = None
            break
    else:
        dk = dn = shift = None
    sigma = float("nan") if dk is None or dn is None else 2.0 * float(np.hypot(dk.sigma_x, dn.sigma_x))
    d_kept = None if dk is None else 2.0 * dk.dx
    d_new = None if dn is None else 2.0 * dn.dx
    ratio = sharpness(new, window) / max(sharpness(kept, window), 1e-12)
    if d_kept is None or d_new is None or shift is None:
        nan = float("nan")
        return FocusComparison(window, nan if d_kept is None else d_kept, nan if d_new is None else d_new, sigma, ratio,
                               (nan, nan), True, False, "the views do not align to a third of the limits even over the "
                               "whole frame (too little texture): focus cannot be verified")
    grown = "" if grow == 1 else f" (in {window[2]} x {window[3]} raw px: the focus window holds too little texture)"
    shift_px = (2.0 * shift.dx, 2.0 * shift.dy)
    view_moved = bool(np.hypot(*shift_px) > t.shift_px)
    d_change = d_new - d_kept
    moved = abs(d_change) > t.dp_disparity_px or abs(ratio - 1.0) > t.sharpness_rel
    reasons = []
    if abs(d_change) > t.dp_disparity_px:
        reasons.append(f"DP disparity {d_kept:+.2f} -> {d_new:+.2f} raw px (limit +-{t.dp_disparity_px:g})")
    if abs(ratio - 1.0) > t.sharpness_rel:
        reasons.append(f"sharpness x{ratio:.2f} (limit +-{100 * t.sharpness_rel:.0f} %)")
    if view_moved:
        reasons.append(f"the view shifted by ({shift_px[0]:+.2f}, {shift_px[1]:+.2f}) raw px (limit {t.shift_px:g})")
    reason = "; ".join(reasons) or (f"DP disparity {d_kept:+.2f} -> {d_new:+.2f} (+-{sigma:.2f}) raw px, sharpness x{ratio:.2f}, "
                                    f"shift ({shift_px[0]:+.2f}, {shift_px[1]:+.2f}) raw px: within the limits")
    return FocusComparison(window, d_kept, d_new, sigma, ratio, shift_px, moved, view_moved, reason + grown)


__all__ = ["FocusThresholds", "FocusComparison", "compare_focus", "focus_window", "dp_disparity_px", "sharpness"]
