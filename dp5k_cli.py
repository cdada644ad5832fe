"""The ``dp5k`` command line: a click group that registers each stage's commands.

Kept thin on purpose: each command lives beside its feature; this module only wires logging,
progress bars and the error policy (one line on stderr, a distinct exit code per error class,
``--verbose`` adds the traceback).
"""

from __future__ import annotations

import logging
import sys
import traceback
from typing import Any

import click

from dp5k_common import __version__
from dp5k_common.errors import DP5KError
from dp5k_common.progress import set_progress_enabled


class _Group(click.Group):
    """Turns dp5k errors into one line on stderr and a distinct exit code."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except DP5KError as exc:
            _report(ctx, f"dp5k: error: {exc.one_line()}")
            ctx.exit(exc.exit_code)
        except KeyboardInterrupt:
            _report(ctx, "dp5k: interrupted; finished work was kept, run the command again to resume")
            ctx.exit(130)
        except MemoryError:
            _report(ctx, "dp5k: error: out of memory; try a smaller size or fewer workers")
            ctx.exit(1)


def _report(ctx: click.Context, line: str) -> None:
    verbose = (ctx.obj or {}).get("verbose", 0)
    if verbose:
        traceback.print_exc(file=sys.stderr)
    click.echo(line, err=True)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug); show tracebacks on errors.")
@click.option("-q", "--quiet", is_flag=True, help="Only warnings and errors; no progress bars.")
@click.version_option(__version__, prog_name="dp5k")
@click.pass_context
def main(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """dp5k: build and use real-world dual-pixel (DP) datasets.

    Capture raw sessions on a two-camera + projector rig (or the virtual studio), process them into
    aligned sharp / DP / depth / CoC pairs, train and compare DP simulators, and diagnose what a
    simulator gets wrong.
    """
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr, force=True)
    if quiet:  # DP5K_PROGRESS=0 in the environment also hides them (CI logs)
        set_progress_enabled(False)


def _register() -> None:
    from dp5k_common.check import check_command

    main.add_command(check_command)
    from dp5k_capture.sim.studio.cli import studio_group; main.add_command(studio_group)  # noqa: E702
    from dp5k_capture.cli import capture_command, devices_command, verify_command; [main.add_command(c) for c in (capture_command, devices_command, verify_command)]  # noqa: E702
    from neural_dp.cli import evaluate_command, synthesize_command, train_command; [main.add_command(c) for c in (train_command, evaluate_command, synthesize_command)]  # noqa: E702
    from dp5k_process.cli import process_command, validate_depth_command; [main.add_command(c) for c in (process_command, validate_depth_command)]  # noqa: E702
    from dp5k_diagnose.cli import diagnose_command, import_command; [main.add_command(c) for c in (diagnose_command, import_command)]  # noqa: E702

    from dp5k_demo.cli import demo_command; main.add_command(demo_command)  # noqa: E702


_register()

if __name__ == "__main__":
    main()
