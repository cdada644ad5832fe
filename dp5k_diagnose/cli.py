"""The ``dp5k diagnose`` command."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from dp5k_common.cli_conventions import check_out_location, device_option, out_option
from dp5k_common.deprecation import warn_deprecated
from dp5k_common.errors import BadInputError
from dp5k_learn.config import FinetuneConfig
from neural_dp.registry import SYNTAX, SimulatorSpec

log = logging.getLogger(__name__)


def parse_fit_pairs(text: str, dataset: Path, auto) -> int | None:
    """``--fit-pairs``: a positive count, ``all`` (None) or ``auto`` (``auto(dataset)``)."""
    t = text.strip().lower()
    if t == "all":
        return None
    if t == "auto":
        return auto(dataset)
    try:
        n = int(t)
    except ValueError:
        n = 0
    if n < 1:
        raise BadInputError(f"--fit-pairs must be 'auto', 'all' or a count >= 1, got {text!r}", where="--fit-pairs")
    return n


@click.command("diagnose")
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--simulator", default=None, metavar="SPEC", help=f"The simulator to diagnose (default: base): {SYNTAX}.")
@click.option("--model", default=None, metavar="SPEC", help="Deprecated: --simulator SPEC.")
@out_option("Report folder, replaced on each run.", required=False, default_text="DATASET/diagnose-<simulator>")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seeds crop positions and the bootstrap.")
@click.option("--fit-pairs", default="auto", show_default=True, metavar="auto|all|N",
              help="Training pairs used to fit: N, all, or auto = all where train has at most 8 pairs, else 8.")
@click.option("--nominal-noise", default="2e-5,1e-3", show_default=True, metavar="SHOT_VAR,READ_SIGMA",
              help="The sensor's expected view noise in linear units (variance = SHOT_VAR * I + READ_SIGMA^2); only noise beyond it is the 'noise' effect.")
@click.option("--neural-steps", default=FinetuneConfig.steps, show_default=True, type=click.IntRange(1),
              help="For neural:CKPT: fine-tuning steps of the structural extension and of its control (each).")
@device_option("For neural:CKPT: the fine-tuning and its held-out scoring; the base model is fitted on the CPU.")
@click.option("--sharp-f-number", "sharp_f_number", default="auto", show_default=True, metavar="auto|N",
              help="How to read `sharp` in pairs whose params.json has no sharp_f_number: auto = diagnose with f/22 and "
                   "with all-in-focus and keep the reading that predicts the detection pairs better; N = that f-number (0 = all-in-focus).")
@click.option("--threads", default=1, show_default=True, type=click.IntRange(0),
              help="PyTorch threads while diagnosing (0 = PyTorch's default). Renders of ~100 px crops barely profit from more, and "
                   "on shared cores waiting threads slow them down many times (docs/diagnose.md).")
def diagnose_command(dataset: Path, simulator: str | None, model: str | None, out: Path | None, seed: int, fit_pairs: str,
                     nominal_noise: str, neural_steps: int, device: str, sharp_f_number: str, threads: int) -> None:
    """Fit the simulator on DATASET's train split, name the physical cause of its errors, extend it and measure the gain.

    Writes DIR/report.json and DIR/report.md (with figures); prints the cause and the gain.
    """
    from .config import DiagnoseConfig
    from .data import auto_fit_pairs
    from .neural_reach import NeuralReachConfig
    from .run import run_diagnose

    if model is not None:
        if simulator is not None:
            raise BadInputError("give --simulator or the older --model, not both", where="--model")
        warn_deprecated("--model SPEC", "--simulator SPEC")
    spec = SimulatorSpec.parse(simulator or model or "base")
    try:
        shot_var, read_sigma = (float(v) for v in nominal_noise.split(","))
    except ValueError as exc:
        raise BadInputError(f"--nominal-noise must be SHOT_VAR,READ_SIGMA, got {nominal_noise!r}", where="--nominal-noise") from exc
    if not (shot_var >= 0 and read_sigma >= 0):
        raise BadInputError(f"--nominal-noise values must be >= 0, got {nominal_noise!r}", where="--nominal-noise")
    sharp_n: float | None = None
    if sharp_f_number.strip().lower() != "auto":
        try:
            sharp_n = float(sharp_f_number)
        except ValueError:
            sharp_n = -1.0
        if not (sharp_n >= 0 and sharp_n < float("inf")):
            raise BadInputError(f"--sharp-f-number must be 'auto' or a number >= 0 (0 = all-in-focus), got {sharp_f_number!r}",
                                where="--sharp-f-number")
    check_out_location(out or dataset / f"diagnose-{spec.folder_name()}")  # the default too, before any work
    n_fit = parse_fit_pairs(fit_pairs, dataset, auto_fit_pairs)  # last: "auto" reads the dataset
    out = out or (dataset / f"diagnose-{spec.folder_name()}")
    neural = NeuralReachConfig(finetune=FinetuneConfig(steps=neural_steps), device=device)
    res = run_diagnose(dataset, spec, out, DiagnoseConfig(seed=seed, fit_pairs=n_fit, nominal_shot_var=shot_var, nominal_read_sigma=read_sigma,
                                                          neural=neural, sharp_f_number=sharp_n, threads=threads))
    print_summary(res, out)


def print_summary(res: dict, out: Path) -> None:
    """Print what ``res`` (report.json's content) found: the causes in order, look-alikes, suspects, the fits'
    coverage, the held-out gain and where the report is."""
    g = res["gain"]
    sr = res.get("sharp_reading") or {}
    if sr.get("source") == "selected":
        click.echo(f"sharp: {sr['pairs_without_key']} pairs do not state sharp_f_number; read as "
                   f"{'all-in-focus' if sr['f_number'] == 0 else 'f/%g' % sr['f_number']} (the base model fits it better)")
    click.echo(f"cause: {res['cause']}")
    for c in res["causes"]:
        click.echo(f"  {c['step']}. {c['name']}: {c['explanation']}")
        click.echo(f"     adds {c['gain_db']:+.3f} dB given the other causes (95% CI over held-out tiles [{c['gain_ci_db'][0]:+.3f}, "
                   f"{c['gain_ci_db'][1]:+.3f}]); this step {c['step_gain_db']:+.3f} dB, cumulative {c['cumulative_gain_db']:+.3f} dB")
    for group in res.get("lookalikes") or []:
        click.echo(f"explained: {group['names'][1]} by {group['names'][0]} (to tell them apart, capture {group['captures'][0]})")
    for sp in res.get("suspects") or []:
        click.echo(f"suspect, not named: {sp['name']}: its signature differs, but the held-out gain is {sp['gain_db']:+.3f} dB "
                   f"(95% CI over held-out tiles [{sp['gain_ci_db'][0]:+.3f}, {sp['gain_ci_db'][1]:+.3f}])")
    at = res.get("atlas") or {}
    if at.get("unmeasured"):
        click.echo(f"atlas: {len(at['unmeasured'])} of {at['cells']} cells not measured (too few pixels or pairs; nothing is named from them)")
    cov = res["fit_coverage"]
    click.echo(f"atlas measured on {cov['atlas_pairs']} pairs; fits saw {cov['pairs']} pairs of {cov['scenes']} scenes, "
               f"{cov['field_zones']} of {cov['field_zones_of']} field zones")
    click.echo(f"gain on {g['split']} (predictable pixels): PSNR {g['psnr_before']:.3f} -> {g['psnr_after']:.3f} dB "
               f"(95% CI of the gain over pairs [{g['psnr_gain_ci95'][0]:+.3f}, {g['psnr_gain_ci95'][1]:+.3f}])")
    av = g.get("all_valid")
    if av:
        click.echo(f"  all valid pixels: PSNR {av['psnr_before']:.3f} -> {av['psnr_after']:.3f} dB "
                   f"(95% CI [{av['psnr_gain_ci95'][0]:+.3f}, {av['psnr_gain_ci95'][1]:+.3f}])")
    ne = res.get("neural_extension")
    if ne:
        gc = ne["gain_vs_control"]
        click.echo(f"neural extension ({ne['extension'].get('kind', 'multi-scale')}): PSNR gain over an equally fine-tuned control "
                   f"{gc['psnr_after'] - gc['psnr_before']:+.3f} dB (95% CI [{gc['psnr_gain_ci95'][0]:+.3f}, {gc['psnr_gain_ci95'][1]:+.3f}])")
    click.echo(f"report: {out / 'report.md'}")
