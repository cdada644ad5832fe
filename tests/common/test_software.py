from importlib import metadata

import cv2
import numpy
import scipy
import torch

from dp5k_common import __version__
from dp5k_common.software import software_line, software_versions


def test_software_versions_are_the_installed_ones() -> None:
    v = software_versions()
    assert v["dp5k"] == __version__
    assert (v["numpy"], v["scipy"], v["torch"]) == (numpy.__version__, scipy.__version__, torch.__version__)
    # the wheel's version (5.1.0.95) starts with the module's (5.1.0)
    assert v["opencv"].startswith(cv2.__version__.split("-")[0]), (v["opencv"], cv2.__version__)


def test_a_missing_distribution_reads_absent(monkeypatch) -> None:
    real = metadata.version

    def version(dist: str) -> str:
        if dist == "scipy":
            raise metadata.PackageNotFoundError(dist)
        return real(dist)

    monkeypatch.setattr(metadata, "version", version)
    assert software_versions()["scipy"] == "absent"
    assert "scipy absent" in software_line(software_versions())


def test_provenance_names_the_checkout_and_its_changes(tmp_path, monkeypatch) -> None:
    """The commit is the HEAD of the checkout the code runs from (None outside one); dirty follows git status."""
    import subprocess

    from dp5k_common.software import REPO_ROOT, git_state, provenance

    git_state.cache_clear()  # as the tree is now
    try:
        head = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(REPO_ROOT), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):  # not a git checkout (an sdist), or no git
        head, status = None, None
    p = provenance()
    assert p["dp5k"] == __version__ and p["commit"] == head
    assert p["dirty"] == (None if head is None else bool(status))
    assert git_state(tmp_path) == (None, None)  # not a checkout
    monkeypatch.setattr("sys.argv", ["myscript.py", "--flag"])
    assert provenance()["command"] == ["myscript.py", "--flag"]  # outside the CLI: the process's own command line


def test_every_result_file_records_its_provenance(tmp_path) -> None:
    """dataset.json (studio make-dataset) and metrics.json (evaluate) carry the version, commit and the dp5k command
    line as given, also when the CLI runs in-process."""
    import json

    from click.testing import CliRunner

    from dp5k_cli import main
    from dp5k_common.dataset import DatasetReader
    from dp5k_common.software import git_state

    make = ["studio", "make-dataset", "--out", str(tmp_path / "ds"), "--scenes", "3", "--size", "48x32",
            "--f-numbers", "2"]
    assert CliRunner().invoke(main, ["-q", *make]).exit_code == 0
    index = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    assert index["provenance"] == {"dp5k": __version__, "commit": git_state()[0], "dirty": git_state()[1],
                                   "command": ["dp5k", "-q", *make]}
    reader = DatasetReader(tmp_path / "ds")
    assert reader.provenance == index["provenance"] and "provenance" not in reader.extra  # not an extra to copy on
    ev = ["evaluate", str(tmp_path / "ds"), "--simulator", "disk", "--figures", "0", "--out", str(tmp_path / "e")]
    res = CliRunner().invoke(main, ev)
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["provenance"]["command"] == ["dp5k", *ev]
