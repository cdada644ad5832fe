"""``dp5k sl-depth`` never exits 0 with depth that is wrong or empty (issue 31, item 2), and refuses bad input in one
line before any work (item 3), on a small synthetic stereo Gray-code capture (``dp5k_testing.sl_rig``): the true
calibration, cam1 drifted by 1.5 deg of yaw and 0.5 of roll, a calibration of another rig, T in metres read as mm,
and a dark scene."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_process.sl_input import check_scene_depth
from dp5k_testing.sl_rig import SLCapture, write_sl_capture

PROJ = "320x200"
DRIFT_DEG = (0.0, 1.5, 0.5)
"""cam1 turned by 1.5 deg about its y axis (yaw) and 0.5 deg about its optical axis (roll) since calibration."""


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> SLCapture:
    return write_sl_capture(tmp_path_factory.mktemp("sl") / "img")


def _run(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["-q", "sl-depth", *args])
    return res.exit_code, res.output


def _depth_error(out: Path, cap: SLCapture) -> float:
    """Median signed relative error of camera 0's depth against the truth."""
    d = cv2.imread(str(out / "depth_m.tif"), cv2.IMREAD_UNCHANGED)
    ok = np.isfinite(d) & np.isfinite(cap.depth_m)
    return float(np.median((d[ok] - cap.depth_m[ok]) / cap.depth_m[ok]))


