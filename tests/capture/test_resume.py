"""A resumed scene is still one scene: one focus per body (locked, checked, re-shot where it moved), whole ChArUco
pairs, nothing of a moved view mixed in. The simulated bodies outlive each client (as real ones do); every AF after
a body's first lands 0.3-1 % elsewhere and every placement of the board is a new pose, so these tests fail against a
client that refocuses on resume or re-shoots one side of a pair."""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_capture.ptp.codes import FOCUS_MODE_MF, EosProp, Op
from dp5k_capture.ptp.errors import DisconnectedError
from dp5k_capture.rawsession import plan_scene, verify_session
from dp5k_capture.sim.fault_spec import BodyFaultPlan
from dp5k_capture.sim.world import SimRig
from dp5k_cli import main
from dp5k_common.errors import DeviceError
from dp5k_common.rawfile import read_dual_pixel

from .conftest import SMALL_RIG, client_run, replug, small_sim_rig

FILES = 2 * len(plan_scene(SMALL_RIG))  # both bodies' files of one scene


def _manifest(out: Path) -> dict:
    return json.loads((out / "s1/manifest.json").read_text())


def _hashes(out: Path) -> dict[str, str]:
    return {f["path"]: f["sha256"] for f in _manifest(out)["files"]}


def _interrupted(sim: SimRig, out: Path, cam: str, download: int) -> dict[str, str]:
    """Run a client until ``cam`` vanishes halfway through its ``download``-th raw; plug it back in."""
    sim.usb_devices[cam].arm(BodyFaultPlan(disconnect_at_download=download))
    with pytest.raises(DisconnectedError):
        client_run(sim, out)
    replug(sim, cam)
    return _hashes(out)


def _focus_of(out: Path, cam: str, kinds: tuple[str, ...] = ("dp", "sharp")) -> list[float]:
    """The distinct focus distances the body recorded in its kept frames of these kinds."""
    m = _manifest(out)
    return sorted({read_dual_pixel(out / "s1" / f["path"]).metadata["focus_distance_m"] for f in m["files"]
                   if f["camera"] == cam and f["kind"] in kinds})


def test_a_resume_keeps_the_locked_focus_and_every_kept_frame(sim_rig: SimRig, tmp_path: Path) -> None:
    kept = _interrupted(sim_rig, tmp_path, "cam1", 6)  # cam1 vanishes in its dp_f2.8 (cam0 kept it: 6 + 5 files)
    assert len(kept) == 11
    n = client_run(sim_rig, tmp_path)
    assert n == FILES - 11
    after = _hashes(tmp_path)
    assert {p: after[p] for p in kept} == kept  # nothing set aside, nothing rewritten
    m = _manifest(tmp_path)
    assert [q["kind"] for q in m["quarantined"]] == ["leftover"]  # only the image cut off by the disconnect
    assert len(m["runs"]) == 2 and m["runs"][1]["resumed"] is True
    for cam in ("cam0", "cam1"):
        body = sim_rig.bodies[cam]
        assert body.op_log.count(Op.EOS_DO_AF) == 1  # one AF per body and scene: the resume did not refocus
        assert body.props[EosProp.FOCUS_MODE] == FOCUS_MODE_MF  # locked after the AF
        rec = m["focus"][cam]
        assert "set to 3 (MF) and confirmed" in rec["lock"]["locked_by"] and rec["lock"]["af_state"] == "in focus"
        check = rec["checks"][-1]
        assert check["verdict"] == "kept" and check["reference"] == f"{cam}/dp_f1.8.dng"
        assert abs(check["dp_disparity_change_px"]) < 0.05 and (tmp_path / "s1" / check["path"]).is_file()
        assert len(_focus_of(tmp_path, cam)) == 1  # all DP apertures and the sharp frame at one focus
    assert verify_session(tmp_path / "s1").problems == []


