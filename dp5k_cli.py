"""The ``dp5k`` command line: a click group that registers each stage's commands.

Kept thin on purpose: each command lives beside its feature; this module only wires logging,
progress bars and the error policy (one line on stderr, a distinct exit code per error class,
``--verbose`` adds the traceback).
"""

from __future__ import annotations

import importlib
import logging
import sys
import traceback
from typing import Any

import click

from dp5k_common import __version__
from dp5k_common.deprecation import collect_deprecations
from dp5k_common.errors import DP5KError
from dp5k_common.progress import set_progress_enabled


# name -> (module, attribute, one-line help). Commands are imported only when run, so ``dp5k --help`` and
# light commands start without loading torch, Open3D or pygame. tests/test_cli.py keeps the help in sync.
COMMANDS: dict[str, tuple[str, str, str]] = {
    "capture": ("dp5k_capture.cli", "capture_command", "Capture one scene on the rig (or --sim): DP raws, ChArUco, Gray code."),
    "devices": ("dp5k_capture.cli", "devices_command", "Canon bodies and projector ports: serial, access, battery, card, holder."),
    "verify": ("dp5k_capture.cli", "verify_command", "Verify raw sessions (sizes, SHA-256, counts, DP); datasets: dp5k check."),
    "process": ("dp5k_process.cli", "process_command", "Process raw sessions into the dataset format v1."),
    "validate-depth": ("dp5k_process.cli", "validate_depth_command", "Depth accuracy against a ChArUco wall (Eq. 4)."),
    "sl-depth": ("dp5k_process.sl_depth", "sl_depth_command", "Structured-light depth of camera 0 from any stereo rig's Gray code."),
    "check": ("dp5k_common.check", "check_command", "Validate a format-v1 dataset pair by pair."),
    "studio": ("dp5k_studio.cli", "studio_group", "The virtual studio: scenes, renders, datasets with effects."),
    "train": ("neural_dp.cli", "train_command", "Train the Neural DP Simulator on a dataset."),
    "evaluate": ("neural_dp.cli", "evaluate_command", "Compare every DP simulator: masked MAE / PSNR / SSIM (Table 2)."),
    "synthesize": ("neural_dp.cli", "synthesize_command", "Synthesize DP pairs from RGBD frames with any simulator."),
    "deblur": ("dp5k_deblur.cli", "deblur_group", "DP defocus deblurring: a U-Net from the DP views to the sharp image."),
    "diagnose": ("dp5k_diagnose.cli", "diagnose_command", "Name what a DP simulator gets wrong, extend it, measure the gain."),
    "import": ("dp5k_import.cli", "import_command", "Import DP data (DP5K release, Sdirt, DPDD, your own) into format v1."),
    "study": ("dp5k_deblur.cli", "study_group", "Downstream proof: a deblurrer trained on each simulator (Tables 3, 4)."),
    "demo": ("dp5k_demo.cli", "demo_command", "Run the whole pipeline on the virtual studio; write a report."),
}


class _Group(click.Group):
    """Lazy command table; turns dp5k errors into one line on stderr and a distinct exit code."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attr, _ = COMMANDS[name]
        return getattr(importlib.import_module(module), attr)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        with formatter.section("Commands"):
            formatter.write_dl([(name, COMMANDS[name][2]) for name in self.list_commands(ctx)])

    def invoke(self, ctx: click.Context) -> Any:
        # deprecated spellings print their line after the command's output, or inside its one error line
        with collect_deprecations() as notes:
            try:
                return super().invoke(ctx)
            except DP5KError as exc:
                _report(ctx, f"dp5k: error: {exc.one_line()}{notes.take_suffix()}")
                ctx.exit(exc.exit_code)
            except KeyboardInterrupt:
                _report(ctx, f"dp5k: interrupted; finished work was kept, run the command again to resume{notes.take_suffix()}")
                ctx.exit(130)
            except MemoryError:
                _report(ctx, f"dp5k: error: out of memory; try a smaller size or fewer workers{notes.take_suffix()}")
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


if __name__ == "__main__":
    main()
