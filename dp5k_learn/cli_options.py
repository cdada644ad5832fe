"""The command-line options every training command shares (``dp5k train``, ``dp5k deblur train``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from dp5k_common.errors import BadInputError

F = TypeVar("F", bound=Callable[..., Any])


def training_options(config_module: str) -> Callable[[F], F]:
    """A config file, the common overrides, ``--set`` and ``--no-resume``; ``config_module`` names where the
    command's config is documented."""
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


def report_run(out: Path, result: Any) -> str:
    """The line a training command prints when done: epochs, steps and the best checkpoint (a ``TrainResult``)."""
    return (f"{out}: {result.epochs_done} epoch(s), {result.steps} steps; best val SSIM {result.best_val_ssim:.4f} "
            f"at epoch {result.best_epoch} -> {out / 'best.pt'}")
