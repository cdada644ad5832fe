"""The raw capture session on disk (docs/data-format.md, "Raw capture session, version 1").

``RAW/<scene>/manifest.json`` + ``cam0/``, ``cam1/`` raw files (+ ``ground_truth/`` for simulated
sessions). Every file is written under a temporary name, checked, fsynced and renamed; the manifest is
rewritten atomically after each file, so an interrupted capture resumes where it stopped and a completed
file is never overwritten. :func:`verify_session` re-hashes everything.

A resume may set kept files aside (a body whose focus moved, one side of a ChArUco pair): they move to
``quarantine/run<k>/`` (never deleted), leave ``files`` for ``quarantined`` in the manifest, and the plan
re-shoots them. ``focus/`` holds the frames a resume shot to check each body's focus. Each run is recorded
in ``runs`` with what it did. A move is recorded before the rename, and a move a kill interrupted is
completed when the session is reopened.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import hashlib
import os
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from dp5k_common.errors import BadInputError, DatasetFormatError, DP5KError
from dp5k_common.io import new_file_mode, read_json, sha256_file, write_json_atomic

from .paths import check_scene_name
from .patterns import projection_count
from .rig import RigConfig

FORMAT = "dp5k-raw-session"
VERSION = 1
KINDS = ("charuco", "dp", "sharp", "sl")
QUARANTINE_DIR = "quarantine"
FOCUS_DIR = "focus"
PART_SUFFIX = ".part"  # temporary names of files written outside camN/ (``.<name>.<random>.part``)


@dataclass(frozen=True)
class Shot:
    """One planned exposure of both bodies.

    Attributes:
        kind: ``charuco``, ``dp``, ``sharp`` or ``sl``.
        stem: file name without extension (``dp_f1.8``, ``sl_07``, ``charuco_2``).
        f_number: aperture N.
        shutter_s: exposure time (s), a value the body can set.
        iso: ISO speed.
        index: projection index (sl) or board view (charuco); None otherwise.
    """

    kind: str
    stem: str
    f_number: float
    shutter_s: float
    iso: int
    index: int | None = None


def f_label(f_number: float) -> str:
    """``1.8 -> "1.8"``, ``2.0 -> "2"``, ``22.0 -> "22"`` (file names ``dp_f2``, ``sharp_f22``)."""
    return f"{f_number:g}"


def plan_scene(rig: RigConfig) -> list[Shot]:
    """The scene's exposures in capture order: ChArUco views, DP apertures, the sharp frame, structured light."""
    e = rig.exposure
    shots = [Shot("charuco", f"charuco_{v}", e.charuco_f_number, e.charuco_shutter_s, e.iso, v) for v in range(e.charuco_views)]
    shots += [Shot("dp", f"dp_f{f_label(f)}", f, e.dp_shutter_s(f), e.iso) for f in e.dp_f_numbers]
    shots.append(Shot("sharp", f"sharp_f{f_label(e.sharp_f_number)}", e.sharp_f_number, e.sharp_shutter_s, e.iso))
    n = projection_count(rig.projector.width, rig.projector.height)
    shots += [Shot("sl", f"sl_{k:02d}", e.sl_f_number, e.sl_shutter_s, e.iso, k) for k in range(n)]
    return shots


def now_iso() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")


class CaptureStorageError(DP5KError):
    """Writing the session failed (disk full, permissions); completed files were kept."""


