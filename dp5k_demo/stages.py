"""A tiny stage runner: each stage runs once, records its outputs and timing, and is reused on the next run.

A stage's record lives in ``OUT/.stages/<name>.json`` (:data:`STATE_DIR`) and is written (atomically) only when the stage
succeeds, so an interrupted or failed run resumes at the first unfinished stage. A failure becomes a
:class:`~dp5k_common.errors.StageError` that names the stage and the fix.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dp5k_common.errors import DP5KError, StageError
from dp5k_common.io import read_json, write_json_atomic

log = logging.getLogger(__name__)

STATE_DIR = ".stages"  # OUT/.stages/<stage>.json: the records of finished stages


@dataclass(frozen=True)
class Stage:
    """One step of the demo.

    Attributes:
        name: short id, also the record's file name.
        title: what the report calls it.
        run: ``run(ctx) -> dict`` doing the work; returns JSON-able results for the report.
        fix: the hint printed when the stage fails (what the user should do).
        always: run even when an earlier run finished it (cheap stages whose output must reflect this run).
    """

    name: str
    title: str
    run: Callable[[dict[str, Any]], dict[str, Any]]
    fix: str
    always: bool = False


def run_stages(stages: list[Stage], ctx: dict[str, Any], out: Path, *, force: bool = False) -> dict[str, dict[str, Any]]:
    """Run ``stages`` in order, reusing finished ones; return ``{name: record}``.

    Each record is ``{"title", "seconds", "cpu_seconds", "reused", "result"}`` (``seconds`` wall time,
    ``cpu_seconds`` user + system time of this process and its finished children: what load does not inflate); ``ctx["results"][name]`` gives later stages
    the earlier results.

    Raises:
        StageError: a stage failed; the message names it and the fix. Earlier stages stay recorded.
    """
    records: dict[str, dict[str, Any]] = {}
    ctx.setdefault("results", {})
    ctx["records"] = records
    state = out / STATE_DIR
    for i, stage in enumerate(stages, 1):
        path = state / f"{stage.name}.json"
        if path.is_file() and not force and not stage.always:
            record = read_json(path)
            record["reused"] = True
            log.info("[%d/%d] %s: reused (finished in an earlier run)", i, len(stages), stage.title)
        else:
            log.info("[%d/%d] %s ...", i, len(stages), stage.title)
            t0, c0 = time.perf_counter(), cpu_seconds()
            try:
                result = stage.run(ctx)
            except KeyboardInterrupt:
                raise
            except DP5KError as exc:
                raise StageError(f"{exc.one_line()}; fix: {stage.fix}", where=f"demo stage '{stage.name}'") from exc
            except Exception as exc:  # any bug or library failure: name the stage, keep the cause for -v
                raise StageError(
                    f"{type(exc).__name__}: {exc}; fix: {stage.fix} (rerun with -v for the traceback)",
                    where=f"demo stage '{stage.name}'",
                ) from exc
            record = {"title": stage.title, "seconds": round(time.perf_counter() - t0, 2),
                      "cpu_seconds": round(cpu_seconds() - c0, 2), "reused": False, "result": result}
            write_json_atomic(path, record)
            log.info("[%d/%d] %s: done in %.1f s (%.1f CPU s)", i, len(stages), stage.title, record["seconds"],
                     record["cpu_seconds"])
        ctx["results"][stage.name] = record["result"]
        records[stage.name] = record
    return records


def cpu_seconds() -> float:
    """CPU time (s) of this process and its waited-for children, user + system (``os.times``)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def peak_memory_note() -> str:
    """A short note on this process's peak resident memory (Linux ``ru_maxrss``)."""
    import resource

    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return f"{kib / 1024 / 1024:.2f} GiB"


__all__ = ["STATE_DIR", "Stage", "run_stages", "cpu_seconds", "peak_memory_note"]
