"""End-to-end on CPU (nerfstudio-style): train -> save -> interrupt -> resume -> evaluate, and the config."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.errors import BadInputError
from dp5k_learn.checkpoint import load_checkpoint
from neural_dp.config import load_config
from neural_dp.registry import get_simulator
from neural_dp.train import train
from dp5k_testing.tiny_dataset import make_tiny_dataset

TINY = ["model.base_channels=4", "model.levels=2", "data.crop_px=32", "data.batch_size=2",
        "data.samples_per_epoch=2", "optim.epochs=2", "device=cpu"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tiny") / "ds"
    make_tiny_dataset(root, scenes=6, W=48, H=32)
    return root


def test_train_save_interrupt_resume_is_exact_then_evaluate(tiny: Path, tmp_path: Path) -> None:
    cfg = load_config(None, TINY)
    straight = train(tiny, tmp_path / "straight", cfg)
    assert straight.steps == 2 and straight.epochs_done == 2

    def interrupt(epoch: int, record: dict[str, float]) -> None:
        if epoch == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(tiny, tmp_path / "resumed", cfg, on_epoch_end=interrupt)
    first = load_checkpoint(tmp_path / "resumed" / "last.pt")
    assert first["epoch"] == 1 and first["step"] == 1
    resumed = train(tiny, tmp_path / "resumed", cfg)
    assert resumed.steps == 2 and len(resumed.history) == 2
    a = load_checkpoint(tmp_path / "straight" / "last.pt")["model"]
    b = load_checkpoint(tmp_path / "resumed" / "last.pt")["model"]
    for key in a:
        assert torch.equal(a[key], b[key]), key  # resuming reproduces the uninterrupted run bit for bit
    assert json.loads((tmp_path / "resumed" / "config.json").read_text())["optim"]["epochs"] == 2

    # the best checkpoint loads safely into the registry and evaluates beside the peers
    sim = get_simulator("neural", tmp_path / "straight" / "best.pt")
    assert sim.name == "neural"
    out = tmp_path / "eval"
    res = CliRunner().invoke(main, ["-q", "evaluate", str(tiny), "--out", str(out), "--simulator", "disk", "--simulator",
                                    "butterworth", "--simulator", "raytrace", "--simulator",
                                    f"neural:{tmp_path / 'straight' / 'best.pt'}", "--figures", "1"])
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["means"]) == {"disk", "butterworth", "raytrace", "neural"}
    for m in metrics["means"].values():
        assert 0 < m["ssim"] <= 1 and m["psnr"] > 5 and m["mae"] >= 0
    assert "| PSNR (dB) |" in (out / "table.md").read_text()
    assert len(list((out / "figures").glob("*.png"))) == 1


def test_cli_train_default_out_and_evaluate_finds_its_checkpoint(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3, W=48, H=32)
    args = ["-q", "train", str(ds), "--epochs", "1", "--crop", "32", "--batch-size", "1"]
    for item in TINY[:2]:
        args += ["--set", item]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "ds-neural_dp" / "best.pt").is_file()
    res = CliRunner().invoke(main, ["-q", "evaluate", str(ds), "--simulator", "disk", "--simulator", "neural", "--figures", "0"])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "ds-eval-test" / "metrics.json").read_text())["checkpoint"].endswith("best.pt")


def test_evaluate_of_neural_without_checkpoint_is_a_clear_error(tmp_path: Path) -> None:
    """Named, a neural without a checkpoint is refused; the default leaves it out (tests/test_cli_conventions.py)."""
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3, W=48, H=32)
    res = CliRunner().invoke(main, ["evaluate", str(ds), "--simulator", "disk", "--simulator", "neural"])
    assert res.exit_code == 3 and "dp5k train" in res.output


def test_checkpoints_refuse_pickled_code(tmp_path: Path) -> None:
    bad = tmp_path / "bad.pt"
    torch.save({"model": {}, "evil": Path("/")}, bad)  # a non-tensor object: rejected by weights_only
    with pytest.raises(BadInputError, match="bad.pt"):
        load_checkpoint(bad)
    with pytest.raises(BadInputError):
        get_simulator("neural", bad)
    with pytest.raises(BadInputError, match="checkpoint"):
        get_simulator("neural")


def test_config_file_then_overrides(tmp_path: Path) -> None:
    f = tmp_path / "c.toml"
    f.write_text('seed = 3\n[data]\ncrop_px = 64\n[optim]\nepochs = 7\nlr = 1e-3\n')
    cfg = load_config(f, ["optim.epochs=9", "model.norm=group", "optim.amp=false"])
    assert (cfg.seed, cfg.data.crop_px, cfg.optim.epochs, cfg.optim.lr) == (3, 64, 9, 1e-3)
    assert cfg.model.norm == "group" and cfg.optim.amp is False
    with pytest.raises(BadInputError, match="unknown config key 'optim.epoch'"):
        load_config(None, ["optim.epoch=3"])
    with pytest.raises(BadInputError, match="must be an integer"):
        load_config(None, ["optim.epochs=many"])
    f.write_text("[data\n")
    with pytest.raises(BadInputError, match="cannot parse"):
        load_config(f)