class RawSessionWriter:
    """Writes one scene's raw session; resumes an incomplete one.

    Args:
        root: the ``--out`` folder (``RAW``).
        scene: scene name (one safe folder name, :func:`~dp5k_capture.paths.check_scene_name`).
        rig: the rig (recorded in the manifest).
        ext: raw file extension (``CR2`` on the rig, ``dng`` from simulated bodies).
        extra: additional manifest keys (e.g. ``simulated``).

    Raises:
        BadInputError: a hostile scene name, the scene is already complete (never overwritten), or its manifest
            is unreadable.
    """

    def __init__(self, root: str | Path, scene: str, rig: RigConfig, ext: str, extra: dict[str, Any] | None = None) -> None:
        check_scene_name(scene)
        self.dir = Path(root) / scene
        self.scene = scene
        self.ext = ext
        self.manifest_path = self.dir / "manifest.json"
        if self.manifest_path.exists():
            self.manifest = read_json(self.manifest_path)
            if self.manifest.get("format") != FORMAT:
                raise BadInputError("not a dp5k raw session manifest", where=self.manifest_path)
            if self.manifest.get("complete"):
                raise BadInputError("scene already captured and complete; captured data is never overwritten (use another --scene or --out)", where=self.dir)
            if self.manifest.get("rig", {}).get("bodies") != _rig_json(rig)["bodies"]:
                raise BadInputError("an incomplete session of this scene was captured with a different rig; finish it with that rig or use another --scene", where=self.manifest_path)
        else:
            self.manifest = {
                "format": FORMAT, "version": VERSION, "scene": scene, "created": now_iso(), "updated": now_iso(),
                "rig": _rig_json(rig), "exposure": asdict(rig.exposure), "focus_point_px": {}, "files": [],
                "complete": False, **(extra or {}),
            }
        self._by_path = {f["path"]: f for f in self.manifest["files"]}
        m = self.manifest
        for key, empty in (("runs", []), ("quarantined", []), ("focus", {}), ("in_flight", {})):
            m.setdefault(key, empty)
        self.run = prior_runs(m) + 1
        m["runs"].append({"run": self.run, "started": now_iso(), "resumed": bool(m["files"]), "notes": []})
        self._finish_quarantine()
        self._remove_stale_temporaries()
        if self.manifest_path.exists():
            self._save()  # the run is numbered before anything moves: quarantine/run<k>/ never mixes two runs

    def _remove_stale_temporaries(self) -> None:
        """Delete what a killed run left under temporary names (``.manifest.json.*``, ``camN/.<file>.*``): never
        a captured file, which only exists under its final name."""
        if not self.dir.is_dir():
            return
        stale = [*self.dir.glob(".manifest.json.*"), *self.dir.glob(f"*/.*.{self.ext}"),
                 *self.dir.glob(f"{FOCUS_DIR}/.*{PART_SUFFIX}"), *self.dir.glob(f"{QUARANTINE_DIR}/**/.*{PART_SUFFIX}")]
        for path in stale:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()

    # ------------------------------------------------------------------ state
    def relpath(self, camera: str, shot: Shot) -> str:
        return f"{camera}/{shot.stem}.{self.ext}"

    def done(self, camera: str, shot: Shot) -> bool:
        """The file is recorded and present with its recorded size (a cheap check; verify re-hashes)."""
        rel = self.relpath(camera, shot)
        entry = self._by_path.get(rel)
        path = self.dir / rel
        return entry is not None and path.is_file() and path.stat().st_size == entry["size"]

    def set_focus_point(self, camera: str, point_px: tuple[int, int]) -> None:
        self.manifest["focus_point_px"][camera] = [int(point_px[0]), int(point_px[1])]
        self._save()

    def _save(self) -> None:
        self.manifest["updated"] = now_iso()
        try:
            write_json_atomic(self.manifest_path, self.manifest)
        except OSError as exc:
            raise _storage_error(exc, self.manifest_path) from exc

    # ------------------------------------------------------------------ files
    def add(self, camera: str, shot: Shot, data: bytes, meta: dict[str, Any],
            check: Callable[[Path], None] | None = None) -> dict[str, Any]:
        """Write one raw file atomically, run ``check`` on it before it gets its final name, record it (and clear
        the camera's in-flight download record in the same manifest write).

        Never overwrites: a file already at the final name that is not recorded (a crash between the
        rename and the manifest update) is adopted if ``check`` accepts it, else it is an error.
        """
        rel = self.relpath(camera, shot)
        final = self.dir / rel
        if rel in self._by_path and final.exists():
            raise BadInputError("already captured; never overwritten", where=final)
        if final.exists():
            data = final.read_bytes()  # adopt the orphan completed file (written atomically earlier)
            if check is not None:
                check(final)
        else:
            _write_new(final, data, check, prefix=f".{final.name}.", suffix=f".{self.ext}")
        entry = {
            "path": rel, "kind": shot.kind, "camera": camera, "f_number": shot.f_number, "shutter_s": shot.shutter_s,
            "iso": shot.iso, **({"pattern": shot.index} if shot.kind == "sl" else {}),
            **({"view": shot.index} if shot.kind == "charuco" else {}),
            "timestamp": now_iso(), "size": len(data), "sha256": hashlib.sha256(data).hexdigest(), **meta,
        }
        self.manifest["files"].append(entry)
        self._by_path[rel] = entry
        self.manifest["in_flight"].pop(camera, None)
        self._save()
        return entry

    def store_extra(self, rel: str, data: bytes, check: Callable[[Path], None] | None = None) -> dict[str, Any]:
        """Write a file outside the plan (a focus check frame, an image rescued from a body) under ``rel``, or
        beside it with a number if that name is taken (never overwritten). Returns its path, size and SHA-256."""
        final = _free_path(self.dir / rel)
        _write_new(final, data, check, prefix=f".{final.name}.", suffix=PART_SUFFIX)
        return {"path": final.relative_to(self.dir).as_posix(), "size": len(data), "sha256": hashlib.sha256(data).hexdigest()}

    def kept(self, camera: str, kinds: tuple[str, ...]) -> list[dict[str, Any]]:
        """The recorded files of ``camera`` of these kinds (manifest entries, capture order)."""
        return [f for f in self.manifest["files"] if f["camera"] == camera and f["kind"] in kinds]

    def quarantine(self, rel: str, reason: str) -> str:
        """Set a recorded file aside: ``quarantine/run<k>/<rel>`` (never deleted), out of ``files``, so the plan
        re-shoots it. The manifest records the move before the rename (a killed move is completed on reopen).
        Returns the new relative path."""
        entry = self._by_path.pop(rel)
        self.manifest["files"].remove(entry)
        dest = _free_path(self.dir / QUARANTINE_DIR / f"run{self.run}" / rel)
        moved = {**entry, "path": dest.relative_to(self.dir).as_posix(), "original_path": rel, "reason": reason,
                 "run": self.run, "quarantined": now_iso()}
        self.manifest["quarantined"].append(moved)
        self._save()
        self._move(self.dir / rel, dest)
        return moved["path"]

    def quarantine_data(self, camera: str, name: str, data: bytes, reason: str, meta: dict[str, Any]) -> str:
        """Keep bytes that belong to no planned shot (an image a body announced to an interrupted run) in
        ``quarantine/run<k>/leftover/<camera>/<name>``; recorded in ``quarantined``. Returns the relative path."""
        stored = self.store_extra(f"{QUARANTINE_DIR}/run{self.run}/leftover/{camera}/{name}", data)
        self.manifest["quarantined"].append({**stored, "camera": camera, "kind": "leftover", "reason": reason,
                                             "run": self.run, "quarantined": now_iso(), **meta})
        self._save()
        return str(stored["path"])

    def _move(self, src: Path, dest: Path) -> None:
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dest)
        except OSError as exc:
            raise _storage_error(exc, dest) from exc

    def _finish_quarantine(self) -> None:
        """Complete moves into quarantine that a kill interrupted (recorded, but the file is still in place)."""
        for q in self.manifest.get("quarantined", []):
            src, dest = self.dir / q.get("original_path", ""), self.dir / q["path"]
            if "original_path" in q and not dest.exists() and src.is_file() and q["original_path"] not in self._by_path \
                    and src.stat().st_size == q["size"]:
                self._move(src, dest)

    # ------------------------------------------------------------------ what a run knows and did
    def note(self, text: str) -> None:
        """Record what this run did (re-shot, quarantined, rescued) in its ``runs`` entry."""
        self.manifest["runs"][-1]["notes"].append(text)
        self._save()

    def focus_record(self, camera: str) -> dict[str, Any]:
        """The manifest's ``focus`` record of ``camera`` (AF results, lock, checks); created empty."""
        return self.manifest["focus"].setdefault(camera, {"af": [], "checks": []})

    def save_focus(self) -> None:
        self._save()

    def set_board(self, view: int | None) -> None:
        """The ChArUco board is (``view``) or is no longer (None) in the scene: a resume clears it first."""
        self.manifest["board_in_view"] = view
        self._save()

    def set_in_flight(self, camera: str, record: dict[str, Any]) -> None:
        """An image ``camera`` announced and the client is downloading: handle, name, size (reopen rescues it)."""
        self.manifest["in_flight"][camera] = record
        self._save()

    def clear_in_flight(self, camera: str) -> None:
        if self.manifest["in_flight"].pop(camera, None) is not None:
            self._save()

    def finish(self, rig: RigConfig) -> None:
        """Verify every file of the plan (size + SHA-256) and mark the session complete."""
        report = verify_session(self.dir, check_dual_pixel=False, rig=rig)
        if report.problems:
            raise DatasetFormatError(f"session not complete: {report.problems[0]} (+{len(report.problems) - 1} more)", where=self.dir)
        self.manifest["complete"] = True
        self.manifest["completed"] = now_iso()
        self._save()


