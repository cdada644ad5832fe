"""dp5k evaluate resumes: after a Ctrl-C the rerun keeps the pairs already scored, scores the rest, and writes the
numbers an uninterrupted run writes; other settings, or a finished run, start afresh."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

import neural_dp.evaluate as ev
from dp5k_cli import main
from dp5k_common.dataset import write_index, write_pair
from dp5k_testing.tiny_dataset import make_arrays, make_params

SIMS = ["--simulator", "disk", "--simulator", "base", "--figures", "1", "--fit-pairs", "1"]


def dataset(root: Path) -> Path:
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for i, split in enumerate(["train", "test", "test", "test", "test"]):
        params = make_params(f"s{i}_cam0_f1.8", scene=f"s{i}", W=32, H=24)
        write_pair(root, params, **make_arrays(params, seed=i))
        splits[split].append(params.pair_id)
    write_index(root, splits, source="tests")
    return root


def run(ds: Path, out: Path, *extra: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["-q", "evaluate", str(ds), "--out", str(out), *SIMS, *extra])
    return res.exit_code, res.output


def count_scored(monkeypatch: pytest.MonkeyPatch, stop_at: int | None = None) -> list[int]:
    """Count view_metrics calls (one per pair and simulator); Ctrl-C at call ``stop_at``."""
    real, calls = ev.view_metrics, [0]

    def view_metrics(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls[0] += 1
        if calls[0] == stop_at:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(ev, "view_metrics", view_metrics)
    return calls


def test_an_interrupted_evaluate_resumes_with_the_same_numbers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds = dataset(tmp_path / "ds")
    assert run(ds, tmp_path / "whole")[0] == 0
    whole = json.loads((tmp_path / "whole" / "metrics.json").read_text())
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        count_scored(m, stop_at=6)  # the third pair's second simulator: two pairs scored
        code, text = run(ds, out)
    assert code == 130 and "run the command again to resume" in text, text
    assert not (out / "metrics.json").exists()
    assert len(json.loads((out / ev.PROGRESS_FILE).read_text())["state"]["per_pair"]) == 2

    with monkeypatch.context() as m:
        calls = count_scored(m)
        code, text = run(ds, out)
    assert code == 0, text
    assert calls[0] == 2 * 2  # the two pairs left, two simulators each
    resumed = json.loads((out / "metrics.json").read_text())
    assert resumed["per_pair"] == whole["per_pair"] and resumed["fitted_parameters"] == whole["fitted_parameters"]
    assert {k: {m: v for m, v in d.items() if m != "seconds_per_pair"} for k, d in resumed["means"].items()} == \
        {k: {m: v for m, v in d.items() if m != "seconds_per_pair"} for k, d in whole["means"].items()}
    assert not (out / ev.PROGRESS_FILE).exists()

    with monkeypatch.context() as m:  # a finished run is replaced: every pair scored again
        calls = count_scored(m)
        assert run(ds, out)[0] == 0
    assert calls[0] == 4 * 2


def test_other_settings_do_not_reuse_an_interrupted_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    ds = dataset(tmp_path / "ds")
    out = tmp_path / "out"
    with monkeypatch.context() as m:
        count_scored(m, stop_at=5)
        assert run(ds, out)[0] == 130
    with monkeypatch.context() as m:
        calls = count_scored(m)
        assert run(ds, out, "--max-pairs", "3")[0] == 0
    assert calls[0] == 3 * 2
    assert json.loads((out / "metrics.json").read_text())["pairs"] == ["s1_cam0_f1.8", "s2_cam0_f1.8", "s3_cam0_f1.8"]
