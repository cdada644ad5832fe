"""``dp5k demo [--out OUT] [--scale small|medium|paper]``."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import click

from dp5k_common.cli_conventions import out_option, overwrite_option, refuse_earlier_run, resume_option
from dp5k_common.deprecation import warn_deprecated

from .pipeline import SCALES, build_stages, hidden_effect
from .stages import STATE_DIR, peak_memory_note, run_stages

log = logging.getLogger(__name__)


@click.command("demo")
@out_option("Folder for every stage's output and the report.", default=Path("demo-out"), legacy_positional=True,
            resumes=True)
@click.option("--scale", type=click.Choice(list(SCALES)), default="medium", show_default=True,
              help="small: a quick look (what the test suite runs); medium: the default demo; paper: 1680x1120 (hours). "
                   "Timings: README.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of scenes, splits and the hidden effect.")
@resume_option("Reuse the stages an earlier run finished in OUT; --no-resume refuses an OUT that holds some.")
@overwrite_option("Rerun every stage, replacing what an earlier run left in OUT.")
@click.option("--force", "legacy_force", is_flag=True, help="Deprecated: --overwrite.")
def demo_command(out: Path, scale: str, seed: int, resume: bool, overwrite: bool, legacy_force: bool) -> None:
    """Run the whole pipeline on the virtual studio and write OUT/report.html.

    Simulated capture (PTP bodies, ESC/VP21 projector), process, validate-depth, a short train, evaluate
    of every simulator, diagnose of the base model and of the Neural DP Simulator on a dataset with a
    hidden effect, and synthesize on RGBD frames. A second run reuses finished stages.
    """
    if legacy_force:
        warn_deprecated("--force", "--overwrite")
        overwrite = True
    if not (resume or overwrite):
        refuse_earlier_run(out / STATE_DIR, "an earlier demo run's finished stages")
    out.mkdir(parents=True, exist_ok=True)
    sc = SCALES[scale]
    t0 = time.perf_counter()
    stages = build_stages(out, sc, seed)
    records = run_stages(stages, {"scale": sc, "seed": seed}, out, force=overwrite)
    report = records["report"]["result"]["report"]
    click.echo(f"demo finished in {time.perf_counter() - t0:.0f} s (peak memory {peak_memory_note()}); "
               f"hidden effect was '{hidden_effect(seed)}'")
    click.echo(f"report: {report}")