def prior_runs(manifest: dict[str, Any]) -> int:
    """How many runs a session's manifest records (a session from before run records counts one if it has files)."""
    runs = manifest.get("runs")
    return len(runs) if runs else int(bool(manifest.get("files")))


def count_prior_runs(session_dir: str | Path) -> int:
    """:func:`prior_runs` of the session at ``session_dir`` (0 if there is none yet)."""
    path = Path(session_dir) / "manifest.json"
    if not path.is_file():
        return 0
    m = read_json(path)
    return prior_runs(m) if isinstance(m, dict) else 0


def _free_path(path: Path) -> Path:
    """``path``, or ``name.1.ext``, ``name.2.ext``, ... if it exists (extra files are never overwritten)."""
    k = 0
    cand = path
    while cand.exists():
        k += 1
        cand = path.with_name(f"{path.stem}.{k}{path.suffix}")
    return cand


def _write_new(final: Path, data: bytes, check: Callable[[Path], None] | None, *, prefix: str, suffix: str) -> None:
    """Write ``data`` to a temporary file beside ``final``, fsync, run ``check`` on it, give it the umask's
    mode and rename it to ``final`` (which must not exist)."""
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=final.parent)
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if check is not None:
            check(tmp)
        if final.exists():
            raise BadInputError("appeared while writing; never overwritten", where=final)
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, final)
    except OSError as exc:
        raise _storage_error(exc, final) from exc
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def _storage_error(exc: OSError, path: Path) -> DP5KError:
    if exc.errno == errno.ENOSPC:
        return CaptureStorageError("disk full; completed files were kept; free space and rerun to resume", where=path)
    return CaptureStorageError(f"cannot write ({exc.strerror or exc}); completed files were kept; rerun to resume", where=path)


