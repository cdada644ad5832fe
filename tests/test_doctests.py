"""The ``>>>`` examples of every package run with the suite: pyproject's testpaths (with --doctest-modules) name
every package setuptools installs, so a new package's examples are collected the day it lands."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_testpaths_cover_every_package_and_module() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = {p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]}
    modules = {f"{m}.py" for m in project["tool"]["setuptools"]["py-modules"]}
    pytest_ini = project["tool"]["pytest"]["ini_options"]
    assert "--doctest-modules" in pytest_ini["addopts"].split()
    assert packages | modules <= set(pytest_ini["testpaths"]), sorted(packages | modules - set(pytest_ini["testpaths"]))

