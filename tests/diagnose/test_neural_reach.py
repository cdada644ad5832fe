"""``diagnose_neural``: reach of a Neural DP checkpoint per |CoC| bin, exact multi-scale extension, fair control."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from dp5k_studio.dataset import make_dataset
from dp5k_common.dataset import DatasetReader
from dp5k_diagnose.neural_reach import NeuralReachConfig, diagnose_neural, format_table
from dp5k_learn.config import DataConfig, FinetuneConfig, OptimConfig
from neural_dp.config import TrainConfig
from neural_dp.model import ModelConfig
from neural_dp.registry import SimulatorSpec, get_simulator
from neural_dp.train import train


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny f/1.8 studio set (|CoC| beyond 8 px) and a tiny 5 x 5 checkpoint trained on it."""
    root = tmp_path_factory.mktemp("neural_reach")
    ds = make_dataset(root / "ds", scenes=3, size=(64, 48), f_numbers=(1.8,), seed=2)
    cfg = TrainConfig(seed=0, device="cpu", data=DataConfig(crop_px=32, batch_size=2, samples_per_epoch=4, vflip=False),
                      model=ModelConfig(base_channels=4, levels=2, norm="group", tile_px=0),
                      optim=OptimConfig(epochs=2, lr=2e-3, amp=False))
    train(ds, root / "ckpt", cfg)
    return ds, root / "ckpt" / "best.pt"


def test_diagnose_neural_extends_exactly_and_reports_gain_per_coc_bin(trained: tuple[Path, Path], tmp_path: Path) -> None:
    torch.set_num_threads(1)
    ds, ckpt = trained
    r = DatasetReader(ds)
    coc = max(float(abs(r.load(p).coc_px[r.load(p).valid]).max()) for p in r.ids("test"))
    assert coc > 8.0  # the held-out pairs reach past the dilation-2 scale

    study = NeuralReachConfig(finetune=FinetuneConfig(steps=4, seed=0, crop_px=32, batch_size=2), levels=2, n_boot=200)
    res = diagnose_neural(ds, ckpt, tmp_path / "out", study)
    json.dumps(res, allow_nan=False)  # JSON-able, NaN written as null
    assert json.loads((tmp_path / "out" / "neural_reach.json").read_text())["n_pairs"] == res["n_pairs"] == 2
    assert (tmp_path / "out" / "neural_reach.png").stat().st_size > 0

    ext = res["extension"]
    # the extension starts as the checkpoint, bit for bit: the gain is learned, not an artefact of the init
    assert ext["init_max_abs_diff"] == 0.0
    assert ext["dilations_px"] == [2, 4] and ext["reach_px_before"] == 2 and ext["reach_px_after"] == 10
    # same budget for the control and the extension, on the same crops
    ft = res["finetune"]
    assert len(ft["loss_control"]) == len(ft["loss_extended"]) == 4
    assert ft["loss_extended"][0] == pytest.approx(ft["loss_control"][0], rel=1e-5)  # identical first step
    assert ft["loss_extended"][1:] != ft["loss_control"][1:]  # then the new scales change the fit

    # the checkpoint's error is measured per |CoC| bin and grows with it
    assert res["error_growth"]["grows"] is True
    bins = [b for b in res["per_bin"] if b["pixels"] > 0]
    assert bins[0]["bin_px"][0] == 0.0 and bins[-1]["bin_px"][0] >= 8.0
    for b in bins:
        if b["gain_db"] is not None:
            lo, hi = b["gain_ci95"]
            assert lo <= b["gain_db"] <= hi
            assert math.isfinite(b["psnr_before"]) and math.isfinite(b["psnr_extended"])
    g = res["gain_vs_control"]
    assert set(g) >= {"split", "psnr_before", "psnr_after", "ssim_before", "ssim_after", "mae_before", "mae_after",
                      "psnr_gain_ci95"}
    assert g["psnr_before"] == pytest.approx(res["metrics"]["control"]["psnr"])
    assert res["gain"]["psnr_before"] == pytest.approx(res["metrics"]["before"]["psnr"])
    assert "| abs(CoC) px |" in format_table(res)

    # the fine-tuned extension is a loadable multi-scale checkpoint
    sim = get_simulator("neural", checkpoint=res["checkpoints"]["extended"])
    assert sim.cfg.multiscale_levels == 2


def test_cli_diagnose_neural_checkpoint_reports_its_extension(trained: tuple[Path, Path], tmp_path: Path) -> None:
    """``dp5k diagnose DS --simulator neural:CKPT`` carries the structural extension's per-|CoC| gains into the report."""
    from dp5k_diagnose.run import DiagnoseConfig, run_diagnose

    torch.set_num_threads(1)
    ds, ckpt = trained
    out = tmp_path / "diag"
    res = run_diagnose(ds, SimulatorSpec.parse(f"neural:{ckpt}"), out,
                       DiagnoseConfig(fit_pairs=2, n_boot=100, neural=NeuralReachConfig(finetune=FinetuneConfig(steps=2))))
    saved = json.loads((out / "report.json").read_text())
    ne = saved["neural_extension"]
    assert saved["model"] == f"neural:{ckpt}" and ne == json.loads(json.dumps(res["neural_extension"]))
    assert ne["extension"]["init_max_abs_diff"] == 0.0 and ne["extension"]["reach_px_after"] > ne["extension"]["reach_px_before"]
    assert {"psnr_before", "psnr_after", "psnr_gain_ci95"} <= set(ne["gain_vs_control"])
    assert len(ne["per_bin"]) == len(ne["bins_px"]) and all((out / f).is_file() for f in ne["figures"])
    md = (out / "report.md").read_text()
    assert "structural extension" in md and "gain vs control" in md


def test_cli_diagnose_neural_missing_checkpoint_is_a_one_line_error(trained: tuple[Path, Path], tmp_path: Path) -> None:
    from click.testing import CliRunner

    from dp5k_cli import main

    ds, _ = trained
    res = CliRunner().invoke(main, ["diagnose", str(ds), "--simulator", f"neural:{tmp_path / 'nope.pt'}", "--out", str(tmp_path / "o")])
    assert res.exit_code == 3 and "checkpoint not found" in res.output and "nope.pt" in res.output
    assert not (tmp_path / "o" / "report.json").exists()
