"""Shared measurements for the studio tests: point-source PSFs and their moments."""

from __future__ import annotations

import numpy as np

from dp5k_studio import EffectSet, LensSetting, render_dp

PITCH_MM = 36.0 / 288  # a 288 px wide output image


def lens(f_number: float = 1.8, focus_mm: float = 2000.0, pitch_mm: float = PITCH_MM) -> LensSetting:
    return LensSetting(85.0, f_number, focus_mm, pitch_mm)


def dot_views(depth_mm: float, lens_: LensSetting, effects: EffectSet | None = None, size: int = 129, full: bool = False,
              at: tuple[int, int] | None = None, shape: tuple[int, int] | None = None):
    """Render a single bright pixel on black at one depth: the (left, right[, full]) PSF images (H, W, 3)."""
    H, W = shape or (size, size)
    y, x = at or (H // 2, W // 2)
    img = np.zeros((H, W, 3), np.float32)
    img[y, x] = 1.0
    depth = np.full((H, W), depth_mm)
    return render_dp(img, depth, lens_, effects, full=full)


def moments(psf: np.ndarray) -> tuple[float, float, float, float, float]:
    """(mass, centroid x, centroid y, var x, var y) of a 2D non-negative image."""
    H, W = psf.shape
    m = float(psf.sum())
    yy, xx = np.mgrid[0:H, 0:W]
    cx = float((psf * xx).sum() / m)
    cy = float((psf * yy).sum() / m)
    vx = float((psf * (xx - cx) ** 2).sum() / m)
    vy = float((psf * (yy - cy) ** 2).sum() / m)
    return m, cx, cy, vx, vy


def textured(H: int, W: int, seed: int = 0) -> np.ndarray:
    """A band-limited random texture (H, W, 3) in [0.1, 0.9]."""
    import cv2

    rng = np.random.default_rng(seed)
    img = rng.random((H, W, 3)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 1.2)
    img = (img - img.min()) / (img.max() - img.min())
    return (0.1 + 0.8 * img).astype(np.float32)


def lowfreq_disparity_px(left: np.ndarray, right: np.ndarray, kmax: int = 4) -> float:
    """Centroid separation (right minus left, px, +x right) of the views' PSFs, from the phase slope of the
    cross-power spectrum at the lowest horizontal frequencies (as w -> 0, H_R/H_L -> exp(-i w dx)).

    Args:
        left, right: (H, W) views of a plane (one shift everywhere).
        kmax: highest horizontal frequency index used.
    """
    H, W = left.shape
    win = np.outer(np.hanning(H), np.hanning(W))
    Lf = np.fft.fft2((left - left.mean()) * win)
    Rf = np.fft.fft2((right - right.mean()) * win)
    S = np.conj(Lf) * Rf
    num = 0.0
    den = 0.0
    for k in range(1, kmax + 1):
        col = S[:, k]
        w = 2.0 * np.pi * k / W
        ph = np.angle(col.sum())
        num += -ph / w * abs(col.sum())
        den += abs(col.sum())
    return float(num / den)
