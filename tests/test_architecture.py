"""The layering of docs/architecture.md: the world (dp5k_studio) and the models being judged (neural_dp) never
import each other, and each stage imports only what lies below it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

STAGES = ("dp5k_capture", "dp5k_process", "neural_dp", "dp5k_diagnose", "dp5k_import", "dp5k_studio", "dp5k_demo", "calib",
          "dp5k_deblur")


def imported_modules(package: str) -> set[str]:
    """Absolute module names imported anywhere in ROOT/``package`` (fails when the folder is missing)."""
    package_dir = ROOT / package
    assert package_dir.is_dir() and (package_dir / "__init__.py").is_file(), f"{package_dir} is not a package"
    found: set[str] = set()
    for path in package_dir.rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module)
    return found


def offending(package: str, forbidden: tuple[str, ...]) -> list[str]:
    return sorted(m for m in imported_modules(package) if m.split(".")[0] in forbidden)


def test_models_never_import_the_world() -> None:
    assert not offending("neural_dp", ("dp5k_studio", "dp5k_capture", "dp5k_diagnose", "dp5k_demo", "dp5k_deblur"))


def test_world_never_imports_the_models_or_the_capture_layer() -> None:
    assert not offending("dp5k_studio", ("neural_dp", "dp5k_diagnose", "dp5k_capture", "dp5k_process", "dp5k_import", "dp5k_demo",
                                         "dp5k_deblur"))


def test_simulated_devices_render_through_the_world_only() -> None:
    assert not offending("dp5k_capture", ("neural_dp", "dp5k_diagnose", "dp5k_process", "dp5k_import", "dp5k_demo"))


def test_importers_are_a_stage_below_diagnose() -> None:
    assert not offending("dp5k_import", ("dp5k_diagnose", "neural_dp", "dp5k_studio", "dp5k_capture", "dp5k_demo"))


def test_deblurrer_uses_only_common_and_the_simulators() -> None:
    """dp5k_deblur trains on datasets and synthesizes with neural_dp's simulators; it never reaches the world, capture,
    processing, importers, diagnose or the demo (a diagnose report reaches it as a file)."""
    assert not offending("dp5k_deblur", tuple(s for s in STAGES if s not in ("neural_dp", "dp5k_deblur")))


def test_common_imports_no_stage() -> None:
    assert not offending("dp5k_common", STAGES)


def test_a_missing_package_fails_the_check() -> None:
    with pytest.raises(AssertionError, match="not a package"):
        imported_modules("no_such_package")


def test_benchmarks_import_the_package_never_the_tests() -> None:
    found: set[str] = set()
    for path in (ROOT / "benchmarks").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module)
    assert found and not sorted(m for m in found if m.split(".")[0] == "tests")


def test_the_pipeline_never_imports_the_test_support_package() -> None:
    for package in STAGES:
        assert not offending(package, ("dp5k_testing", "tests")), package
