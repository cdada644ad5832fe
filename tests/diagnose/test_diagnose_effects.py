"""Hide an effect with the studio, require diagnose (base model) to name it, fit it and gain on held-out pairs.

Which effect a case plants, and how strongly, is drawn from a seed (``_draw``), so nothing in diagnose can
key on a test's name. The planted truth is read back from the studio's dataset.json by the TEST only.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from dp5k_common.effects import EFFECT_NAMES, NO_EFFECT
import dp5k_studio.dataset as studio


CASES = (*EFFECT_NAMES, NO_EFFECT)
SIZE = (160, 96)
SCENES = 13
"""Scenes per case: the studio's paper proportions then give 2 test scenes (8 held-out pairs for the gain's
bootstrap CI; 8 scenes gave one scene's 4 pairs, too few to bound a gain of a few tenths of a dB)."""
SMALL_EFFECTS: set[str] = {"chromatic_defocus"}
"""Effects that are physically invisible at SIZE and moderate strength: the test then requires only that no
other effect is named and that nothing gets worse (see docs/diagnose.md). chromatic_defocus moves red's and blue's
CoC by about 0.1 px here, and the atlas of 26 pairs at 160 x 96 reads each to +-0.2 px (95 %), under its 0.15 px
minimum; at the benchmark's size (docs/results.md) it is named."""


KNOWN_GAPS: dict[str, str] = {
    "front_back_asymmetry": "at 160 x 96 its own signatures (the size's growth, the profile's front-minus-back) read "
                            "+-0.045 and +-0.06, four times their minimum, while its bright back rim moves the pooled "
                            "profile index beyond its interval: psf_profile is named in its place",
}
"""Effects diagnose does not yet fully diagnose at this size, with the reason (docs/diagnose.md). Their cases
run as strict xfails: the assertions are unchanged, and a case that starts passing fails the suite until its entry is removed."""


def _draw(case: int) -> tuple[str, float]:
    rng = np.random.default_rng(20261121)
    order = rng.permutation(len(CASES))
    strengths = rng.uniform(0.9, 1.3, len(CASES))
    return CASES[int(order[case])], float(strengths[case])


def _near(fitted: dict, truth: dict, effect: str) -> list[str]:
    """Parameter checks: fitted values near the planted physical parameters (problems as text)."""
    bad = []

    def close(name: str, got: float, want: float, tol: float) -> None:
        if not abs(got - want) <= tol:
            bad.append(f"{name}: fitted {got:.4f}, planted {want:.4f} (tol {tol})")

    t = truth[effect]
    if effect == "lr_gain_imbalance":
        close("lr_ratio_center", fitted["lr_ratio_center"], t["lr_ratio_center"], 0.03)
        close("ax", fitted["ax"], t["log_ratio_coeffs"][1], 0.04)
    elif effect == "disparity_scale":
        close("disparity_scale", fitted["disparity_scale"], t["disparity_factor"], 0.08)
    elif effect == "misregistration":
        close("shift_dx", fitted["shift_px"][0], t["shift_px"][0], 0.12)
        close("shift_dy", fitted["shift_px"][1], t["shift_px"][1], 0.12)
    elif effect == "focus_offset":
        close("focus_factor", fitted["focus_factor"], t["focus_factor"], 0.025)
    elif effect == "field_varying_psf":
        close("edge_leak", fitted["edge_leak"], t["edge_leak"], 0.08)
        close("coc_growth_at_corner", fitted["coc_growth_at_corner"], t["coc_growth_at_corner"], 0.25)
    elif effect == "front_back_asymmetry":
        close("front_size_factor", fitted["front_size_factor"], t["front_size_factor"], 0.08)
        if not fitted["back_rim_gain"] > 0:
            bad.append("back rim gain should be > 0")
    elif effect == "psf_profile":
        if not fitted["rim_gain"] > 0.3 * t["rim_gain"]:
            bad.append(f"rim_gain {fitted['rim_gain']:.3f} vs planted {t['rim_gain']:.3f}")
    elif effect == "chromatic_defocus":
        r, _, b = t["focal_shift_mm_rgb"]
        close("focal_shift_r_mm", fitted["focal_shift_r_mm"], r, 0.015)
        close("focal_shift_b_mm", fitted["focal_shift_b_mm"], b, 0.015)
    elif effect == "noise":
        shot = t["shot_var_factor"] * studio.NOISE_SHOT
        if not 0.4 * shot <= fitted["shot_var"] <= 2.5 * shot:
            bad.append(f"shot_var {fitted['shot_var']:.2e} vs planted {shot:.2e}")
    return bad


