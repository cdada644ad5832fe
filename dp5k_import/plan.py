"""What an import writes where, decided before any image is read: safe source ids, the split of every source, and
what an earlier, partial import already holds (``--resume``).

**Sources, not tiles, are split.** A *source* is one capture of the input (a scene folder, a photo): every pair cut
from it (tiles, cameras, f-numbers) carries its id as params.json ``source_id`` and lands in one split, so no
held-out figure is measured on tiles of a photo that was also trained on. Sources are split in the paper's
proportions (:func:`~dp5k_common.dataset.split_scenes`, seeded); with exactly two, one is train and the other test
and val stays empty (format v1 allows empty splits; every reader copes: ``neural_dp`` trains without validation,
``dp5k diagnose`` detects on the train pairs it did not fit); with one, everything is train.
"""

from __future__ import annotations

import re
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dp5k_common.dataset import PAIR_FILES, split_scenes
from dp5k_common.errors import BadInputError
from dp5k_common.io import read_json

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def safe_id(name: str) -> str:
    """A folder-safe id for a source named ``name`` (format v1 ids: letters, digits, ``.``, ``_``, ``-``, starting with
    a letter or digit): accents dropped (``scène`` -> ``scene``), every other run of characters -> ``_``."""
    ascii_name = unicodedata.normalize("NFKD", name).encode("ascii", "ignore").decode("ascii")
    out = _UNSAFE.sub("_", ascii_name).strip("._-")
    return out or "source"


def safe_ids(names: Sequence[str]) -> dict[str, str]:
    """``name -> id`` for every source name: :func:`safe_id`, made unique with ``-2``, ``-3``, ... in name order
    (names that are already safe keep themselves)."""
    out: dict[str, str] = {}
    taken = {n for n in names if safe_id(n) == n}
    for name in sorted(set(names), key=lambda n: (safe_id(n) != n, n)):
        base = candidate = safe_id(name)
        k = 2
        while candidate in taken and (candidate != name):
            candidate = f"{base}-{k}"
            k += 1
        out[name] = candidate
        taken.add(candidate)
    return out


def split_sources(ids: Sequence[str], seed: int = 0) -> dict[str, str]:
    """``source id -> split`` for sources without a split of their own (module docstring): two sources give one
    train and one test (seeded which), otherwise :func:`~dp5k_common.dataset.split_scenes`."""
    ids = sorted(set(ids))
    halves = {"fractions": (0.5, 0.0, 0.5)} if len(ids) == 2 else {}
    return {sid: name for name, members in split_scenes(ids, seed=seed, **halves).items() for sid in members}


def split_note(split_of: dict[str, str], own: bool) -> str | None:
    """One line for the report and the log when the split holds nothing back (one source) or only one source per
    held-out split (two sources); None otherwise."""
    n = len(split_of)
    if own or n > 2:
        return None
    if n == 1:
        return (f"only one source capture ({next(iter(split_of))}): every pair is in train, val and test are empty "
                f"(nothing is held out; a source's pairs never cross splits)")
    train = next((s for s, v in split_of.items() if v == "train"), "?")
    test = next((s for s, v in split_of.items() if v == "test"), "?")
    return (f"only two source captures: {train} is train, {test} is test, val is empty (a source's pairs never "
            f"cross splits, so no more can be held out)")


@dataclass
class Previous:
    """What an earlier import of the same OUT holds (``--resume``).

    Attributes:
        kept: ``source id -> (split, pair ids)`` of the sources whose pairs are all there: kept as they are.
        failed: the source ids it could not import (dataset.json ``import_failures``): retried.
        records: its report's per-source records (report.json ``scenes``), reused for the kept sources.
    """

    kept: dict[str, tuple[str, list[str]]] = field(default_factory=dict)
    failed: set[str] = field(default_factory=set)
    records: dict[str, dict[str, Any]] = field(default_factory=dict)


def read_previous(root: Path, resume: bool) -> Previous:
    """The state of an earlier import at ``root`` (empty without a dataset.json).

    Raises:
        BadInputError: a dataset exists and ``resume`` is off (imports never overwrite), or it is not an import.
    """
    index_path = root / "dataset.json"
    if not index_path.exists():
        return Previous()
    index = read_json(index_path)
    failures = index.get("import_failures") if isinstance(index, dict) else None
    if not resume:
        hint = (f"; --resume keeps its pairs and retries the {len(failures)} scene(s) that failed" if failures else "")
        raise BadInputError(f"a dataset already exists here (imports never overwrite){hint}", where=index_path)
    if not isinstance(index, dict) or not isinstance(failures, list) or not isinstance(index.get("splits"), dict):
        raise BadInputError("--resume: this dataset.json was not written by dp5k import (no import_failures)",
                            where=index_path)
    prev = Previous(failed={str(f.get("source_id", f.get("scene"))) for f in failures if isinstance(f, dict)})
    complete: dict[str, bool] = {}
    for split, pids in index["splits"].items():
        for pid in pids:
            params_path = root / "pairs" / str(pid) / "params.json"
            try:
                params = read_json(params_path)
                sid = str(params.get("source_id", params["scene"]))
            except (BadInputError, KeyError, AttributeError):
                continue  # a pair that is not there: its source is retried
            prev.kept.setdefault(sid, (split, []))[1].append(str(pid))
            complete[sid] = complete.get(sid, True) and all((params_path.parent / f).is_file() for f in PAIR_FILES)
    prev.kept = {sid: v for sid, v in prev.kept.items() if complete.get(sid)}
    report = root / "report.json"
    if report.is_file():
        try:
            scenes = read_json(report).get("scenes", [])
            prev.records = {r["source_id"]: r for r in scenes if isinstance(r, dict) and "source_id" in r}
        except (BadInputError, AttributeError):
            pass  # an unreadable old report is rewritten from what is known
    return prev

__all__ = ["Previous", "read_previous", "safe_id", "safe_ids", "split_note", "split_sources"]
