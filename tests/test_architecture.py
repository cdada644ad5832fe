"""The world (studio) and the models being judged never import each other."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(package_dir: Path) -> set[str]:
    found: set[str] = set()
    for path in package_dir.rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module)
    return found


def test_models_never_import_the_world() -> None:
    mods = imported_modules(ROOT / "neural_dp")
    assert not [m for m in mods if m.startswith("dp5k_capture")], mods


def test_world_never_imports_the_models() -> None:
    sim = ROOT / "dp5k_capture" / "sim"
    mods = imported_modules(sim) if sim.exists() else set()
    assert not [m for m in mods if m.startswith(("neural_dp", "dp5k_diagnose"))], mods


def test_common_imports_no_stage() -> None:
    mods = imported_modules(ROOT / "dp5k_common")
    stages = ("dp5k_capture", "dp5k_process", "neural_dp", "dp5k_diagnose", "calib")
    assert not [m for m in mods if m.startswith(stages)], mods
