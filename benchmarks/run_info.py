"""What every long benchmark run prints beside its tables: when, at which commit, at what load, and its cost in wall
and CPU seconds (this process and the commands it ran, e.g. ``dp5k import`` and ``dp5k diagnose``); and the results
store: :func:`record_result` writes a run's table to ``benchmarks/results/<benchmark>/latest.json``, from which
``scripts/gen_results.py`` generates docs/results.md."""

from __future__ import annotations

import datetime
import json
import os
import platform
import re
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def machine() -> str:
    """``date, commit, load average 1 / 5 / 15 on N cores``."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    load = os.getloadavg()
    return (f"{datetime.datetime.now().isoformat(timespec='seconds')}, commit {commit}, load average "
            f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on {os.cpu_count()} cores")


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (every thread) and of its finished child processes."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class Stopwatch:
    """Wall and CPU seconds since it was made."""

    def __init__(self) -> None:
        self.wall0, self.cpu0 = time.perf_counter(), cpu_seconds()

    def __str__(self) -> str:
        return f"{(time.perf_counter() - self.wall0) / 60:.1f} min wall, {(cpu_seconds() - self.cpu0) / 60:.1f} CPU-min"


# ----------------------------------------------------------------------------------------------- results store
RESULTS = Path(__file__).resolve().parent / "results"
"""``benchmarks/results/<benchmark>/latest.json``: the last run of every benchmark, which ``scripts/gen_results.py``
turns into docs/results.md (``DP5K_RESULTS_DIR`` points it elsewhere, e.g. for a trial run)."""


def stamp() -> dict[str, Any]:
    """When, at which commit (``+changes`` when tracked files other than the results store differ from it), at
    what load (1 / 5 / 15-minute averages) and on what machine a result is recorded."""
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
                                cwd=here).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ":(exclude)benchmarks/results"],
                               capture_output=True, text=True, check=True, cwd=here.parent).stdout.strip()
        commit += "+changes" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {"date": f"{datetime.datetime.now():%Y-%m-%d %H:%M}", "commit": commit,
            "load": [round(v, 2) for v in os.getloadavg()], "machine": f"{os.cpu_count()} CPUs, {platform.machine()}"}


def record_result(name: str, title: str, columns: list[str], rows: list[list[Any]], command: str | None = None,
                  notes: str = "", *, tables: list[dict[str, Any]] | None = None, **extra: Any) -> Path:
    """Store one benchmark run as ``RESULTS/<name>/latest.json`` (atomically), replacing the run before.

    ``columns`` and ``rows`` are the run's main table (cells are written as given; format numbers first);
    ``tables`` holds further ones as ``{"title", "columns", "rows"}``; ``command`` defaults to this process's
    command line. Date, commit, load and machine are taken now. ``python scripts/gen_results.py`` then
    regenerates docs/results.md from the store.
    """
    root = Path(os.environ.get("DP5K_RESULTS_DIR") or RESULTS)
    if command is None:
        script = Path(sys.argv[0]).resolve()
        try:
            script = script.relative_to(Path(__file__).resolve().parents[1])
        except ValueError:
            pass
        command = " ".join(["python", str(script), *sys.argv[1:]])
    result = {"benchmark": name, "title": title, **stamp(), "command": command, "columns": list(columns),
              "rows": [list(r) for r in rows], "notes": notes, **({"tables": tables} if tables else {}), **extra}
    path = root / name / "latest.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".latest.json.tmp-{os.getpid()}")
    tmp.write_text(dumps(result))
    tmp.replace(path)
    print(f"recorded {path} (python scripts/gen_results.py regenerates docs/results.md)", flush=True)
    return path


def dumps(result: dict[str, Any]) -> str:
    """JSON with one line per key and one per table row (readable diffs in the store)."""
    def rows(value: Any, indent: str) -> str:
        if isinstance(value, list) and value and all(isinstance(r, list) for r in value):
            return "[\n" + ",\n".join(indent + "  " + json.dumps(r, default=str) for r in value) + "\n" + indent + "]"
        if isinstance(value, list) and value and all(isinstance(t, dict) for t in value):
            return "[\n" + ",\n".join(indent + "  {" + ", ".join(f"{json.dumps(k)}: {rows(v, indent + '  ')}" for k, v in t.items()) + "}"
                                        for t in value) + "\n" + indent + "]"
        return json.dumps(value, default=str)
    return "{\n" + ",\n".join(f" {json.dumps(k)}: {rows(v, ' ')}" for k, v in result.items()) + "\n}\n"


def markdown_table(text: str) -> tuple[list[str], list[list[str]]]:
    """The first Markdown table in ``text`` as (columns, rows), for benchmarks that already print one."""
    lines = [l.strip() for l in text.splitlines()]
    start = next((i for i, l in enumerate(lines) if l.startswith("|") and i + 1 < len(lines)
                  and set(lines[i + 1].replace("|", "").strip()) <= set("-: ") and lines[i + 1].startswith("|")), None)
    if start is None:
        return [], []
    cells = lambda l: [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", l.strip()[1:-1] if l.strip().endswith("|") else l.strip()[1:])]  # noqa: E731
    rows = []
    for l in lines[start + 2:]:
        if not l.startswith("|"):
            break
        rows.append(cells(l))
    return cells(lines[start]), rows


def markdown_tables(text: str) -> tuple[list[tuple[list[str], list[list[str]]]], str]:
    """Every Markdown table in ``text`` as (columns, rows), and the other non-empty lines joined (the notes)."""
    tables, notes, rest = [], [], text.splitlines()
    while rest:
        columns, rows = markdown_table("\n".join(rest))
        if not columns:
            notes += [l.strip() for l in rest if l.strip()]
            break
        header = next(i for i, l in enumerate(rest) if l.strip().startswith("|"))
        notes += [l.strip() for l in rest[:header] if l.strip() and not l.strip().startswith("|")]
        tables.append((columns, rows))
        rest = rest[header + 2 + len(rows):]
    return tables, "\n".join(notes)


class _Tee:
    def __init__(self, stream: Any) -> None:
        self.stream, self.parts = stream, []

    def write(self, text: str) -> int:
        self.parts.append(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)


class recording:  # noqa: N801  (used as ``with recording(...):``)
    """``with recording(name, title): part()``: what the block prints still goes to stdout; when it ends without
    an error (or by ``SystemExit(0)``), the Markdown tables it printed are recorded as one result (the first is the
    main table, the others ``tables``; the other lines are the notes), via :func:`record_result`. ``enabled=False``
    records nothing (smoke runs such as ``--quick``)."""

    def __init__(self, name: str, title: str, notes: str = "", enabled: bool = True) -> None:
        self.name, self.title, self.notes, self.enabled = name, title, notes, enabled

    def __enter__(self) -> "recording":
        self.tee = _Tee(sys.stdout)
        sys.stdout = self.tee
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        sys.stdout = self.tee.stream
        succeeded = exc_type is None or (exc_type is SystemExit and exc.code in (0, None))
        if not (succeeded and self.enabled):
            return
        tables, notes = markdown_tables("".join(self.tee.parts))
        if not tables:
            return
        (columns, rows), more = tables[0], tables[1:]
        record_result(self.name, self.title, columns, rows, notes="\n".join(filter(None, [self.notes, notes])),
                      tables=[{"title": "", "columns": c, "rows": r} for c, r in more])


def options_suffix(argv: list[str]) -> str:
    """``-seed-1-sampling-tent`` for ``--seed 1 --sampling tent``: runs with other options get results of their own
    (paths and ``--out`` left out)."""
    keep, skip = [], False
    for arg in argv:
        if skip or arg in ("--out",):
            skip = arg == "--out"
            continue
        if "/" in arg or arg.startswith("."):
            continue
        keep.append(arg.lstrip("-").replace(",", "-").replace("=", "-"))
    return "".join("-" + k for k in keep if k)


def device_suffix(argv: list[str]) -> str:
    """``""`` for a CPU run, ``-cuda`` when ``--device cuda[:N]`` is on the command line: a GPU run gets its own result."""
    dev = argv[argv.index("--device") + 1] if "--device" in argv[:-1] else "cpu"
    return "" if dev == "cpu" else "-" + dev.split(":")[0]
