"""One imported full-frame DP capture in dataset units, and the image readers adapters share."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError

F32 = NDArray[np.float32]


@dataclass
class Capture:
    """One full-frame DP capture in dataset units.

    Attributes:
        scene: scene id (splits never share one; tiles get ``<scene>_t<row><col>``).
        sharp, left, right: (H, W, 3) float32 linear; ``left + right`` ~ full-aperture blur of ``sharp``.
        depth_mm: (H, W) float32 z-depth, 0 = invalid.
        f_number, focus_distance_mm, focal_length_mm, pixel_pitch_mm: imaging parameters.
        camera: camera id.
        extra: extra params.json keys (source, licence, ...).
    """

    scene: str
    sharp: F32
    left: F32
    right: F32
    depth_mm: F32
    f_number: float
    focus_distance_mm: float
    focal_length_mm: float
    pixel_pitch_mm: float
    camera: str = "cam0"
    extra: dict[str, Any] = field(default_factory=dict)


def srgb_to_linear(img_u8: NDArray[np.uint8]) -> F32:
    """IEC 61966-2-1 inverse transfer: 8-bit sRGB -> linear [0, 1]."""
    c = img_u8.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_rgb8(path: Path) -> NDArray[np.uint8]:
    """An 8-bit RGB image (RGB order); a clear error for a missing or unreadable file."""
    if not path.is_file():
        raise BadInputError("missing file", where=path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInputError("not a readable image", where=path)
    if img.dtype != np.uint8:
        raise BadInputError(f"expected 8-bit, got {img.dtype}", where=path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
