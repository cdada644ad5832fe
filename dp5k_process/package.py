"""``dp5k process``: many sessions -> the processed dataset format v1, in parallel, resumable.

Layout written besides the format's ``dataset.json`` and ``pairs/``::

    OUT/reports/<scene>/report.json        status, reason (failed), numbers, checksums of the pair files
    OUT/reports/<scene>/contact_sheet.png  sharp | left | right | depth | CoC per camera
    OUT/reports/<scene>/calibration.yaml   the stereo calibration of this focus setting (FileStorage YAML)

A scene whose report says ``ok`` and whose pair files still match the recorded SHA-256 is skipped on the next
run. A failing scene is reported with its reason, nothing of it enters ``pairs/`` and the others continue; the
command then ends with :class:`PartialFailureError`.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from dp5k_common.dataset import split_scenes, write_index, write_pair
from dp5k_common.errors import BadInputError, DP5KError, PartialFailureError
from dp5k_common.io import read_json, sha256_file, write_json_atomic
from dp5k_common.progress import progress

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


def run_scene(session_dir: str, out_dir: str, cfg: ProcessConfig) -> SceneOutcome:
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
        rep = dict(res.report, status="ok", checksums=checksums, seconds=time.perf_counter() - t0)
        write_json_atomic(rdir / "report.json", rep)
        return SceneOutcome(scene, "ok", pairs=tuple(checksums))
    except DP5KError as exc:
        for folder in written:  # a failed scene leaves none of its pairs behind
            shutil.rmtree(folder, ignore_errors=True)
        write_json_atomic(rdir / "report.json", {"scene": scene, "status": "failed", "reason": exc.one_line(),
                                                  "error": type(exc).__name__})
        return SceneOutcome(scene, "failed", exc.one_line())


def process_sessions(raw_root: str | os.PathLike[str], out_root: str | os.PathLike[str],
                     cfg: ProcessConfig = ProcessConfig(), workers: int = 1, seed: int = 0) -> list[SceneOutcome]:
    """Process every session under ``raw_root`` into ``out_root`` and write ``dataset.json``.

    Raises:
        PartialFailureError: at the end, when some scenes failed (their reasons are in the message and reports).
    """
    out = Path(out_root)
    out.mkdir(parents=True, exist_ok=True)
    sessions = find_sessions(Path(raw_root))
    outcomes: list[SceneOutcome] = []
    todo = []
    for sd in sessions:
        done = scene_done(out, sd.name)
        if done is not None:
            outcomes.append(SceneOutcome(sd.name, "skipped", pairs=done))
        else:
            todo.append(sd)
    if workers <= 1 or len(todo) <= 1:
        for sd in progress(todo, desc="scenes", unit="scene"):
            outcomes.append(run_scene(str(sd), str(out), cfg))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futs = [pool.submit(run_scene, str(sd), str(out), cfg) for sd in todo]
            for f in progress(as_completed(futs), desc="scenes", unit="scene", total=len(futs)):
                outcomes.append(f.result())
    good = {o.scene: o.pairs for o in outcomes if o.status in ("ok", "skipped")}
    split = split_scenes(sorted(good), seed=seed)
    splits = {name: sorted(pid for sc in scenes for pid in good[sc]) for name, scenes in split.items()}
    write_index(out, splits, source="dp5k process", scenes=sorted(good))
    failed = [o for o in outcomes if o.status == "failed"]
    for o in failed:
        log.error("scene %s failed: %s", o.scene, o.reason)
    if failed:
        raise PartialFailureError(
            f"{len(failed)} of {len(outcomes)} scenes failed ({'; '.join(o.reason for o in failed[:3])}"
            f"{' ...' if len(failed) > 3 else ''}); see reports/<scene>/report.json", where=out)
    return sorted(outcomes, key=lambda o: o.scene)
