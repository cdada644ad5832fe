"""Train the DP deblurrer on any format-v1 dataset: Charbonnier loss against ``sharp``, Adam + cosine annealing,
best-by-val-SSIM, resume and torchrun, all through the epoch loop ``dp5k train`` uses (:mod:`neural_dp.epochs`).

``train_deblur`` writes into ``out_dir`` what :func:`neural_dp.epochs.run_epochs` writes (``config.json``,
``last.pt``, ``best.pt``, ``history.json``). With ``init_from`` a fresh run starts from another run's weights
(the paper's transfer setting: pre-train on synthetic data, fine-tune on a few real pairs).

Launch on several GPUs: ``torchrun --nproc_per_node G -m dp5k_cli deblur train DATASET --out DIR``.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path

import torch
from torch import Tensor
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler

from dp5k_common.errors import BadInputError, EmptySplitError, StageError
from neural_dp import distributed as D
from neural_dp.batch import DPBatch
from neural_dp.checkpoint import load_checkpoint
from neural_dp.data import CropSpec, DPPairDataset, collate_dp
from neural_dp.epochs import EpochLoop, TrainResult, run_epochs
from neural_dp.losses import CHARBONNIER_EPS, masked_charbonnier, masked_gradient_charbonnier
from neural_dp.metrics import masked_mae, masked_psnr, masked_ssim

from .config import DeblurTrainConfig
from .model import DeblurNetConfig, DPDeblurNet


def target_mask(valid: Tensor) -> Tensor:
    """(B, 1, H, W) float: the valid-depth mask, or all ones for an item without any valid depth (a DPDD import:
    the sharp target is defined everywhere even where depth is not)."""
    v = valid.float()
    has_depth = v.flatten(1).amax(1).view(-1, 1, 1, 1) > 0
    return torch.where(has_depth, v, torch.ones_like(v))


def deblur_loss(pred: Tensor, sharp: Tensor, mask: Tensor, grad_weight: float = 0.0, eps: float = CHARBONNIER_EPS) -> Tensor:
    """Masked Charbonnier (``eps`` in linear intensity) of the prediction against ``sharp`` (plus ``grad_weight`` x
    the gradient term). Scalar."""
    loss = masked_charbonnier(pred, sharp, mask, eps)
    if grad_weight:
        loss = loss + grad_weight * masked_gradient_charbonnier(pred, sharp, mask, eps)
    return loss


def views(batch: DPBatch, where: str) -> tuple[Tensor, Tensor]:
    """The batch's (left, right) views, (B, 3, H, W). Raises BadInputError when the dataset has none."""
    if batch.left is None or batch.right is None:
        raise BadInputError("a deblurring pair needs its left and right views", where=where)
    return batch.left, batch.right


def deblur_step(net: torch.nn.Module, module: torch.nn.Module, batch: DPBatch, opt: torch.optim.Optimizer,
                sched: torch.optim.lr_scheduler.LRScheduler, *, grad_weight: float, grad_clip: float, eps: float = CHARBONNIER_EPS,
                amp: bool = False, step: int = 0) -> Tensor:
    """One optimiser step: forward, masked Charbonnier loss, backward, gradient clipping, Adam, schedule.

    Raises:
        StageError: the loss is not finite.
    """
    left, right = views(batch, "deblur train")
    with torch.autocast(device_type=batch.sharp.device.type, dtype=torch.bfloat16, enabled=amp):
        pred = net(left, right)
    loss = deblur_loss(pred.float(), batch.sharp, target_mask(batch.valid), grad_weight, eps)
    if not torch.isfinite(loss):
        raise StageError(f"loss is {float(loss)} at step {step} (lower the learning rate?)", where="deblur train")
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(module.parameters(), grad_clip)
    opt.step()
    sched.step()
    return loss.detach()


def sharp_metrics(pred: Tensor, sharp: Tensor, valid: Tensor) -> dict[str, Tensor]:
    """Masked MAE, PSNR (dB) and SSIM of (B, 3, H, W) images against ``sharp`` (:func:`target_mask`). Each (B,)."""
    m = target_mask(valid)
    return {"mae": masked_mae(pred, sharp, m), "psnr": masked_psnr(pred, sharp, m), "ssim": masked_ssim(pred, sharp, m)}


@torch.no_grad()
def validate_deblur(net: DPDeblurNet, ds: DPPairDataset, info: D.DistInfo, max_pairs: int = 0) -> dict[str, float]:
    """Mean masked SSIM / PSNR / MAE of the prediction against ``sharp`` on whole val pairs, sharded over processes."""
    was_training = net.training
    net.eval()
    n = len(ds.ids) if max_pairs <= 0 else min(max_pairs, len(ds.ids))
    acc = torch.zeros(4, dtype=torch.float64, device=info.device)
    for i in range(info.rank, n, info.world_size):
        batch = collate_dp([ds[i]]).to(info.device)
        m = sharp_metrics(net(*views(batch, "deblur validate")).float(), batch.sharp, batch.valid)
        acc += torch.tensor([float(m["ssim"][0]), float(m["psnr"][0]), float(m["mae"][0]), 1.0], dtype=torch.float64,
                            device=info.device)
    acc = D.all_reduce_sum(acc, info)
    net.train(was_training)
    count = max(float(acc[3]), 1.0)
    return {"ssim": float(acc[0]) / count, "psnr": float(acc[1]) / count, "mae": float(acc[2]) / count}


