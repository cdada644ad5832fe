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

## Conventions (every command)

- **Inputs are arguments, the output is `--out` (`-o`).** `dp5k COMMAND INPUT... --out OUT`. Where a command
  has a default OUT, its help says which; where it has none, `--out` is required. (`import`, `sl-depth`,
  `process`, `synthesize`, `studio make-dataset`, `studio render` and `demo` used to take OUT as their last
  argument: that still works for this release, with a deprecation line.)
- **`--device auto|cpu|cuda|cuda:N`, default `auto`** (the first CUDA GPU torch sees, else the CPU) in every
  command that runs a network: `train`, `evaluate`, `synthesize`, `diagnose`, `deblur train`, `deblur
  evaluate`, `study downstream`. A CUDA device the machine does not have is refused before any work (exit 3).
- **`--crop` is a region of the input frames** (`import`: `CAM=ROW0:ROW1,COL0:COL1`, `release`, `none`). The
  side of a training patch is `--crop-size PX` (`train`, `deblur train`; their old `--crop PX` is deprecated).
- **Earlier results in OUT: `--resume` / `--no-resume` / `--overwrite`**, the same words everywhere:
  - `--resume`: continue: what OUT already holds is checked and kept, the rest is done. The default of the
    commands built to be interrupted: `process`, `train`, `deblur train`, `demo`; `capture`, `synthesize` and
    `study downstream` always resume. `import` resumes only when asked (`--resume`), so that two imports are
    never mixed by accident.
  - `--no-resume`: an OUT that holds an earlier run is refused; nothing is mixed or lost.
  - `--overwrite`: start afresh, replacing the earlier run's results (`process`, `sl-depth`, `studio
    make-dataset`, `train`, `deblur train`, `demo`; `demo --force` is its deprecated spelling). Raw captures and
    imports are never overwritten: `capture` and `import` have no `--overwrite`.
  - `studio make-dataset` continues an interrupted run when run again with the same options (a finished dataset
    is refused without `--overwrite`); `evaluate` continues an interrupted run with the same settings.
  - Reports computed from their inputs (`evaluate` once finished, `diagnose`, `validate-depth`, `deblur
    evaluate`, `studio render`) are replaced on each run.
- **Deprecated spellings** still work for this release and print one line, `OLD is deprecated; use NEW`, on
  stderr after the command's output; when the command fails, the note ends its one error line instead.
- A processed dataset is validated by `dp5k check DATASET`; `dp5k verify` is for raw capture sessions and,
  given a dataset, says so and runs the same check.

## The contract (every command)

`tests/test_cli_contract.py` checks it over the whole command tree, so a new command is held to it the day it lands.

- **OUT is checked before any work.** An `--out` that is a file (where a folder goes), lies under a file, or
  cannot be written is refused in one line, exit 3, and nothing is created.
- **Inputs are checked before OUT is made.** A missing input file or folder is exit 3 in every command; an
  existing folder that is not a format-v1 dataset (or lacks the split a command needs) is exit 4. OUT is created
  only once the inputs passed.
- **An earlier result in OUT** is continued (the commands that resume), refused without `--overwrite` (exit 3),
  or, for a report computed from its inputs, replaced; never mixed.
- **Numbers carry their ranges.** A count, size, seed or f-number outside its range (`train --epochs 0`,
  `evaluate --max-pairs -3`, `--batch-size 0`) is a usage error, exit 2; a `WxH` size below its minimum
  (`studio make-dataset --size 0x0`, `import --tile 0x0`) is bad input, exit 3.
- **Interrupted** (Ctrl-C, exit 130): finished work is kept. The commands that resume say "run the command again
  to resume": {resuming}. The others say they start over when run again.
- **`-v` / `-q` go before or after the command**: `dp5k -q train DS` and `dp5k train DS -q` are the same.

## Global options and exit codes

`dp5k [-v|-vv] [-q] COMMAND ...` (or after the command) — `-v` more logging and tracebacks on errors, `-q` only
warnings and no progress bars (`DP5K_PROGRESS=0` also hides them). Errors print one line,
`dp5k: error: <file/device/stage>: <problem>`, and exit with:

| code | meaning |
|---|---|
| 0 | success |
| 1 | other dp5k failure |
| 2 | usage error (bad option, a number outside its range; click's own) |
| 3 | bad input: a file, folder or argument is missing or malformed; an unusable `--out` |
| 4 | an existing dataset not in format v1 (or without the split the command needs) |
| 5 | device fault, timeout or protocol error |
| 6 | calibration failed or exceeded its bound |
| 7 | a pipeline stage failed |
| 8 | some items failed, the others completed (see the report) |
| 9 | the result was written but is below its quality bound, marked so in its report (`sl-depth`: low coverage, a calibration the refinement could not fix) |
| 130 | interrupted; finished work kept; the commands that resume continue when run again |
"""


def render() -> str:
    sys.path.insert(0, str(ROOT))
    from dp5k_cli import COMMANDS, main

    from dp5k_common.cli_conventions import command_resumes

    runner = CliRunner()
    ctx = click.Context(main)
    tree: list[tuple[list[str], click.Command]] = []
    for name in sorted(COMMANDS):
        cmd = main.get_command(ctx, name)
        tree.append(([name], cmd))
        if isinstance(cmd, click.Group):
            tree += [([name, sub], cmd.get_command(ctx, sub)) for sub in sorted(cmd.list_commands(ctx))]
    resuming = ", ".join(f"`{' '.join(path)}`" for path, cmd in tree if command_resumes(cmd))
    parts = [HEAD.replace("{resuming}", resuming)]
    for path, _ in tree:
        out = runner.invoke(main, [*path, "--help"], prog_name="dp5k", terminal_width=100).output
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