def test_a_resume_whose_af_moved_reshoots_that_bodys_focus_frames_and_says_so(
        sim_rig: SimRig, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    kept = _interrupted(sim_rig, tmp_path, "cam1", 6)
    focus0, focus1 = sim_rig.bodies["cam0"].focus_distance_m, sim_rig.bodies["cam1"].focus_distance_m
    sim_rig.bodies["cam1"]._autofocus()  # someone half-pressed cam1's shutter between the runs: its AF landed elsewhere
    assert sim_rig.bodies["cam1"].focus_distance_m != pytest.approx(focus1, rel=1e-3)
    with caplog.at_level(logging.WARNING, logger="dp5k_capture"):
        n = client_run(sim_rig, tmp_path)
    assert n == FILES - 11 + 2  # cam1's dp_f1.8 and dp_f2 again
    m = _manifest(tmp_path)
    # cam1: its kept focus-dependent frames went to quarantine, unchanged; the new ones share the body's new focus
    moved = {q["original_path"]: q for q in m["quarantined"] if q["kind"] != "leftover"}
    assert set(moved) == {"cam1/dp_f1.8.dng", "cam1/dp_f2.dng"}
    for rel, q in moved.items():
        assert q["path"] == f"quarantine/run2/{rel}" and "focus moved" in q["reason"]
        assert hashlib.sha256((tmp_path / "s1" / q["path"]).read_bytes()).hexdigest() == kept[rel]
    assert _focus_of(tmp_path, "cam1") == [pytest.approx(sim_rig.bodies["cam1"].focus_distance_m)]
    assert _focus_of(tmp_path, "cam0") == [pytest.approx(focus0)]
    after = _hashes(tmp_path)
    assert all(after[p] == h for p, h in kept.items() if p.startswith("cam0/"))  # cam0 untouched
    assert sim_rig.bodies["cam0"].op_log.count(Op.EOS_DO_AF) == 1 and sim_rig.bodies["cam1"].op_log.count(Op.EOS_DO_AF) == 2
    assert [c["verdict"] for c in (m["focus"]["cam0"]["checks"][-1], m["focus"]["cam1"]["checks"][-1])] == ["kept", "moved"]
    assert m["focus"]["cam1"]["checks"][-1]["dp_disparity_change_px"] != pytest.approx(0.0, abs=0.25)
    assert len(m["focus"]["cam1"]["af"]) == 2 and "refocus" in m["focus"]["cam1"]["af"][1]["why"]
    # and says so: in the log and in the run's record
    said = [r.getMessage() for r in caplog.records if "focus moved" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("cam1: focus moved since the kept frames (DP disparity")
    assert any(t.startswith("cam1: focus moved") for t in m["runs"][1]["notes"])
    assert verify_session(tmp_path / "s1").problems == []


def test_new_bodies_of_a_later_in_process_run_are_checked_and_reshot(tmp_path: Path) -> None:
    """In-process ``--sim`` makes new bodies each run: their lenses sit where an earlier AF left them, not where the
    kept frames were shot, so both bodies' focus frames are re-shot."""
    first = small_sim_rig()
    try:
        _interrupted(first, tmp_path, "cam1", 6)
    finally:
        first.close()
    later = small_sim_rig(run=1)
    try:
        assert client_run(later, tmp_path) == FILES - 11 + 3 + 2  # cam0's 3 and cam1's 2 DP frames again
    finally:
        later.close()
    m = _manifest(tmp_path)
    assert [m["focus"][c]["checks"][-1]["verdict"] for c in ("cam0", "cam1")] == ["moved", "moved"]
    assert all(len(_focus_of(tmp_path, c)) == 1 for c in ("cam0", "cam1"))
    assert verify_session(tmp_path / "s1").problems == []


def test_a_resume_inside_the_charuco_sequence_reshoots_both_sides(sim_rig: SimRig, tmp_path: Path) -> None:
    kept = _interrupted(sim_rig, tmp_path, "cam1", 2)  # cam1 vanishes in charuco_1: cam0's charuco_1 is kept alone
    assert set(kept) == {"cam0/charuco_0.dng", "cam1/charuco_0.dng", "cam0/charuco_1.dng"}
    assert _manifest(tmp_path)["board_in_view"] == 1
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(tmp_path), "--sim", "--dry-run"])
    assert res.exit_code == 0 and "  resume: charuco_1: only cam0 kept: both sides re-shot" in res.output, res.output
    assert "  resume: cam1: the image of charuco_1 cut off by the interruption is moved to quarantine/" in res.output
    client_run(sim_rig, tmp_path)
    m = _manifest(tmp_path)
    [q] = [q for q in m["quarantined"] if q["kind"] != "leftover"]
    assert q["original_path"] == "cam0/charuco_1.dng" and q["path"] == "quarantine/run2/cam0/charuco_1.dng"
    assert "ChArUco pair" in q["reason"] and any("charuco_1: only cam0" in t for t in m["runs"][1]["notes"])

    def board(rel: str) -> dict:
        return read_dual_pixel(tmp_path / "s1" / rel).metadata["board"]

    for view in range(3):  # every pose is one placement of the board, seen by both bodies
        b0, b1 = board(f"cam0/charuco_{view}.dng"), board(f"cam1/charuco_{view}.dng")
        assert b0 == b1 and b0["view"] == view
    assert board(q["path"])["placement"] != board("cam0/charuco_1.dng")["placement"]  # the board moved between runs
    assert _hashes(tmp_path)["cam0/charuco_0.dng"] == kept["cam0/charuco_0.dng"]
    assert verify_session(tmp_path / "s1").problems == []


def test_a_moved_view_stops_the_resume_and_sets_nothing_aside(sim_rig: SimRig, tmp_path: Path) -> None:
    kept = _interrupted(sim_rig, tmp_path, "cam1", 6)
    sim_rig.optics.albedo = np.roll(sim_rig.optics.albedo, 2, axis=1)  # the scene moved 2 px between the runs
    with pytest.raises(DeviceError, match=r"focus check: .*the view shifted by \(\+\d\.\d\d, [+-]\d\.\d\d\) raw px.*"
                                          r"capture it under a new --scene") as err:
        client_run(sim_rig, tmp_path)
    assert str(err.value).startswith("cam0 (")
    m = _manifest(tmp_path)
    assert [q["kind"] for q in m["quarantined"]] == ["leftover"] and _hashes(tmp_path) == kept
    assert m["focus"]["cam0"]["checks"][-1]["verdict"] == "view moved"


def test_without_a_settable_focus_mode_the_lock_is_releases_without_af(tmp_path: Path,
                                                                       caplog: pytest.LogCaptureFixture) -> None:
    sim = small_sim_rig()
    try:
        for body in sim.bodies.values():
            body.faults.focus_mode_fixed = True  # the lens switch decides FocusMode: the PC may not set it
        with caplog.at_level(logging.WARNING, logger="dp5k_capture"):
            kept = _interrupted(sim, tmp_path, "cam1", 6)
            client_run(sim, tmp_path)
        lock = _manifest(tmp_path)["focus"]["cam0"]["lock"]
        assert lock["focus_mode"] == 0 and lock["locked_by"].startswith("releases without AF only")
        assert any("set the lens switch to MF" in r.getMessage() for r in caplog.records)
        assert all(b.op_log.count(Op.EOS_DO_AF) == 1 for b in sim.bodies.values())
        assert {p: _hashes(tmp_path)[p] for p in kept} == kept
    finally:
        sim.close()
