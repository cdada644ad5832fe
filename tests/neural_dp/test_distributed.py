"""torchrun with two CPU processes (gloo): DistributedDataParallel training and resume; sharded synthesis."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from dp5k_common.dataset import DatasetReader
from dp5k_testing.tiny_dataset import make_tiny_dataset
from dp5k_testing.torchrun import run_torchrun
from dp5k_learn.checkpoint import load_checkpoint
from neural_dp.synthesize import SynthConfig, synthesize

from .test_synthesize import _frames


def _torchrun(ds: Path, out: Path, epochs: int) -> subprocess.CompletedProcess[str]:
    return run_torchrun(["train", ds, "--out", out, "--device", "cpu", "--epochs", epochs, "--crop", "32",
                         "--batch-size", "2", "--set", "data.samples_per_epoch=4", "--set", "model.base_channels=4",
                         "--set", "model.levels=2"])


@pytest.mark.distributed
@pytest.mark.slow
def test_torchrun_two_processes_gloo_train_and_resume(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=6, W=48, H=32)
    out = tmp_path / "run"
    proc = _torchrun(ds, out, epochs=1)
    assert proc.returncode == 0, proc.stderr[-3000:]
    state = load_checkpoint(out / "last.pt")
    # 4 samples per epoch over 2 ranks with batch 2: one step per rank per epoch
    assert state["epoch"] == 1 and state["step"] == 1
    assert json.loads((out / "history.json").read_text())[0]["val_ssim"] > 0
    proc = _torchrun(ds, out, epochs=2)  # resume under torchrun
    assert proc.returncode == 0, proc.stderr[-3000:]
    state2 = load_checkpoint(out / "last.pt")
    assert state2["epoch"] == 2 and state2["step"] == 2
    changed = any(not torch.equal(state["model"][k], state2["model"][k]) for k in state["model"])
    assert changed


def _torchrun_synthesize(src: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return run_torchrun(["synthesize", src, out, "--simulator", "disk", "--depth-scale", "1000", "--batch-size", "2"])


def _written_per_rank(stdout: str) -> dict[int, int]:
    """Rank -> pairs it wrote, from each rank's closing line '... (rank R of 2): wrote K pair(s), ...'."""
    found = re.findall(r"\(rank (\d) of 2\): wrote (\d+) pair", stdout)
    return {int(r): int(k) for r, k in found}


def _assert_same_dataset(a: Path, b: Path) -> None:
    """Same index (split assignment and order), same parameters and same images, pair by pair (the provenance names
    each run's own command)."""
    index_a, index_b = (json.loads((d / "dataset.json").read_text()) for d in (a, b))
    index_a.pop("provenance"), index_b.pop("provenance")
    assert index_a == index_b
    ra, rb = DatasetReader(a), DatasetReader(b)
    assert ra.ids() == rb.ids()
    for pid in ra.ids():
        assert (a / "pairs" / pid / "params.json").read_text() == (b / "pairs" / pid / "params.json").read_text()
        pa, pb = ra.load(pid), rb.load(pid)
        for key in ("sharp", "left", "right", "depth_mm"):
            np.testing.assert_array_equal(getattr(pa, key), getattr(pb, key), err_msg=f"{pid} {key}")


@pytest.mark.distributed
@pytest.mark.slow
def test_torchrun_synthesize_writes_each_frame_once_and_equals_one_process(tmp_path: Path) -> None:
    _frames(tmp_path / "in", n=5)
    one = synthesize(tmp_path / "in", tmp_path / "one", SynthConfig(simulator="disk", depth_scale=1000.0, batch_size=2))
    assert one["written"] == 5 and one["world_size"] == 1
    proc = _torchrun_synthesize(tmp_path / "in", tmp_path / "two")
    assert proc.returncode == 0, proc.stderr[-3000:]
    # frames 0, 2, 4 to rank 0 and 1, 3 to rank 1: each written by exactly one rank
    assert _written_per_rank(proc.stdout) == {0: 3, 1: 2}
    _assert_same_dataset(tmp_path / "one", tmp_path / "two")


@pytest.mark.distributed
@pytest.mark.slow
def test_torchrun_synthesize_resumes_each_share_without_rewriting(tmp_path: Path) -> None:
    """A run that stopped part-way (two pairs of different ranks' shares and the index missing) is finished by
    a 2-rank run: only the missing pairs are written, the finished ones are left untouched."""
    _frames(tmp_path / "in", n=5)
    cfg = SynthConfig(simulator="disk", depth_scale=1000.0, batch_size=2)
    synthesize(tmp_path / "in", tmp_path / "ref", cfg)
    shutil.copytree(tmp_path / "ref", tmp_path / "out")
    for pid in ("frame_01", "frame_02"):  # one of rank 1's frames, one of rank 0's
        shutil.rmtree(tmp_path / "out" / "pairs" / pid)
    (tmp_path / "out" / "dataset.json").unlink()
    kept = {pid: (tmp_path / "out" / "pairs" / pid / "params.json").stat().st_mtime_ns
            for pid in ("frame_00", "frame_03", "frame_04")}
    proc = _torchrun_synthesize(tmp_path / "in", tmp_path / "out")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert _written_per_rank(proc.stdout) == {0: 1, 1: 1}
    for pid, mtime in kept.items():
        assert (tmp_path / "out" / "pairs" / pid / "params.json").stat().st_mtime_ns == mtime, pid
    _assert_same_dataset(tmp_path / "ref", tmp_path / "out")
