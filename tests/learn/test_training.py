"""The shared learning layer: one rank type read from torchrun's environment, one run set-up, one optimiser step,
validation over the split, fine-tuning's fixed steps."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from dp5k_common.errors import BadInputError, StageError
from dp5k_common.sharding import RankInfo, rank_info
from dp5k_learn import training
from dp5k_learn.batch import DPBatch
from dp5k_learn.config import DataConfig, FinetuneConfig, OptimConfig
from dp5k_learn.data import collate_dp
from dp5k_testing.tiny_dataset import make_tiny_dataset


def test_rank_info_reads_and_checks_torchrun_s_environment() -> None:
    assert rank_info({}) == RankInfo(0, 1, 0) and not rank_info({}).enabled
    info = rank_info({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"})
    assert (info.rank, info.world_size, info.local_rank, info.is_main, info.enabled) == (3, 4, 1, False, True)
    for env, message in (({"RANK": "x", "WORLD_SIZE": "2"}, "not integers"),
                         ({"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "a"}, "not integers"),
                         ({"RANK": "2", "WORLD_SIZE": "2"}, "RANK=2 is not in 0..WORLD_SIZE-1"),
                         ({"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "-1"}, "LOCAL_RANK=-1")):
        with pytest.raises(BadInputError, match=message):
            rank_info(env)


class _Scale(nn.Module):
    """out = w * sharp: one parameter, so a step's effect can be computed by hand."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.tensor(2.0))

    def forward(self, batch: DPBatch) -> torch.Tensor:
        return self.w * batch.sharp


def _mse(out: torch.Tensor, batch: DPBatch) -> torch.Tensor:
    return ((out - batch.left) ** 2).mean()


def test_one_optimiser_step_clips_steps_and_schedules(tmp_path: Path) -> None:
    make_tiny_dataset(tmp_path / "ds", scenes=3)
    train_ds, val_ds = training.open_splits(tmp_path / "ds", DataConfig(crop_px=8, batch_size=2, samples_per_epoch=4),
                                            seed=0)
    assert len(train_ds) == 4 and val_ds.split == "val"
    model = _Scale()
    run = training.build_run(model, train_ds, DataConfig(batch_size=2), OptimConfig(epochs=3, lr=0.1, grad_clip=1e-3),
                             seed=0, rank=RankInfo(), device=torch.device("cpu"))
    assert run.net is model and not run.amp  # no DDP wrapper alone, no autocast on the CPU
    assert len(run.loader) == 2 and run.sched.T_max == 3 * 2
    batch = next(iter(run.loader))
    w0 = float(model.w.detach())
    loss = run.step(batch, 0, model, _mse)
    assert loss.ndim == 0 and not loss.requires_grad
    # Adam's first step moves by lr whatever the (clipped) gradient's size, against the gradient's sign
    grad_sign = torch.sign(((w0 * batch.sharp - batch.left) * batch.sharp).mean())
    assert float(model.w.detach()) == pytest.approx(w0 - 0.1 * float(grad_sign), abs=1e-5)
    assert run.sched.last_epoch == 1 and run.opt.param_groups[0]["lr"] < 0.1


def test_a_non_finite_loss_is_a_stage_error_naming_the_step() -> None:
    model = _Scale()
    opt = torch.optim.Adam(model.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)
    batch = collate_dp([_item()])
    with pytest.raises(StageError, match="loss is nan at step 7"):
        training.optimiser_step(model, opt, sched, batch, model, lambda out, b: out.sum() * float("nan"), grad_clip=0,
                                step=7)
    assert float(model.w.detach()) == 2.0  # nothing was stepped


def _item() -> dict[str, object]:
    ones = torch.ones(3, 4, 4)
    return {"sharp": ones, "left": ones * 0.4, "right": ones * 0.6, "coc_px": torch.zeros(1, 4, 4),
            "depth_mm": torch.ones(1, 4, 4), "valid": torch.ones(1, 4, 4, dtype=torch.bool),
            **{k: torch.tensor(1.0) for k in ("f_number", "focus_distance_mm", "focal_length_mm", "pixel_pitch_mm",
                                             "sharp_f_number")},
            "focus_point_px": torch.zeros(2), "pair_id": "p"}


def test_validation_averages_every_pair_in_eval_mode(tmp_path: Path) -> None:
    make_tiny_dataset(tmp_path / "ds", scenes=6)
    _, val_ds = training.open_splits(tmp_path / "ds", DataConfig(crop_px=8), seed=0)
    model = _Scale().train()
    seen: list[tuple[str, bool]] = []

    def score(batch: DPBatch) -> dict[str, torch.Tensor]:
        seen.append((batch.pair_ids[0], model.training))
        return {"ssim": torch.tensor([len(seen) * 1.0]), "psnr": torch.tensor([10.0]), "mae": torch.tensor([0.0])}

    got = training.validate_pairs(model, val_ds, score, RankInfo(), torch.device("cpu"))
    assert [pid for pid, _ in seen] == val_ds.ids and not any(mode for _, mode in seen)
    assert got == {"ssim": sum(range(1, len(seen) + 1)) / len(seen), "psnr": 10.0, "mae": 0.0} and model.training
    seen.clear()
    training.validate_pairs(model, val_ds, score, RankInfo(), torch.device("cpu"), max_pairs=1)
    assert [pid for pid, _ in seen] == val_ds.ids[:1]


def test_finetune_takes_exactly_its_steps_on_the_same_crops(tmp_path: Path) -> None:
    make_tiny_dataset(tmp_path / "ds", scenes=6)
    cfg = FinetuneConfig(steps=5, lr=0.05, crop_px=8, batch_size=2, seed=3)
    runs = []
    for _ in range(2):
        model = _Scale()
        losses = training.finetune(model, tmp_path / "ds", cfg, model, _mse, is_new=lambda name: name == "w")
        runs.append((losses, float(model.w.detach())))
        assert len(losses) == 5 and not model.training
    assert runs[0] == runs[1]  # the crops and their order depend only on the seed
    assert runs[0][1] != 2.0
