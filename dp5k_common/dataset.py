"""The processed dataset format, version 1: the contract every dp5k stage reads and writes.

Layout (docs/data-format.md is the normative description)::

    ROOT/dataset.json        {"format": "dp5k-dataset", "version": 1,
                              "splits": {"train": [ids], "val": [ids], "test": [ids]}, ...extra keys}
    ROOT/pairs/<pair_id>/sharp.png   uint16 RGB, linear, value / 65535 (f/22, exposure-matched)
                         left.png    uint16 RGB, linear, same scale
                         right.png   uint16 RGB, linear, same scale
                         depth.png   uint16 single channel, millimetres, 0 = invalid
                         coc.tif     float32 single channel, signed CoC diameter in output pixels,
                                     NaN where depth is invalid
                         depth.tif   optional float32 single channel, millimetres (sub-mm depth); read in
                                     place of depth.png's values where present (depth.png stays)
                         params.json see :class:`PairParams`

Reading is lazy: :class:`DatasetReader` validates ``dataset.json`` on open and each pair when it is
loaded. Every problem raises :class:`~dp5k_common.errors.DatasetFormatError` naming the pair and file.
Writing is atomic per pair: a pair is written into a hidden temporary folder and renamed into place,
so an interrupted writer never leaves a half-written pair under its final name.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import BadInputError, DatasetFormatError
from .io import new_dir_mode, read_image_raw, read_json, to_uint16, write_json_atomic, write_png16, write_tiff_float32

FORMAT_NAME = "dp5k-dataset"
FORMAT_VERSION = 1
SPLITS: tuple[str, ...] = ("train", "val", "test")
PAIR_FILES: tuple[str, ...] = ("sharp.png", "left.png", "right.png", "depth.png", "coc.tif", "params.json")
DEPTH_TIF = "depth.tif"
"""Optional per-pair file: float32 depth in mm, the sub-millimetre values behind depth.png's whole mm."""
DEPTH_TIF_TOL_MM = 0.501
"""Largest |depth.tif - depth.png| (mm) where depth.png is valid and below its 65535 mm ceiling: rounding to
whole mm moves a value by at most 0.5 mm; more means the two files describe different depths."""
_PAIR_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


def _check_pair_id(pair_id: str, where: str) -> None:
    if not isinstance(pair_id, str) or not _PAIR_ID.match(pair_id):
        raise DatasetFormatError(
            f"pair id {pair_id!r} is not a folder-safe name (letters, digits, '.', '_', '-')", where=where
        )


SHARP_F_NUMBER = 22.0
"""The f-number of a pair's ``sharp`` image when params.json does not say (``sharp_f_number``)."""


def _check_frame_geometry(obj: Mapping[str, Any], size: tuple[int, int], where: str) -> None:
    """The optional tile keys: both or neither, integers, and the (W, H) = ``size`` crop inside the frame."""
    keys = ("crop_origin_px", "full_image_size")
    present = [k for k in keys if k in obj]
    if not present:
        return
    if len(present) == 1:
        raise DatasetFormatError(f"'{present[0]}' needs '{(set(keys) - set(present)).pop()}' too (a tile states both)", where=where)
    vals = []
    for key in keys:
        v = obj[key]
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x != int(x) for x in v)):
            raise DatasetFormatError(f"'{key}' must be a list of 2 integers, got {v!r}", where=where)
        vals.append((int(v[0]), int(v[1])))
    (x0, y0), (Wf, Hf) = vals
    W, H = size
    if x0 < 0 or y0 < 0 or x0 + W > Wf or y0 + H > Hf:
        raise DatasetFormatError(f"the {W}x{H} tile at crop_origin_px {[x0, y0]} does not fit full_image_size {[Wf, Hf]}", where=where)


