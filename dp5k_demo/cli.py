"""``dp5k demo [OUT] [--scale small|medium|paper]``."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import click

from .pipeline import SCALES, build_stages, hidden_effect
from .stages import peak_memory_note, run_stages

log = logging.getLogger(__name__)


@click.command("demo")
@click.argument("out", type=click.Path(path_type=Path), default=Path("demo-out"))
@click.option("--scale", type=click.Choice(list(SCALES)), default="medium", show_default=True,
              help="small: a quick look (~1 min); medium: the default demo (~8.5 min on 2 CPU cores, 2.5 GiB); paper: 1680x1120 (hours).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of scenes, splits and the hidden effect.")
@click.option("--force", is_flag=True, help="Rerun every stage (default: reuse stages finished by an earlier run).")
def demo_command(out: Path, scale: str, seed: int, force: bool) -> None:
    """Run the whole pipeline on the virtual studio and write OUT/report.html.

    Simulated capture (PTP bodies, ESC/VP21 projector), process, validate-depth, a short train, evaluate
    of every simulator, diagnose of the base model and of the Neural DP Simulator on a dataset with a
    hidden effect, and synthesize on RGBD frames. A second run reuses finished stages.
    """
    out.mkdir(parents=True, exist_ok=True)
    sc = SCALES[scale]
    t0 = time.perf_counter()
    stages = build_stages(out, sc, seed)
    records = run_stages(stages, {"scale": sc, "seed": seed}, out, force=force)
    report = records["report"]["result"]["report"]
    click.echo(f"demo finished in {time.perf_counter() - t0:.0f} s (peak memory {peak_memory_note()}); "
               f"hidden effect was '{hidden_effect(seed)}'")
    click.echo(f"report: {report}")
