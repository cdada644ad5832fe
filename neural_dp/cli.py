"""``dp5k train``, ``dp5k evaluate`` and ``dp5k synthesize``: thin click wrappers over the library."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from dp5k_common.cli_conventions import check_out_location, device_option, out_option
from dp5k_common.deprecation import warn_deprecated
from dp5k_common.errors import BadInputError
from dp5k_learn.cli_options import check_training_inputs, config_overrides, prepare_run_dir, report_run, training_options

from .config import load_config
from .simulators.catalog import PEERS, SYNTAX, SimulatorSpec, spec_texts

log = logging.getLogger(__name__)


def default_run_dir(dataset: Path) -> Path:
    """Where ``dp5k train`` writes by default and ``dp5k evaluate`` looks: ``<dataset>-neural_dp`` beside it."""
    dataset = dataset.resolve()
    return dataset.parent / f"{dataset.name}-neural_dp"


@click.command("train")
@click.argument("dataset", type=click.Path(path_type=Path))
@out_option("Run folder (checkpoints, config, history).", required=False, default_text="DATASET-neural_dp beside the dataset",
            resumes=True)
@training_options("neural_dp/config.py")
def train_command(dataset: Path, out: Path | None, config_file: Path | None, epochs: int | None,
                  batch_size: int | None, lr: float | None, crop_size: int | None, device: str | None, seed: int | None,
                  sets: tuple[str, ...], resume: bool, overwrite: bool) -> None:
    """Train the Neural DP Simulator on DATASET's train split and keep it only if it beats the physical model.

    By default the network starts as the physical base model (fitted on the train pairs) and learns only what
    that model gets wrong; it trains with DP-geometry augmentations, stops early on held-out validation pairs
    (the val split, else whole train photos, else spatially separate tiles of the one photo), and best.pt is the
    network only if it beats the physical model on them, else the physical model itself; report.json and the
    last line say why. --set model.prior=none trains the paper's network as released. A train split
    without valid depth, or one photo as one pair (nothing to hold out), is refused before anything is
    written (exit 3).

    Runs again in the same --out resume from last.pt. Multi-GPU / multi-node:
    torchrun --nproc_per_node G -m dp5k_cli train DATASET --out DIR
    """
    from .holdout import plan_holdout
    from .train import train

    cfg = load_config(config_file, config_overrides(sets, epochs, batch_size, lr, crop_size, device, seed))
    check_training_inputs(dataset)
    run_dir = out or default_run_dir(dataset)
    check_out_location(run_dir)  # the derived default too (an explicit --out was checked already)
    if cfg.model.prior == "physical":
        plan_holdout(dataset, cfg.select.holdout, cfg.seed)  # a dataset it cannot train on is refused before anything is touched
    result = train(dataset, run_dir, cfg, resume=prepare_run_dir(run_dir, resume, overwrite))
    rep = result.report
    if not rep:
        click.echo(report_run(run_dir, result))
        return
    net = rep["network_val"]
    click.echo(f"{run_dir}: {result.epochs_done} epoch(s), {result.steps} steps; the network's best epoch {result.best_epoch} "
               f"(val PSNR {net['psnr']:.2f} dB, SSIM {net['ssim']:.4f}) -> {run_dir / 'network.pt'}")
    click.echo(f"{run_dir / 'best.pt'}: {rep['why']}")


def evaluate_specs(dataset: Path, simulators: tuple[str, ...], legacy_names: str | None,
                   checkpoint: Path | None) -> list[SimulatorSpec]:
    """The simulators ``dp5k evaluate`` compares: each ``--simulator`` (or the deprecated ``--simulators a,b``), by
    default every one available: the peers, the base model, and the Neural DP Simulator when there is a checkpoint
    for it (the deprecated ``--checkpoint``, else the ``best.pt`` that ``dp5k train`` wrote into its default run
    folder); without one the default leaves it out and says so.

    Raises:
        BadInputError: ``--simulator`` together with ``--simulators``, a bad spec, or a named ``neural`` with no
            checkpoint.
    """
    texts = spec_texts(simulators, legacy_names)
    if checkpoint is not None:
        warn_deprecated("--checkpoint CKPT", "--simulator neural:CKPT")
    guess = default_run_dir(dataset) / "best.pt"
    if not texts:
        texts = [*PEERS, "base", "neural"]
        if checkpoint is None and not guess.is_file():
            texts.remove("neural")
            log.info("no Neural DP checkpoint at %s (dp5k train writes one): comparing %s; --simulator neural:CKPT "
                     "adds another checkpoint", guess, ", ".join(texts))
    elif "neural" in texts and checkpoint is None and not guess.is_file():
        raise BadInputError(f"no checkpoint at {guess}; run 'dp5k train' first, name one with --simulator neural:CKPT, "
                            "or pick --simulator without neural", where=dataset)
    return [SimulatorSpec.parse(t, checkpoint or guess) for t in texts]


@click.command("evaluate")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--split", default="test", show_default=True, help="Split to evaluate.")
@out_option("Output folder (metrics.json, table.md, figures/). An interrupted run continues in it (the same command "
            "again); a finished one is replaced.", required=False, default_text="DATASET-eval-SPLIT beside the dataset",
            resumes=True)
@click.option("--simulator", "simulators", multiple=True, metavar="SPEC",
              help=f"A simulator to compare, repeatable: {SYNTAX}. Default: every one available: disk, butterworth, "
                   "raytrace, base, and neural when DATASET-neural_dp/best.pt exists (what dp5k train wrote; a bare "
                   "neural means that checkpoint).")
@click.option("--simulators", "legacy_names", default=None, metavar="A,B", help="Deprecated: --simulator A --simulator B.")
@click.option("--checkpoint", type=click.Path(path_type=Path), default=None, help="Deprecated: --simulator neural:CKPT.")
@device_option()
@click.option("--max-pairs", type=click.IntRange(min=0), default=0, help="Evaluate at most this many pairs (0 = all).")
@click.option("--figures", type=click.IntRange(min=0), default=2, show_default=True, help="Pairs that get a comparison picture.")
@click.option("--fit-pairs", type=click.IntRange(min=1), default=8, show_default=True,
              help="Training pairs (one crop of at most 256 px each) that simulators with free parameters (base) are "
                   "fitted on before they are compared.")
def evaluate_command(dataset: Path, split: str, out: Path | None, simulators: tuple[str, ...], legacy_names: str | None,
                     checkpoint: Path | None, device: str, max_pairs: int, figures: int, fit_pairs: int) -> None:
    """Table 2: masked MAE / PSNR / SSIM of every simulator on the same pairs of DATASET."""
    from dp5k_common.dataset import DatasetReader

    from .evaluate import evaluate

    DatasetReader(dataset).ids(split)  # the input first (missing: exit 3), before the simulators are looked for
    out = out or dataset.resolve().parent / f"{dataset.resolve().name}-eval-{split}"
    check_out_location(out)  # the derived default too (an explicit --out was checked already)
    specs = evaluate_specs(dataset, simulators, legacy_names, checkpoint)
    result = evaluate(dataset, out, split=split, simulators=specs, device=device, max_pairs=max_pairs, figures=figures,
                      fit_pairs=fit_pairs)
    click.echo(result.table_md.rstrip())
    click.echo(f"-> {out / 'metrics.json'}, {out / 'table.md'}, {out / 'figures'}")


@click.command("synthesize")
@click.argument("in_dir", type=click.Path(path_type=Path))
@out_option("The DP dataset (format v1) to write or continue.", legacy_positional=True, resumes=True)
@click.option("--simulator", metavar="SPEC", default=None, help=f"The simulator (required): {SYNTAX}.")
@click.option("--checkpoint", type=click.Path(path_type=Path), default=None, help="Deprecated: --simulator neural:CKPT.")
@click.option("--f-number", "f_numbers", type=click.FloatRange(min=0, min_open=True), multiple=True,
              help="Fixed f-number; repeat to draw one per frame (default: 1.8, 2, 2.8, 4, 5.6).")
@click.option("--focus-mm", type=click.FloatRange(min=0, min_open=True), default=None, help="Fixed focus distance (default: random 60x40 window).")
@click.option("--max-coc-px", type=click.FloatRange(min=0, min_open=True), default=20.0, show_default=True,
              help="Sensor-size adjustment target: 99th-percentile |CoC| at f/1.8, px.")
@click.option("--no-sensor-adjust", is_flag=True, help="Keep the nominal 36 mm sensor (no 5.3.1 adjustment).")
@click.option("--sensor-width-mm", type=click.FloatRange(min=0, min_open=True), default=36.0, show_default=True)
@click.option("--encoding", type=click.Choice(["srgb", "linear"]), default="srgb", show_default=True,
              help="How image.png is encoded.")
@click.option("--depth-scale", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True, help="depth.npy values x this = mm.")
@click.option("--noise", "noise", metavar="SPEC", default="nominal", show_default=True,
              help="Sensor noise on the views (shot + read per channel, linear): nominal (variance 2e-5 I + (1e-3)^2), "
                   "none, measured:DATASET (measured from a dataset's views), diagnosed:REPORT.json, or "
                   "shot=S,read=R (per channel S:S:S). Drawn from --seed.")
@click.option("--batch-size", type=click.IntRange(min=1), default=4, show_default=True)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@device_option()
def synthesize_command(in_dir: Path, out: Path, simulator: str | None, checkpoint: Path | None,
                       f_numbers: tuple[float, ...], focus_mm: float | None, max_coc_px: float, no_sensor_adjust: bool,
                       sensor_width_mm: float, encoding: str, depth_scale: float, noise: str, batch_size: int, seed: int,
                       device: str) -> None:
    """Turn RGBD frames IN_DIR/<frame>/{image.png, depth.png|depth.npy, intrinsics.json} into a DP dataset --out OUT.

    Always resumes: frames already in OUT are skipped. Sharded over processes or machines (each rank
    converts every N-th frame and resumes its own share; rank 0 writes the index once all are done):

    \b
    torchrun --nproc_per_node N -m dp5k_cli synthesize IN_DIR --out OUT ...
    """
    from .synthesize import PAPER_F_NUMBERS, SynthConfig, synthesize

    if checkpoint is not None:
        warn_deprecated("--checkpoint CKPT", "--simulator neural:CKPT")
    elif simulator is None:
        raise BadInputError(f"--simulator is required: {SYNTAX}", where="--simulator")
    cfg = SynthConfig(
        simulator=str(SimulatorSpec.parse(simulator or "neural", checkpoint)),
        f_numbers=tuple(f_numbers) or PAPER_F_NUMBERS, focus_mm=focus_mm,
        max_coc_px=None if no_sensor_adjust else max_coc_px, sensor_width_mm=sensor_width_mm, encoding=encoding,
        depth_scale=depth_scale, batch_size=batch_size, seed=seed, device=device, noise=noise,
    )
    summary = synthesize(in_dir, out, cfg)
    rank = f" (rank {summary['rank']} of {summary['world_size']})" if summary["world_size"] > 1 else ""
    click.echo(f"{out}{rank}: wrote {summary['written']} pair(s), skipped {summary['skipped']} already done; "
               f"{summary['pairs']} pair(s) in the dataset")
