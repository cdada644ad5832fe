"""The CLI contract (docs/cli.md, "The contract"), checked over the whole command tree.

Every test walks ``dp5k_cli.COMMANDS`` (groups and their subcommands), so a new command is held to the contract the
day it lands: an unusable --out is refused in one line (exit 3) and leaves nothing behind; a missing input is exit 3
and OUT is not made; numbers carry their ranges; each writer says what it does with an earlier result; the interrupted
line promises a resume only where the command resumes; -q / -v work after the command. Only refusals that come
before any work are run here, on tiny inputs.
"""

from __future__ import annotations

from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from dp5k_cli import COMMANDS, main
from dp5k_common.cli_conventions import command_resumes
from dp5k_testing.tiny_dataset import make_tiny_dataset

# Options a command needs before it reaches its input checks, which the generic filler cannot guess.
NEEDS = {"synthesize": ["--simulator", "disk"]}
# Writers whose result is a report computed from their inputs: replaced on each run (docs/cli.md, "Conventions").
REPLACED = {"diagnose", "validate-depth", "deblur evaluate", "studio render"}
# Writers that neither resume nor replace: an earlier result is refused (without --overwrite). For each, what to
# plant in OUT and the words of the refusal.
REFUSES = {"sl-depth": ("report.json", "already holds a report (use --overwrite)"),
           "import": ("dataset.json", "a dataset already exists here (imports never overwrite)")}
# INT / FLOAT options with no range, and why a negative or zero value means something there.
UNBOUNDED: dict[tuple[str, str], str] = {}


def all_commands() -> dict[str, click.Command]:
    ctx = click.Context(main)
    found: dict[str, click.Command] = {}
    for name in COMMANDS:
        cmd = main.get_command(ctx, name)
        assert cmd is not None
        found[name] = cmd
        if isinstance(cmd, click.Group):
            found.update({f"{name} {sub}": cmd.get_command(ctx, sub) for sub in cmd.list_commands(ctx)})
    return found


def writers() -> dict[str, click.Command]:
    return {name: cmd for name, cmd in all_commands().items() if any(p.name == "out" for p in cmd.params)}


def out_is_file(cmd: click.Command) -> bool:
    return next(p for p in cmd.params if p.name == "out").metavar == "FILE"


def required_args(cmd: click.Command, path: Path) -> list[str]:
    """Arguments and required options that let ``cmd`` parse: paths are ``path``, choices their first choice, the
    rest a text that any of them accepts (a scene name, a WxH)."""
    args: list[str] = []
    for p in cmd.params:
        if not p.required or p.name == "out":
            continue
        if isinstance(p.type, click.Path):
            value = str(path)
        elif isinstance(p.type, click.Choice):
            value = str(p.type.choices[0])
        else:
            value = "64x32"
        args += [value] if isinstance(p, click.Argument) else [p.opts[-1], value]
    return args


def has_path_input(cmd: click.Command) -> bool:
    return any(p.required and isinstance(p.type, click.Path) and p.name != "out" for p in cmd.params)


def listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def invoke(args: list[str]) -> tuple[int, list[str], str]:
    res = CliRunner().invoke(main, args)
    lines = [line for line in res.output.splitlines() if line.strip()]
    return res.exit_code, lines, res.output


@pytest.fixture
def workdir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """tmp_path as the current folder (so a default OUT would land where the listing sees it), with a tiny dataset
    ``ds`` and a file ``afile``."""
    monkeypatch.chdir(tmp_path)
    make_tiny_dataset(tmp_path / "ds", scenes=3, W=48, H=32)
    (tmp_path / "afile").write_text("x")
    return tmp_path


def test_the_command_tree_is_what_the_contract_covers() -> None:
    """The walk finds every command, and every writer declares what it does with an earlier result in OUT."""
    commands = all_commands()
    assert {"train", "evaluate", "studio make-dataset", "deblur evaluate", "study downstream"} <= set(commands)
    for name, cmd in writers().items():
        overwrite = any(p.name == "overwrite" for p in cmd.params)
        assert command_resumes(cmd) or overwrite or name in REPLACED or name in REFUSES, name
    assert REPLACED <= set(writers()) and set(REFUSES) <= set(writers())


