"""Atomic file writing and image I/O in the dataset's units.

Everything that writes a file goes through :func:`atomic_path` (write to a temporary name in the same
folder, then ``os.replace``), so a crash never leaves a half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile
from numpy.typing import NDArray

from .errors import BadInputError

cv2.setNumThreads(max(1, os.cpu_count() or 1))


def new_file_mode() -> int:
    """The mode a newly created file gets under this process's umask: ``0o666 & ~umask`` (0o644 under 022).

    ``tempfile.mkstemp`` creates its files 0600; :func:`atomic_path` gives them this mode before the rename,
    so every file a stage writes is readable as an ordinary file would be.
    """
    return 0o666 & ~_umask()


def new_dir_mode() -> int:
    """The mode a newly created folder gets under this process's umask: ``0o777 & ~umask`` (0o755 under 022).

    ``tempfile.mkdtemp`` creates its folders 0700; a folder written under a temporary name and renamed into
    place (a dataset pair) is given this mode first, so a shared dataset stays readable by others.
    """
    return 0o777 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike[str], suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``final``; on success give it the umask's mode and rename it to ``final``,
    on failure delete it.

    Args:
        final: the destination path.
        suffix: extension the temporary file needs (for writers that infer format from it, e.g. ".png").
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=suffix or final.suffix, dir=final.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, new_file_mode())
        os.replace(tmp_path, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (fsync before rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def write_json_atomic(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    write_bytes_atomic(path, (json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n").encode())


def finite_json(obj: Any) -> Any:
    """``obj`` with every non-finite float (NaN, inf) as None and numpy scalars as Python numbers, for
    :func:`write_json_atomic` (which writes strict JSON: no NaN)."""
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def read_json(path: str | os.PathLike[str]) -> Any:
    """Read a JSON file; a missing or malformed file raises :class:`BadInputError` naming it."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise BadInputError("file not found", where=path) from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BadInputError(f"not valid JSON ({exc})", where=path) from exc


def sha256_file(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file, streamed."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def to_uint16(image01: NDArray[np.floating]) -> NDArray[np.uint16]:
    """Linear float image in [0, 1] to uint16 (value * 65535, rounded, clipped)."""
    return np.clip(np.rint(np.asarray(image01, dtype=np.float64) * 65535.0), 0, 65535).astype(np.uint16)


def write_png16(path: str | os.PathLike[str], image: NDArray[np.uint16]) -> None:
    """Write a uint16 image (H, W) or RGB (H, W, 3) as a 16-bit PNG, atomically. RGB order in memory."""
    image = np.asarray(image)
    if image.dtype != np.uint16:
        raise BadInputError(f"16-bit PNG needs uint16 data, got {image.dtype}", where=path)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise BadInputError("could not write PNG", where=path)


def read_image_raw(path: str | os.PathLike[str]) -> NDArray[Any]:
    """Read a PNG/JPEG/TIFF as stored (any dtype); colour images come back in RGB order.

    Raises:
        BadInputError: the file is missing or cannot be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise BadInputError("file not found", where=path)
    if path.suffix.lower() in (".tif", ".tiff"):
        try:
            return np.asarray(tifffile.imread(path))
        except Exception as exc:  # tifffile raises many types for corrupt files
            raise BadInputError(f"cannot read TIFF ({exc})", where=path) from exc
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise BadInputError("cannot decode image (corrupt or unsupported)", where=path)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


def write_tiff_float32(path: str | os.PathLike[str], image: NDArray[np.floating]) -> None:
    """Write a single-channel float32 TIFF atomically (NaN preserved)."""
    with atomic_path(path, suffix=".tif") as tmp:
        tifffile.imwrite(tmp, np.asarray(image, dtype=np.float32))
