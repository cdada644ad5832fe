"""Pictures people would rather look at than read: contact sheets of pairs and colour-mapped depth maps.

``dp5k process`` writes a contact sheet per scene, ``dp5k import`` one per imported source, ``dp5k sl-depth`` a
depth preview. 8-bit PNGs for viewing only (gamma-encoded, colour-mapped); the data stay in the dataset's files.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from .io import write_bytes_atomic


def display_rgb(img: NDArray[np.float32], gain: float) -> NDArray[np.uint8]:
    """Linear (H, W, 3) RGB -> 8-bit BGR for viewing (sRGB-like gamma 1/2.2 after scaling by ``gain``)."""
    v = np.clip(img * gain, 0, 1) ** (1 / 2.2)
    return cv2.cvtColor((v * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)


def colormap(a: NDArray[np.float32], lo: float, hi: float, cmap: int) -> NDArray[np.uint8]:
    """(H, W) values mapped from [lo, hi] through an OpenCV colour map to 8-bit BGR; invalid pixels black (NaN, and
    0 for ``COLORMAP_TURBO``, the depth map's invalid value)."""
    ok = np.isfinite(a) & (a != 0) if cmap == cv2.COLORMAP_TURBO else np.isfinite(a)
    v = np.clip((np.nan_to_num(a) - lo) / max(hi - lo, 1e-9), 0, 1)
    out = cv2.applyColorMap((v * 255).astype(np.uint8), cmap)
    out[~ok] = 0
    return out


def contact_sheet(rows: Sequence[tuple[str, NDArray, NDArray, NDArray, NDArray, NDArray]], path: Path) -> None:
    """Write a PNG with one row per camera: sharp | left | right | depth (turbo, near = blue) | CoC (signed).

    Args:
        rows: (label, sharp, left, right, depth_mm (0 invalid), coc_px (NaN invalid)) per camera, linear RGB.
    """
    lines = []
    for label, sharp, left, right, depth, coc in rows:
        g = 0.8 / max(float(np.percentile(sharp, 99)), 1e-6)
        lo, hi = depth_range(depth)
        c = np.abs(coc[np.isfinite(coc)])
        cm = float(np.percentile(c, 99)) if c.size else 1.0
        tiles = [display_rgb(sharp, g), display_rgb(left, 2 * g), display_rgb(right, 2 * g),
                 colormap(depth.astype(np.float32), lo, hi, cv2.COLORMAP_TURBO),
                 colormap(coc.astype(np.float32), -cm, cm, cv2.COLORMAP_COOL)]
        row = np.hstack(tiles)
        cv2.putText(row, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        lines.append(row)
    write_png8(path, np.vstack(lines))


def depth_range(depth: NDArray[np.floating]) -> tuple[float, float]:
    """(1st, 99th) percentile of the valid (finite, > 0) depth, the colour map's range; (0, 1) without any."""
    d = depth[np.isfinite(depth) & (depth > 0)]
    return (float(np.percentile(d, 1)), float(np.percentile(d, 99))) if d.size else (0.0, 1.0)


def depth_preview(depth_m: NDArray[np.floating], path: Path, title: str = "") -> tuple[float, float]:
    """Write a colour-mapped depth map (turbo: near = blue, far = red; no depth = black) with its range in metres
    written on it; returns that range (m)."""
    lo, hi = depth_range(depth_m)
    img = colormap(np.where(np.isfinite(depth_m), depth_m, 0).astype(np.float32), lo, hi, cv2.COLORMAP_TURBO)
    bar = np.zeros((18, img.shape[1], 3), np.uint8)
    bar[:, :] = cv2.applyColorMap(np.linspace(0, 255, img.shape[1]).astype(np.uint8)[None], cv2.COLORMAP_TURBO)[0]
    text = f"{title}: {lo:.3g} (blue) - {hi:.3g} m, black: none" if title else f"{lo:.3g} (blue) - {hi:.3g} m, black: none"
    out = np.vstack([img, bar, np.zeros((18, img.shape[1], 3), np.uint8)])
    cv2.putText(out, text, (3, out.shape[0] - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    write_png8(path, out)
    return lo, hi


def write_png8(path: Path, bgr: NDArray[np.uint8]) -> None:
    """Write an 8-bit BGR (or gray) image as PNG, atomically."""
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    write_bytes_atomic(path, buf.tobytes())
