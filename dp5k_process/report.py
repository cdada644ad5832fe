"""Per-scene report: JSON numbers and a contact-sheet PNG (sharp, left, right, depth, CoC per camera)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.io import write_bytes_atomic


def _display(img: NDArray[np.float32], gain: float) -> NDArray[np.uint8]:
    """Linear RGB -> 8-bit BGR for viewing (sRGB-like gamma 1/2.2 after scaling by ``gain``)."""
    v = np.clip(img * gain, 0, 1) ** (1 / 2.2)
    return cv2.cvtColor((v * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)


def _colormap(a: NDArray[np.float32], lo: float, hi: float, cmap: int) -> NDArray[np.uint8]:
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
        d = depth[depth > 0]
        lo, hi = (float(np.percentile(d, 1)), float(np.percentile(d, 99))) if d.size else (0.0, 1.0)
        c = np.abs(coc[np.isfinite(coc)])
        cm = float(np.percentile(c, 99)) if c.size else 1.0
        tiles = [_display(sharp, g), _display(left, 2 * g), _display(right, 2 * g),
                 _colormap(depth.astype(np.float32), lo, hi, cv2.COLORMAP_TURBO),
                 _colormap(coc.astype(np.float32), -cm, cm, cv2.COLORMAP_COOL)]
        row = np.hstack(tiles)
        cv2.putText(row, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        lines.append(row)
    ok, buf = cv2.imencode(".png", np.vstack(lines))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    write_bytes_atomic(path, buf.tobytes())
