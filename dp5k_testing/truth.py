"""Ground-truth helpers for the processing accuracy tests (studio truth at raw resolution)."""

from __future__ import annotations

import numpy as np


def seen_by_both(gt0: dict, gt1: dict, cell_px: float = 2.0) -> np.ndarray:
    """(H, W) bool: camera-0 pixels lit by the projector whose projector point camera 1 also sees.

    A camera-0 pixel counts when camera 1 has a pixel whose projector coordinate falls in the same
    ``cell_px`` x ``cell_px`` projector cell (or an adjacent one)."""
    p0, p1 = gt0["proj_xy"], gt1["proj_xy"]
    Wp, Hp = gt0["projector"]["width"], gt0["projector"]["height"]
    gw, gh = int(np.ceil(Wp / cell_px)) + 2, int(np.ceil(Hp / cell_px)) + 2
    grid = np.zeros((gh, gw), bool)
    ok1 = np.isfinite(p1[..., 0])
    gx = np.clip((p1[..., 0][ok1] / cell_px).astype(int) + 1, 0, gw - 1)
    gy = np.clip((p1[..., 1][ok1] / cell_px).astype(int) + 1, 0, gh - 1)
    grid[gy, gx] = True
    grid = grid | np.roll(grid, 1, 0) | np.roll(grid, -1, 0)
    grid = grid | np.roll(grid, 1, 1) | np.roll(grid, -1, 1)
    ok0 = np.isfinite(p0[..., 0])
    out = np.zeros(ok0.shape, bool)
    gx0 = np.clip((p0[..., 0][ok0] / cell_px).astype(int) + 1, 0, gw - 1)
    gy0 = np.clip((p0[..., 1][ok0] / cell_px).astype(int) + 1, 0, gh - 1)
    out[ok0] = grid[gy0, gx0]
    return out


def half(a: np.ndarray, reduce: str = "all") -> np.ndarray:
    """2x2 block reduction of a raw-resolution map to the half-size output grid."""
    H, W = a.shape[:2]
    b = a[: H - H % 2, : W - W % 2].reshape(H // 2, 2, W // 2, 2, *a.shape[2:])
    return b.all(axis=(1, 3)) if reduce == "all" else b.mean(axis=(1, 3))