def test_true_calibration_fits_is_not_refined_and_says_so(capture: SLCapture, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import dp5k_common.progress as progress

    monkeypatch.setattr(progress, "_enabled", True)  # as for a user at a terminal (no -q)
    cal = capture.write_calibration(tmp_path / "true.yaml")
    res = CliRunner().invoke(main, ["sl-depth", str(capture.images), str(cal), str(tmp_path / "o"), "--projector", PROJ])
    code, out = res.exit_code, res.output
    assert code == 0, out
    assert "sl-depth: decode" in out and "72/74" in out  # the progress bar: 2 x 36 images, then check and depth
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    ref = rep["refinement"]
    assert not ref["triggered"] and not ref["failed"] and not rep["quality"]["low"]
    assert ref["epipolar_error_px_given"] < 0.3 and ref["epipolar_systematic_px_given"] < 0.05  # always reported
    assert "median epipolar error" in out
    assert abs(_depth_error(tmp_path / "o", capture)) < 0.005 and rep["depth_coverage"] > 0.7
    # the outputs people open: a colour preview of the depth and report.md pointing at it
    prev = cv2.imread(str(tmp_path / "o" / "depth_preview.png"))
    assert prev.shape[1] == 320 and prev.shape[0] > 240 and prev[..., :].std() > 10
    md = (tmp_path / "o" / "report.md").read_text()
    assert "![depth](depth_preview.png)" in md and "LOW QUALITY" not in md and "| given | 0." in md


def test_small_yaw_and_roll_drift_is_detected_and_refined(capture: SLCapture, tmp_path: Path) -> None:
    """Most matches still pass the 1.5 px ray gap (the old trigger stays silent) while depth is a quarter off; the
    epipolar error's systematic part triggers the refinement, the scene's depth structure pins the free fit, and
    depth comes back within 1 %."""
    cal = capture.write_calibration(tmp_path / "drift.yaml", turn_deg=DRIFT_DEG)
    code, out = _run(str(capture.images), str(cal), str(tmp_path / "raw"), "--projector", PROJ, "--no-refine")
    assert code == 9, out  # --no-refine still checks: the misfit is reported, not silent
    assert "not refined" in out and "LOW QUALITY" in out
    assert _depth_error(tmp_path / "raw", capture) < -0.15  # what the drift does to depth
    rep = json.loads((tmp_path / "raw" / "report.json").read_text())
    assert rep["refinement"]["gate_pass_rate_charuco"] > 0.5  # the gate-based trigger would not have fired
    code, out = _run(str(capture.images), str(cal), str(tmp_path / "o"), "--projector", PROJ)
    assert code == 0, out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    ref = rep["refinement"]
    assert ref["triggered"] and ref["applied"] and ref["mode"] == "five parameters"
    assert ref["epipolar_systematic_px_given"] > 0.2 > ref["epipolar_systematic_px"]
    assert ref["three_parameters"]["epipolar_error_px"] > ref["five_parameters"]["epipolar_error_px"]  # both reported
    assert ref["five_parameters"]["depth_sd_pct"] < 1.0 and ref["five_parameters"]["used"]
    assert abs(_depth_error(tmp_path / "o", capture)) < 0.01
    assert "WARNING: the stereo calibration did not fit the structured light" in out
    assert "| five parameters (free) **(used)** |" in (tmp_path / "o" / "report.md").read_text()


def test_calibration_of_another_rig_writes_depth_marked_low_quality_exit_9(capture: SLCapture, tmp_path: Path) -> None:
    """A calibration that no refinement can make fit: 0 % coverage used to exit 0; now the depth is written, marked
    low quality in report.json and report.md, and the command exits 9 (LowQualityResultError)."""
    cal = capture.write_calibration(tmp_path / "other.yaml", turn_deg=(-6, 9, 3), T_m=np.array([0.05, -0.3, 0.1]))
    code, out = _run(str(capture.images), str(cal), str(tmp_path / "o"), "--projector", PROJ)
    assert code == 9, out
    assert out.strip().splitlines()[-1].startswith("dp5k: error: ") and "LOW QUALITY" in out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["quality"]["low"] and rep["refinement"]["failed"] and rep["depth_coverage"] < 0.05
    assert any("does not fit the images" in r for r in rep["quality"]["reasons"])
    assert (tmp_path / "o" / "depth_mm.png").is_file() and (tmp_path / "o" / "depth_m.tif").is_file()
    assert (tmp_path / "o" / "report.md").read_text().startswith("# Structured-light depth (dp5k sl-depth)\n\n**LOW QUALITY")


def test_dark_scene_warns_and_exits_9(tmp_path: Path) -> None:
    cap = write_sl_capture(tmp_path / "img", gain=0.3, ambient=0.01, albedo_sigma=0.4)
    cal = cap.write_calibration(tmp_path / "true.yaml")
    code, out = _run(str(cap.images), str(cal), str(tmp_path / "o"), "--projector", PROJ)
    assert code == 9, out
    assert "WARNING: DARK: the projector lights only" in out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert 0 < rep["depth_coverage"] < 0.1 and rep["lit_fraction"]["cam0"] < 0.25
    assert any("--min-coverage" in r for r in rep["quality"]["reasons"])
    code, out = _run(str(cap.images), str(cal), str(tmp_path / "o"), "--projector", PROJ, "--overwrite",
                     "--min-coverage", "0.01")
    assert code == 0, out  # the bound is the user's to set


def test_t_in_metres_read_as_mm_is_refused_with_its_cause(capture: SLCapture, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """T in metres with --units mm gave depth of 1 mm and exit 0; the baseline is checked before any decoding."""
    _no_decoding(monkeypatch)
    cal = capture.write_calibration(tmp_path / "metres.yaml", units="m")
    code, out = _run(str(capture.images), str(cal), str(tmp_path / "o"), "--projector", PROJ)
    assert code == 3 and "use --units m" in out and len(out.strip().splitlines()) == 1, out
    cal = capture.write_calibration(tmp_path / "mm.yaml", units="mm")
    code, out = _run(str(capture.images), str(cal), str(tmp_path / "o"), "--projector", PROJ, "--units", "m")
    assert code == 3 and "use --units mm" in out, out
    assert not (tmp_path / "o").exists()


def test_scene_depth_against_the_baseline() -> None:
    """The check sl-depth runs on the triangulated matches (its numbers are unit-free against the baseline)."""
    check_scene_depth(1.5, 0.12, "mm", Path("c.yaml"))
    with pytest.raises(Exception, match="use --units m"):
        check_scene_depth(0.0015, 0.004, "mm", Path("c.yaml"))
    with pytest.raises(Exception, match="does not belong to these images"):
        check_scene_depth(300.0, 0.1, "mm", Path("c.yaml"))
    with pytest.raises(Exception, match="behind camera 0"):
        check_scene_depth(-1.2, 0.1, "mm", Path("c.yaml"))


def _no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any decoding fails loudly (a traceback, exit 1): the checks under test must come before it."""
    import dp5k_process.sl_input as sl_input

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("decoding started before the input was checked")

    monkeypatch.setattr(sl_input, "decode_graycode", boom)


GARBAGE = {
    "random.yaml": bytes(range(256)) * 3,
    "text.yaml": b"K0: [1, 2\n  ::: not yaml {{{\n",
    "missing.yaml": b"%YAML:1.0\nK0: [500, 0, 160, 0, 500, 120, 0, 0, 1]\n",
    "words.yaml": b"%YAML:1.0\nK0: \"a camera\"\ndist0: [0, 0, 0, 0, 0]\n",
}


def test_bad_out_and_garbage_calibration_one_line_exit_3_before_work(capture: SLCapture, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    _no_decoding(monkeypatch)
    cal = capture.write_calibration(tmp_path / "true.yaml")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, why in ((a_file, "is a file"), (a_file / "out", "is a file"), (Path("/proc/dp5k-sl"), "cannot write into /proc")):
        code, text = _run(str(capture.images), str(cal), str(out), "--projector", PROJ)
        assert code == 3 and why in text and len(text.strip().splitlines()) == 1, (out, text)
    for name, data in GARBAGE.items():
        (tmp_path / name).write_bytes(data)
        code, text = _run(str(capture.images), str(tmp_path / name), str(tmp_path / "o"), "--projector", PROJ)
        assert code == 3 and len(text.strip().splitlines()) == 1 and "Traceback" not in text, (name, text)
        assert text.startswith(f"dp5k: error: {tmp_path / name}: "), text
    assert not (tmp_path / "o").exists()
