"""``dp5k deblur train|evaluate`` and ``dp5k study downstream``: thin click wrappers over the library."""

from __future__ import annotations

from pathlib import Path

import click

from dp5k_common.errors import BadInputError


@click.group("deblur")
def deblur_group() -> None:
    """DP defocus deblurring: a DPDNet-like U-Net from the two DP views to the sharp image."""


@deblur_group.command("train")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True,
              help="Run folder (config.json, last.pt, best.pt, history.json).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), default=None,
              help="TOML (or JSON) config file; see dp5k_deblur/config.py.")
@click.option("--epochs", type=int, default=None, help="Override optim.epochs.")
@click.option("--batch-size", type=int, default=None, help="Override data.batch_size (per process).")
@click.option("--lr", type=float, default=None, help="Override optim.lr.")
@click.option("--crop", type=int, default=None, help="Override data.crop_px.")
@click.option("--device", default=None, help="cpu, cuda, cuda:N or auto (default: auto).")
@click.option("--seed", type=int, default=None, help="Override seed.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Any config override; repeatable.")
@click.option("--init-from", type=click.Path(path_type=Path), default=None,
              help="Start a fresh run from this deblurrer checkpoint's weights (fine-tuning).")
@click.option("--no-resume", is_flag=True, help="Ignore an existing last.pt (refuses if it exists, to protect it).")
def deblur_train_command(dataset: Path, out_dir: Path, config_file: Path | None, epochs: int | None, batch_size: int | None,
                         lr: float | None, crop: int | None, device: str | None, seed: int | None, sets: tuple[str, ...],
                         init_from: Path | None, no_resume: bool) -> None:
    """Train the deblurrer on DATASET's train split (any format-v1 dataset; best checkpoint by val SSIM).

    Runs again in the same --out resume from last.pt. Multi-GPU / multi-node:
    torchrun --nproc_per_node G -m dp5k_cli deblur train DATASET --out DIR
    """
    from .config import load_deblur_config
    from .train import train_deblur

    overrides = list(sets)
    for key, value in (("optim.epochs", epochs), ("data.batch_size", batch_size), ("optim.lr", lr),
                       ("data.crop_px", crop), ("device", device), ("seed", seed)):
        if value is not None:
            overrides.append(f"{key}={value}")
    cfg = load_deblur_config(config_file, overrides)
    if no_resume and (out_dir / "last.pt").exists():
        raise BadInputError("--no-resume but a previous run's last.pt exists here; choose another --out", where=out_dir)
    result = train_deblur(dataset, out_dir, cfg, resume=not no_resume, init_from=init_from)
    click.echo(f"{out_dir}: {result.epochs_done} epoch(s), {result.steps} steps; best val SSIM {result.best_val_ssim:.4f} "
               f"at epoch {result.best_epoch} -> {out_dir / 'best.pt'}")


@deblur_group.command("evaluate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True, help="A dp5k deblur train checkpoint (best.pt).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True,
              help="Output folder (metrics.json, table.md, figures/).")
@click.option("--split", default="test", show_default=True, help="Split to evaluate.")
@click.option("--device", default="cpu", show_default=True)
@click.option("--max-pairs", type=int, default=0, help="Evaluate at most this many pairs (0 = all).")
def deblur_evaluate_command(dataset: Path, checkpoint: Path, out_dir: Path, split: str, device: str, max_pairs: int) -> None:
    """Masked MAE / PSNR / SSIM of the deblurred image against sharp, beside the blurred input L+R."""
    from .evaluate import evaluate_deblur, table_md

    scores = evaluate_deblur(dataset, checkpoint, out_dir, split=split, device=device, max_pairs=max_pairs)
    click.echo(table_md(scores).rstrip())
    click.echo(f"-> {out_dir / 'metrics.json'}, {out_dir / 'table.md'}, {out_dir / 'figures'}")
