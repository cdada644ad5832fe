"""The sRGB transfer curve (IEC 61966-2-1): images that others encoded for display, decoded to linear light.

dp5k's own images are linear (docs/data-format.md); camera software (Canon DPP) and RGBD datasets write sRGB.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def srgb_to_linear(values01: NDArray) -> NDArray[np.floating]:
    """Inverse transfer: sRGB-encoded values in [0, 1] -> linear [0, 1].

    uint8 input is scaled by 1/255 first (float32 result); float input keeps its precision; other dtypes are
    read as float64.
    """
    c = np.asarray(values01)
    if c.dtype == np.uint8:
        c = c.astype(np.float32) / np.float32(255.0)
    elif not np.issubdtype(c.dtype, np.floating):
        c = c.astype(np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(c.dtype, copy=False)


def linear_to_srgb(linear01: NDArray) -> NDArray[np.float32]:
    """Forward transfer (for writing test layouts and previews): linear [0, 1] (clipped) -> sRGB [0, 1], float32."""
    c = np.clip(np.asarray(linear01, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)
