"""``dp5k synthesize --simulator diagnosed:REPORT.json`` renders the model a diagnose report extended."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_demo.rgbd import write_rgbd_frames
from dp5k_testing.tiny_dataset import make_tiny_dataset
from neural_dp.registry import get_simulator
from tests.diagnose.plant import make_planted_dataset

SYNTH = ["--f-number", "2.8", "--focus-mm", "1500", "--no-sensor-adjust", "--encoding", "linear", "--seed", "1"]


def lr_ratio(root: Path) -> float:
    """Mean left / right intensity over every pair of a dataset."""
    r = DatasetReader(root)
    pairs = [r.load(pid) for pid in r.ids()]
    return float(np.mean([p.left.mean() / p.right.mean() for p in pairs]))


@pytest.mark.slow
def test_diagnosed_simulator_renders_the_fitted_effect(tmp_path: Path) -> None:
    data = tmp_path / "ds"
    make_planted_dataset(data, "lr_gain_imbalance", {"a0": 0.2, "ax": 0.1}, scenes=8, size=(96, 64), seed=3)
    runner = CliRunner()
    res = runner.invoke(main, ["-q", "diagnose", str(data), "--out", str(tmp_path / "rep")])
    assert res.exit_code == 0, res.output
    report = tmp_path / "rep" / "report.json"
    assert json.loads(report.read_text())["cause"] == "lr_gain_imbalance"
    frames = tmp_path / "rgbd"
    write_rgbd_frames(data, frames, count=3)
    for sim in ("base", f"diagnosed:{report}"):
        out = tmp_path / sim.split(":")[0]
        res = runner.invoke(main, ["-q", "synthesize", str(frames), str(out), "--simulator", sim, *SYNTH])
        assert res.exit_code == 0, res.output
    # planted: ln(L/R) = 0.2 + 0.1 x; the diagnosed simulator's views carry it, the plain base model's do not
    assert abs(lr_ratio(tmp_path / "base") - 1.0) < 0.02
    assert abs(lr_ratio(tmp_path / "diagnosed") - np.exp(0.2)) < 0.06
    model = get_simulator(f"diagnosed:{report}")
    assert [c.name for c in model.components] == ["lr_gain_imbalance"]


def test_a_report_without_the_spec_is_a_one_line_error(tmp_path: Path) -> None:
    make_tiny_dataset(tmp_path / "tiny", scenes=1)
    frames = tmp_path / "rgbd"
    write_rgbd_frames(tmp_path / "tiny", frames, count=1)
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"cause": "none"}))
    res = CliRunner().invoke(main, ["synthesize", str(frames), str(tmp_path / "out"), "--simulator", f"diagnosed:{report}"])
    assert res.exit_code != 0 and res.output.count("\n") == 1
    assert "no 'extended_model_spec' in this report" in res.output and str(report) in res.output
    res = CliRunner().invoke(main, ["synthesize", str(frames), str(tmp_path / "out"), "--simulator", "diagnosed"])
    assert res.exit_code != 0 and "diagnosed:REPORT.json" in res.output
    assert not (tmp_path / "out").exists()