def load_deblurrer(checkpoint: str | os.PathLike[str], device: torch.device | str = "cpu") -> DPDeblurNet:
    """A trained deblurrer from a ``dp5k deblur train`` checkpoint, in eval mode.

    Raises:
        BadInputError: missing, unreadable or not a deblurrer's checkpoint.
    """
    state = load_checkpoint(checkpoint, map_location=device)
    cfg = state.get("model_config")
    try:
        net = DPDeblurNet(DeblurNetConfig(**cfg))  # type: ignore[arg-type]
        net.load_state_dict(state["model"])
    except (TypeError, RuntimeError) as exc:
        raise BadInputError("not a deblurrer checkpoint (dp5k deblur train writes one)", where=checkpoint) from exc
    return net.to(device).eval()


def _val_split(root: Path, seed: int) -> DPPairDataset:
    for split in ("val", "train"):
        try:
            return DPPairDataset(root, split, CropSpec(), seed=seed)
        except EmptySplitError:
            continue
    raise EmptySplitError("the train split is empty; nothing to train on", where=root / "dataset.json")


def train_deblur(dataset: str | os.PathLike[str], out_dir: str | os.PathLike[str], cfg: DeblurTrainConfig, *,
                 resume: bool = True, init_from: str | os.PathLike[str] | None = None) -> TrainResult:
    """Train (or resume training) the deblurrer on ``dataset``'s train split; select by val SSIM (train when no val).

    Args:
        dataset: any format-v1 dataset (studio, synthesized, imported).
        out_dir: run folder (created).
        cfg: the run's configuration.
        resume: continue from ``out_dir/last.pt`` when it exists.
        init_from: a deblurrer checkpoint whose weights a fresh run starts from (fine-tuning).

    Raises:
        EmptySplitError: no train pairs. BadInputError: unusable checkpoint or config. StageError: NaN loss.
    """
    info = D.setup(cfg.device)
    try:
        return _train(Path(dataset), Path(out_dir), cfg, info, resume, init_from)
    finally:
        D.teardown()


def _train(root: Path, out: Path, cfg: DeblurTrainConfig, info: D.DistInfo, resume: bool,
           init_from: str | os.PathLike[str] | None) -> TrainResult:
    device = info.device
    out.mkdir(parents=True, exist_ok=True)
    crop = CropSpec(cfg.data.crop_px, cfg.data.min_valid_fraction, vflip=cfg.data.vflip)
    try:
        train_ds = DPPairDataset(root, "train", crop, seed=cfg.seed, length=cfg.data.samples_per_epoch)
    except EmptySplitError as exc:
        raise EmptySplitError("the train split is empty; nothing to train on", where=root / "dataset.json") from exc
    val_ds = _val_split(root, cfg.seed)
    torch.manual_seed(cfg.seed)
    net = DPDeblurNet(cfg.model).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.optim.lr, betas=(0.9, 0.999))
    sampler = DistributedSampler(train_ds, num_replicas=info.world_size, rank=info.rank, shuffle=True, seed=cfg.seed,
                                 drop_last=False)
    loader = DataLoader(train_ds, batch_size=cfg.data.batch_size, sampler=sampler, num_workers=cfg.data.num_workers,
                        collate_fn=collate_dp)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, cfg.optim.epochs * len(loader)),
                                                       eta_min=cfg.optim.lr_min)
    wrapped: torch.nn.Module = net
    if info.enabled:
        wrapped = DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None)
    use_amp = cfg.optim.amp and device.type == "cuda"

    def step(batch: DPBatch, k: int) -> Tensor:
        return deblur_step(wrapped, net, batch, opt, sched, grad_weight=cfg.optim.grad_weight, grad_clip=cfg.optim.grad_clip,
                           eps=cfg.charbonnier_eps, amp=use_amp, step=k)

    def start_from_checkpoint() -> None:
        if init_from is not None:
            net.load_state_dict(load_deblurrer(init_from, device).state_dict())

    loop = EpochLoop(module=net, opt=opt, sched=sched, train_ds=train_ds, loader=loader, sampler=sampler, step=step,
                     validate=lambda: validate_deblur(net, val_ds, info, cfg.data.val_pairs), model_config=asdict(cfg.model),
                     config={**cfg.to_dict(), "init_from": None if init_from is None else str(init_from)},
                     epochs=cfg.optim.epochs, seed=cfg.seed, defaults=asdict(DeblurNetConfig()))
    return run_epochs(loop, out, info, resume=resume, on_fresh_start=start_from_checkpoint, desc="deblur train")
