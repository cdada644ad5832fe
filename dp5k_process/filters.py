"""Depth-map filtering (paper section 3.5): hole closing, statistical outlier removal, valid-only median, Eq. 3.

Depth maps here are (H, W) float32 in metres with NaN = invalid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from .grid_outliers import grid_outlier_mask


@dataclass(frozen=True)
class FilterConfig:
    """Settings of the filter chain.

    Attributes:
        close_px: side of the square structuring element of the dilation-erosion (closing), pixels.
        sor_neighbors, sor_std_ratio: Open3D ``remove_statistical_outlier`` (paper [21]; 20, 2.0).
        sor_method: ``"grid"``: the same statistic with the neighbours chosen on the pixel grid within
            ``sor_window_px`` x ``sor_window_px`` (``dp5k_process.grid_outliers``: linear cost; 1.8 s against
            Open3D's 105 s on 7.5 M points in ``bench_process.py`` part C); ``"open3d"``: Open3D's KD-tree.
        sor_window_px: odd window side of the grid method, pixels.
        median_px: side of the valid-only median window (odd), pixels.
        fill_steps: number of steps of Eq. 3 (paper: i = 1..3, i.e. scales 1, 1/2, 1/4; 4 adds 1/8). The
            pipeline adds one coarser step for each of these scales whose projector pixel is smaller than a
            camera pixel (``dp5k_process.pipeline.fill_steps_for``), up to the decoded scales.
    """

    close_px: int = 3
    sor_neighbors: int = 20
    sor_std_ratio: float = 2.0
    sor_method: str = "grid"
    sor_window_px: int = 7
    median_px: int = 5
    fill_steps: int = 3


def close_holes(depth_m: NDArray[np.float32], close_px: int = 3) -> NDArray[np.float32]:
    """Morphological dilation then erosion of the valid mask; the holes it closes get the mean of their valid
    neighbours in the same window (so no depth is invented outside small holes)."""
    if close_px <= 1:
        return depth_m
    valid = np.isfinite(depth_m)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (close_px, close_px))
    closed = cv2.erode(cv2.dilate(valid.astype(np.uint8), k), k).astype(bool)
    holes = closed & ~valid
    if not holes.any():
        return depth_m
    d = np.where(valid, depth_m, 0).astype(np.float32)
    num = cv2.boxFilter(d, -1, (close_px, close_px), normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(valid.astype(np.float32), -1, (close_px, close_px), normalize=False,
                        borderType=cv2.BORDER_CONSTANT)
    out = depth_m.copy()
    fill = holes & (den > 0)
    out[fill] = num[fill] / den[fill]
    return out


def backproject(depth_m: NDArray[np.float32], rays: NDArray[np.float32]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """3D points (N, 3) metres of the valid pixels, ``X = z (x_n, y_n, 1)``, and the valid mask (H, W)."""
    valid = np.isfinite(depth_m)
    z = depth_m[valid].astype(np.float64)
    r = rays[valid].astype(np.float64)
    return np.column_stack([r[:, 0] * z, r[:, 1] * z, z]), valid


def statistical_outliers(depth_m: NDArray[np.float32], rays: NDArray[np.float32], nb_neighbors: int = 20,
                         std_ratio: float = 2.0) -> NDArray[np.float32]:
    """Back-project to 3D, run Open3D's ``remove_statistical_outlier``, invalidate the removed pixels."""
    pts, valid = backproject(depth_m, rays)
    if pts.shape[0] <= nb_neighbors:
        return depth_m
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, keep = pc.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    keep_mask = np.zeros(pts.shape[0], bool)
    keep_mask[np.asarray(keep, dtype=np.int64)] = True
    out = depth_m.copy()
    ys, xs = np.nonzero(valid)
    out[ys[~keep_mask], xs[~keep_mask]] = np.nan
    return out


MEDIAN_CHUNK_PX = 65536
"""Pixels per chunk of the valid-only median's stack-and-sort path (a (chunk, ksize**2) stack)."""


def valid_median(depth_m: NDArray[np.float32], ksize: int = 5, chunk_px: int = MEDIAN_CHUNK_PX) -> NDArray[np.float32]:
    """Median over the valid pixels of each ``ksize`` x ``ksize`` window, at valid pixels only.

    Where the whole window is valid (most of a depth map) this is ``cv2.medianBlur`` (float input: ksize 3 or
    5). The pixels whose window holds invalid pixels or leaves the image (edges of the valid region, a few %)
    get their ksize^2 neighbours gathered into a stack, sorted (NaN sorts last) and the median of the n valid
    entries taken, ``chunk_px`` pixels at a time.
    """
    if ksize <= 1:
        return depth_m
    r = ksize // 2
    H, W = depth_m.shape
    valid = np.isfinite(depth_m)
    d = np.where(valid, depth_m, 0).astype(np.float32)
    out = np.full((H, W), np.nan, np.float32)
    if ksize in (3, 5):
        n_valid = cv2.boxFilter(valid.astype(np.float32), -1, (ksize, ksize), normalize=False,
                                borderType=cv2.BORDER_CONSTANT)
        full = valid & (n_valid > ksize * ksize - 0.5)
        out[full] = cv2.medianBlur(d, ksize)[full]
        ys, xs = np.nonzero(valid & ~full)
    else:
        ys, xs = np.nonzero(valid)
    pad = np.pad(np.where(valid, d, np.nan), r, constant_values=np.nan).ravel()
    Wp = W + 2 * r
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    off = (dy * Wp + dx).ravel()
    for i in range(0, ys.size, chunk_px):
        y, x = ys[i:i + chunk_px], xs[i:i + chunk_px]
        stack = np.take(pad, ((y + r) * Wp + (x + r))[:, None] + off)
        stack.sort(axis=1)
        n = np.isfinite(stack).sum(1)
        lo = np.take_along_axis(stack, ((n - 1) // 2)[:, None], 1)[:, 0]
        hi = np.take_along_axis(stack, (n // 2)[:, None], 1)[:, 0]
        out[y, x] = 0.5 * (lo + hi)
    return out


def filter_depth(depth_m: NDArray[np.float32], rays: NDArray[np.float32], cfg: FilterConfig = FilterConfig()
                 ) -> NDArray[np.float32]:
    """The per-scale chain: close small holes, statistical outlier removal in 3D, valid-only median."""
    d = close_holes(depth_m, cfg.close_px)
    if cfg.sor_method == "open3d":
        d = statistical_outliers(d, rays, cfg.sor_neighbors, cfg.sor_std_ratio)
    elif cfg.sor_method == "grid":
        d = np.where(grid_outlier_mask(d, rays, cfg.sor_neighbors, cfg.sor_std_ratio, cfg.sor_window_px), np.nan, d)
    else:
        raise ValueError(f"unknown outlier filter {cfg.sor_method!r} (grid or open3d)")
    return valid_median(d, cfg.median_px)


def recursive_fill(depths_m: Sequence[NDArray[np.float32]], steps: int | None = None) -> NDArray[np.float32]:
    r"""Eq. 3: :math:`D_i = D_{i-1} + M_i \odot D_{s_i}`, :math:`D_0 = 0`, :math:`M_i` = invalid pixels of
    :math:`D_{i-1}`, scales in the given order (finest first), for i = 1..steps. Returns NaN where still invalid."""
    steps = len(depths_m) if steps is None else min(steps, len(depths_m))
    out = np.zeros_like(depths_m[0])
    for i in range(steps):
        d = np.nan_to_num(depths_m[i], nan=0.0)
        out = out + (out == 0) * d
    out[out <= 0] = np.nan
    return out
