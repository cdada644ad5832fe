"""The command-line options every training command shares (``dp5k train``, ``dp5k deblur train``)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from dp5k_common.cli_conventions import device_option, overwrite_option, refuse_earlier_run, resume_option
from dp5k_common.deprecation import warn_deprecated
from dp5k_common.errors import BadInputError

F = TypeVar("F", bound=Callable[..., Any])


def training_options(config_module: str) -> Callable[[F], F]:
    """A config file, the common overrides, ``--set``, ``--resume/--no-resume`` and ``--overwrite``;
    ``config_module`` names where the command's config is documented. The deprecated ``--crop PX`` arrives as
    ``crop_size`` with its deprecation line (``--crop`` is a region of the input frames everywhere else)."""
    options = [
        click.option("--config", "config_file", type=click.Path(path_type=Path), default=None,
                     help=f"TOML (or JSON) config file; see {config_module}."),
        click.option("--epochs", type=click.IntRange(min=1), default=None, help="Override optim.epochs."),
        click.option("--batch-size", type=click.IntRange(min=1), default=None, help="Override data.batch_size (per process)."),
        click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=None, help="Override optim.lr."),
        click.option("--crop-size", type=click.IntRange(min=1), default=None, metavar="PX",
                     help="Override data.crop_px: the side of the square training patches, px."),
        click.option("--crop", "legacy_crop", type=click.IntRange(min=1), default=None, metavar="PX", help="Deprecated: --crop-size PX."),
        device_option(config_default=True),
        click.option("--seed", type=click.IntRange(min=0), default=None, help="Override seed."),
        click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Any config override; repeatable."),
        resume_option("Continue from OUT's last.pt when there is one; --no-resume refuses an OUT that holds one."),
        overwrite_option("Start afresh in OUT, deleting an earlier run's checkpoints, history and report."),
    ]

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def run(*args: Any, crop_size: int | None = None, legacy_crop: int | None = None, **kwargs: Any) -> Any:
            if legacy_crop is not None:
                if crop_size is not None:
                    raise BadInputError("give --crop-size, not the older --crop too", where="--crop")
                warn_deprecated("--crop PX (a training patch size)", "--crop-size PX")
                crop_size = legacy_crop
            return fn(*args, crop_size=crop_size, **kwargs)

        for option in reversed(options):
            run = option(run)
        return run  # type: ignore[return-value]

    return wrap


def config_overrides(sets: tuple[str, ...], epochs: int | None, batch_size: int | None, lr: float | None,
                     crop_size: int | None, device: str | None, seed: int | None) -> list[str]:
    """``SECTION.KEY=VALUE`` overrides from ``--set`` and the named options that were given."""
    overrides = list(sets)
    for key, value in (("optim.epochs", epochs), ("data.batch_size", batch_size), ("optim.lr", lr),
                       ("data.crop_px", crop_size), ("device", device), ("seed", seed)):
        if value is not None:
            overrides.append(f"{key}={value}")
    return overrides


def check_training_inputs(dataset: Path, init_from: Path | None = None) -> None:
    """What a training command reads, checked before OUT is made or an earlier run is touched: the dataset (missing:
    exit 3; not format v1 or no train pair: 4) and a checkpoint to start from (missing: 3).

    Raises:
        BadInputError / DatasetFormatError / EmptySplitError: as above.
    """
    from dp5k_common.dataset import DatasetReader
    from dp5k_common.errors import EmptySplitError

    if not DatasetReader(dataset).ids("train"):
        raise EmptySplitError("the train split is empty; nothing to train on", where=Path(dataset) / "dataset.json")
    if init_from is not None and not Path(init_from).is_file():
        raise BadInputError("checkpoint not found", where=init_from)


RUN_FILES = ("last.pt", "best.pt", "history.json", "network.pt", "report.json")
"""What a training run leaves in its folder (epochs.py; ``neural_dp``'s physics-first runs add the last two)."""


def prepare_run_dir(out: Path, resume: bool, overwrite: bool) -> bool:
    """Apply ``--resume/--no-resume`` and ``--overwrite`` to a training run folder; return whether to resume.

    ``--overwrite`` deletes the earlier run's files (:data:`RUN_FILES`) and starts afresh; ``--no-resume`` without it
    never touches an earlier run: it refuses when ``out/last.pt`` exists.

    Raises:
        BadInputError: ``--no-resume`` (without ``--overwrite``) and an earlier run's last.pt is in ``out``.
    """
    if overwrite:
        for name in RUN_FILES:
            (out / name).unlink(missing_ok=True)
        for name in RUN_FILES:  # a pre-training stage's own run (neural_dp.pretrain)
            (out / "pretrain" / name).unlink(missing_ok=True)
        return False
    if not resume:
        refuse_earlier_run(out / "last.pt", "an earlier run's last.pt")
    return resume


def report_run(out: Path, result: Any) -> str:
    """The line a training command prints when done: epochs, steps and the best checkpoint (a ``TrainResult``)."""
    return (f"{out}: {result.epochs_done} epoch(s), {result.steps} steps; best val SSIM {result.best_val_ssim:.4f} "
            f"at epoch {result.best_epoch} -> {out / 'best.pt'}")
