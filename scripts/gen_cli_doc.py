"""Regenerate docs/cli.md from the commands' own --help (tests/test_cli_doc.py fails when it is stale).

Usage: python scripts/gen_cli_doc.py [--check]
"""

from __future__ import annotations

import sys
from pathlib import Path

import click
from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[1]
HEAD = """# CLI reference

Generated from the commands' own help by `scripts/gen_cli_doc.py`; do not edit by hand. Each stage's
design and numbers are in its own page: [capture](capture.md), [studio](studio.md),
[processing](processing.md), [simulators](simulators.md), [diagnose](diagnose.md); formats in
[data-format](data-format.md).

`dp5k [-v|-vv] [-q] COMMAND ...` — `-v` more logging and tracebacks on errors, `-q` only warnings and no
progress bars (`DP5K_PROGRESS=0` also hides them). Errors print one line,
`dp5k: error: <file/device/stage>: <problem>`, and exit with:

| code | meaning |
|---|---|
| 0 | success |
| 1 | other dp5k failure |
| 2 | usage error (bad option; click's own) |
| 3 | bad input: a file, folder or argument is missing or malformed |
| 4 | dataset not in format v1 |
| 5 | device fault, timeout or protocol error |
| 6 | calibration failed or exceeded its bound |
| 7 | a pipeline stage failed |
| 8 | some items failed, the others completed (see the report) |
| 9 | the result was written but is below its quality bound, marked so in its report (`sl-depth`: low coverage, a calibration the refinement could not fix) |
| 130 | interrupted; finished work kept, rerun to resume |
"""


def render() -> str:
    sys.path.insert(0, str(ROOT))
    from dp5k_cli import COMMANDS, main

    runner = CliRunner()
    parts = [HEAD]
    ctx = click.Context(main)
    for name in sorted(COMMANDS):
        cmd = main.get_command(ctx, name)
        paths = [[name]]
        if isinstance(cmd, click.Group):
            paths += [[name, sub] for sub in sorted(cmd.list_commands(ctx))]
        for path in paths:
            out = runner.invoke(main, [*path, "--help"], terminal_width=100).output
            parts.append(f"\n## `dp5k {' '.join(path)}`\n\n```text\n{out.rstrip()}\n```\n")
    return "".join(parts)


def main() -> int:
    text = render()
    target = ROOT / "docs" / "cli.md"
    if "--check" in sys.argv:
        return 0 if target.read_text() == text else 1
    target.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
