"""``dp5k deblur train|evaluate`` and ``dp5k study downstream``: thin click wrappers over the library."""

from __future__ import annotations

from pathlib import Path

import click

from dp5k_common.cli_conventions import device_option, out_option
from dp5k_common.deprecation import warn_deprecated
from dp5k_common.errors import BadInputError
from dp5k_learn.cli_options import check_training_inputs, config_overrides, prepare_run_dir, report_run, training_options
from neural_dp.registry import DIAGNOSED_PREFIX, NEURAL_PREFIX, SYNTAX, spec_texts


@click.group("deblur")
def deblur_group() -> None:
    """DP defocus deblurring: a DPDNet-like U-Net from the two DP views to the sharp image."""


@deblur_group.command("train")
@click.argument("dataset", type=click.Path(path_type=Path))
@out_option("Run folder (config.json, last.pt, best.pt, history.json).", resumes=True)
@training_options("dp5k_deblur/config.py")
@click.option("--init-from", type=click.Path(path_type=Path), default=None,
              help="Start a fresh run from this deblurrer checkpoint's weights (fine-tuning).")
def deblur_train_command(dataset: Path, out: Path, config_file: Path | None, epochs: int | None, batch_size: int | None,
                         lr: float | None, crop_size: int | None, device: str | None, seed: int | None, sets: tuple[str, ...],
                         init_from: Path | None, resume: bool, overwrite: bool) -> None:
    """Train the deblurrer on DATASET's train split (any format-v1 dataset; best checkpoint by val SSIM).

    Runs again in the same --out resume from last.pt. Multi-GPU / multi-node:
    torchrun --nproc_per_node G -m dp5k_cli deblur train DATASET --out DIR
    """
    from .config import load_deblur_config
    from .train import train_deblur

    cfg = load_deblur_config(config_file, config_overrides(sets, epochs, batch_size, lr, crop_size, device, seed))
    check_training_inputs(dataset, init_from)
    result = train_deblur(dataset, out, cfg, resume=prepare_run_dir(out, resume, overwrite), init_from=init_from)
    click.echo(report_run(out, result))


@deblur_group.command("evaluate")
@click.argument("dataset", type=click.Path(path_type=Path))
@out_option("Output folder (metrics.json, table.md, figures/), replaced on each run.")
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True, help="A dp5k deblur train checkpoint (best.pt).")
@click.option("--split", default="test", show_default=True, help="Split to evaluate.")
@device_option()
@click.option("--max-pairs", type=click.IntRange(min=0), default=0, help="Evaluate at most this many pairs (0 = all).")
def deblur_evaluate_command(dataset: Path, out: Path, checkpoint: Path, split: str, device: str, max_pairs: int) -> None:
    """Masked MAE / PSNR / SSIM of the deblurred image against sharp, beside the blurred input L+R."""
    from dp5k_learn.distributed import resolve_device

    from .evaluate import evaluate_deblur, table_md

    scores = evaluate_deblur(dataset, checkpoint, out, split=split, device=str(resolve_device(device)),
                             max_pairs=max_pairs)
    click.echo(table_md(scores).rstrip())
    click.echo(f"-> {out / 'metrics.json'}, {out / 'table.md'}, {out / 'figures'}")


@click.group("study")
def study_group() -> None:
    """Studies across stages: the downstream proof of the simulators (the paper's Tables 3 and 4)."""


@study_group.command("downstream")
@click.argument("rgbd_dir", type=click.Path(path_type=Path))
@click.argument("measured", type=click.Path(path_type=Path))
@out_option("Study folder (tables.md, study.json; per test set table3/table4 .md/.json, differences.json, figure.png; "
            "synth/, runs/, neural/ inside); an interrupted study resumes in it.", resumes=True)
@click.option("--real", "real_pairs", type=click.Path(path_type=Path), default=None,
              help="A second test set of real pairs, any format-v1 dataset with train and test splits (e.g. "
                   "'dp5k import sdirt', split by photo): its test split is scored, its train split feeds its own "
                   "transfer setting.")
@click.option("--simulator", "simulators", multiple=True, metavar="[LABEL=]SPEC",
              help=f"A simulator to study, repeatable: {SYNTAX}; LABEL= names its row (two checkpoints, two reports). "
                   "Default: disk, butterworth, raytrace, base.")
@click.option("--simulators", "legacy_names", default=None, metavar="A,B", help="Deprecated: --simulator A --simulator B.")
@click.option("--neural-checkpoint", type=click.Path(path_type=Path), default=None,
              help="Deprecated: --simulator neural:CKPT (adds it).")
