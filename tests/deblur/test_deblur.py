"""The deblurrer: trained for a few hundred steps on small studio DP pairs it beats the blurred input (L + R) on
held-out pairs by PSNR against sharp; evaluate writes metrics and a picture per pair; bad input gives one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_deblur.model import DeblurNetConfig, DPDeblurNet
from dp5k_deblur.train import target_mask
from dp5k_studio import make_dataset
from dp5k_testing.deblur_transfer import SUITE_TRAIN_ARGS

TRAIN_ARGS = SUITE_TRAIN_ARGS
"""The suite's deblurrer and budget (300 Adam steps on 48 px crops; dp5k_testing/deblur_transfer.py)."""


def studio_pairs(root: Path) -> Path:
    """8 studio scenes at 96 x 64, f/2 and f/4, no sensor noise, the all-in-focus radiance as sharp."""
    make_dataset(root, scenes=8, size=(96, 64), f_numbers=(2.0, 4.0), cameras=(0,), seed=3, noise=False,
                 all_in_focus_sharp=True)
    return root


def test_unet_takes_any_size_and_starts_near_the_blurred_input() -> None:
    net = DPDeblurNet(DeblurNetConfig(base_channels=4, levels=3))
    left, right = torch.rand(2, 3, 37, 53), torch.rand(2, 3, 37, 53)
    out = net(left, right)
    assert out.shape == (2, 3, 37, 53)
    assert (out - (left + right)).abs().mean() < 0.02  # a small initial head: the correction starts near 0
    plain = DPDeblurNet(DeblurNetConfig(base_channels=4, levels=2, input_skip=False))
    assert not torch.allclose(plain(left, right), left + right)


def test_target_mask_uses_depth_validity_or_the_whole_image_without_depth() -> None:
    valid = torch.zeros(2, 1, 4, 4, dtype=torch.bool)
    valid[0, :, :2] = True
    m = target_mask(valid)
    assert m[0].sum() == 8 and m[1].sum() == 16


@pytest.mark.slow
def test_trained_deblurrer_beats_the_blurred_input_on_held_out_pairs(tmp_path: Path) -> None:
    data = studio_pairs(tmp_path / "studio")
    run = tmp_path / "run"
    runner = CliRunner()
    res = runner.invoke(main, ["-q", "deblur", "train", str(data), "--out", str(run), *TRAIN_ARGS])
    assert res.exit_code == 0, res.output
    history = json.loads((run / "history.json").read_text())
    assert history[-1]["step"] == 300

    res = runner.invoke(main, ["-q", "deblur", "train", str(data), "--out", str(run), *TRAIN_ARGS])  # resumes: nothing left
    assert res.exit_code == 0 and "30 epoch(s), 300 steps" in res.output, res.output

    out = tmp_path / "eval"
    res = runner.invoke(main, ["-q", "deblur", "evaluate", str(data), "--checkpoint", str(run / "last.pt"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    test_ids = json.loads((data / "dataset.json").read_text())["splits"]["test"]
    assert [p["pair_id"] for p in metrics["pairs"]] == test_ids
    assert all((out / "figures" / f"{pid}.png").is_file() for pid in test_ids)
    pred, floor = metrics["mean"]["prediction"], metrics["mean"]["input"]
    assert pred["psnr"] > floor["psnr"] + 0.1, metrics["mean"]
    assert pred["mae"] < floor["mae"], metrics["mean"]


def test_bad_inputs_give_one_line_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(main, ["deblur", "evaluate", str(tmp_path), "--checkpoint", str(tmp_path / "none.pt"),
                               "--out", str(tmp_path / "o")])
    assert res.exit_code != 0 and "checkpoint not found" in res.output and res.output.count("\n") == 1
    res = runner.invoke(main, ["deblur", "train", str(tmp_path / "nothing"), "--out", str(tmp_path / "r")])
    assert res.exit_code != 0 and res.output.startswith("dp5k: error:") and res.output.count("\n") == 1
    assert not (tmp_path / "o").exists()
