"""studio make-dataset resumes: an interrupted run keeps its pairs, the rerun finishes the dataset, and the result is
byte for byte the one an uninterrupted run writes (the noise generators continue where they stopped)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

import dp5k_studio.dataset as studio_dataset
from dp5k_cli import main
from dp5k_common.dataset import DatasetReader

ARGS = ["--scenes", "2", "--size", "48x32", "--f-numbers", "2,4", "--seed", "5"]


def make(out: Path, *extra: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["-q", "studio", "make-dataset", "--out", str(out), *ARGS, *extra])
    return res.exit_code, res.output


def interrupt_at(monkeypatch: pytest.MonkeyPatch, n: int) -> None:
    """Ctrl-C during the n-th pair write (the pairs before it are written)."""
    real, calls = studio_dataset.write_pair, [0]

    def write_pair(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls[0] += 1
        if calls[0] == n:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(studio_dataset, "write_pair", write_pair)


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / "pairs").rglob("*")) if p.is_file()}


@pytest.mark.parametrize("extra", [[], ["--random-captures", "2"]])
def test_an_interrupted_make_dataset_finishes_on_the_rerun(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           extra: list[str]) -> None:
    whole, out = tmp_path / "whole", tmp_path / "out"
    assert make(whole, *extra)[0] == 0
    # 4 views (2 scenes x 2 cameras) of 2 pairs: the 6th write is the second pair of the third view, so that view is
    # left half written
    with monkeypatch.context() as m:
        interrupt_at(m, 6)
        code, text = make(out, *extra)
    assert code == 130 and "run the command again to resume" in text, text
    assert not (out / "dataset.json").exists() and len(list((out / "pairs").iterdir())) == 5
    progress = json.loads((out / studio_dataset.PROGRESS_FILE).read_text())
    assert progress["state"]["done"] == 2  # views finished before the interruption

    calls = []
    real = studio_dataset.write_pair
    monkeypatch.setattr(studio_dataset, "write_pair", lambda *a, **k: calls.append(a[1].pair_id) or real(*a, **k))
    code, text = make(out, *extra)
    assert code == 0, text
    assert len(calls) == 4  # only the last two views were rendered again
    assert not (out / studio_dataset.PROGRESS_FILE).exists()
    assert DatasetReader(out).splits == DatasetReader(whole).splits
    assert files(out) == files(whole)
    assert make(out, *extra)[0] == 3  # finished: refused now, as any finished dataset


def test_a_rerun_with_other_options_is_refused_and_touches_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        interrupt_at(m, 3)
        assert make(out)[0] == 130
    before = files(out)
    code, text = make(out, "--no-noise")
    assert code == 3 and "interrupted make-dataset with other options" in text and "noise: True -> False" in text, text
    assert files(out) == before
    code, text = make(out, "--no-noise", "--overwrite")  # afresh, with the new options
    assert code == 0, text
    assert json.loads((out / "pairs" / DatasetReader(out).ids()[0] / "params.json").read_text())["noise"] is None


def test_pairs_that_no_run_left_are_not_mixed_in(tmp_path: Path) -> None:
    out = tmp_path / "out"
    (out / "pairs" / "someone_elses").mkdir(parents=True)
    code, text = make(out)
    assert code == 3 and "holds pairs but neither a dataset nor an interrupted make-dataset" in text, text
