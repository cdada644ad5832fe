"""The README's first screen gives exactly two commands, and CI runs the README's test command."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def first_screen_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    first_screen = text.split("\n---", 1)[0]
    blocks = re.findall(r"```(?:bash|sh)?\n(.*?)```", first_screen, flags=re.S)
    lines = [l.split("#", 1)[0].strip() for b in blocks for l in b.splitlines()]
    return [l for l in lines if l]


def test_first_screen_has_exactly_demo_and_test() -> None:
    assert first_screen_commands() == ["make demo", "make test"]


def test_ci_runs_the_readme_test_command() -> None:
    ci = (ROOT / ".ci" / "run").read_text()
    test_cmd = first_screen_commands()[1]
    assert re.search(rf"^\s*{re.escape(test_cmd)}\s*$", ci, flags=re.M), ci


def test_make_targets_set_up_first() -> None:
    makefile = (ROOT / "Makefile").read_text()
    for target in ("demo", "test"):
        rule = re.search(rf"^{target}:(.*)$", makefile, flags=re.M)
        assert rule and "setup" in rule.group(1), f"make {target} must depend on setup"
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    assert "torch==2.13.0" in setup and "libusb-1.0-0" in setup and "venv" in setup
