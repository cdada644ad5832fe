"""diagnose on data from a renderer that shares no code with dp5k (dp5k_testing/foreign_dp.py).

The studio and the base model were built side by side; an outside suite plants the same vocabulary with its
own renderer. This one scatters every pixel's half disc, has its own scenes, textures and effect formulas,
and samples its PSFs over pixel areas (a box) where the base model and the studio splat them (a triangle):
below ~2 px of CoC that alone changed the views by 10 x the noise, and hid five of the nine effects until
the base fit learned the sampling (``pixel_box``). Three cases at 192 x 128 (12 scenes x f/2, f/4).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from neural_dp.registry import SimulatorSpec
from dp5k_diagnose.run import DiagnoseConfig, run_diagnose
from dp5k_testing.foreign_dp import write_dataset

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("effect", ["none", "psf_profile", "chromatic_defocus"])
def test_diagnose_names_an_effect_planted_by_another_renderer(tmp_path: Path, effect: str) -> None:
    ds = tmp_path / "ds"
    write_dataset(ds, effect, 1.0, scenes=12, size=(192, 128), seed=0, sampling="box")
    res = run_diagnose(ds, SimulatorSpec(), tmp_path / "report", DiagnoseConfig(fit_pairs=6))
    assert res["base_params"]["pixel_box"] > 0.8  # the data's PSFs are box-sampled
    assert res["cause"] == effect
    g = res["gain"]
    if effect == "none":
        assert res["causes"] == [] and g["psnr_gain_ci95"] == [0.0, 0.0]
    else:
        assert g["psnr_gain_ci95"][0] > 0
        assert [c["name"] for c in res["causes"]] == [effect] and res["signatures"][effect]["differs"]


def test_a_bright_rim_and_a_focus_offset_from_another_renderer_are_both_named(tmp_path: Path) -> None:
    """Two effects that hide each other in the views' error, rendered by foreign code (its rim is quadratic, the base
    model's quartic): each has its own signature in the atlas (the profile index; where the disparity vanishes),
    so both are named, each gaining given the other."""
    from dp5k_diagnose.run import diagnose_base

    ds = tmp_path / "ds"
    write_dataset(ds, "psf_profile+focus_offset", 1.0, scenes=12, size=(192, 128), seed=1)
    rep = diagnose_base(ds, DiagnoseConfig(fit_pairs=6)).to_json()
    names = [c["name"] for c in rep["causes"]]
    assert set(names[:2]) == {"psf_profile", "focus_offset"}, names
    by = {c["name"]: c for c in rep["causes"]}
    assert by["focus_offset"]["params"]["focus_factor"] == pytest.approx(1.06, abs=0.02)  # planted 1 + 0.06
    rim = by["psf_profile"]["params"]
    # a bright rim (planted 1 + 1.2 (rho/R)^2): the fitted weight at the rim, 1 + rim_gain2 + rim_gain, is above 1.3
    assert rim["rim_gain"] + rim["rim_gain2"] > 0.3, rim
    for name in ("psf_profile", "focus_offset"):
        assert by[name]["gain_ci_db"][0] > 0, by[name]  # each adds to a model that has the other
