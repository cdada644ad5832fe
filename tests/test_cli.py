"""The CLI's error policy: one line, distinct exit codes, tracebacks only with --verbose."""

from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from dp5k_cli import main
from dp5k_testing.tiny_dataset import make_tiny_dataset


def test_help_lists_commands() -> None:
    result = CliRunner().invoke(main, ["--help"])
    assert result.exit_code == 0
    assert "check" in result.output and "dual-pixel" in result.output


def test_bad_path_gives_one_line_and_exit_code(tmp_path: Path) -> None:
    """A missing folder is bad input (3); an existing folder that is not a dataset is not format v1 (4)."""
    result = CliRunner().invoke(main, ["check", str(tmp_path / "missing")])
    assert result.exit_code == 3
    lines = [l for l in result.output.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("dp5k: error:") and "missing" in lines[0]
    assert "Traceback" not in result.output
    result = CliRunner().invoke(main, ["check", str(tmp_path)])
    assert result.exit_code == 4 and "missing dataset.json" in result.output


def test_verbose_adds_traceback(tmp_path: Path) -> None:
    result = CliRunner().invoke(main, ["-v", "check", str(tmp_path / "missing")])
    assert result.exit_code == 3 and "Traceback" in result.output


def test_verbose_and_quiet_work_after_the_command_too(tmp_path: Path) -> None:
    """-v after the subcommand (and after a group's subcommand) adds the traceback as -v before it does; -q after it
    silences the info log."""
    import logging

    result = CliRunner().invoke(main, ["check", str(tmp_path / "missing"), "-v"])
    assert result.exit_code == 3 and "Traceback" in result.output
    result = CliRunner().invoke(main, ["studio", "make-dataset", "--out", str(tmp_path / "x"), "--size", "0x0", "-v"])
    assert result.exit_code == 3 and "Traceback" in result.output
    result = CliRunner().invoke(main, ["check", str(tmp_path / "missing"), "-q"])
    assert result.exit_code == 3 and "Traceback" not in result.output
    assert logging.getLogger().level == logging.WARNING
    CliRunner().invoke(main, ["check", str(tmp_path / "missing"), "-vv"])
    assert logging.getLogger().level == logging.DEBUG


def test_check_valid_dataset_summarises(tmp_path: Path) -> None:
    make_tiny_dataset(tmp_path / "ds", scenes=3)
    result = CliRunner().invoke(main, ["-q", "check", str(tmp_path / "ds")])
    assert result.exit_code == 0, result.output
    assert "3 pairs" in result.output


def test_check_detects_scene_crossing_splits(tmp_path: Path) -> None:
    import json

    make_tiny_dataset(tmp_path / "ds", scenes=3)
    p = tmp_path / "ds/pairs/s1_cam0_f1.8/params.json"
    params = json.loads(p.read_text())
    params["scene"] = "s0"
    p.write_text(json.dumps(params))
    result = CliRunner().invoke(main, ["-q", "check", str(tmp_path / "ds")])
    assert result.exit_code == 4 and "appear in both" in result.output


def test_lazy_command_table_matches_the_commands() -> None:
    """Every listed command imports under its own name and has help text; the listed one-liners fit one line."""
    import click

    from dp5k_cli import COMMANDS

    ctx = click.Context(main)
    for name, (_, _, short) in COMMANDS.items():
        cmd = main.get_command(ctx, name)
        assert isinstance(cmd, click.Command) and cmd.name == name
        assert cmd.help and cmd.help.strip(), name
        assert short.endswith(".") and len(short) <= 72, name


def test_help_does_not_import_heavy_stages() -> None:
    import subprocess
    import sys

    code = "import sys; from click.testing import CliRunner; from dp5k_cli import main; " \
           "r = CliRunner().invoke(main, ['--help']); assert r.exit_code == 0; " \
           "print(sorted(m for m in ('torch', 'open3d', 'pygame', 'neural_dp') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"


def test_unknown_command_is_a_usage_error() -> None:
    result = CliRunner().invoke(main, ["nope"])
    assert result.exit_code == 2 and "No such command" in result.output


def test_verbose_shows_the_chained_cause(tmp_path: Path) -> None:
    """A user error keeps its original exception as the cause: one line without -v, the chain with it."""
    args = ["studio", "make-dataset", str(tmp_path / "ds"), "--size", "288xabc"]
    quiet = CliRunner().invoke(main, args)
    assert quiet.exit_code == 3 and "Traceback" not in quiet.output and "--size" in quiet.output
    loud = CliRunner().invoke(main, ["-v"] + args)
    assert loud.exit_code == 3
    assert "ValueError" in loud.output and "direct cause of the following exception" in loud.output
    assert not (tmp_path / "ds").exists()