def _rig_json(rig: RigConfig) -> dict[str, Any]:
    return {
        "bodies": [{"id": b.id, "model": b.model, "serial": b.serial, "lens": b.lens,
                    "sensor_size_mm": list(b.sensor_size_mm), "raw_size_px": list(b.raw_size_px),
                    **({"K": [list(r) for r in b.K], "dist": list(b.dist)} if b.K else {})} for b in rig.bodies],
        "projector": {"model": rig.projector.model, "resolution": [rig.projector.width, rig.projector.height],
                      "port": rig.projector.port, "source": rig.projector.source},
        "aux_view": rig.aux_view,
    }


@dataclass
class VerifyReport:
    """Result of :func:`verify_session`: counts per kind and every problem found (empty = good)."""

    counts: dict[str, int]
    problems: list[str]
    files: int
    bytes: int


def verify_session(scene_dir: str | Path, *, check_dual_pixel: bool = True, rig: RigConfig | None = None) -> VerifyReport:
    """Check a raw session: manifest, every file's size and SHA-256, the per-kind counts, and (optionally)
    that every raw is a two-frame Dual Pixel RAW.

    Raises:
        BadInputError: no manifest or not a raw session manifest.
    """
    scene_dir = Path(scene_dir)
    manifest = read_json(scene_dir / "manifest.json")
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT or manifest.get("version") != VERSION:
        raise DatasetFormatError(f"not a {FORMAT} v{VERSION} manifest", where=scene_dir / "manifest.json")
    problems: list[str] = []
    counts = {k: 0 for k in KINDS}
    total = 0
    bodies = [b["id"] for b in manifest.get("rig", {}).get("bodies", [])]
    for entry in manifest.get("files", []):
        path = scene_dir / entry["path"]
        if not path.is_file():
            problems.append(f"{entry['path']}: missing")
            continue
        size = path.stat().st_size
        if size != entry["size"]:
            problems.append(f"{entry['path']}: size {size} != manifest {entry['size']}")
            continue
        if sha256_file(path) != entry["sha256"]:
            problems.append(f"{entry['path']}: SHA-256 mismatch")
            continue
        if check_dual_pixel:
            from dp5k_common.rawfile import read_dual_pixel

            try:
                read_dual_pixel(path)
            except BadInputError as exc:
                problems.append(f"{entry['path']}: {exc.message}")
                continue
        counts[entry["kind"]] = counts.get(entry["kind"], 0) + 1
        total += size
    nb = max(len(bodies), 1)
    exposure = manifest.get("exposure", {})
    res = manifest.get("rig", {}).get("projector", {}).get("resolution", [1920, 1200])
    expected = {
        "dp": nb * len(exposure.get("dp_f_numbers", (1.8, 2, 2.8, 4, 5.6))),
        "sharp": nb,
        "charuco": nb * int(exposure.get("charuco_views", 3)),
        "sl": nb * projection_count(int(res[0]), int(res[1])),
    }
    for kind, want in expected.items():
        if counts.get(kind, 0) != want:
            problems.append(f"{kind}: {counts.get(kind, 0)} verified files, expected {want}")
    for b in bodies:
        if b not in manifest.get("focus_point_px", {}):
            problems.append(f"{b}: no focus point recorded")
    kept_aside = [*manifest.get("quarantined", []),
                  *(c for rec in manifest.get("focus", {}).values() for c in rec.get("checks", []) if "path" in c)]
    for entry in kept_aside:  # set aside, never lost: still present and unchanged
        path = scene_dir / entry["path"]
        if not path.is_file():
            problems.append(f"{entry['path']}: missing (set aside by a resume)")
        elif path.stat().st_size != entry["size"] or sha256_file(path) != entry["sha256"]:
            problems.append(f"{entry['path']}: changed since it was set aside (size or SHA-256)")
    if manifest.get("simulated") and not (scene_dir / "ground_truth" / "truth.json").is_file():
        problems.append("ground_truth/truth.json: missing (a simulated session carries its ground truth)")
    return VerifyReport(counts, problems, sum(counts.values()), total)