@pytest.mark.slow
@pytest.mark.parametrize("case", range(len(CASES)))
def test_diagnose_names_the_hidden_effect(case: int, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    from dp5k_diagnose.run import diagnose_base

    effect, strength = _draw(case)
    if effect in KNOWN_GAPS:
        request.applymarker(pytest.mark.xfail(strict=True, reason=f"known gap: {KNOWN_GAPS[effect]}"))
    root = tmp_path / "ds"
    os.environ.setdefault("DP5K_PROGRESS", "0")
    studio.make_dataset(root, scenes=SCENES, effects={} if effect == NO_EFFECT else {effect: strength}, size=SIZE,
                        f_numbers=(1.8, 2.8), cameras=(0, 1), seed=case)
    truth = json.loads((root / "dataset.json").read_text())["effects"]
    diag = diagnose_base(root)
    report = diag.to_json()
    g = report["gain"]
    summary = f"planted {effect}@{strength:.2f}; got {[c['name'] for c in report['causes']]}; differ: " + ", ".join(
        e for e, s in report["signatures"].items() if s["differs"])
    assert set(report["signatures"]) == set(EFFECT_NAMES)
    if effect == NO_EFFECT:
        assert report["cause"] == NO_EFFECT and report["causes"] == [], summary
        assert g["psnr_after"] == g["psnr_before"] and g["psnr_gain_ci95"] == [0.0, 0.0]
        return
    if effect in SMALL_EFFECTS:
        assert report["cause"] in (effect, NO_EFFECT), summary
        assert g["psnr_gain_ci95"][0] >= -0.05, summary
        return
    assert report["cause"] == effect and report["causes"][0]["name"] == effect, summary
    assert [c["name"] for c in report["causes"]] == [effect], summary
    fitted = report["causes"][0]["params"]
    assert not _near(fitted, truth, effect), (summary, _near(fitted, truth, effect))
    if effect == "noise":
        # a prediction is an expectation: modelling noise cannot raise PSNR; it must not lower it either
        assert g["psnr_after"] == pytest.approx(g["psnr_before"], abs=1e-6)
    else:
        assert g["psnr_after"] > g["psnr_before"] and g["psnr_gain_ci95"][0] > 0, summary


@pytest.mark.slow
def test_a_clean_set_whose_fit_pairs_barely_constrain_the_rim_names_none(tmp_path: Path) -> None:
    """No false alarm from an unconverged base fit. On this clean set (8 scenes, seed 11) the fit crops hold
    little in-focus texture, so the base model's rim softness is barely constrained by them, while the
    detection crops' in-focus pixel-scale checkers are very sensitive to it; stopped after 3 iterations
    (rim 0.063 px instead of 0.024), every effect's fit, which refits the rim, was credited with the rest of
    its convergence and front_back_asymmetry was named at 0.89 of the systematic error. The base fit now runs to
    convergence before the atlas is measured against it."""
    from dp5k_diagnose.run import diagnose_base

    os.environ.setdefault("DP5K_PROGRESS", "0")
    root = tmp_path / "ds"
    studio.make_dataset(root, scenes=8, size=SIZE, f_numbers=(1.8, 2.8), cameras=(0, 1), seed=11)
    report = diagnose_base(root).to_json()
    differ = [e for e, s in report["signatures"].items() if s["differs"]]
    assert report["cause"] == NO_EFFECT and report["causes"] == [], (differ, report["suspects"])
    assert report["gain"]["psnr_gain_ci95"] == [0.0, 0.0]
