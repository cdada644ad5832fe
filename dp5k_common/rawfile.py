"""Dual Pixel RAW files: write a Canon-style two-frame DNG, read both frames back through rawpy/LibRaw.

A Canon Dual Pixel RAW holds two equal-size raw images: frame 0 is the main image (both photodiodes of
every pixel summed, A+B), frame 1 one photodiode (A). The other view is ``B = (main - black) - (aux - black)``.
LibRaw exposes the frames through ``shot_select`` (it counts raw IFDs of equal size, ``raw_count == 2``).

Pitfall (verified with rawpy 0.28 / LibRaw 0.22.2, see ``tests/process/test_rawfile.py``):
``rawpy.imread(path, shot_select=1)`` returns **frame 0** because it sets ``shot_select`` after
``open_file``. The frame must be chosen *before* opening: ``RawPy(); set_unpack_params(shot_select=i);
open_file(path); unpack()`` -- which is what :func:`read_dual_pixel` does.

The simulated camera bodies write their files with :func:`write_dual_pixel_dng`; the real rig writes CR2
files, which :func:`read_dual_pixel` opens the same way (same LibRaw frame-selection code).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import rawpy
import tifffile
from numpy.typing import NDArray

from .errors import BadInputError
from .io import atomic_path

log = logging.getLogger(__name__)

CANON_MAKE = "Canon"
CANON_MODEL = "Canon EOS 5D Mark IV"
_PHOTOMETRIC_CFA = 32803
_CFA_CODES = {"R": 0, "G": 1, "B": 2}


@dataclass
class DualPixelFrames:
    """The two raw frames of one Dual Pixel RAW file.

    Attributes:
        main: uint16 (H, W) Bayer mosaic, both photodiodes summed (frame 0), raw counts incl. black.
        aux: uint16 (H, W) Bayer mosaic, one photodiode (frame 1), raw counts incl. black.
        black_level: black offset in raw counts (same for both frames).
        white_level: saturation level in raw counts.
        wb_gains: as-shot white-balance multipliers (r, g, b), g normalised to 1.
        cfa_pattern: the 2x2 colour filter layout as a string, row-major, e.g. ``"RGGB"``.
        metadata: the JSON metadata stored in the file's ImageDescription (empty for camera files).
    """

    main: NDArray[np.uint16]
    aux: NDArray[np.uint16]
    black_level: int
    white_level: int
    wb_gains: tuple[float, float, float]
    cfa_pattern: str
    metadata: dict[str, Any] = field(default_factory=dict)

    def other_view(self) -> NDArray[np.float32]:
        """The complementary photodiode, ``(main - black) - (aux - black)``, float32 (H, W) in raw counts."""
        return self.main.astype(np.float32) - self.aux.astype(np.float32)


def _rational(x: float) -> tuple[int, int]:
    f = Fraction(float(x)).limit_denominator(1 << 20)
    return f.numerator, f.denominator


def write_dual_pixel_dng(
    path: str | os.PathLike[str],
    main: NDArray[np.uint16],
    aux: NDArray[np.uint16],
    black_level: int,
    white_level: int,
    wb_gains: tuple[float, float, float],
    metadata: dict[str, Any] | None = None,
) -> None:
    """Write a two-frame Dual Pixel DNG (Make Canon, Model EOS 5D Mark IV, CFA RGGB), atomically.

    Args:
        path: destination ``.dng``.
        main: uint16 (H, W) Bayer RGGB mosaic, frame 0 (A+B), raw counts including black.
        aux: uint16 (H, W) Bayer RGGB mosaic, frame 1 (one photodiode), same size.
        black_level: black offset in raw counts.
        white_level: saturation in raw counts (16383 for 14-bit).
        wb_gains: white-balance multipliers (r, g, b); stored as AsShotNeutral = 1 / gain (g-normalised).
        metadata: JSON-serialisable dict stored in the ImageDescription of frame 0.
    """
    main = np.ascontiguousarray(main)
    aux = np.ascontiguousarray(aux)
    if main.dtype != np.uint16 or aux.dtype != np.uint16:
        raise BadInputError(f"raw frames must be uint16, got {main.dtype}/{aux.dtype}", where=path)
    if main.ndim != 2 or main.shape != aux.shape:
        raise BadInputError(f"raw frames must be equal-size 2-D, got {main.shape}/{aux.shape}", where=path)
    if main.shape[0] % 2 or main.shape[1] % 2:
        raise BadInputError(f"raw frame size must be even for a 2x2 CFA, got {main.shape}", where=path)
    g = float(wb_gains[1])
    neutral = [g / float(v) for v in wb_gains]
    ident = [1, 0, 0, 0, 1, 0, 0, 0, 1]
    ifd0_tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, CANON_MODEL, True),  # UniqueCameraModel
        (271, "s", 0, CANON_MAKE, True),  # Make
        (272, "s", 0, CANON_MODEL, True),  # Model
        (50728, "2I", 3, tuple(v for n in neutral for v in _rational(n)), True),  # AsShotNeutral
        (50721, "2i", 9, tuple(v for n in ident for v in _rational(n)), True),  # ColorMatrix1 (camera = XYZ)
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1 = D65
    ]
    raw_tags = [
        (33421, "H", 2, (2, 2), False),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), False),  # CFAPattern RGGB
        (50714, "I", 1, int(black_level), False),  # BlackLevel
        (50717, "I", 1, int(white_level), False),  # WhiteLevel
    ]
    description = json.dumps(metadata or {}, sort_keys=True)
    with atomic_path(path, suffix=".dng") as tmp:
        with tifffile.TiffWriter(tmp) as tw:
            tw.write(main, photometric=_PHOTOMETRIC_CFA, subfiletype=0, metadata=None,
                     description=description, extratags=ifd0_tags + raw_tags)
            tw.write(aux, photometric=_PHOTOMETRIC_CFA, subfiletype=0, metadata=None, extratags=raw_tags)


def _open_frame(path: Path, shot: int) -> rawpy.RawPy:
    """Open frame ``shot`` of a raw file: shot_select is set BEFORE open_file (imread sets it too late)."""
    raw = rawpy.RawPy()
    raw.set_unpack_params(shot_select=shot)
    raw.open_file(str(path))
    raw.unpack()
    return raw


def _cfa_string(raw: rawpy.RawPy) -> str:
    desc = raw.color_desc.decode("ascii")  # e.g. "RGBG": index -> colour letter
    return "".join(desc[int(i)] for i in np.asarray(raw.raw_pattern).ravel())


def _read_description(path: Path) -> dict[str, Any]:
    try:
        with tifffile.TiffFile(path) as tf:
            text = tf.pages[0].description
        obj = json.loads(text) if text else {}
        return obj if isinstance(obj, dict) else {}
    except Exception:  # noqa: BLE001 - camera CR2 files carry no JSON description
        return {}


def read_frame(path: str | os.PathLike[str], shot: int = 0) -> tuple[NDArray[np.uint16], int, int]:
    """One raw frame only (``shot`` 0 = main, 1 = aux), for images where the DP split is not needed
    (structured light, ChArUco): ``(mosaic uint16 (H, W), black_level, white_level)``.

    Raises:
        BadInputError: missing, unreadable or truncated file, or no such frame.
    """
    path = Path(path)
    if not path.is_file():
        raise BadInputError("raw file not found", where=path)
    try:
        raw = _open_frame(path, shot)
    except rawpy.LibRawRequestForNonexistentImageError as exc:
        raise BadInputError(f"raw file has no frame {shot}", where=path) from exc
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise BadInputError(f"unreadable or truncated raw file ({type(exc).__name__}: {exc})", where=path) from exc
    with raw:
        try:
            img = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
        except (rawpy.LibRawError, ValueError) as exc:
            raise BadInputError(f"unreadable raw data ({exc})", where=path) from exc
        return img, int(np.round(np.mean(raw.black_level_per_channel))), int(raw.white_level)


def read_dual_pixel(path: str | os.PathLike[str]) -> DualPixelFrames:
    """Read both frames of a Dual Pixel RAW file (DNG from the simulated body, CR2 from the 5D IV).

    Raises:
        BadInputError: the file is missing, unreadable or truncated, or is not a Dual Pixel RAW
            (LibRaw finds fewer than two equal-size raw frames, or the two frames are identical).
    """
    path = Path(path)
    if not path.is_file():
        raise BadInputError("raw file not found", where=path)
    frames: list[NDArray[np.uint16]] = []
    info: dict[str, Any] = {}
    for shot in (0, 1):
        try:
            raw = _open_frame(path, shot)
        except rawpy.LibRawRequestForNonexistentImageError as exc:
            raise BadInputError("not a Dual Pixel RAW: it holds only one raw frame", where=path) from exc
        except (rawpy.LibRawError, OSError, ValueError) as exc:
            raise BadInputError(f"unreadable or truncated raw file ({type(exc).__name__}: {exc})",
                                where=path) from exc
        with raw:
            try:
                img = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
            except (rawpy.LibRawError, ValueError) as exc:
                raise BadInputError(f"unreadable raw data ({exc})", where=path) from exc
            frames.append(img)
            if shot == 0:
                wb = [float(v) for v in raw.camera_whitebalance[:3]]
                if wb[1] <= 0:
                    wb = [1.0, 1.0, 1.0]
                info = dict(
                    black_level=int(np.round(np.mean(raw.black_level_per_channel))),
                    white_level=int(raw.white_level),
                    wb_gains=(wb[0] / wb[1], 1.0, wb[2] / wb[1]),
                    cfa_pattern=_cfa_string(raw),
                )
    try:  # a third equal-size frame means this is not a two-frame Dual Pixel RAW
        with _open_frame(path, 2):
            raise BadInputError("not a Dual Pixel RAW: more than two raw frames", where=path)
    except rawpy.LibRawRequestForNonexistentImageError:
        pass  # exactly two raw frames: the expected case
    except rawpy.LibRawError as exc:
        # LibRaw lists a third image but cannot decode it as a raw frame, so it is not a third DP frame: the
        # file is still read as two frames, and the oddity is reported rather than hidden.
        log.warning("%s: a third raw image is present but unreadable (%s: %s); using frames 0 and 1", path, type(exc).__name__, exc)
    main, aux = frames
    if main.shape != aux.shape:
        raise BadInputError(f"Dual Pixel frames differ in size {main.shape} vs {aux.shape}", where=path)
    if np.array_equal(main, aux):
        raise BadInputError("not a Dual Pixel RAW: frame 1 equals frame 0 (frame selection failed)", where=path)
    return DualPixelFrames(main=main, aux=aux, metadata=_read_description(path), **info)
