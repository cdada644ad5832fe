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
from dp5k_common.cli_conventions import command_resumes
from dp5k_common.deprecation import collect_deprecations
from dp5k_common.errors import DP5KError
from dp5k_common.progress import set_progress_enabled
from dp5k_common.software import COMMAND_META_KEY


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
        return _with_log_options(getattr(importlib.import_module(module), attr))

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta[COMMAND_META_KEY] = ["dp5k", *args]  # the command line, for the provenance of what it writes
        return super().parse_args(ctx, args)

    def resolve_command(self, ctx: click.Context, args: list[str]) -> tuple[str | None, click.Command | None, list[str]]:
        return _note_resumes(ctx, super().resolve_command(ctx, args))

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
                if ctx.meta.get(RESUMES_KEY):  # noted when the subcommand was resolved (docs/cli.md, "The contract")
                    what = "finished work was kept, run the command again to resume"
                else:
                    what = "this command does not resume: run it again to start over"
                _report(ctx, f"dp5k: interrupted; {what}{notes.take_suffix()}")
                ctx.exit(130)
            except MemoryError:
                _report(ctx, f"dp5k: error: out of memory; try a smaller size or fewer workers{notes.take_suffix()}")
                ctx.exit(1)


VERBOSE_HELP = "More log output (-vv for debug); show tracebacks on errors."
QUIET_HELP = "Only warnings and errors; no progress bars."


def _set_logging(ctx: click.Context, verbose: int = 0, quiet: bool = False) -> None:
    """Add ``verbose`` / ``quiet`` to what the command line gave so far (before or after the subcommand) and set the
    log level and progress bars from the sum."""
    state = ctx.find_root().ensure_object(dict)
    state["verbose"] = state.get("verbose", 0) + verbose
    state["quiet"] = state.get("quiet", False) or quiet
    level = logging.WARNING if state["quiet"] else (logging.DEBUG if state["verbose"] >= 2 else logging.INFO)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr, force=True)
    if state["quiet"]:  # DP5K_PROGRESS=0 in the environment also hides them (CI logs)
        set_progress_enabled(False)


def _log_option_given(ctx: click.Context, param: click.Parameter, value: Any) -> None:
    if value:
        _set_logging(ctx, **{param.name: value})  # type: ignore[arg-type]


RESUMES_KEY = "dp5k.resumes"
"""``click.Context.meta`` key (shared by nested contexts): whether the command being run resumes when run again."""


def _note_resumes(ctx: click.Context, resolved: tuple[str | None, click.Command | None, list[str]]
                  ) -> tuple[str | None, click.Command | None, list[str]]:
    """Record, before the subcommand parses its arguments, whether it resumes (``out_option(resumes=True)``), for the
    line an interruption prints."""
    if resolved[1] is not None:
        ctx.meta[RESUMES_KEY] = command_resumes(resolved[1])
    return resolved


def _with_log_options(cmd: click.Command) -> click.Command:
    """Give ``cmd`` (and, for a group, each of its subcommands) the global ``-v`` / ``-q``, so that they work after
    the subcommand too: ``dp5k train DS -q`` is ``dp5k -q train DS``. Done once per command object."""
    if not getattr(cmd, "_dp5k_log_options", False):
        cmd.params += [
            click.Option(["-v", "--verbose", "verbose"], count=True, expose_value=False, callback=_log_option_given,
                         help=VERBOSE_HELP),
            click.Option(["-q", "--quiet", "quiet"], is_flag=True, expose_value=False, callback=_log_option_given,
                         help=QUIET_HELP),
        ]
        cmd._dp5k_log_options = True  # type: ignore[attr-defined]
    if isinstance(cmd, click.Group):
        if not getattr(cmd, "_dp5k_notes_resumes", False):  # a group inside dp5k: its subcommand says it too
            resolve = cmd.resolve_command
            cmd.resolve_command = lambda ctx, args: _note_resumes(ctx, resolve(ctx, args))  # type: ignore[method-assign]
            cmd._dp5k_notes_resumes = True  # type: ignore[attr-defined]
        for sub in cmd.commands.values():
            _with_log_options(sub)
    return cmd


def _report(ctx: click.Context, line: str) -> None:
    verbose = (ctx.obj or {}).get("verbose", 0)
    if verbose:
        traceback.print_exc(file=sys.stderr)
    click.echo(line, err=True)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.option("-v", "--verbose", count=True, help=VERBOSE_HELP + " Also after the command.")
@click.option("-q", "--quiet", is_flag=True, help=QUIET_HELP + " Also after the command.")
@click.version_option(__version__, prog_name="dp5k")
@click.pass_context
def main(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """dp5k: build and use real-world dual-pixel (DP) datasets.

    Capture raw sessions on a two-camera + projector rig (or the virtual studio), process them into
    aligned sharp / DP / depth / CoC pairs, train and compare DP simulators, and diagnose what a
    simulator gets wrong.
    """
    ctx.ensure_object(dict).update(verbose=0, quiet=False)
    _set_logging(ctx, verbose, quiet)


if __name__ == "__main__":
    main()
