"""One imported DP capture in dataset units, the scene sources adapters yield, and the readers they share."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError
from dp5k_common.io import read_image_raw
from dp5k_common.transfer import srgb_to_linear

from .exposure import linearity_warning

F32 = NDArray[np.float32]
log = logging.getLogger(__name__)

CURVES = ("srgb", "linear")
"""Transfer curves an importer can undo: ``srgb`` (IEC 61966-2-1, what Canon DPP and most converters write)
and ``linear`` (the values are already proportional to light)."""


@dataclass
class Capture:
    """One DP capture (one camera, one f-number) in dataset units.

    Attributes:
        scene: scene id (splits never share one; tiles get ``<scene>_t<row><col>``).
        sharp, left, right: (H, W, 3) float32 linear; ``left + right`` ~ full-aperture blur of ``sharp``.
        depth_mm: (H, W) float32 z-depth, 0 = invalid.
        f_number, focus_distance_mm, focal_length_mm, pixel_pitch_mm: imaging parameters.
        camera: camera id.
        extra: extra params.json keys (source, licence, ``sharp_f_number``, measured exposure, ...).
        split: the source's own split (train / val / test) to keep, None = split by scene at random.
        focus_point_px: (x, y) in this capture's pixels, None = the image centre.
        frame_origin_px, frame_size: where this capture lies in its camera's full frame (x0, y0) and that
            frame's (W, H), in this capture's pixels, when the source itself is a crop (None = whole frame).
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
    split: str | None = None
    focus_point_px: tuple[float, float] | None = None
    frame_origin_px: tuple[int, int] | None = None
    frame_size: tuple[int, int] | None = None


@dataclass
class SceneSource:
    """One scene of a source layout, loaded only when written (a malformed scene fails alone).

    Attributes:
        scene: scene id as the source names it.
        where: the scene's folder (error messages name it).
        load: yields the scene's captures; raises :class:`BadInputError` naming the file on bad input.
        split: the source's own split of this scene (train / val / test), None = split by source at random.
    """

    scene: str
    where: Path
    load: Callable[[], Iterator[Capture]]
    split: str | None = None


def decode_curve(values01: NDArray[np.floating], curve: str) -> F32:
    """Undo the transfer curve ``curve`` (one of :data:`CURVES`) of values scaled to [0, 1]."""
    if curve == "srgb":
        return srgb_to_linear(values01).astype(np.float32, copy=False)
    if curve == "linear":
        return np.asarray(values01, dtype=np.float32)
    raise BadInputError(f"unknown transfer curve {curve!r} (known: {', '.join(CURVES)})")


@dataclass(frozen=True)
class Stored:
    """How an image file stored its values.

    Attributes:
        bits: 8 or 16.
        gray: the file had one channel (replicated to RGB on load).
    """

    bits: int
    gray: bool


def read_rgb01(path: Path) -> tuple[F32, Stored]:
    """An 8- or 16-bit RGB (or gray, replicated) image scaled to [0, 1] as stored, and how it was stored.

    Raises:
        BadInputError: missing, unreadable, float or otherwise not 8/16-bit, or not 1/3/4 channels.
    """
    img = read_image_raw(path)
    if img.dtype == np.uint8:
        bits = 8
    elif img.dtype == np.uint16:
        bits = 16
    else:
        raise BadInputError(f"expected an 8- or 16-bit image, got {img.dtype}", where=path)
    gray = img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1)
    if gray:
        img = np.repeat(img.reshape(img.shape[0], img.shape[1], 1), 3, axis=2)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim != 3 or img.shape[2] != 3:
        raise BadInputError(f"expected an RGB or gray image, got shape {img.shape}", where=path)
    return (img.astype(np.float32) / float((1 << bits) - 1)).astype(np.float32), Stored(bits, gray)


def read_linear_rgb(path: Path, curve: str) -> tuple[F32, Stored]:
    """:func:`read_rgb01` then :func:`decode_curve`: linear (H, W, 3) float32 and how the file stored it."""
    img, stored = read_rgb01(path)
    return decode_curve(img, curve), stored


