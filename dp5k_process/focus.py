r"""Focus distance (paper Eq. 5): Huber-skip robust mean of depth in a window around the focus point.

.. math:: F = \mathrm{mean}\left(W \;\middle|\; \left|\frac{W - \mathrm{median}(W)}{\mathrm{MAD}(W)}\right| \le \tau\right)

* MAD is the **normalised** median absolute deviation, ``1.4826 * median(|W - median(W)|)`` (a consistent
  estimate of sigma for Gaussian data), so tau = 3.5 keeps values within 3.5 sigma. (With the raw MAD the same tau
  would be about 2.36 sigma and drop ~1.8 % of clean samples.) ``scaled_mad=False`` selects the raw MAD.
* MAD = 0 (more than half the window has the same depth): the kept set is the values equal to the median, so
  F = median(W).
* Only valid depth (finite, > 0) enters W; a window with no valid depth is an error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError, StageError

MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class FocusConfig:
    """Attributes:
        window_px: (width, height) of the window in output pixels (paper 30 x 20; released code 60 x 40).
        tau: Huber-skip threshold (3.5).
        scaled_mad: normalise the MAD by 1.4826 (default).
    """

    window_px: tuple[int, int] = (30, 20)
    tau: float = 3.5
    scaled_mad: bool = True


def huber_skip_mean(values: NDArray[np.floating], tau: float = 3.5, scaled_mad: bool = True) -> float:
    """Mean of the values within ``tau`` (normalised) MADs of the median; the median when MAD = 0."""
    w = np.asarray(values, dtype=np.float64).ravel()
    w = w[np.isfinite(w)]
    if w.size == 0:
        raise StageError("no valid values for the Huber-skip mean")
    med = float(np.median(w))
    mad = float(np.median(np.abs(w - med))) * (MAD_TO_SIGMA if scaled_mad else 1.0)
    if mad == 0.0:
        return med
    keep = np.abs(w - med) / mad <= tau
    return float(w[keep].mean())


def focus_window(depth: NDArray[np.floating], point_xy: tuple[float, float], window_px: tuple[int, int]
                 ) -> NDArray[np.floating]:
    """The (h, w) window of ``depth`` centred at ``point_xy`` (clipped at the image border).

    Raises:
        BadInputError: the point lies outside the image.
    """
    H, W = depth.shape
    x, y = point_xy
    if not (0 <= x < W and 0 <= y < H):
        raise BadInputError(f"focus point ({x:.1f}, {y:.1f}) lies outside the {W}x{H} image")
    ww, wh = window_px
    x0 = int(round(x - ww / 2))
    y0 = int(round(y - wh / 2))
    return depth[max(0, y0):min(H, y0 + wh), max(0, x0):min(W, x0 + ww)]


def focus_distance(depth: NDArray[np.floating], point_xy: tuple[float, float], cfg: FocusConfig = FocusConfig()
                   ) -> float:
    """Eq. 5 on a depth map (any unit; 0 or NaN invalid): the focus distance in the depth's unit.

    Raises:
        BadInputError: focus point outside the image.
        StageError: no valid depth in the window.
    """
    win = np.asarray(focus_window(depth, point_xy, cfg.window_px), dtype=np.float64)
    vals = win[np.isfinite(win) & (win > 0)]
    if vals.size == 0:
        raise StageError(f"the {cfg.window_px[0]}x{cfg.window_px[1]} focus window at "
                         f"({point_xy[0]:.0f}, {point_xy[1]:.0f}) has no valid depth")
    return huber_skip_mean(vals, cfg.tau, cfg.scaled_mad)
