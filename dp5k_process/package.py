"""``dp5k process``: many sessions -> the processed dataset format v1, in parallel, resumable.

Layout written besides the format's ``dataset.json`` and ``pairs/``::

    OUT/reports/<scene>/report.json        status, reason (failed), numbers, checksums of the pair files
    OUT/reports/<scene>/contact_sheet.png  sharp | left | right | depth | CoC per camera
    OUT/reports/<scene>/calibration.yaml   the stereo calibration of this focus setting (FileStorage YAML)

A scene whose report says ``ok`` and whose pair files still match the recorded SHA-256 is skipped on the next
run. A failing scene is reported with its reason, nothing of it enters ``pairs/`` and the others continue; the
command then ends with :class:`PartialFailureError`.

Under ``torchrun --nproc_per_node N -m dp5k_cli process RAW --out OUT`` (``RANK`` / ``WORLD_SIZE`` in the environment,
``dp5k_common.sharding``) each rank owns every N-th scene of the sorted list, whatever has been done before, so
each scene is written by exactly one rank and a restarted rank resumes its own share. Every rank then rewrites
``dataset.json`` from all the scenes' reports on disk, under a lock (``OUT/.dataset.lock``): the last rank to
finish writes the complete index. ``--workers`` runs a rank's (or a lone process's) scenes in a process pool.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from dp5k_common.dataset import split_scenes, write_index, write_pair
from dp5k_common.errors import BadInputError, DP5KError, PartialFailureError
from dp5k_common.io import read_json, sha256_file, write_json_atomic
from dp5k_common.software import provenance
from dp5k_common.progress import progress
from dp5k_common.sharding import RankInfo, rank_info, shard

from .pipeline import ProcessConfig, process_scene
from .report import contact_sheet
from .session import load_session

log = logging.getLogger(__name__)
PAIR_FILES = ("sharp.png", "left.png", "right.png", "depth.png", "coc.tif", "params.json")


@dataclass
class SceneOutcome:
    """What happened to one scene: ``ok``, ``skipped`` (already done) or ``failed`` (with the reason)."""

    scene: str
    status: str
    reason: str = ""
    pairs: tuple[str, ...] = ()


def find_sessions(raw_root: Path) -> list[Path]:
    """Scene folders (those holding a manifest.json) under ``raw_root``, sorted; ``raw_root`` itself if it is one."""
    raw_root = Path(raw_root)
    if not raw_root.is_dir():
        raise BadInputError("raw capture folder not found", where=raw_root)
    if (raw_root / "manifest.json").is_file():
        return [raw_root]
    scenes = sorted(p for p in raw_root.iterdir() if p.is_dir() and (p / "manifest.json").is_file())
    if not scenes:
        raise BadInputError("no capture sessions (folders with manifest.json) found", where=raw_root)
    return scenes


def scene_done(out: Path, scene: str) -> tuple[str, ...] | None:
    """The pair ids of a finished scene whose files still match their checksums, else None."""
    rp = out / "reports" / scene / "report.json"
    if not rp.is_file():
        return None
    try:
        rep = read_json(rp)
    except DP5KError:
        return None
    if rep.get("status") != "ok":
        return None
    sums = rep.get("checksums", {})
    for pid, files in sums.items():
        for name, digest in files.items():
            f = out / "pairs" / pid / name
            if not f.is_file() or sha256_file(f) != digest:
                log.info("%s: %s changed or missing, reprocessing the scene", scene, f)
                return None
    return tuple(sums)


def reported_pairs(out: Path, scene: str) -> tuple[str, ...] | None:
    """The pair ids of a scene whose report says ``ok`` (another rank's scene: its owner verified it), else None."""
    rp = out / "reports" / scene / "report.json"
    try:
        rep = read_json(rp) if rp.is_file() else {}
    except DP5KError:
        return None
    return tuple(rep.get("checksums", {})) if rep.get("status") == "ok" else None


@contextmanager
def index_lock(out: Path) -> Iterator[None]:
    """Exclusive lock on ``OUT/.dataset.lock`` while a rank reads the reports and writes ``dataset.json``."""
    with open(out / ".dataset.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def write_dataset_index(out: Path, sessions: list[Path], outcomes: list[SceneOutcome], seed: int) -> None:
    """``dataset.json`` over every finished scene: this process's outcomes and the other ranks' reports."""
    with index_lock(out):
        good = {o.scene: o.pairs for o in outcomes if o.status in ("ok", "skipped")}
        mine = {o.scene for o in outcomes}
        for sd in sessions:
            if sd.name not in mine and (pairs := reported_pairs(out, sd.name)) is not None:
                good[sd.name] = pairs
        split = split_scenes(sorted(good), seed=seed)
        splits = {name: sorted(pid for sc in scenes for pid in good[sc]) for name, scenes in split.items()}
        write_index(out, splits, source="dp5k process", scenes=sorted(good))


def run_scene(session_dir: str, out_dir: str, cfg: ProcessConfig, rank: RankInfo = RankInfo()) -> SceneOutcome:
    """Process and write one scene (runs in a worker process). Never raises for a dp5k error: it reports."""
    out = Path(out_dir)
    scene = Path(session_dir).name
    rdir = out / "reports" / scene
    t0 = time.perf_counter()
    written: list[Path] = []
    try:
        session = load_session(session_dir)
        scene = session.scene
        rdir = out / "reports" / scene
        res = process_scene(session, cfg)
        checksums: dict[str, dict[str, str]] = {}
        for p in res.pairs:
            folder = write_pair(out, p.params, sharp=p.sharp, left=p.left, right=p.right, depth_mm=p.depth_mm,
                                coc_px=p.coc_px, overwrite=True)
            written.append(folder)
            checksums[p.params.pair_id] = {n: sha256_file(folder / n) for n in PAIR_FILES}
        res.calibration.save_yaml(rdir / "calibration.yaml")
        rows = []
        for cam in ("cam0", "cam1"):
            first = next(p for p in res.pairs if p.params.camera == cam)
            rows.append((f"{scene} {cam} f/{first.params.f_number:g}", first.sharp, first.left, first.right,
                         first.depth_mm, first.coc_px))
        contact_sheet(rows, rdir / "contact_sheet.png")
        rep = dict(res.report, status="ok", checksums=checksums, seconds=time.perf_counter() - t0,
                   rank={"rank": rank.rank, "world_size": rank.world_size}, provenance=provenance())
        write_json_atomic(rdir / "report.json", rep)
        return SceneOutcome(scene, "ok", pairs=tuple(checksums))
    except DP5KError as exc:
        for folder in written:  # a failed scene leaves none of its pairs behind
            shutil.rmtree(folder, ignore_errors=True)
        write_json_atomic(rdir / "report.json", {"scene": scene, "status": "failed", "reason": exc.one_line(),
                                                  "error": type(exc).__name__, "provenance": provenance()})
        return SceneOutcome(scene, "failed", exc.one_line())


def process_sessions(raw_root: str | os.PathLike[str], out_root: str | os.PathLike[str],
                     cfg: ProcessConfig = ProcessConfig(), workers: int = 1, seed: int = 0,
                     rank: RankInfo | None = None, overwrite: bool = False) -> list[SceneOutcome]:
    """Process this rank's share of the sessions under ``raw_root`` into ``out_root`` and write ``dataset.json``.

    Args:
        rank: this process's rank and the rank count; None = from torchrun's environment (alone: 0 of 1).
        overwrite: process every scene again, even those ``out_root`` already holds (default: skip them).

    Returns:
        The outcomes of this rank's scenes, sorted by scene.

    Raises:
        PartialFailureError: at the end, when some of this rank's scenes failed (reasons in the message and reports).
    """
    info = rank_info() if rank is None else rank
    out = Path(out_root)
    sessions = find_sessions(Path(raw_root))  # the input first: a missing RAW leaves no empty OUT behind
    out.mkdir(parents=True, exist_ok=True)
    outcomes: list[SceneOutcome] = []
    todo = []
    for sd in shard(sessions, info):  # the owner of a scene depends only on the sorted list and the rank count
        done = None if overwrite else scene_done(out, sd.name)
        if done is not None:
            outcomes.append(SceneOutcome(sd.name, "skipped", pairs=done))
        else:
            todo.append(sd)
    desc = f"scenes (rank {info.rank} of {info.world_size})" if info.enabled else "scenes"
    if workers <= 1 or len(todo) <= 1:
        for sd in progress(todo, desc=desc, unit="scene"):
            outcomes.append(run_scene(str(sd), str(out), cfg, info))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futs = [pool.submit(run_scene, str(sd), str(out), cfg, info) for sd in todo]
            for f in progress(as_completed(futs), desc=desc, unit="scene", total=len(futs)):
                outcomes.append(f.result())
    write_dataset_index(out, sessions, outcomes, seed)
    failed = [o for o in outcomes if o.status == "failed"]
    for o in failed:
        log.error("scene %s failed: %s", o.scene, o.reason)
    if failed:
        raise PartialFailureError(
            f"{len(failed)} of {len(outcomes)} scenes failed ({'; '.join(o.reason for o in failed[:3])}"
            f"{' ...' if len(failed) > 3 else ''}); see reports/<scene>/report.json", where=out)
    return sorted(outcomes, key=lambda o: o.scene)