class Frames:
    """Reads the images of one capture (one pair) and remembers how each was stored, for :meth:`warnings`.

    Args:
        curve: the transfer curve to undo (:data:`CURVES`).
    """

    def __init__(self, curve: str) -> None:
        self.curve = curve
        self.stored: dict[str, Stored] = {}

    def read(self, name: str, path: Path) -> F32:
        """The linear (H, W, 3) image at ``path``, remembered under ``name`` (a file name for the messages)."""
        img, self.stored[name] = read_linear_rgb(path, self.curve)
        return img

    def note(self, name: str, stored: Stored) -> None:
        """Remember an image read before (a sharp frame shared by several f-numbers)."""
        self.stored[name] = stored

    @property
    def bits(self) -> int:
        """The bit depth of the pair (the highest of its files)."""
        return max(s.bits for s in self.stored.values())

    def warnings(self) -> list[str]:
        """One line per inconsistency between the files of this pair: a gray frame beside colour ones (its colour
        is lost: a gray sharp frame cannot predict colour views), and 8-bit files mixed with 16-bit ones (often
        two different converters, with different curves or scales)."""
        out = []
        gray = sorted(n for n, s in self.stored.items() if s.gray)
        colour = sorted(n for n, s in self.stored.items() if not s.gray)
        if gray and colour:
            out.append(f"gray {', '.join(gray)} beside colour {', '.join(colour)}: the gray frame was copied into R, "
                       f"G and B, so colour is lost there")
        bits = {n: s.bits for n, s in self.stored.items()}
        if len(set(bits.values())) > 1:
            by = {b: sorted(n for n, v in bits.items() if v == b) for b in sorted(set(bits.values()))}
            out.append("8-bit and 16-bit files mixed in one pair (" + "; ".join(f"{b}-bit: {', '.join(n)}" for b, n in by.items())
                       + "): probably two converters, with different curves or scales")
        return out

    def settle(self, left: F32, right: F32, sharp: F32, combined: F32 | None, residual: float, strict: bool,
               where: Path | str) -> list[str]:
        """:meth:`warnings` plus, with a combined frame, :func:`~.exposure.linearity_warning` (the curve does not
        linearise: ``left + right`` against ``combined``, ``residual`` = ``Exposure.combined_residual``), logged;
        with ``strict`` the first is a :class:`BadInputError` (the scene is not imported). Returns them for
        params.json ``input_warnings`` and the import report."""
        warns = self.warnings()
        if combined is not None and (w := linearity_warning(left, right, sharp, combined, self.curve, residual)):
            warns.append(w)
        if warns and strict:
            raise BadInputError(f"{warns[0]} (--strict)", where=where)
        for w in warns:
            log.warning("%s: %s", where, w)
        return warns


def read_rgb8(path: Path) -> NDArray[np.uint8]:
    """An 8-bit RGB image (RGB order); a clear error for a missing, unreadable or non-8-bit file."""
    if not path.is_file():
        raise BadInputError("missing file", where=path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInputError("not a readable image", where=path)
    if img.dtype != np.uint8:
        raise BadInputError(f"expected 8-bit, got {img.dtype}", where=path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth_mm_u16(path: Path) -> F32:
    """A single-channel 16-bit depth map in millimetres (0 = invalid) as float32 mm."""
    d = read_image_raw(path)
    if d.dtype != np.uint16 or d.ndim != 2:
        raise BadInputError(f"expected single-channel 16-bit depth in mm, got {d.dtype} with shape {d.shape}", where=path)
    return d.astype(np.float32)


def same_size(where: Path, **images: NDArray[Any]) -> tuple[int, int]:
    """(H, W) shared by all ``images``; a BadInputError naming them when they differ."""
    shapes = {name: tuple(np.shape(a)[:2]) for name, a in images.items()}
    if len(set(shapes.values())) != 1:
        raise BadInputError("images differ in size: " + ", ".join(f"{k} {v[1]}x{v[0]}" for k, v in shapes.items()),
                            where=where)
    return next(iter(shapes.values()))  # type: ignore[return-value]
