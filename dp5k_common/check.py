"""``dp5k check DATASET``: validate a format-v1 dataset completely and summarise it."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import click
import numpy as np

from .dataset import DatasetReader
from .errors import DatasetFormatError
from .progress import progress


def _crossing(kind: str, per_split: dict[str, set[str]], where: Path) -> None:
    """A :class:`DatasetFormatError` naming the first ``kind`` (scene, source) found in two splits, and the splits."""
    names = list(per_split)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            shared = sorted(per_split[a] & per_split[b])
            if shared:
                named = ", ".join(shared[:3]) + (f" and {len(shared) - 3} more" if len(shared) > 3 else "")
                raise DatasetFormatError(
                    f"{kind}(s) {named} appear in both the '{a}' and '{b}' splits: held-out pairs of one {kind} leak "
                    f"into the others (split by {kind})", where=where)


def check_dataset(root: Path) -> dict[str, Any]:
    """Load and validate every pair of a dataset; return a summary.

    Besides each pair (format v1), no scene and no source capture (``params.json`` ``source_id``: the photo a
    tile was cut from) may have pairs in two splits. ``import_failures`` (scenes an import could not read) are
    reported, not failed: the pairs that are there are valid.

    Raises:
        DatasetFormatError: at the first problem, naming the pair and file, or the scene or source and its splits.
    """
    reader = DatasetReader(root)
    scenes_per_split: dict[str, set[str]] = {name: set() for name in reader.splits}
    sources_per_split: dict[str, set[str]] = {name: set() for name in reader.splits}
    f_numbers: Counter[float] = Counter()
    valid_fraction: list[float] = []
    sizes: set[tuple[int, int]] = set()
    for pid in progress(reader.ids(), desc="checking pairs", unit="pair"):
        pair = reader.load(pid)
        split = reader.split_of(pid)
        scenes_per_split[split].add(pair.params.scene)
        sources_per_split[split].add(pair.params.source_id)
        f_numbers[pair.params.f_number] += 1
        valid_fraction.append(float(pair.valid.mean()))
        sizes.add(pair.params.image_size)
    _crossing("scene", scenes_per_split, reader.root / "dataset.json")
    _crossing("source", sources_per_split, reader.root / "dataset.json")
    failures = reader.extra.get("import_failures") or []
    return {
        "pairs": {name: len(ids) for name, ids in reader.splits.items()},
        "scenes": {name: len(s) for name, s in scenes_per_split.items()},
        "sources": {name: len(s) for name, s in sources_per_split.items()},
        "f_numbers": dict(sorted(f_numbers.items())),
        "image_sizes": sorted(sizes),
        "mean_valid_depth_fraction": float(np.mean(valid_fraction)) if valid_fraction else 0.0,
        "import_failures": failures if isinstance(failures, list) else [failures],
    }


@click.command("check")
@click.argument("dataset", type=click.Path(path_type=Path))
def check_command(dataset: Path) -> None:
    """Validate DATASET (format v1) pair by pair and print a summary.

    Exits non-zero with a one-line error naming the pair and file at the first problem, or the scene or source
    capture (params.json source_id) that has pairs in two splits. Scenes an import could not read
    (dataset.json import_failures) are listed with a warning: the dataset is valid but incomplete
    (dp5k import --resume retries them).
    """
    echo_check(dataset)


def echo_check(dataset: Path) -> None:
    """Check ``dataset`` and print the summary ``dp5k check`` prints (``dp5k verify`` given a dataset does too).

    Raises:
        DatasetFormatError: the first problem (:func:`check_dataset`).
    """
    summary = check_dataset(dataset)
    pairs = summary["pairs"]
    click.echo(f"{dataset}: dp5k dataset v1, {sum(pairs.values())} pairs")
    failures = summary.pop("import_failures")
    for key, value in summary.items():
        click.echo(f"  {key}: {value}")
    click.echo(f"  import_failures: {len(failures)}")
    for f in failures:
        line = f"{f.get('scene')}: {f.get('error')}" if isinstance(f, dict) else str(f)
        click.echo(f"WARNING: not imported: {line}", err=True)
