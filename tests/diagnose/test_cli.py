"""``dp5k diagnose`` end to end from the command line, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.effects import EFFECT_NAMES

from .plant import make_planted_dataset


def test_bad_inputs_give_one_line_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(main, ["diagnose", str(tmp_path / "nothing")])
    assert res.exit_code == 3 and "dataset folder not found" in res.output  # missing input: 3, like every command
    res = runner.invoke(main, ["diagnose", str(tmp_path), "--simulator", "nonsense"])
    assert res.exit_code == 3 and "unknown simulator 'nonsense'" in res.output
    res = runner.invoke(main, ["diagnose", str(tmp_path), "--model", "nonsense"])  # the older flag still parses the spec
    assert res.exit_code == 3 and "--model SPEC is deprecated; use --simulator SPEC" in res.output
    assert "unknown simulator 'nonsense'" in res.output
    res = runner.invoke(main, ["diagnose", str(tmp_path), "--model", "base", "--simulator", "base"])
    assert res.exit_code == 3 and "not both" in res.output
    for bad in ("2e-5", "a,b", "-1,0.001"):
        res = runner.invoke(main, ["diagnose", str(tmp_path), "--nominal-noise", bad])
        assert res.exit_code == 3 and "--nominal-noise" in res.output, (bad, res.output)
    for bad in ("f/22", "-1", "inf", "nan"):
        res = runner.invoke(main, ["diagnose", str(tmp_path), "--sharp-f-number", bad])
        assert res.exit_code == 3 and "--sharp-f-number" in res.output, (bad, res.output)
    for bad in ("0", "some", "-2"):
        res = runner.invoke(main, ["diagnose", str(tmp_path), "--fit-pairs", bad])
        assert res.exit_code == 3 and "--fit-pairs" in res.output, (bad, res.output)


@pytest.mark.slow
def test_cli_diagnose_writes_report_json_and_md(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    make_planted_dataset(root, "lr_gain_imbalance", {"a0": 0.2, "ax": 0.1}, scenes=8, size=(96, 64), seed=3)
    out = tmp_path / "rep"
    res = CliRunner().invoke(main, ["-q", "diagnose", str(root), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rep = json.loads((out / "report.json").read_text())
    assert rep["model"] == "base" and rep["cause"] == "lr_gain_imbalance"
    assert set(rep["signatures"]) == set(EFFECT_NAMES)  # every effect measured, or said why not
    for e, s in rep["signatures"].items():
        assert s["unmeasured"] or all(set(v) >= {"name", "unit", "value", "interval95", "p_value", "min_effect"} for v in s["values"]), e
    assert rep["signatures"]["lr_gain_imbalance"]["differs"]
    g = rep["gain"]
    assert set(g) >= {"split", "psnr_before", "psnr_after", "ssim_before", "ssim_after", "mae_before", "mae_after", "psnr_gain_ci95"}
    assert g["split"] == "test" and g["psnr_gain_ci95"][0] > 0
    # the headline gain counts predictable pixels; the same metrics over all valid pixels ride along
    assert g["mask"] == "predictable" and g["all_valid"]["mask"] == "valid"
    assert set(g["all_valid"]) >= {"psnr_before", "psnr_after", "ssim_before", "mae_after", "psnr_gain_ci95"}
    assert g["all_valid"]["psnr_after"] > g["all_valid"]["psnr_before"]
    assert rep["causes"][0]["name"] == "lr_gain_imbalance" and rep["causes"][0]["gain_ci_db"][0] > 0
    lo, hi = rep["causes"][0]["param_intervals"]["a0"]
    assert lo <= rep["causes"][0]["params"]["a0"] <= hi and lo < 0.2 < hi  # planted a0 = 0.2
    nm = rep["noise_model"]
    assert nm["measured"] and nm["intervals"]["read_sigma"][0] <= nm["read_sigma"] <= nm["intervals"]["read_sigma"][1]
    assert rep["fit_coverage"]["pairs"] == 8 and rep["fit_coverage"]["field_zones"] >= 1  # --fit-pairs auto: 10 train pairs
    assert rep["fit_coverage"]["atlas_pairs"] == 16 and rep["atlas"]["pairs"] == 16  # the atlas reads every pair
    import numpy as np
    z = np.load(out / "atlas.npz")
    assert list(z["view_sets"]) == ["measured", "simulator", "extended"] and len(z["pair_ids"]) == 16
    md = (out / "report.md").read_text()
    assert "**Causes, in order: `lr_gain_imbalance`**" in md and "## Causes, in order" in md and "## The PSF atlas" in md
    for fig in rep["figures"].values():
        assert (out / fig).is_file() and (out / fig).stat().st_size > 1000
    # which libraries computed these numbers: they change what is named across releases (docs/diagnose.md)
    import numpy, torch
    assert rep["software"]["numpy"] == numpy.__version__ and rep["software"]["torch"] == torch.__version__
    assert "diagnose" in rep["provenance"]["command"] and rep["provenance"]["dp5k"]  # what wrote it
    assert f"numpy {numpy.__version__}" in md


def test_the_default_report_folder_is_named_for_the_simulator(tmp_path: Path) -> None:
    from neural_dp.registry import SimulatorSpec

    spec = SimulatorSpec.parse(f"neural:{tmp_path / 'a.pt'}")
    assert "/" not in spec.folder_name() and ":" not in spec.folder_name() and spec.folder_name().startswith("neural_")
    res = CliRunner().invoke(main, ["diagnose", str(tmp_path), "--simulator", str(spec), "--fit-pairs", "6"])
    assert res.exit_code == 3 and "Neural DP checkpoint not found" in res.output and "a.pt" in res.output


def _summary_input(lookalikes: list[dict], suspects: list[dict]) -> dict:
    """The parts of report.json that :func:`print_summary` reads, as a diagnosis with two causes writes them."""
    cause = {"step": 1, "name": "psf_profile", "explanation": "the blur disc is not uniform", "gain_db": 0.5, "gain_ci_db": [0.2, 0.8],
             "step_gain_db": 0.5, "cumulative_gain_db": 0.5}
    return {"cause": "psf_profile", "causes": [cause, {**cause, "step": 2, "name": "focus_offset"}], "lookalikes": lookalikes,
            "suspects": suspects, "atlas": {"cells": 40, "unmeasured": [{"bin": 9, "zone": 0}]},
            "fit_coverage": {"atlas_pairs": 24, "pairs": 4, "scenes": 2, "field_zones": 8, "field_zones_of": 9},
            "gain": {"split": "test", "psnr_before": 30.0, "psnr_after": 30.5, "psnr_gain_ci95": [0.2, 0.8]}}


def test_summary_prints_causes_lookalikes_suspects_and_the_gain_last(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every cause in order with its sentence, what another cause explains, the suspects, the atlas's unmeasured cells,
    then the gain and where the report is (a look-alike printed before the gain once reused the gain's variable)."""
    from dp5k_diagnose.cli import print_summary

    groups = [{"names": ["field_varying_psf", "lr_gain_imbalance"], "captures": ["a flat field"], "kinds": ["explains"]}]
    suspects = [{"name": "disparity_scale", "gain_db": 0.01, "gain_ci_db": [-0.01, 0.03]}]
    print_summary(_summary_input(groups, suspects), tmp_path)
    out = capsys.readouterr().out
    assert "cause: psf_profile" in out and "1. psf_profile: the blur disc is not uniform" in out and "2. focus_offset" in out
    assert "explained: lr_gain_imbalance by field_varying_psf (to tell them apart, capture a flat field)" in out
    assert "suspect, not named: disparity_scale" in out and "1 of 40 cells not measured" in out
    assert out.index("suspect") < out.index("gain on test (predictable pixels): PSNR 30.000 -> 30.500 dB")
    assert out.rstrip().endswith(f"report: {tmp_path / 'report.md'}")
