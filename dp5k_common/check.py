"""``dp5k check DATASET``: validate a format-v1 dataset completely and summarise it."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import click
import numpy as np

from .dataset import DatasetReader
from .errors import DatasetFormatError
from .progress import progress


def check_dataset(root: Path) -> dict[str, object]:
    """Load and validate every pair of a dataset; return a summary.

    Raises:
        DatasetFormatError: at the first problem, naming the pair and file.
    """
    reader = DatasetReader(root)
    scenes_per_split: dict[str, set[str]] = {name: set() for name in reader.splits}
    f_numbers: Counter[float] = Counter()
    valid_fraction: list[float] = []
    sizes: set[tuple[int, int]] = set()
    for pid in progress(reader.ids(), desc="checking pairs", unit="pair"):
        pair = reader.load(pid)
        scenes_per_split[reader.split_of(pid)].add(pair.params.scene)
        f_numbers[pair.params.f_number] += 1
        valid_fraction.append(float(pair.valid.mean()))
        sizes.add(pair.params.image_size)
    names = list(scenes_per_split)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            shared = scenes_per_split[a] & scenes_per_split[b]
            if shared:
                raise DatasetFormatError(
                    f"scene(s) {', '.join(sorted(shared))} appear in both '{a}' and '{b}' splits",
                    where=reader.root / "dataset.json",
                )
    return {
        "pairs": {name: len(ids) for name, ids in reader.splits.items()},
        "scenes": {name: len(s) for name, s in scenes_per_split.items()},
        "f_numbers": dict(sorted(f_numbers.items())),
        "image_sizes": sorted(sizes),
        "mean_valid_depth_fraction": float(np.mean(valid_fraction)) if valid_fraction else 0.0,
    }


@click.command("check")
@click.argument("dataset", type=click.Path(path_type=Path))
def check_command(dataset: Path) -> None:
    """Validate DATASET (format v1) pair by pair and print a summary.

    Exits non-zero with a one-line error naming the pair and file at the first problem.
    """
    summary = check_dataset(dataset)
    pairs = summary["pairs"]
    assert isinstance(pairs, dict)
    click.echo(f"{dataset}: dp5k dataset v1, {sum(pairs.values())} pairs")
    for key, value in summary.items():
        click.echo(f"  {key}: {value}")
