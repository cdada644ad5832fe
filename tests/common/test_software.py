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