def test_an_unusable_out_is_one_line_exit_3_and_creates_nothing(workdir: Path) -> None:
    """--out a file (a folder for a FILE output) and a path under a file: refused before any work, in one line that
    names it, exit 3, no traceback, nothing created; with valid inputs, so that the refusal is OUT's."""
    afile = workdir / "afile"
    (workdir / "adir").mkdir()
    before = listing(workdir)
    for name, cmd in writers().items():
        wrong = [workdir / "adir" if out_is_file(cmd) else afile, afile / "sub" / "out"]
        for out in wrong:
            args = [*name.split(), *required_args(cmd, workdir / "ds"), *NEEDS.get(name, []), "--out", str(out)]
            code, lines, text = invoke(args)
            assert code == 3 and len(lines) == 1 and "Traceback" not in text, (args, text)
            assert lines[0].startswith("dp5k: error: ") and str(out).startswith(lines[0].split(": ")[2]), (args, text)
            assert listing(workdir) == before, (args, sorted(set(listing(workdir)) - set(before)))


# Writers whose OUT has a default: a fixed folder, or one derived from the input (DATASET = "ds" in workdir).
DEFAULT_OUT = {"capture": "raw", "demo": "demo-out", "train": "ds-neural_dp", "evaluate": "ds-eval-test",
               "diagnose": "ds/diagnose-base", "validate-depth": "ds/validate-depth"}


def test_a_default_out_is_checked_as_a_given_one(workdir: Path) -> None:
    """Where --out has a default, a file in its place is refused the same way (one line, exit 3, before any work)."""
    with_default = {name for name, cmd in writers().items()
                    if "Default:" in (next(p for p in cmd.params if p.name == "out").help or "")}
    assert with_default == set(DEFAULT_OUT)
    for name, default in DEFAULT_OUT.items():
        (workdir / default).parent.mkdir(parents=True, exist_ok=True)
        (workdir / default).write_text("in the way")
        before = listing(workdir)
        args = [*name.split(), *required_args(writers()[name], Path("ds")), *NEEDS.get(name, [])]
        code, lines, text = invoke(args)
        assert code == 3 and len(lines) == 1 and "Traceback" not in text, (args, text)
        assert f"{default}: not a folder" in lines[0], (args, text)
        assert listing(workdir) == before, args
        (workdir / default).unlink()


def test_a_missing_input_is_exit_3_and_out_is_not_made(workdir: Path) -> None:
    """Every required path input missing: one line naming it, exit 3 (not 4: it is missing, not malformed), and OUT
    is not created."""
    missing, out = workdir / "missing", workdir / "new-out"
    checked = []
    for name, cmd in writers().items():
        if not has_path_input(cmd):
            continue
        args = [*name.split(), *required_args(cmd, missing), *NEEDS.get(name, []), "--out", str(out)]
        code, lines, text = invoke(args)
        assert code == 3 and len(lines) == 1 and "Traceback" not in text, (args, text)
        assert str(missing) in lines[0], (args, text)
        assert not out.exists(), args
        checked.append(name)
    assert {"train", "evaluate", "process", "diagnose", "deblur train", "import", "synthesize"} <= set(checked)
    for name in ("check", "verify"):  # readers only
        code, lines, _ = invoke([name, str(missing)])
        assert code == 3 and len(lines) == 1 and str(missing) in lines[0], name


def test_every_number_carries_its_range_and_is_refused_outside_it(workdir: Path) -> None:
    """Every INT / FLOAT option is an IntRange / FloatRange (or is listed in UNBOUNDED with its reason); a value just
    below each lower bound is a usage error (exit 2) before any work."""
    before = listing(workdir)
    bounded = 0
    for name, cmd in all_commands().items():
        for p in cmd.params:
            if not isinstance(p, click.Option) or not isinstance(p.type, (click.types.IntParamType, click.types.FloatParamType)):
                continue
            if (name, p.opts[-1]) in UNBOUNDED:
                continue
            assert isinstance(p.type, (click.IntRange, click.FloatRange)), f"{name} {p.opts[-1]}: no range"
            if p.count or p.type.min is None:
                continue
            below = p.type.min if p.type.min_open else p.type.min - 1
            args = [*name.split(), *required_args(cmd, workdir / "ds"), *NEEDS.get(name, []), p.opts[-1], str(below)]
            if any(q.name == "out" for q in cmd.params):
                args += ["--out", str(workdir / "new-out")]
            code, _, text = invoke(args)
            assert code == 2 and "Invalid value" in text and p.opts[-1] in text, (args, text)
            bounded += 1
    assert listing(workdir) == before
    assert bounded > 30


