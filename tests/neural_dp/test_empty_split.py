"""An empty split is one typed error (EmptySplitError, exit 4) that callers which can do without it catch;
every other dataset problem propagates."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.errors import DatasetFormatError, EmptySplitError
from dp5k_learn.data import DPPairDataset
from neural_dp.evaluate import _fit_batches
from dp5k_testing.tiny_dataset import make_tiny_dataset


def _only_val_and_test(root: Path) -> None:
    make_tiny_dataset(root, scenes=3)
    index = json.loads((root / "dataset.json").read_text())
    index["splits"]["val"] += index["splits"].pop("train")
    index["splits"]["train"] = []
    (root / "dataset.json").write_text(json.dumps(index))


def test_empty_split_is_typed_and_train_refuses_it(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    _only_val_and_test(root)
    with pytest.raises(EmptySplitError, match="split 'train' is empty"):
        DPPairDataset(root, "train")
    res = CliRunner().invoke(main, ["-q", "train", str(root), "--out", str(tmp_path / "run"), "--epochs", "1", "--device", "cpu"])
    assert res.exit_code == EmptySplitError.exit_code == 4, res.output
    assert "train split is empty" in res.output


def test_evaluate_fits_nothing_on_an_empty_train_split_but_reports_a_broken_pair(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    _only_val_and_test(root)
    assert _fit_batches(root, 2, 16, torch.device("cpu")) == []
    broken = tmp_path / "broken"
    make_tiny_dataset(broken, scenes=3)
    (broken / "pairs" / "s0_cam0_f1.8" / "left.png").unlink()  # s0 is the train pair
    with pytest.raises(DatasetFormatError) as info:
        _fit_batches(broken, 2, 16, torch.device("cpu"))
    assert not isinstance(info.value, EmptySplitError)
