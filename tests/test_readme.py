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


# --------------------------------------------------------------------------- the README as a front door
HEAD_LINES = 40
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
COMMIT = re.compile(r"\b[0-9a-f]{7,40}\b")
TIMING = re.compile(r"\b\d+(\.\d+)?\s?(s|ms|sec|secs|seconds|min|mins|minutes|h|hours?)\b", flags=re.I)
TOUR_STAGES = {"capture", "process", "train", "evaluate", "diagnose", "synthesize", "import"}


def test_readme_head_holds_no_date_commit_or_timing() -> None:
    head = "\n".join((ROOT / "README.md").read_text().splitlines()[:HEAD_LINES])
    for name, pattern in (("date", DATE), ("commit hash", COMMIT), ("timing", TIMING)):
        found = [m.group(0) for m in pattern.finditer(head)]
        assert not found, f"README's first {HEAD_LINES} lines hold a {name}: {found} (figures belong in docs/results.md)"


def tour_commands() -> list[list[str]]:
    text = (ROOT / "README.md").read_text()
    tour = re.search(r"^## A tour.*?(?=^## )", text, flags=re.S | re.M)
    assert tour, "README has no '## A tour' section"
    blocks = re.findall(r"```(?:bash|sh)?\n(.*?)```", tour.group(0), flags=re.S)
    return [line.split() for b in blocks for line in b.splitlines() if line.split()[:1] in (["dp5k"], [".venv/bin/dp5k"])]


def test_the_tour_runs_every_stage_with_commands_that_exist() -> None:
    import dp5k_cli

    commands = tour_commands()
    named = {c[1] for c in commands}
    assert named <= set(dp5k_cli.COMMANDS), f"unknown commands in the tour: {sorted(named - set(dp5k_cli.COMMANDS))}"
    assert TOUR_STAGES <= named, f"the tour misses {sorted(TOUR_STAGES - named)}"
    assert all("--out" in c or c[1] == "check" for c in commands), "every tour command writes to --out"


def test_readme_picture_exists_and_is_small() -> None:
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (ROOT / "README.md").read_text())
    assert images, "README shows no picture"
    for img in images:
        path = ROOT / img
        assert path.is_file() and path.stat().st_size < 150_000, img