@click.option("--diagnose-report", type=click.Path(path_type=Path), default=None,
              help="Deprecated: --simulator diagnosed:REPORT.json (adds it).")
@click.option("--train-neural/--no-train-neural", default=True, show_default=True,
              help="Train the Neural DP Simulator on MEASURED's train split (every seed, the deblurrers' budget) and study "
                   "it as 'neural'.")
@click.option("--neural-channels", type=click.IntRange(4), default=12, show_default=True,
              help="Base channels of that Neural DP network (the paper: 64).")
@click.option("--neural-levels", type=click.IntRange(1), default=3, show_default=True, help="Its U-Net levels (the paper: 4).")
@click.option("--config", "config_file", type=click.Path(path_type=Path), default=None,
              help="Deblurrer TOML config (the same budget for every run); see dp5k_deblur/config.py.")
@click.option("--set", "sets", multiple=True, metavar="SECTION.KEY=VALUE", help="Deblurrer config override; repeatable.")
@click.option("--few-real-pairs", type=click.IntRange(1), default=4, show_default=True,
              help="Measured train pairs of the transfer setting.")
@click.option("--finetune-epochs", type=click.IntRange(1), default=10, show_default=True)
@click.option("--max-coc-px", type=click.FloatRange(min=0, min_open=True), default=None, help="Synthesize's sensor adjustment (default: the frames' pitch).")
@click.option("--encoding", type=click.Choice(["srgb", "linear"]), default="linear", show_default=True,
              help="How the frames' image.png is encoded.")
@device_option()
@click.option("--seeds", default="0,1,2", show_default=True, metavar="A,B,...",
              help="Seeds; each synthesizes, trains and fine-tunes everything again (the intervals span them).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Deprecated: --seeds N (one seed).")
def study_downstream_command(rgbd_dir: Path, measured: Path, out: Path, real_pairs: Path | None, simulators: tuple[str, ...],
                             legacy_names: str | None, neural_checkpoint: Path | None, diagnose_report: Path | None,
                             train_neural: bool, neural_channels: int, neural_levels: int,
                             config_file: Path | None, sets: tuple[str, ...], few_real_pairs: int, finetune_epochs: int,
                             max_coc_px: float | None, encoding: str, device: str, seeds: str, seed: int | None) -> None:
    """Synthesize DP data from RGBD_DIR with every simulator (and the Neural DP Simulator trained on MEASURED), train a
    deblurrer on each, score them on MEASURED's test split and --real's (Table 3), and fine-tune each on a few train
    pairs of each test set (Table 4); 95 % intervals over test scenes and seeds, and which differences are resolved."""
    from dataclasses import replace

    from dp5k_learn.distributed import resolve_device
    from neural_dp.registry import ModelConfig

    from .config import load_deblur_config
    from .study import PEER_SIMULATORS, StudyConfig, run_downstream

    specs = spec_texts(simulators, legacy_names) or list(PEER_SIMULATORS)
    for flag, prefix, path in (("--neural-checkpoint CKPT", NEURAL_PREFIX, neural_checkpoint),
                               ("--diagnose-report REPORT.json", DIAGNOSED_PREFIX, diagnose_report)):
        if path is not None:
            warn_deprecated(flag, f"--simulator {prefix}{flag.split()[1]}")
            specs.append(f"{prefix}{path}")
    if seed is not None:
        warn_deprecated("--seed N", "--seeds N")
        seed_list = (seed,)
    else:
        try:
            seed_list = tuple(int(s) for s in seeds.split(",") if s.strip())
        except ValueError as exc:
            raise BadInputError(f"--seeds must be integers separated by commas, got {seeds!r}", where="--seeds") from exc
    cfg = StudyConfig(
        simulators=tuple(specs), train_neural=train_neural,
        neural_model=replace(ModelConfig(), base_channels=neural_channels, levels=neural_levels),
        max_coc_px=max_coc_px, encoding=encoding, train=load_deblur_config(config_file, sets),
        few_real_pairs=few_real_pairs, finetune_epochs=finetune_epochs, device=str(resolve_device(device)), seeds=seed_list,
    )
    run_downstream(rgbd_dir, measured, out, cfg, real_pairs=real_pairs)
    click.echo((out / "tables.md").read_text().rstrip() + "\n")
    click.echo(f"-> {out / 'tables.md'}, {out / 'study.json'}, figure.png per test set")
