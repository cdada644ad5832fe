"""The layering of docs/architecture.md: the world (dp5k_studio) and the models being judged (neural_dp) never
import each other, each stage imports only what lies below it, other stages reach neural_dp only through its
registry, and no import inside a function hides an import cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

STAGES = ("dp5k_capture", "dp5k_process", "neural_dp", "dp5k_diagnose", "dp5k_import", "dp5k_studio", "dp5k_demo", "calib",
          "dp5k_deblur")
PACKAGES = ("dp5k_common", "dp5k_learn", *STAGES, "dp5k_testing")
"""Every package of the project (``dp5k_cli.py`` is a module beside them)."""
REGISTRY = "neural_dp.registry"
"""The one module through which other stages use ``neural_dp``."""


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
    """dp5k_deblur trains on datasets (dp5k_learn) and synthesizes with neural_dp's simulators; it never reaches the
    world, capture, processing, importers, diagnose or the demo (a diagnose report reaches it as a file)."""
    assert not offending("dp5k_deblur", tuple(s for s in STAGES if s not in ("neural_dp", "dp5k_deblur")))


def test_common_imports_no_stage() -> None:
    assert not offending("dp5k_common", (*STAGES, "dp5k_learn"))


def test_the_learning_layer_imports_no_stage() -> None:
    """dp5k_learn (data, losses, metrics, set-up, step, epochs) sits on dp5k_common, beneath every trainer."""
    assert not offending("dp5k_learn", STAGES)


@pytest.mark.parametrize("package", ["dp5k_deblur", "dp5k_diagnose"])
def test_other_stages_reach_the_simulators_only_through_the_registry(package: str) -> None:
    """dp5k_deblur and dp5k_diagnose take simulators, the base model's parts, fine-tuning and synthesis from
    neural_dp.registry, and the training tools from dp5k_learn; no deeper reach into neural_dp."""
    deeper = sorted(m for m in imported_modules(package) if m.split(".")[0] == "neural_dp" and m != REGISTRY)
    assert not deeper, deeper
    assert REGISTRY in imported_modules(package)


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


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    """The modules an ``ImportFrom`` may import (``from .x import y`` may import module ``x.y``)."""
    if node.level:
        base = module.split(".")
        base = base[: len(base) - node.level + (1 if is_package else 0)]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    return [target] + [f"{target}.{alias.name}" for alias in node.names]


def import_graph(root: Path, packages: tuple[str, ...], modules: tuple[str, ...] = ()
                 ) -> tuple[dict[str, set[str]], dict[str, set[tuple[str, int]]]]:
    """Module -> the project modules it imports at module level (what importing it runs, ``TYPE_CHECKING`` blocks
    aside), and module -> (module, line) of each import made inside a function, over ``packages`` and the
    top-level ``modules`` under ``root``."""
    files = {_module_name(p, root): p for pkg in packages for p in (root / pkg).rglob("*.py")}
    files.update({m: root / f"{m}.py" for m in modules})
    top: dict[str, set[str]] = {m: set() for m in files}
    inner: dict[str, set[tuple[str, int]]] = {m: set() for m in files}

    def targets(node: ast.Import | ast.ImportFrom, module: str) -> list[str]:
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            names = _resolve(node, module, files[module].name == "__init__.py")
        found = []
        for name in names:  # importing a module also runs its packages' __init__
            parts = name.split(".")
            found += [".".join(parts[:k]) for k in range(1, len(parts) + 1) if ".".join(parts[:k]) in files]
        return found

    for module, path in files.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))]
        nested = {id(n) for f in functions for n in ast.walk(f)}
        type_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If) and ast.unparse(block.test) in
                     ("TYPE_CHECKING", "typing.TYPE_CHECKING") for n in ast.walk(block)}  # never run
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in type_only:
                continue
            if id(node) in nested:
                inner[module].update((t, node.lineno) for t in targets(node, module))
            else:
                top[module].update(targets(node, module))
    return top, inner


def reaches(graph: dict[str, set[str]], start: str, goal: str) -> bool:
    """Whether importing ``start`` imports ``goal`` at module level, directly or through other modules."""
    seen, todo = set(), [start]
    while todo:
        m = todo.pop()
        if m == goal:
            return True
        if m not in seen:
            seen.add(m)
            todo += graph.get(m, ())
    return False


def hidden_cycles(root: Path, packages: tuple[str, ...], modules: tuple[str, ...] = ()) -> list[str]:
    """Each import inside a function whose module imports the current one, directly or transitively (its own
    packages aside: they are always imported already)."""
    top, inner = import_graph(root, packages, modules)
    return sorted(f"{module}:{line} imports {target}, which imports {module}"
                  for module, imports in inner.items() for target, line in imports
                  if target != module and not module.startswith(target + ".") and reaches(top, target, module))


def test_no_import_inside_a_function_hides_a_cycle() -> None:
    """An import deferred into a function is for start-up time (the CLI's lazy commands, heavy optional parts),
    never to get round a cycle: the module it imports must not import the current one, directly or transitively."""
    hidden = hidden_cycles(ROOT, PACKAGES, ("dp5k_cli",))
    assert not hidden, "\n".join(hidden)


def test_the_cycle_check_finds_a_hidden_cycle(tmp_path: Path) -> None:
    """On a small project: b imports a inside a function while a imports c, which imports b (found); d's deferred
    import of e is no cycle, nor is a type-only one (not found)."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    files = {"__init__": "", "a": "from . import c\n", "c": "from .b import helper\n",
             "b": "def helper():\n    from .a import thing\n    return thing\n",
             "d": "def later():\n    import pkg.e\n", "e": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import d\n"}
    for name, text in files.items():
        (pkg / f"{name}.py").write_text(text)
    assert hidden_cycles(tmp_path, ("pkg",)) == ["pkg.b:2 imports pkg.a, which imports pkg.b"]
