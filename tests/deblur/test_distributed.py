"""``dp5k deblur train`` under torchrun: two CPU processes (gloo), one step each, then a resumed epoch."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import torch

from dp5k_testing.tiny_dataset import make_tiny_dataset
from dp5k_testing.torchrun import run_torchrun
from dp5k_learn.checkpoint import load_checkpoint


def _torchrun(ds: Path, out: Path, epochs: int) -> subprocess.CompletedProcess[str]:
    return run_torchrun(["deblur", "train", ds, "--out", out, "--device", "cpu", "--epochs", epochs, "--crop", "32",
                         "--batch-size", "2", "--set", "data.samples_per_epoch=4", "--set", "model.base_channels=4",
                         "--set", "model.levels=2"])


@pytest.mark.distributed
@pytest.mark.slow
def test_torchrun_two_processes_train_and_resume(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=6, W=48, H=32)
    out = tmp_path / "run"
    proc = _torchrun(ds, out, epochs=1)
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = load_checkpoint(out / "last.pt")
    assert state["epoch"] == 1 and state["step"] == 1  # 4 crops over 2 ranks with batch 2: one step per rank
    assert json.loads((out / "history.json").read_text())[0]["val_psnr"] > 0
    proc = _torchrun(ds, out, epochs=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    state2 = load_checkpoint(out / "last.pt")
    assert state2["epoch"] == 2 and state2["step"] == 2
    assert any(not torch.equal(state["model"][k], state2["model"][k]) for k in state["model"])
