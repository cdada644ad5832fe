"""``dp5k train``, ``dp5k evaluate`` and ``dp5k synthesize``: thin click wrappers over the library."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from dp5k_common.errors import BadInputError

from .config import load_config


F = TypeVar("F", bound=Callable[..., Any])


def training_options(config_module: str) -> Callable[[F], F]:
    """The options every training command shares (``dp5k train``, ``dp5k deblur train``): a config file, the
    common overrides, ``--set`` and ``--no-resume``; ``config_module`` names where the config is documented."""
    options = [
        click.option("--config", "config_file", type=click.Path(path_type=Path), default=None,
                     help=f"TOML (or JSON) config file; see {config_module}."),
        click.option("--epochs", type=int, default=None, help="Override optim.epochs."),
        click.option("--batch-size", type=int, default=None, help="Override data.batch_size (per process)."),
        click.option("--lr", type=float, default=None, help="Override optim.lr."),
        click.option("--crop", type=int, default=None, help="Override data.crop_px."),
        click.option("--device", default=None, help="cpu, cuda, cuda:N or auto (default: auto)."),
        click.option("--seed", type=int, default=None, help="Override seed."),
        click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Any config override; repeatable."),
        click.option("--no-resume", is_flag=True, help="Ignore an existing last.pt (refuses if it exists, to protect it)."),
    ]

    def wrap(fn: F) -> F:
        for option in reversed(options):
            fn = option(fn)
        return fn

    return wrap


def config_overrides(sets: tuple[str, ...], epochs: int | None, batch_size: int | None, lr: float | None,
                     crop: int | None, device: str | None, seed: int | None) -> list[str]:
    """``SECTION.KEY=VALUE`` overrides from ``--set`` and the named options that were given."""
    overrides = list(sets)
    for key, value in (("optim.epochs", epochs), ("data.batch_size", batch_size), ("optim.lr", lr),
                       ("data.crop_px", crop), ("device", device), ("seed", seed)):
        if value is not None:
            overrides.append(f"{key}={value}")
    return overrides


def refuse_fresh_run_over(out: Path, no_resume: bool) -> None:
    """``--no-resume`` never overwrites a previous run: refuse when ``out/last.pt`` exists."""
    if no_resume and (out / "last.pt").exists():
        raise BadInputError("--no-resume but a previous run's last.pt exists here; choose another --out", where=out)


def default_run_dir(dataset: Path) -> Path:
    """Where ``dp5k train`` writes by default and ``dp5k evaluate`` looks: ``<dataset>-neural_dp`` beside it."""
    dataset = dataset.resolve()
    return dataset.parent / f"{dataset.name}-neural_dp"


@click.command("train")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Run folder (checkpoints, config, history). Default: DATASET-neural_dp beside the dataset.")
@training_options("neural_dp/config.py")
def train_command(dataset: Path, out_dir: Path | None, config_file: Path | None, epochs: int | None,
                  batch_size: int | None, lr: float | None, crop: int | None, device: str | None, seed: int | None,
                  sets: tuple[str, ...], no_resume: bool) -> None:
    """Train the Neural DP Simulator on DATASET's train split (best checkpoint by val SSIM).

    Runs again in the same --out resume from last.pt. Multi-GPU / multi-node:
    torchrun --nproc_per_node G -m dp5k_cli train DATASET --out DIR
    """
    from .train import train

    cfg = load_config(config_file, config_overrides(sets, epochs, batch_size, lr, crop, device, seed))
    out = out_dir or default_run_dir(dataset)
    refuse_fresh_run_over(out, no_resume)
    result = train(dataset, out, cfg, resume=not no_resume)
    click.echo(f"{out}: {result.epochs_done} epoch(s), {result.steps} steps; best val SSIM {result.best_val_ssim:.4f} "
               f"at epoch {result.best_epoch} -> {out / 'best.pt'}")


@click.command("evaluate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--split", default="test", show_default=True, help="Split to evaluate.")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (metrics.json, table.md, figures/). Default: DATASET-eval-SPLIT beside the dataset.")
@click.option("--checkpoint", type=click.Path(path_type=Path), default=None,
              help="Neural DP checkpoint. Default: best.pt of DATASET-neural_dp (what dp5k train wrote).")
@click.option("--simulators", default=None, help="Comma-separated names (default: all available).")
@click.option("--device", default="cpu", show_default=True)
@click.option("--max-pairs", type=int, default=0, help="Evaluate at most this many pairs (0 = all).")
@click.option("--figures", type=int, default=2, show_default=True, help="Pairs that get a comparison picture.")
def evaluate_command(dataset: Path, split: str, out_dir: Path | None, checkpoint: Path | None, simulators: str | None,
                     device: str, max_pairs: int, figures: int) -> None:
    """Table 2: masked MAE / PSNR / SSIM of every simulator on the same pairs of DATASET."""
    from .evaluate import evaluate

    names = [s.strip() for s in simulators.split(",") if s.strip()] if simulators else None
    if checkpoint is None:
        guess = default_run_dir(dataset) / "best.pt"
        if guess.is_file():
            checkpoint = guess
        elif names is None or "neural" in names:
            raise BadInputError(
                f"no checkpoint at {guess}; run 'dp5k train' first, pass --checkpoint, or pick --simulators without neural",
                where=dataset,
            )
    out = out_dir or dataset.resolve().parent / f"{dataset.resolve().name}-eval-{split}"
    result = evaluate(dataset, out, split=split, simulators=names, checkpoint=checkpoint, device=device,
                      max_pairs=max_pairs, figures=figures)
    click.echo(result.table_md.rstrip())
    click.echo(f"-> {out / 'metrics.json'}, {out / 'table.md'}, {out / 'figures'}")


@click.command("synthesize")
@click.argument("in_dir", type=click.Path(path_type=Path))
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("--simulator", default="neural", show_default=True, help="disk, butterworth, raytrace, base, neural or diagnosed:REPORT.json (a dp5k diagnose report).")
@click.option("--checkpoint", type=click.Path(path_type=Path), default=None, help="Needed by --simulator neural.")
@click.option("--f-number", "f_numbers", type=float, multiple=True,
              help="Fixed f-number; repeat to draw one per frame (default: 1.8, 2, 2.8, 4, 5.6).")
@click.option("--focus-mm", type=float, default=None, help="Fixed focus distance (default: random 60x40 window).")
@click.option("--max-coc-px", type=float, default=20.0, show_default=True,
              help="Sensor-size adjustment target: 99th-percentile |CoC| at f/1.8, px.")
@click.option("--no-sensor-adjust", is_flag=True, help="Keep the nominal 36 mm sensor (no 5.3.1 adjustment).")
@click.option("--sensor-width-mm", type=float, default=36.0, show_default=True)
@click.option("--encoding", type=click.Choice(["srgb", "linear"]), default="srgb", show_default=True,
              help="How image.png is encoded.")
@click.option("--depth-scale", type=float, default=1.0, show_default=True, help="depth.npy values x this = mm.")
@click.option("--batch-size", type=int, default=4, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", default="cpu", show_default=True)
def synthesize_command(in_dir: Path, out_dir: Path, simulator: str, checkpoint: Path | None,
                       f_numbers: tuple[float, ...], focus_mm: float | None, max_coc_px: float, no_sensor_adjust: bool,
                       sensor_width_mm: float, encoding: str, depth_scale: float, batch_size: int, seed: int,
                       device: str) -> None:
    """Turn RGBD frames IN_DIR/<frame>/{image.png, depth.png|depth.npy, intrinsics.json} into a DP dataset OUT_DIR.

    Resumable: frames already in OUT_DIR are skipped. Sharded over processes or machines (each rank
    converts every N-th frame and resumes its own share; rank 0 writes the index once all are done):

    \b
    torchrun --nproc_per_node N -m dp5k_cli synthesize IN_DIR OUT_DIR ...
    """
    from .synthesize import PAPER_F_NUMBERS, SynthConfig, synthesize

    cfg = SynthConfig(
        simulator=simulator, checkpoint=None if checkpoint is None else str(checkpoint),
        f_numbers=tuple(f_numbers) or PAPER_F_NUMBERS, focus_mm=focus_mm,
        max_coc_px=None if no_sensor_adjust else max_coc_px, sensor_width_mm=sensor_width_mm, encoding=encoding,
        depth_scale=depth_scale, batch_size=batch_size, seed=seed, device=device,
    )
    summary = synthesize(in_dir, out_dir, cfg)
    rank = f" (rank {summary['rank']} of {summary['world_size']})" if summary["world_size"] > 1 else ""
    click.echo(f"{out_dir}{rank}: wrote {summary['written']} pair(s), skipped {summary['skipped']} already done; "
               f"{summary['pairs']} pair(s) in the dataset")
