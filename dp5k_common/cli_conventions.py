"""The command-line conventions every ``dp5k`` command follows (docs/cli.md, "Conventions"), as click pieces.

* Inputs are arguments; the output is ``--out`` / ``-o`` (:func:`out_option`). Commands that took OUT as their
  last argument still accept it there for a release, with a deprecation line.
* ``--device auto|cpu|cuda|cuda:N``, default ``auto``, wherever a network runs (:func:`device_option`).
* Earlier results in OUT: ``--resume/--no-resume`` and ``--overwrite`` (:func:`resume_option`,
  :func:`overwrite_option`, :func:`refuse_earlier_run`).
* ``--crop`` is a region of the input frames; a training patch is ``--crop-size`` (dp5k_learn.cli_options).

Only click is imported here, so ``dp5k --help`` stays light.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from .deprecation import warn_deprecated
from .errors import BadInputError
from .outdir import check_out_dir

F = TypeVar("F", bound=Callable[..., Any])

DEVICE_CHOICES = "auto|cpu|cuda|cuda:N"
DEVICE_HELP = "Where the networks run: auto (the first CUDA GPU torch sees, else the CPU), cpu, cuda or cuda:N."
_DEVICE_RE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


class _LegacyOutArgument(click.Argument):
    """OUT as the last argument, the deprecated spelling of ``--out``: accepted, left out of the usage line."""

    def get_usage_pieces(self, ctx: click.Context) -> list[str]:
        return []


def check_device(text: str) -> str:
    """``text`` if it names a device the convention allows (``auto``, ``cpu``, ``cuda``, ``cuda:N``).

    Raises:
        BadInputError: anything else (exit 3).
    """
    value = text.strip().lower()
    if not _DEVICE_RE.match(value):
        raise BadInputError(f"--device must be one of {DEVICE_CHOICES}, got {text!r}", where="--device")
    return value


def device_option(help_suffix: str = "", *, config_default: bool = False) -> Callable[[F], F]:
    """``--device auto|cpu|cuda|cuda:N`` with the default every command shares: ``auto``.

    With ``config_default`` the value is None when the option is not given, so that a config file's device
    (itself ``auto`` by default) is not overridden.
    """
    text = DEVICE_HELP + (f" {help_suffix}" if help_suffix else "")
    if config_default:
        text += " Default: the config file's device, itself auto by default."
    return click.option("--device", default=None if config_default else "auto", show_default=not config_default,
                        metavar=DEVICE_CHOICES, help=text,
                        callback=lambda ctx, param, value: None if value is None else check_device(value))


def out_option(help: str, *, default: Path | None = None, required: bool = True, legacy_positional: bool = False,
               file: bool = False, default_text: str | None = None, resumes: bool = False) -> Callable[[F], F]:
    """``--out`` / ``-o`` (the callback's ``out`` keyword), the one way every command is told where to write.

    Args:
        help: what OUT receives (the default and the deprecation note are added).
        default: OUT when ``--out`` is not given (None: none).
        required: a command without a default refuses to run without ``--out`` (click's usage error, exit 2).
            A command that derives its default from its inputs passes ``required=False`` and ``default_text``
            (it then receives None when neither spelling was given).
        legacy_positional: the command used to take OUT as its last argument; that spelling still works, with a
            deprecation line. Put this decorator right below the command's last ``@click.argument``.
        file: OUT is a file (``studio render``), not a folder: an existing file is fine (replaced), a folder is not.
        resumes: a rerun after an interruption continues in OUT (the interrupted line then says so;
            :func:`command_resumes`).

    Before the command's body runs, OUT (given, or ``default``) is checked (:func:`check_out_location`): a file
    (for a folder OUT), a folder (for a file OUT), a path under a file or an unwritable place is refused in one line,
    exit 3, and nothing is created. Commands make OUT only once their inputs were checked.
    """
    metavar = "FILE" if file else "DIR"
    text = help
    if default is not None or default_text:
        text += f" Default: {default_text or default}."
    if legacy_positional:
        text += " (OUT as the last argument is deprecated.)"
    if required and default is None and not default_text:
        text += "  [required]"

    def wrap(fn: F) -> F:
        @functools.wraps(fn)
        def run(*args: Any, out: Path | None = None, legacy_out: Path | None = None, **kwargs: Any) -> Any:
            if legacy_out is not None:
                if out is not None:
                    raise BadInputError(f"OUT given twice, as the last argument ({legacy_out}) and as --out ({out}); "
                                        "give --out only", where="--out")
                warn_deprecated("OUT as the last argument", "--out OUT")
                out = legacy_out
            if out is None:
                out = default
            if out is not None:  # given, or the fixed default (a default derived from the inputs: the command checks it)
                check_out_location(out, file=file)
            if out is None and required:
                raise click.MissingParameter(ctx=click.get_current_context(), param=out_param)
            return fn(*args, out=out, **kwargs)

        out_param = click.Option(["-o", "--out", "out"], type=click.Path(path_type=Path), default=None,
                                 metavar=metavar, help=text)  # required is checked in run(), which sees both spellings
        params = list(getattr(run, "__click_params__", []))
        params.append(out_param)  # click reverses this list: the option comes where the decorator stands
        if legacy_positional:
            params.append(_LegacyOutArgument(["legacy_out"], required=False, type=click.Path(path_type=Path)))
        run.__click_params__ = params  # type: ignore[attr-defined]
        run.dp5k_resumes = resumes  # type: ignore[attr-defined]  # read by command_resumes (functools.wraps copies it)
        return run  # type: ignore[return-value]

    return wrap


def check_out_location(out: Path, *, file: bool = False) -> None:
    """Refuse an OUT that cannot be written before any work: a file where a folder goes (or a folder where a file
    goes), a path under a file, a read-only place. Creates nothing.

    Raises:
        BadInputError: one line naming OUT (exit 3).
    """
    out = Path(out)
    if file:
        if out.is_dir():
            raise BadInputError("is a folder; --out names the file to write", where=out)
        check_out_dir(out.parent, create=False)
    else:
        check_out_dir(out, create=False)


def command_resumes(command: click.Command) -> bool:
    """Whether running ``command`` again continues where an interrupted run stopped (``out_option(resumes=True)``)."""
    return bool(getattr(command.callback, "dp5k_resumes", False))


def resume_option(help: str, *, default: bool = True) -> Callable[[F], F]:
    """``--resume/--no-resume`` (the callback's ``resume`` keyword): continue an earlier run in OUT, or refuse it."""
    return click.option("--resume/--no-resume", "resume", default=default, show_default=True, help=help)


def overwrite_option(help: str) -> Callable[[F], F]:
    """``--overwrite`` (the callback's ``overwrite`` keyword): start afresh, replacing an earlier run's results."""
    return click.option("--overwrite", is_flag=True, help=help)


def refuse_earlier_run(marker: Path, what: str, *, resumable: bool = True) -> None:
    """``--no-resume`` without ``--overwrite`` never mixes with or loses an earlier run: refuse when ``marker``
    (the file or folder an earlier run leaves in OUT) exists.

    Raises:
        BadInputError: ``marker`` exists (exit 3).
    """
    if marker.exists():
        hint = "run without --no-resume to continue it, " if resumable else ""
        raise BadInputError(f"--no-resume but {what} is here; {hint}add --overwrite to replace it, or choose "
                            "another --out", where=marker)