@pytest.mark.parametrize("args, code", [
    (["train", "ds", "--epochs", "0"], 2), (["train", "ds", "--epochs", "-1"], 2),
    (["evaluate", "ds", "--max-pairs", "-3"], 2), (["train", "ds", "--crop-size", "0"], 2),
    (["deblur", "train", "ds", "--batch-size", "0"], 2),
    (["studio", "make-dataset", "--size", "0x0"], 3), (["process", "raw", "--size", "0x0"], 3),
    (["import", "generic", "ds", "--tile", "0x0"], 3),
])
def test_the_issues_examples_are_refused(workdir: Path, args: list[str], code: int) -> None:
    """A number outside its range is click's usage error (2); a WxH size below its minimum is bad input (3, one
    line naming it). Nothing is written either way."""
    (workdir / "raw").mkdir()
    got, lines, text = invoke([*args, "--out", str(workdir / "new-out")])
    assert got == code and "Traceback" not in text, text
    assert ("Invalid value" in text) if code == 2 else (len(lines) == 1 and "0x0" in lines[0]), text
    assert not (workdir / "new-out").exists()


@pytest.mark.parametrize("name", sorted(REFUSES))
def test_an_earlier_result_is_refused_without_its_flag(workdir: Path, name: str) -> None:
    marker, words = REFUSES[name]
    out = workdir / "out"
    out.mkdir()
    (out / marker).write_text("{}")
    before = listing(workdir)
    cmd = writers()[name]
    code, lines, text = invoke([*name.split(), *required_args(cmd, workdir / "ds"), "--out", str(out)])
    assert code == 3 and len(lines) == 1 and words in lines[0], text
    assert listing(workdir) == before


def test_a_finished_studio_dataset_is_refused_without_overwrite(workdir: Path) -> None:
    """studio make-dataset resumes an interrupted run, but a finished dataset is refused (with the flag's dashes)."""
    code, lines, text = invoke(["studio", "make-dataset", "--out", str(workdir / "ds")])
    assert code == 3 and len(lines) == 1 and "add --overwrite" in lines[0], text


def test_the_interrupted_line_promises_a_resume_only_where_the_command_resumes(
        workdir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C in evaluate (which resumes) says to run it again to resume; in diagnose (which does not) it says it
    starts over; both exit 130 with one line."""
    import dp5k_diagnose.run
    import neural_dp.evaluate

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(neural_dp.evaluate, "evaluate", interrupted)
    monkeypatch.setattr(dp5k_diagnose.run, "run_diagnose", interrupted)
    commands = all_commands()
    assert command_resumes(commands["evaluate"]) and not command_resumes(commands["diagnose"])
    code, lines, _ = invoke(["evaluate", "ds", "--simulator", "disk", "--out", "e"])
    assert code == 130 and lines == ["dp5k: interrupted; finished work was kept, run the command again to resume"]
    code, lines, _ = invoke(["diagnose", "ds", "--out", "d"])
    assert code == 130 and len(lines) == 1 and "resume" not in lines[0].replace("does not resume", ""), lines
    resuming = {name for name, cmd in commands.items() if command_resumes(cmd)}
    assert {"process", "train", "evaluate", "studio make-dataset", "synthesize", "demo", "capture"} <= resuming
    assert not resuming & (REPLACED | set(REFUSES))


def test_quiet_and_verbose_work_after_every_command() -> None:
    """-q and -v are options of every command and group, so they parse after the command name anywhere."""
    for name, cmd in all_commands().items():
        opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
        assert {"-q", "--quiet", "-v", "--verbose"} <= opts, name
    res = CliRunner().invoke(main, ["studio", "effects", "-q"])
    assert res.exit_code == 0, res.output

