"""Did a body's focus move since its kept frames? A re-shot frame against a kept one, in the focus window.

Both frames are Dual Pixel raws shot with the same settings (the kept DP frame at the widest aperture, where
defocus shows most). In the focus window around the body's AF point, on the raw frames binned 2 x 2 (one
value per Bayer quad, black subtracted), vectorised with numpy and OpenCV:

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
ECC_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)


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
    sharpness_ratio: float
    shift_px: tuple[float, float]
    moved: bool
    view_moved: bool
    reason: str

    @property
    def dp_disparity_change_px(self) -> float:
        return self.dp_disparity_new_px - self.dp_disparity_kept_px

    def to_json(self) -> dict[str, object]:
        out = asdict(self)
        out["dp_disparity_change_px"] = self.dp_disparity_change_px
        return out


def focus_window(point_px: tuple[float, float], raw_size_px: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, w, h)`` in raw px (even, inside the frame) centred on the AF point: the Eq. 5 window scaled to
    this raw width, doubled, at least ``MIN_WINDOW_PX`` square."""
    W, H = raw_size_px
    scale = W / (4 * EQ5_OUTPUT_WIDTH_PX)  # raw px per 6720-wide raw px
    w = min(W, max(MIN_WINDOW_PX, int(round(EQ5_WINDOW_OUT_PX[0] * 4 * scale * WINDOW_SCALE))))
    h = min(H, max(MIN_WINDOW_PX, int(round(EQ5_WINDOW_OUT_PX[1] * 4 * scale * WINDOW_SCALE))))
    w, h = w - w % 2, h - h % 2
    x0 = int(np.clip(round(point_px[0] - w / 2), 0, W - w)) & ~1
    y0 = int(np.clip(round(point_px[1] - h / 2), 0, H - h)) & ~1
    return x0, y0, w, h


def _binned(frame: NDArray[np.uint16] | NDArray[np.float32], window: tuple[int, int, int, int], black: float) -> NDArray[np.float32]:
    """Sum of each 2 x 2 Bayer quad in the window, black subtracted: (h/2, w/2) float32 in raw counts."""
    x0, y0, w, h = window
    a = np.asarray(frame, dtype=np.float32)[y0 : y0 + h, x0 : x0 + w] - np.float32(black)
    return a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]


def _ecc_shift(template: NDArray[np.float32], image: NDArray[np.float32]) -> tuple[float, float] | None:
    """Translation (dx, dy) of ``image`` against ``template`` in their pixels (ECC), None if it does not converge."""
    warp = np.eye(2, 3, dtype=np.float32)
    try:
        _, warp = cv2.findTransformECC(template, image, warp, cv2.MOTION_TRANSLATION, ECC_CRITERIA, None, 1)
    except cv2.error:
        return None
    return float(warp[0, 2]), float(warp[1, 2])


def dp_disparity_px(frames: DualPixelFrames, window: tuple[int, int, int, int], aux_view: str = "left") -> float | None:
    """DP disparity in the window (raw px): the right view's shift against the left along x, + behind focus."""
    aux = _binned(frames.aux, window, frames.black_level)
    other = _binned(frames.main, window, frames.black_level) - aux
    left, right = (aux, other) if aux_view == "left" else (other, aux)
    shift = _ecc_shift(left, right)
    return None if shift is None else 2.0 * shift[0]


def sharpness(frames: DualPixelFrames, window: tuple[int, int, int, int]) -> float:
    """Mean squared Sobel gradient of the binned main frame over its squared mean (dimensionless)."""
    g = _binned(frames.main, window, frames.black_level)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    energy = float(np.mean(gx[1:-1, 1:-1].astype(np.float64) ** 2 + gy[1:-1, 1:-1].astype(np.float64) ** 2))
    return energy / max(float(np.mean(g, dtype=np.float64)) ** 2, 1e-12)


def compare_focus(kept: DualPixelFrames, new: DualPixelFrames, point_px: tuple[float, float],
                  thresholds: FocusThresholds | None = None, aux_view: str = "left") -> FocusComparison:
    """Compare a new frame of a body with its kept one around the AF point ``point_px`` (raw px)."""
    t = thresholds or FocusThresholds()
    H, W = kept.main.shape
    window = focus_window(point_px, (W, H))
    d_kept, d_new = dp_disparity_px(kept, window, aux_view), dp_disparity_px(new, window, aux_view)
    s_kept, s_new = sharpness(kept, window), sharpness(new, window)
    ratio = s_new / max(s_kept, 1e-12)
    shift = _ecc_shift(_binned(kept.main, window, kept.black_level), _binned(new.main, window, new.black_level))
    if d_kept is None or d_new is None or shift is None:
        return FocusComparison(window, float("nan") if d_kept is None else d_kept, float("nan") if d_new is None else d_new,
                               ratio, (float("nan"), float("nan")), True, False,
                               "the focus window has too little texture to align its views: focus cannot be verified")
    shift_px = (2.0 * shift[0], 2.0 * shift[1])
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
    reason = "; ".join(reasons) or (f"DP disparity {d_kept:+.2f} -> {d_new:+.2f} raw px, sharpness x{ratio:.2f}, "
                                    f"shift ({shift_px[0]:+.2f}, {shift_px[1]:+.2f}) raw px: within the limits")
    return FocusComparison(window, d_kept, d_new, ratio, shift_px, moved, view_moved, reason)


__all__ = ["FocusThresholds", "FocusComparison", "compare_focus", "focus_window", "dp_disparity_px", "sharpness"]