@dataclass(frozen=True)
class PairParams:
    """Imaging parameters of one pair (``params.json``).

    Attributes:
        pair_id: the pair's id, equal to its folder name.
        scene: scene id; splits never share a scene.
        camera: camera id (e.g. ``"cam0"``).
        f_number: the DP capture's f-number ``N``.
        focus_distance_mm: focus distance ``F`` in mm (Eq. 5).
        focal_length_mm: thin-lens focal length ``f`` in mm.
        pixel_pitch_mm: pixel pitch of the *output* image in mm (sensor width / image width).
        focus_point_px: the focus point ``(x, y)`` in output pixels.
        image_size: ``(W, H)`` of every image of the pair.
        extra: any other keys of params.json, kept verbatim.
    """

    pair_id: str
    scene: str
    camera: str
    f_number: float
    focus_distance_mm: float
    focal_length_mm: float
    pixel_pitch_mm: float
    focus_point_px: tuple[float, float]
    image_size: tuple[int, int]
    extra: Mapping[str, Any] = field(default_factory=dict)

    REQUIRED = (
        "pair_id",
        "scene",
        "camera",
        "f_number",
        "focus_distance_mm",
        "focal_length_mm",
        "pixel_pitch_mm",
        "focus_point_px",
        "image_size",
    )

    @property
    def sharp_f_number(self) -> float:
        """The f-number of ``sharp`` (optional key ``sharp_f_number``; format v1 default 22; 0 = an
        all-in-focus image, e.g. the radiance a synthetic pair was rendered from)."""
        return float(self.extra.get("sharp_f_number", SHARP_F_NUMBER))

    @property
    def source_id(self) -> str:
        """The source capture this pair comes from (optional key ``source_id``, e.g. the photo a tile was cut
        from; the scene when absent). Splits never share a source: every pair of one capture is in one split."""
        return str(self.extra.get("source_id", self.scene))

    @property
    def frame_geometry(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """(origin (x0, y0) px, full frame size (W, H) px) of this pair inside its camera frame: the optional
        keys ``crop_origin_px`` and ``full_image_size`` of a tile (validated by :meth:`from_json`), else the
        pair is the whole frame."""
        if "crop_origin_px" in self.extra:
            o, fs = self.extra["crop_origin_px"], self.extra["full_image_size"]
            return (int(o[0]), int(o[1])), (int(fs[0]), int(fs[1]))
        return (0, 0), (int(self.image_size[0]), int(self.image_size[1]))

    def to_json(self) -> dict[str, Any]:
        """The params.json object (required keys first, then extras)."""
        out: dict[str, Any] = {
            "pair_id": self.pair_id,
            "scene": self.scene,
            "camera": self.camera,
            "f_number": float(self.f_number),
            "focus_distance_mm": float(self.focus_distance_mm),
            "focal_length_mm": float(self.focal_length_mm),
            "pixel_pitch_mm": float(self.pixel_pitch_mm),
            "focus_point_px": [float(self.focus_point_px[0]), float(self.focus_point_px[1])],
            "image_size": [int(self.image_size[0]), int(self.image_size[1])],
        }
        for key, value in self.extra.items():
            if key not in out:
                out[key] = value
        return out

    @classmethod
    def from_json(cls, obj: Any, where: str) -> PairParams:
        """Validate and convert a params.json object.

        Raises:
            DatasetFormatError: a key is missing, has the wrong type, or a number is not finite / in range.
        """
        if not isinstance(obj, dict):
            raise DatasetFormatError("params must be a JSON object", where=where)
        missing = [k for k in cls.REQUIRED if k not in obj]
        if missing:
            raise DatasetFormatError(f"missing key(s) {', '.join(missing)}", where=where)
        for key in ("pair_id", "scene", "camera"):
            if not isinstance(obj[key], str) or not obj[key]:
                raise DatasetFormatError(f"'{key}' must be a non-empty string, got {obj[key]!r}", where=where)

        def number(key: str, positive: bool = True) -> float:
            value = obj[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise DatasetFormatError(f"'{key}' must be a number, got {value!r}", where=where)
            if not math.isfinite(value):
                raise DatasetFormatError(f"'{key}' is not finite ({value})", where=where)
            if positive and value <= 0:
                raise DatasetFormatError(f"'{key}' must be > 0, got {value}", where=where)
            return float(value)

        f_number = number("f_number")
        focus = number("focus_distance_mm")
        focal = number("focal_length_mm")
        pitch = number("pixel_pitch_mm")
        if focus <= focal:
            raise DatasetFormatError(
                f"'focus_distance_mm' ({focus}) must exceed 'focal_length_mm' ({focal})", where=where
            )

        def pair_of(key: str, kind: type) -> tuple[Any, Any]:
            value = obj[key]
            if not isinstance(value, (list, tuple)) or len(value) != 2:
                raise DatasetFormatError(f"'{key}' must be a list of 2 numbers, got {value!r}", where=where)
            for v in value:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                    raise DatasetFormatError(f"'{key}' must hold 2 finite numbers, got {value!r}", where=where)
                if kind is int and (float(v) != int(v) or v <= 0):
                    raise DatasetFormatError(f"'{key}' must hold 2 positive integers, got {value!r}", where=where)
            return kind(value[0]), kind(value[1])

        focus_point = pair_of("focus_point_px", float)
        size = pair_of("image_size", int)
        if "sharp_f_number" in obj and number("sharp_f_number", positive=False) < 0:
            raise DatasetFormatError(f"'sharp_f_number' must be >= 0 (0 = all-in-focus), got {obj['sharp_f_number']}", where=where)
        if "source_id" in obj and (not isinstance(obj["source_id"], str) or not obj["source_id"]):
            raise DatasetFormatError(f"'source_id' must be a non-empty string, got {obj['source_id']!r}", where=where)
        _check_frame_geometry(obj, size, where)
        extra = {k: v for k, v in obj.items() if k not in cls.REQUIRED}
        return cls(
            pair_id=obj["pair_id"],
            scene=obj["scene"],
            camera=obj["camera"],
            f_number=f_number,
            focus_distance_mm=focus,
            focal_length_mm=focal,
            pixel_pitch_mm=pitch,
            focus_point_px=focus_point,
            image_size=size,
            extra=extra,
        )


@dataclass
class Pair:
    """One loaded pair, in memory, in documented units.

    Attributes:
        params: the pair's :class:`PairParams`.
        sharp: (H, W, 3) float32, linear, [0, 1] (uint16 / 65535).
        left: (H, W, 3) float32, linear, same scale.
        right: (H, W, 3) float32, linear, same scale.
        depth_mm: (H, W) float32, millimetres, 0 where invalid.
        coc_px: (H, W) float32, signed CoC diameter in output pixels, NaN where depth is invalid.
    """

    params: PairParams
    sharp: NDArray[np.float32]
    left: NDArray[np.float32]
    right: NDArray[np.float32]
    depth_mm: NDArray[np.float32]
    coc_px: NDArray[np.float32]

    @property
    def pair_id(self) -> str:
        return self.params.pair_id

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(H, W) bool: depth is valid (depth > 0 and the CoC is finite)."""
        return (self.depth_mm > 0) & np.isfinite(self.coc_px)


class DatasetReader:
    """Lazy, validating reader of a format-v1 dataset.

    Args:
        root: the dataset folder (holding ``dataset.json`` and ``pairs/``).

    Raises:
        BadInputError: the folder does not exist (exit 3).
        DatasetFormatError: ``dataset.json`` is missing or malformed, or a split lists an id with no pair folder.
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        index_path = self.root / "dataset.json"
        if not self.root.is_dir():
            raise BadInputError("dataset folder not found", where=self.root)  # exit 3: missing, not malformed
        if not index_path.is_file():
            raise DatasetFormatError("missing dataset.json (not a dp5k dataset?)", where=index_path)
        try:
            index = read_json(index_path)
        except Exception as exc:
            raise DatasetFormatError(getattr(exc, "message", str(exc)), where=index_path) from exc
        if not isinstance(index, dict):
            raise DatasetFormatError("must be a JSON object", where=index_path)
        if index.get("format") != FORMAT_NAME:
            raise DatasetFormatError(f"'format' must be {FORMAT_NAME!r}, got {index.get('format')!r}", where=index_path)
        if index.get("version") != FORMAT_VERSION:
            raise DatasetFormatError(
                f"unsupported version {index.get('version')!r} (this reader knows version {FORMAT_VERSION})",
                where=index_path,
            )
        splits = index.get("splits")
        if not isinstance(splits, dict):
            raise DatasetFormatError("'splits' must be an object of id lists", where=index_path)
        missing = [s for s in SPLITS if s not in splits]
        if missing:
            raise DatasetFormatError(f"'splits' lacks {', '.join(missing)}", where=index_path)
        seen: dict[str, str] = {}
        self.splits: dict[str, list[str]] = {}
        for name, ids in splits.items():
            if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
                raise DatasetFormatError(f"split '{name}' must be a list of pair id strings", where=index_path)
            for pid in ids:
                _check_pair_id(pid, str(index_path))
                if pid in seen:
                    raise DatasetFormatError(
                        f"pair id {pid!r} listed twice (in '{seen[pid]}' and '{name}')", where=index_path
                    )
                seen[pid] = name
                if not (self.root / "pairs" / pid).is_dir():
                    raise DatasetFormatError(
                        f"split '{name}' lists unknown pair id {pid!r} (no folder pairs/{pid})", where=index_path
                    )
            self.splits[name] = list(ids)
        self._split_of = seen
        self.extra: dict[str, Any] = {k: v for k, v in index.items()
                                      if k not in ("format", "version", "splits", "provenance")}
        self.provenance: dict[str, Any] | None = index.get("provenance")  # what wrote it (write_index), when known

    def ids(self, split: str | None = None) -> list[str]:
        """Pair ids of one split, or of all splits in order train, val, test, others."""
        if split is None:
            return [pid for name in self.splits for pid in self.splits[name]]
        if split not in self.splits:
            raise DatasetFormatError(f"no split {split!r} (have {', '.join(self.splits)})", where=self.root)
        return list(self.splits[split])

    def split_of(self, pair_id: str) -> str:
        """The split a pair belongs to."""
        if pair_id not in self._split_of:
            raise DatasetFormatError(f"unknown pair id {pair_id!r}", where=self.root)
        return self._split_of[pair_id]

    def pair_dir(self, pair_id: str) -> Path:
        return self.root / "pairs" / pair_id

    def params(self, pair_id: str) -> PairParams:
        """Read and validate only ``params.json`` of a pair (cheap)."""
        path = self.pair_dir(pair_id) / "params.json"
        where = f"{self.root.name}/pairs/{pair_id}/params.json"
        if not path.is_file():
            raise DatasetFormatError("missing file", where=where)
        try:
            obj = read_json(path)
        except Exception as exc:
            raise DatasetFormatError(getattr(exc, "message", str(exc)), where=where) from exc
        params = PairParams.from_json(obj, where)
        if params.pair_id != pair_id:
            raise DatasetFormatError(
                f"'pair_id' is {params.pair_id!r} but the folder is {pair_id!r}", where=where
            )
        return params

    def load(self, pair_id: str) -> Pair:
        """Load and validate every file of a pair.

        Raises:
            DatasetFormatError: a file is missing or unreadable, has the wrong dtype, channel count or
                shape, shapes disagree between files or with ``image_size``, or ``coc.tif`` is not finite
                where depth is valid.
        """
        if pair_id not in self._split_of:
            raise DatasetFormatError(f"unknown pair id {pair_id!r}", where=self.root)
        params = self.params(pair_id)
        base = self.pair_dir(pair_id)
        W, H = params.image_size

        def where(name: str) -> str:
            return f"{self.root.name}/pairs/{pair_id}/{name}"

        def read(name: str) -> NDArray[Any]:
            path = base / name
            if not path.is_file():
                raise DatasetFormatError("missing file", where=where(name))
            try:
                return read_image_raw(path)
            except Exception as exc:
                raise DatasetFormatError(getattr(exc, "message", str(exc)), where=where(name)) from exc

        def check_shape(name: str, img: NDArray[Any], channels: int) -> None:
            if channels == 1:
                if img.ndim != 2:
                    raise DatasetFormatError(
                        f"must be single-channel, got shape {img.shape}", where=where(name)
                    )
            elif img.ndim != 3 or img.shape[2] != channels:
                got = 1 if img.ndim == 2 else img.shape[2]
                raise DatasetFormatError(f"must have {channels} channels, got {got}", where=where(name))
            if img.shape[:2] != (H, W):
                raise DatasetFormatError(
                    f"size {img.shape[1]}x{img.shape[0]} disagrees with image_size {W}x{H} in params.json",
                    where=where(name),
                )

        views: dict[str, NDArray[np.float32]] = {}
        for name in ("sharp.png", "left.png", "right.png"):
            img = read(name)
            if img.dtype != np.uint16:
                raise DatasetFormatError(f"must be 16-bit, got {img.dtype}", where=where(name))
            check_shape(name, img, 3)
            views[name] = img.astype(np.float32) / np.float32(65535.0)
        depth = read("depth.png")
        if depth.dtype != np.uint16:
            raise DatasetFormatError(f"must be 16-bit, got {depth.dtype}", where=where("depth.png"))
        check_shape("depth.png", depth, 1)
        coc = read("coc.tif")
        if coc.dtype != np.float32:
            raise DatasetFormatError(f"must be float32, got {coc.dtype}", where=where("coc.tif"))
        check_shape("coc.tif", coc, 1)
        valid_depth = depth > 0
        bad = valid_depth & ~np.isfinite(coc)
        if bad.any():
            raise DatasetFormatError(
                f"{int(bad.sum())} pixel(s) are NaN/inf where depth is valid", where=where("coc.tif")
            )
        if np.isinf(coc).any():
            raise DatasetFormatError("contains inf (use NaN for invalid pixels)", where=where("coc.tif"))
        coc = np.where(valid_depth, coc, np.float32(np.nan)).astype(np.float32)
        depth_mm = depth.astype(np.float32)
        if (base / DEPTH_TIF).is_file():
            depth_mm = self._sub_mm_depth(read(DEPTH_TIF), depth, where(DEPTH_TIF), check_shape)
        return Pair(
            params=params,
            sharp=views["sharp.png"],
            left=views["left.png"],
            right=views["right.png"],
            depth_mm=depth_mm,
            coc_px=coc,
        )

    @staticmethod
    def _sub_mm_depth(tif: NDArray[Any], png: NDArray[np.uint16], where: str, check_shape: Any) -> NDArray[np.float32]:
        """(H, W) float32 mm from depth.tif, 0 wherever depth.png is invalid (0); checked against depth.png."""
        if tif.dtype != np.float32:
            raise DatasetFormatError(f"must be float32, got {tif.dtype}", where=where)
        check_shape(DEPTH_TIF, tif, 1)
        valid = png > 0
        bad = valid & ~(np.isfinite(tif) & (tif > 0))
        if bad.any():
            raise DatasetFormatError(f"{int(bad.sum())} pixel(s) are not a positive finite depth where depth.png is valid", where=where)
        below_cap = valid & (png < np.iinfo(np.uint16).max)
        off = np.abs(tif[below_cap].astype(np.float64) - png[below_cap])
        if off.size and float(off.max()) > DEPTH_TIF_TOL_MM:
            raise DatasetFormatError(f"disagrees with depth.png by up to {float(off.max()):.2f} mm (more than rounding)", where=where)
        return np.where(valid, tif, np.float32(0.0)).astype(np.float32)

    def __iter__(self) -> Iterator[str]:
        return iter(self.ids())

    def __len__(self) -> int:
        return len(self._split_of)


def write_pair(
    root: str | os.PathLike[str],
    params: PairParams,
    *,
    sharp: NDArray[np.floating],
    left: NDArray[np.floating],
    right: NDArray[np.floating],
    depth_mm: NDArray[np.floating],
    coc_px: NDArray[np.floating],
    overwrite: bool = False,
    sub_mm_depth: bool = False,
) -> Path:
    """Write one pair atomically (temporary folder, then rename).

    Args:
        root: dataset folder.
        params: the pair's parameters; ``image_size`` must match the arrays.
        sharp, left, right: (H, W, 3) linear float images in [0, 1] (stored as value * 65535).
        depth_mm: (H, W) depth in mm, 0 (or NaN) = invalid; stored rounded to whole mm, clipped to 65535.
        coc_px: (H, W) signed CoC diameter in output pixels; written NaN wherever depth is invalid.
        overwrite: replace an existing pair folder (otherwise an existing pair is an error).
        sub_mm_depth: also write ``depth.tif``, the depth in mm as float32 (0 where invalid), which readers
            use in place of depth.png's whole millimetres.

    Returns:
        The pair's folder.
    """
    _check_pair_id(params.pair_id, "write_pair")
    W, H = params.image_size
    where = f"pairs/{params.pair_id}"
    for name, arr, ch in (("sharp", sharp, 3), ("left", left, 3), ("right", right, 3)):
        if np.shape(arr) != (H, W, ch):
            raise DatasetFormatError(f"{name} has shape {np.shape(arr)}, expected {(H, W, ch)}", where=where)
    for name, arr in (("depth_mm", depth_mm), ("coc_px", coc_px)):
        if np.shape(arr) != (H, W):
            raise DatasetFormatError(f"{name} has shape {np.shape(arr)}, expected {(H, W)}", where=where)
    root = Path(root)
    final = root / "pairs" / params.pair_id
    if final.exists() and not overwrite:
        raise DatasetFormatError("pair already exists (refusing to overwrite)", where=final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{params.pair_id}-", dir=final.parent))
    try:
        depth = np.nan_to_num(np.asarray(depth_mm, dtype=np.float64), nan=0.0)
        depth_u16 = np.clip(np.rint(depth), 0, 65535).astype(np.uint16)
        coc = np.asarray(coc_px, dtype=np.float32).copy()
        coc[depth_u16 == 0] = np.nan
        if not np.isfinite(coc[depth_u16 > 0]).all():
            raise DatasetFormatError("coc_px is not finite where depth is valid", where=where)
        write_png16(tmp / "sharp.png", to_uint16(sharp))
        write_png16(tmp / "left.png", to_uint16(left))
        write_png16(tmp / "right.png", to_uint16(right))
        write_png16(tmp / "depth.png", depth_u16)
        if sub_mm_depth:
            write_tiff_float32(tmp / DEPTH_TIF, np.where(depth_u16 > 0, depth, 0.0).astype(np.float32))
        write_tiff_float32(tmp / "coc.tif", coc)
        write_json_atomic(tmp / "params.json", params.to_json())
        os.chmod(tmp, new_dir_mode())  # mkdtemp's 0700 would hide a shared dataset's pairs from other users
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def write_index(
    root: str | os.PathLike[str], splits: Mapping[str, Sequence[str]], **extra: Any
) -> Path:
    """Write ``dataset.json`` atomically. ``splits`` must have train, val and test (lists may be empty).

    It records what wrote it under ``"provenance"`` (:func:`dp5k_common.software.provenance`: dp5k version, git
    commit, uncommitted changes, command line) unless ``extra`` gives that key."""
    from .software import PROVENANCE_KEY, provenance

    root = Path(root)
    missing = [s for s in SPLITS if s not in splits]
    if missing:
        raise DatasetFormatError(f"splits lack {', '.join(missing)}", where=root / "dataset.json")
    obj: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "splits": {name: list(ids) for name, ids in splits.items()},
    }
    for key, value in extra.items():
        if key in obj:
            raise DatasetFormatError(f"extra key {key!r} clashes with a format key", where=root)
        obj[key] = value
    obj.setdefault(PROVENANCE_KEY, provenance())
    write_json_atomic(root / "dataset.json", obj)
    return root / "dataset.json"


def copy_pairs(src: str | os.PathLike[str], out: str | os.PathLike[str], splits: Mapping[str, Sequence[str]],
               **extra: Any) -> Path:
    """A new dataset at ``out`` holding copies of ``src``'s pairs under new ``splits`` (train, val and test lists of
    ``src``'s pair ids; e.g. a few train pairs, or a held-out part of a train split). Each pair folder is copied
    under a temporary name and renamed, then ``dataset.json`` is written, so an interrupted copy resumes and
    ``src`` is never touched. ``extra`` goes into ``dataset.json`` (e.g. ``source``).

    Returns:
        ``out``.

    Raises:
        DatasetFormatError: ``src`` is not a dataset, or ``splits`` names a pair it lacks or lacks a split.
    """
    src, out = Path(src), Path(out)
    if not (src / "dataset.json").is_file():
        raise DatasetFormatError("missing dataset.json (not a dp5k dataset?)", where=src / "dataset.json")
    for pid in (p for ids in splits.values() for p in ids):
        if not (src / "pairs" / pid).is_dir():
            raise DatasetFormatError(f"no pair {pid!r} to copy", where=src / "pairs")
        dst = out / "pairs" / pid
        if not dst.is_dir():
            tmp = out / "pairs" / f".{pid}.partial"
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(src / "pairs" / pid, tmp)
            tmp.rename(dst)
    write_index(out, splits, **extra)
    return out


def split_scenes(
    scene_ids: Sequence[str], fractions: tuple[float, float, float] = (3850 / 5130, 640 / 5130, 640 / 5130), seed: int = 0
) -> dict[str, list[str]]:
    """Assign whole scenes to train/val/test in the paper's proportions (75 / 12.5 / 12.5 %), deterministically.

    Scenes are shuffled with ``seed``; val and test get ``round(n * fraction)`` scenes each (at least one
    each when there are three or more scenes), train gets the rest. No scene crosses splits.

    Returns:
        ``{"train": [...], "val": [...], "test": [...]}`` of scene ids.
    """
    scenes = sorted(set(scene_ids))
    rng = np.random.default_rng(seed)
    order = [scenes[i] for i in rng.permutation(len(scenes))]
    n = len(order)
    n_val = int(round(n * fractions[1]))
    n_test = int(round(n * fractions[2]))
    if n >= 3:
        n_val, n_test = max(1, n_val), max(1, n_test)
    return {
        "train": sorted(order[n_val + n_test :]),
        "val": sorted(order[:n_val]),
        "test": sorted(order[n_val : n_val + n_test]),
    }
