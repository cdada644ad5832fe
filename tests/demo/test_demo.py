"""``dp5k demo --scale small`` end to end: the report exists, and its numbers equal their sources.

The demo runs once per test session (module fixture, shared by pytest-xdist's workers); every check reads its
outputs.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from filelock import FileLock

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_demo.build_report import truth_depth_at
from dp5k_demo.pipeline import hidden_effect

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo's output directory. Under pytest-xdist every worker that runs a test of this module needs it:
    the first to take the lock runs the demo in the session's shared temporary directory, the others wait
    for it and reuse it (a failed run leaves no report.json, so the next worker runs it again)."""
    base = tmp_path_factory.getbasetemp()
    out = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "demo-small-seed0"
    with FileLock(str(out) + ".lock"):
        if not (out / "report.json").is_file():
            result = CliRunner().invoke(main, ["-q", "demo", str(out), "--scale", "small", "--seed", "0"])
            assert result.exit_code == 0, result.output
    return out


def table(report: dict, section_prefix: str, key: str) -> dict:
    section = next(v for k, v in report.items() if k.startswith(section_prefix))
    return section[key]


def test_report_written_with_figures(demo_out: Path) -> None:
    html = (demo_out / "report.html").read_text()
    imgs = [part.split('"')[0] for part in html.split('<img src="')[1:]]
    assert len(imgs) >= 8
    for rel in imgs:
        png = demo_out / rel
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", rel


def test_simulator_table_equals_evaluate_metrics(demo_out: Path) -> None:
    report = json.loads((demo_out / "report.json").read_text())
    metrics = json.loads((demo_out / "evaluate-studio" / "metrics.json").read_text())
    t = table(report, "4.", "evaluate_studio")
    sims = t["header"][1:]
    assert set(sims) == set(metrics["simulators"])
    for row in t["rows"]:
        for name, value in zip(sims, row[1:]):
            assert value == pytest.approx(metrics["means"][name][row[0]])


def test_depth_accuracy_recomputed_independently(demo_out: Path) -> None:
    report = json.loads((demo_out / "report.json").read_text())
    rows = table(report, "2.", "depth_accuracy")["rows"]
    reader = DatasetReader(demo_out / "processed")
    by_key = {(reader.params(p).scene, reader.params(p).camera): p for p in reader.ids()}
    for scene, camera, med_pct, coverage_pct, focus_mm, true_mm, focus_err in rows:
        pair = reader.load(by_key[(scene, camera)])
        truth = truth_depth_at(demo_out / "raw" / scene, camera, pair.params.image_size)
        both = pair.valid & (truth > 0)
        rel = np.abs(pair.depth_mm[both] - truth[both]) / truth[both]
        assert med_pct == pytest.approx(100 * np.median(rel), rel=1e-6)
        lit = truth_depth_at(demo_out / "raw" / scene, camera, pair.params.image_size, lit_only=True) > 0
        assert coverage_pct == pytest.approx(100 * (lit & pair.valid).sum() / lit.sum(), rel=1e-6)
        assert med_pct <= 0.5  # the processing accuracy target holds on the demo's own scene
        assert focus_mm == pytest.approx(pair.params.focus_distance_mm)
        truth_json = json.loads((demo_out / "raw" / scene / "ground_truth" / "truth.json").read_text())
        assert true_mm == pytest.approx(1000 * truth_json["cameras"][camera]["focus_distance_true_m"])
        assert focus_err == pytest.approx(abs(focus_mm - true_mm) / true_mm * 100)


def test_diagnosis_numbers_equal_diagnose_reports(demo_out: Path) -> None:
    report = json.loads((demo_out / "report.json").read_text())
    section = next(v for k, v in report.items() if k.startswith("5."))
    assert section["hidden_effect"] == hidden_effect(0)
    for name in ("base", "neural"):
        drep = json.loads((demo_out / f"diagnose-{name}" / "report.json").read_text())
        assert section[f"diagnose_{name}_cause"] == drep["cause"]
        assert section[f"diagnose_{name}_gain"] == drep["gain"]
        assert [r[0] for r in section[f"diagnose_{name}"]["rows"]] == list(drep["signatures"])


def test_second_run_reuses_every_stage(demo_out: Path) -> None:
    result = CliRunner().invoke(main, ["demo", str(demo_out), "--scale", "small", "--seed", "0"])
    assert result.exit_code == 0, result.output
    records = [json.loads(p.read_text()) for p in (demo_out / ".stages").glob("*.json")]
    assert len(records) == 11
    report = json.loads((demo_out / "report.json").read_text())
    timings = table(report, "7.", "timings")["rows"]
    assert all(reused for _, _, reused in timings)


def test_failed_stage_names_stage_and_fix(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    (out / "raw" / "demo01").mkdir(parents=True)
    (out / "raw" / "demo01" / "manifest.json").write_text("{broken")
    result = CliRunner().invoke(main, ["demo", str(out), "--scale", "small"])
    assert result.exit_code == 7
    line = result.output.strip().splitlines()[-1]
    assert line.startswith("dp5k: error: demo stage 'capture':") and "fix:" in line
