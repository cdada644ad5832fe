"""Reading and checking one raw capture session (docs/data-format.md, "Raw capture session, version 1").

Every problem is a :class:`BadInputError` naming the file and what is wrong; the scene is then skipped by
``dp5k process`` (the others continue).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError
from dp5k_common.io import read_json

from .graycode import n_patterns

CAMERAS = ("cam0", "cam1")
RAW_EXTS = (".dng", ".cr2", ".DNG", ".CR2")
_DP_RE = re.compile(r"^dp_f(\d+(?:\.\d+)?)$")


@dataclass
class CameraSession:
    """One body's files and settings.

    Attributes:
        cam_id: ``cam0`` / ``cam1``.
        dp: f-number -> DP raw file, sorted by f-number.
        sharp: the f/22 raw file.
        sl: the structured-light raw files in projection order (patterns, white, black).
        charuco: the ChArUco raw files (3).
        focus_point_raw_px: (x, y) focus point in raw pixels.
        raw_size_px: (W, H) raw size from the manifest (None if not given).
        sensor_size_mm: (w, h) sensor size in mm.
        focal_length_mm: lens (thin-lens) focal length if the manifest or lens name gives it, else None.
        K, dist: a prior intrinsic calibration at raw resolution, if the manifest carries one.
    """

    cam_id: str
    dp: dict[float, Path]
    sharp: Path
    sl: list[Path]
    charuco: list[Path]
    focus_point_raw_px: tuple[float, float]
    raw_size_px: tuple[int, int] | None = None
    sensor_size_mm: tuple[float, float] = (36.0, 24.0)
    focal_length_mm: float | None = None
    K: NDArray[np.float64] | None = None
    dist: NDArray[np.float64] | None = None


@dataclass
class Session:
    """A checked capture session.

    Attributes:
        scene: scene name; root: its folder; cameras: the two bodies; projector_size: (W, H);
        aux_view: which photodiode frame 1 holds (``left`` or ``right``); manifest: the raw manifest.
        file_sizes: relative path -> size in bytes from the manifest (for truncation checks).
    """

    scene: str
    root: Path
    cameras: dict[str, CameraSession]
    projector_size: tuple[int, int]
    aux_view: str
    manifest: dict[str, Any]
    file_sizes: dict[str, int] = field(default_factory=dict)


def _body_entries(manifest: dict[str, Any]) -> dict[str, dict[str, Any]]:
    rig = manifest.get("rig", {}) or {}
    bodies = rig.get("cameras", rig.get("bodies", rig.get("body", [])))
    if isinstance(bodies, dict):
        return {str(k): dict(v, id=k) for k, v in bodies.items()}
    return {str(b.get("id", f"cam{i}")): b for i, b in enumerate(bodies or [])}


def _focal_from_lens(lens: str | None) -> float | None:
    if not lens:
        return None
    m = re.search(r"(\d+(?:\.\d+)?)\s*mm", lens)
    return float(m.group(1)) if m else None


def _pair(v: Any, where: Path, what: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError) as exc:
        raise BadInputError(f"{what} must be two numbers, got {v!r}", where=where) from exc
    return a, b


def _raw_files(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        raise BadInputError("camera folder missing", where=folder)
    return {p.stem: p for p in sorted(folder.iterdir()) if p.suffix in RAW_EXTS and not p.name.startswith(".")}


def load_session(root: str | Path) -> Session:
    """Read ``root/manifest.json`` and the camera folders; check the file counts and names.

    Raises:
        BadInputError: missing/unreadable manifest, missing or extra files, wrong counts, bad settings.
    """
    root = Path(root)
    mpath = root / "manifest.json"
    if not mpath.is_file():
        raise BadInputError("manifest.json missing", where=root)
    manifest = read_json(mpath)
    if not isinstance(manifest, dict):
        raise BadInputError("manifest is not a JSON object", where=mpath)
    if manifest.get("format", "dp5k-raw-session") != "dp5k-raw-session":
        raise BadInputError(f"not a dp5k raw session (format {manifest.get('format')!r})", where=mpath)
    if manifest.get("complete") is not True:
        raise BadInputError("session is not complete (manifest lacks complete: true); resume the capture",
                            where=mpath)
    scene = root.name  # the folder names the scene (RAW/<scene>/); the manifest's name is kept in the report
    rig = manifest.get("rig", {}) or {}
    proj = rig.get("projector", {}) or {}
    if "resolution" in proj:
        psize = _pair(proj["resolution"], mpath, "projector resolution")
    else:
        psize = (float(proj.get("width", 1920)), float(proj.get("height", 1200)))
    projector_size = (int(psize[0]), int(psize[1]))
    aux_view = str(rig.get("aux_view", manifest.get("aux_view", "left")))
    if aux_view not in ("left", "right"):
        raise BadInputError(f"aux_view must be left or right, got {aux_view!r}", where=mpath)
    bodies = _body_entries(manifest)
    fp_all = manifest.get("focus_point_px", {}) or {}
    n_sl = n_patterns(*projector_size) + 2
    sizes = {}
    for f in manifest.get("files", []) or []:
        if isinstance(f, dict) and "path" in f and "size" in f:
            sizes[str(f["path"])] = int(f["size"])
    cams: dict[str, CameraSession] = {}
    for cam in CAMERAS:
        folder = root / cam
        files = _raw_files(folder)
        dp = {}
        for stem, p in files.items():
            m = _DP_RE.match(stem)
            if m:
                dp[float(m.group(1))] = p
        sl = [files.get(f"sl_{k:02d}") for k in range(n_sl)]
        charuco = [files.get(f"charuco_{k}") for k in range(3)]
        missing = [f"sl_{k:02d}" for k, p in enumerate(sl) if p is None] + \
                  [f"charuco_{k}" for k, p in enumerate(charuco) if p is None]
        if "sharp_f22" not in files:
            missing.append("sharp_f22")
        if missing:
            raise BadInputError(f"missing raw files: {', '.join(missing[:6])}"
                                f"{' ...' if len(missing) > 6 else ''} ({len(missing)} in all)", where=folder)
        known = {p for p in sl} | set(charuco) | set(dp.values()) | {files["sharp_f22"]}
        extra = sorted(p.name for p in files.values() if p not in known)
        if extra:
            raise BadInputError(f"unexpected raw files (wrong pattern count?): {', '.join(extra[:6])}", where=folder)
        if len(dp) == 0:
            raise BadInputError("no Dual Pixel captures dp_f<N>", where=folder)
        body = bodies.get(cam, {})
        fp = fp_all.get(cam, body.get("focus_point_px")) if isinstance(fp_all, dict) else None
        if fp is None:
            raise BadInputError(f"no focus point for {cam}", where=mpath)
        raw_size = body.get("raw_size_px")
        K = body.get("K", (body.get("intrinsics") or {}).get("K"))
        dist = body.get("dist", (body.get("intrinsics") or {}).get("dist"))
        cams[cam] = CameraSession(
            cam_id=cam, dp=dict(sorted(dp.items())), sharp=files["sharp_f22"], sl=sl, charuco=charuco,  # type: ignore[arg-type]
            focus_point_raw_px=_pair(fp, mpath, f"{cam} focus point"),
            raw_size_px=None if raw_size is None else tuple(int(v) for v in raw_size),  # type: ignore[arg-type]
            sensor_size_mm=tuple(float(v) for v in body.get("sensor_size_mm", (36.0, 24.0))),  # type: ignore[arg-type]
            focal_length_mm=float(body["focal_length_mm"]) if "focal_length_mm" in body else _focal_from_lens(body.get("lens")),
            K=None if K is None else np.asarray(K, np.float64).reshape(3, 3),
            dist=None if dist is None else np.asarray(dist, np.float64).ravel(),
        )
    if set(cams["cam0"].dp) != set(cams["cam1"].dp):
        raise BadInputError("the two cameras have different DP f-numbers", where=root)
    return Session(scene, root, cams, projector_size, aux_view, manifest, sizes)


def check_size(session: Session, path: Path) -> None:
    """Compare a file's size with the manifest's record (a truncated copy is caught before decoding)."""
    rel = path.relative_to(session.root).as_posix()
    want = session.file_sizes.get(rel)
    if want is not None and path.stat().st_size != want:
        raise BadInputError(f"file is {path.stat().st_size} bytes, the manifest says {want} (truncated?)", where=path)
