"""A few cells of the diagnose confusion matrix (benchmarks/diagnose_matrix.py), in the suite.

Data from the second independent renderer (``dp5k_testing/aperture_dp.py``: a sub-aperture gather with
occlusion, its own scenes, effect physics and sensor noise, a noisy f/22 ``sharp``), diagnosed as ``dp5k
diagnose --nominal-noise 2e-4,2e-3`` would: a clean set names nothing, a single effect is named alone, a pair
is named both. And where the data cannot show what separates two effects (every pixel behind focus: a bright rim
or a rim-heavy back disc), the one that needs both sides of focus is not measured, says so, and is never named.
Small sets (160 x 108, 12 pairs) so that each cell costs well under a minute of one core.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from dp5k_diagnose.config import DiagnoseConfig
from dp5k_diagnose.data import auto_fit_pairs
from dp5k_diagnose.run import run_diagnose
from dp5k_testing.aperture_dp import NOMINAL_READ_SIGMA, NOMINAL_SHOT_VAR, write_matrix_cell
from neural_dp.registry import SimulatorSpec
from tests.diagnose.plant import make_planted_dataset

pytestmark = pytest.mark.slow

SIZE = (160, 108)
PAIRS = 12


def _diagnose(ds: Path, **noise: float) -> dict[str, Any]:
    os.environ.setdefault("DP5K_PROGRESS", "0")
    cfg = DiagnoseConfig(fit_pairs=auto_fit_pairs(ds), **noise)
    return run_diagnose(ds, SimulatorSpec(), None, cfg)


def _aperture(tmp_path: Path, effects: str | None, size: tuple[int, int] = SIZE, pairs: int = PAIRS) -> dict[str, Any]:
    ds = write_matrix_cell(tmp_path / "cell", effects, size=size, pairs=pairs)
    return _diagnose(ds, nominal_shot_var=NOMINAL_SHOT_VAR, nominal_read_sigma=NOMINAL_READ_SIGMA)


def _names(res: dict[str, Any]) -> list[str]:
    return [c["name"] for c in res["causes"]]


def test_a_clean_cell_names_nothing(tmp_path: Path) -> None:
    res = _aperture(tmp_path, None)
    assert _names(res) == [] and res["cause"] == "none", res["suspects"]
    assert res["gain"]["psnr_gain_ci95"] == [0.0, 0.0]


def test_a_single_effect_cell_names_it_alone(tmp_path: Path) -> None:
    res = _aperture(tmp_path, "misregistration")
    assert _names(res) == ["misregistration"], (res["suspects"], res["lookalikes"])
    assert res["causes"][0]["gain_ci_db"][0] > 0


def test_a_pair_cell_names_both(tmp_path: Path) -> None:
    res = _aperture(tmp_path, "lr_gain_imbalance+disparity_scale")
    assert sorted(_names(res)) == ["disparity_scale", "lr_gain_imbalance"], (res["suspects"], res["lookalikes"])
    for c in res["causes"]:
        assert c["gain_ci_db"][0] > 0, c  # each earns its name given the other, on held-out pairs


def test_an_effect_the_data_cannot_show_is_not_measured_and_never_named(tmp_path: Path) -> None:
    """Every pixel behind focus, a quadratic bright rim planted (psf_profile's ``rim_gain2``): behind focus
    front_back_asymmetry's back rim is the same blur, so no data of this kind can tell them apart. Its signature
    needs both sides of focus: it is not measured (and says so), the rim is named."""
    ds = tmp_path / "ds"
    make_planted_dataset(ds, "psf_profile", {"rim_gain2": 1.5, "rim_gain": 0.0}, scenes=12, size=(128, 96), seed=5, noise_sigma=2e-3,
                         behind_focus=True)
    res = _diagnose(ds)
    assert _names(res) == ["psf_profile"], (res["suspects"], res["lookalikes"])
    fba = res["signatures"]["front_back_asymmetry"]
    assert fba["unmeasured"] and "both sides of focus" in fba["unmeasured"] and not fba["differs"]
