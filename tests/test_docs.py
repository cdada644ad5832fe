"""docs/ is a reference: no page over 900 lines, no dated run prose (dates belong in docs/results.md and
CHANGELOG.md), and every relative link between the pages points to a file that exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MAX_LINES = 900
DATE = re.compile(r"20\d\d-\d\d-\d\d")
DATED_ALLOWED = {DOCS / "results.md", ROOT / "CHANGELOG.md"}
LINK = re.compile(r"\]\(([^)#\s]+\.md)(#[^)\s]*)?\)")


def pages() -> list[Path]:
    return sorted(DOCS.glob("*.md"))


def test_no_page_is_over_900_lines() -> None:
    long = {p.name: n for p in pages() if p.name != "results.md" and (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"pages over {MAX_LINES} lines: {long}"


def test_no_dates_outside_results_and_changelog() -> None:
    found = {}
    for p in pages() + [ROOT / "README.md"]:
        if p in DATED_ALLOWED:
            continue
        hits = [f"{i}: {line.strip()[:80]}" for i, line in enumerate(p.read_text().splitlines(), 1) if DATE.search(line)]
        if hits:
            found[p.name] = hits[:3]
    assert not found, f"dated prose (move the run to benchmarks/results/ or CHANGELOG.md): {found}"


def test_changelog_exists_in_keep_a_changelog_form() -> None:
    text = (ROOT / "CHANGELOG.md").read_text()
    assert text.startswith("# Changelog") and "## [Unreleased]" in text
    assert re.search(r"^## \[[^\]]+\] - 20\d\d-\d\d-\d\d", text, flags=re.M)


def test_relative_links_point_to_existing_files() -> None:
    broken = []
    for p in pages() + [ROOT / "README.md", ROOT / "CHANGELOG.md"]:
        for target, _ in LINK.findall(p.read_text()):
            if "://" in target:
                continue
            if not (p.parent / target).resolve().is_file():
                broken.append(f"{p.relative_to(ROOT)} -> {target}")
    assert not broken, f"broken links: {broken}"
