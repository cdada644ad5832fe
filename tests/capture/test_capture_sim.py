"""Whole-scene capture on the simulated rig through the real PTP/USB, EOS, ESC/VP21 and window code."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_capture.capture import RigDevices, run_scene
from dp5k_capture.devices import find_bodies, open_bodies
from dp5k_capture.escvp21 import EpsonProjector, EscVp21Timing, ProjectorError
from dp5k_capture.ptp.errors import DisconnectedError
from dp5k_capture.rawsession import CaptureStorageError, RawSessionWriter, verify_session
from dp5k_capture.rig import RigConfig
from dp5k_capture.sim.world import SimRig, make_sim_rig, write_ground_truth_once
from dp5k_cli import main
from dp5k_common.errors import DeviceError
from dp5k_common.rawfile import read_dual_pixel

from .conftest import FAST, FAST_SESSION


def _run(out: Path, scene: str = "s1", before: Callable[[SimRig], None] | None = None,
         rig: RigConfig | None = None) -> tuple[int, SimRig]:
    sim = make_sim_rig(rig or RigConfig(), raw_size_px=(48, 32), warmup_s=0.05)
    try:
        writer = RawSessionWriter(out, scene, sim.rig, "dng", extra={"simulated": True})
        proj = EpsonProjector(sim.rig.projector.port, timing=EscVp21Timing(poll_s=0.01, default_s=0.5))
        if before:
            before(sim)
        bodies = open_bodies(sim.rig, backend=sim.backend, config=FAST_SESSION, timing=FAST)
        devices = RigDevices(bodies, proj, sim.window, sim.optics)
        try:
            return run_scene(sim.rig, devices, writer, before_complete=lambda d: write_ground_truth_once(sim.optics, d)), sim
        finally:
            devices.close()
    finally:
        sim.close()


def test_devices_are_found_by_vendor_and_serial() -> None:
    sim = make_sim_rig(RigConfig(), raw_size_px=(48, 32))
    try:
        found = find_bodies(sim.backend)
        assert [(f.vid, f.pid, f.serial) for f in found] == [(0x04A9, 0x3281, "SIM5D4000001"), (0x04A9, 0x3281, "SIM5D4000002")]
        rig = sim.rig
        bad = RigConfig(bodies=(rig.bodies[0], type(rig.bodies[1])("cam1", serial="NOPE")))
        with pytest.raises(DeviceError, match="cam1: body with serial NOPE not found on USB"):
            open_bodies(bad, backend=sim.backend, config=FAST_SESSION, timing=FAST)
    finally:
        sim.close()


def test_full_scene_then_resume_after_a_disconnect(tmp_path: Path) -> None:
    def unplug_cam1_mid_transfer(sim: SimRig) -> None:
        expose = sim.optics.expose

        def hooked(settings):  # noqa: ANN001, ANN202
            data = expose(settings)
            if len(sim.optics.exposures) == 22 and settings.serial == "SIM5D4000002":
                dev = sim.usb_devices["cam1"]
                dev.faults.disconnect_after_in_bytes = dev.in_bytes + len(data) // 2
            return data

        sim.optics.expose = hooked

    with pytest.raises(DisconnectedError) as err:
        _run(tmp_path, before=unplug_cam1_mid_transfer)
    msg = str(err.value)
    assert msg.startswith("cam1 (") and "sl_" in msg and "disconnected" in msg  # names device and step
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    done = {f["path"]: f["sha256"] for f in m["files"]}
    assert len(done) == 21 and m["complete"] is False
    assert all((tmp_path / "s1" / p).is_file() for p in done)
    assert not [p for p in (tmp_path / "s1").rglob(".*")]  # no half-written file

    n, sim = _run(tmp_path)  # the next run resumes
    assert n == 110 - 21
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    assert m["complete"] is True and len(m["files"]) == 110
    assert all(f["sha256"] == done[f["path"]] for f in m["files"] if f["path"] in done)  # kept, not rewritten
    rep = verify_session(tmp_path / "s1")
    assert rep.problems == [] and rep.counts == {"charuco": 6, "dp": 10, "sharp": 2, "sl": 92}
    by = {f["path"]: f for f in m["files"]}
    assert by["cam0/dp_f2.8.dng"]["f_number"] == 2.8 and by["cam1/sl_45.dng"]["pattern"] == 45
    assert m["focus_point_px"] == {"cam0": [24, 16], "cam1": [24, 16]}
    # the projector lit the scene with the displayed pattern, and was blanked for the DP frames
    mean = {k: read_dual_pixel(tmp_path / f"s1/cam0/{k}.dng").main.mean() for k in ("sl_44", "sl_45", "sharp_f22")}
    assert mean["sl_44"] > 1.5 * mean["sl_45"] and mean["sharp_f22"] == pytest.approx(mean["sl_45"], rel=0.02)
    # the ChArUco frames show the board, the others do not
    ch = read_dual_pixel(tmp_path / "s1/cam0/charuco_1.dng").main.astype(float)
    dp = read_dual_pixel(tmp_path / "s1/cam0/dp_f1.8.dng").main.astype(float)
    assert not np.allclose(ch / ch.mean(), dp / dp.mean(), atol=0.05)
    with pytest.raises(Exception, match="already captured and complete"):
        _run(tmp_path)


def test_scene_with_non_dual_pixel_raws_is_refused(tmp_path: Path) -> None:
    def dpraw_off(sim: SimRig) -> None:
        sim.bodies["cam1"].faults.dual_pixel_raw = False

    with pytest.raises(DeviceError, match="did not write a Dual Pixel RAW") as err:
        _run(tmp_path, before=dpraw_off)
    assert str(err.value).startswith("cam1 (") and "charuco_0" in str(err.value)
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    assert [f["path"] for f in m["files"]] == ["cam0/charuco_0.dng"]
    assert not (tmp_path / "s1/cam1/charuco_0.dng").exists()


def test_projector_err_stops_before_any_exposure(tmp_path: Path) -> None:
    def refuse(sim: SimRig) -> None:
        sim.projector.faults.err_next = 99

    with pytest.raises(ProjectorError, match="projector start-up: .*refused") as err:
        _run(tmp_path, before=refuse)
    assert "projector (/dev/pts/" in str(err.value)
    assert json.loads((tmp_path / "s1/manifest.json").read_text())["files"] == [] if (tmp_path / "s1/manifest.json").exists() else True


def test_disk_full_mid_scene_then_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import dp5k_capture.rawsession as rs

    real = rs.os.fsync
    calls = {"n": 0}

    def fsync(fd: int) -> None:  # the disk fills up while the 8th raw file is written
        if rs.os.readlink(f"/proc/self/fd/{fd}").endswith(".dng"):
            calls["n"] += 1
        if calls["n"] > 7:
            raise OSError(28, "No space left on device")
        real(fd)

    monkeypatch.setattr(rs.os, "fsync", fsync)
    with pytest.raises(CaptureStorageError, match="disk full"):
        _run(tmp_path)
    monkeypatch.setattr(rs.os, "fsync", real)
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    assert len(m["files"]) == 7
    n, _ = _run(tmp_path)
    assert n == 103


def test_cli_dry_run_touches_nothing(tmp_path: Path) -> None:
    out = tmp_path / "raw"
    res = CliRunner().invoke(main, ["-q", "capture", "--scene", "demo01", "--out", str(out), "--sim", "--dry-run"])
    assert res.exit_code == 0, res.output
    assert "220 raw files" not in res.output and "110 raw files" in res.output
    assert "sl_45" in res.output and "dp_f1.8" in res.output and "f/22" in res.output
    assert not out.exists()


@pytest.mark.slow
def test_dp5k_capture_sim_demo01_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "raw"
    runner = CliRunner()
    res = runner.invoke(main, ["-q", "capture", "--scene", "demo01", "--out", str(out), "--sim"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["verify", str(out / "demo01")])
    assert res.exit_code == 0, res.output
    assert "OK: 110 files" in res.output and "charuco 6, dp 10, sharp 2, sl 92" in res.output
    gt = out / "demo01/ground_truth"
    truth = json.loads((gt / "truth.json").read_text())
    cam0 = truth["cameras"]["cam0"]
    assert cam0["focus_distance_recorded_m"] > 0.5 and len(truth["board_poses"]) == 3
    cam1 = truth["cameras"]["cam1"]  # both bodies focus on the same surface (the scene's focus target)
    assert cam1["focus_distance_recorded_m"] == pytest.approx(cam0["focus_distance_recorded_m"], rel=0.05)
    assert (gt / "cam0_depth_mm.png").is_file() and (gt / "cam1_proj_xy.npy").is_file()
    m = json.loads((out / "demo01/manifest.json").read_text())
    assert m["focus_point_px"]["cam0"] == cam0["focus_point_px"]
    # the manifest carries each body's intrinsics prior, which processing holds fixed while re-estimating R, T
    assert all(np.shape(b["K"]) == (3, 3) and len(b["dist"]) == 5 for b in m["rig"]["bodies"])
    # the recalibration views are usable: the board is found in all 3 views of both bodies
    from calib.detect import detect_charuco
    from dp5k_process.pipeline import raw_gray

    for cam in ("cam0", "cam1"):
        for k in range(3):
            det = detect_charuco(raw_gray(read_dual_pixel(out / f"demo01/{cam}/charuco_{k}.dng")))
            assert det is not None and len(det.ids) >= 30, (cam, k, None if det is None else len(det.ids))
    f = read_dual_pixel(out / "demo01/cam0/dp_f1.8.dng")
    assert f.metadata["f_number"] == 1.8 and f.metadata["focus_distance_m"] == pytest.approx(cam0["focus_distance_recorded_m"])
    # never overwritten: a second capture of the complete scene is refused with exit code 3
    res = runner.invoke(main, ["capture", "--scene", "demo01", "--out", str(out), "--sim"])
    assert res.exit_code == 3 and "never overwritten" in res.output
    # tampering is caught by verify (exit code 4)
    (out / "demo01/cam1/sl_10.dng").write_bytes(b"x")
    res = runner.invoke(main, ["verify", "--no-dp-check", str(out / "demo01")])
    assert res.exit_code == 4 and "cam1/sl_10.dng: size" in res.output


def test_cli_devices_lists_the_simulated_rig() -> None:
    res = CliRunner().invoke(main, ["devices", "--sim"])
    assert res.exit_code == 0, res.output
    assert "Canon bodies (2):" in res.output and "04a9:3281" in res.output and "serial SIM5D4000001" in res.output
    assert "simulated EPSON EB-U42" in res.output and "/dev/pts/" in res.output


def test_cli_verify_rejects_a_folder_without_manifest(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["verify", str(tmp_path)])
    assert res.exit_code == 3 and "no manifest.json" in res.output


def test_cli_real_rig_errors_are_one_line_and_write_nothing(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text('[projector]\nport = "/nonexistent/ttyUSB7"\n')
    out = tmp_path / "raw"
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--rig", str(rig)])
    assert res.exit_code == 5, res.output
    assert "dp5k: error: projector (/nonexistent/ttyUSB7): cannot open serial port" in res.output
    assert not (out / "s1" / "manifest.json").exists()
    rig.write_text("[exposure]\nsharp_f_number = 0.5\n")
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--rig", str(rig), "--dry-run"])
    assert res.exit_code == 3 and "f/0.5" in res.output


def test_projector_falls_silent_mid_scene_then_resume(tmp_path: Path) -> None:
    def silence_after_dp(sim: SimRig) -> None:
        expose = sim.optics.expose

        def hooked(settings):  # noqa: ANN001, ANN202
            if len(sim.optics.exposures) == 17:  # the last DP/sharp frame: next step unblanks the projector
                sim.projector.faults.silent = True
            return expose(settings)

        sim.optics.expose = hooked

    from dp5k_common.errors import DeviceTimeoutError

    with pytest.raises(DeviceTimeoutError, match=r"projector \(/dev/pts/\d+\): unblank projector: 'MUTE OFF': no ':' prompt"):
        _run(tmp_path, before=silence_after_dp)
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    assert len(m["files"]) == 18 and all(f["kind"] != "sl" for f in m["files"])
    n, _ = _run(tmp_path)
    assert n == 110 - 18


def test_ctrl_c_before_the_ground_truth_leaves_the_session_incomplete(tmp_path: Path) -> None:
    """Ctrl-C between the last shot and ground_truth/: not complete, verify flags it, the re-run finishes it."""
    sim = make_sim_rig(RigConfig(), raw_size_px=(48, 32), warmup_s=0.05)
    try:
        writer = RawSessionWriter(tmp_path, "s1", sim.rig, "dng", extra={"simulated": True})
        proj = EpsonProjector(sim.rig.projector.port, timing=EscVp21Timing(poll_s=0.01, default_s=0.5))
        devices = RigDevices(open_bodies(sim.rig, backend=sim.backend, config=FAST_SESSION, timing=FAST), proj, sim.window, sim.optics)

        def ctrl_c(session_dir: Path) -> None:
            raise KeyboardInterrupt

        try:
            with pytest.raises(KeyboardInterrupt):
                run_scene(sim.rig, devices, writer, before_complete=ctrl_c)
        finally:
            devices.close()
    finally:
        sim.close()
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    assert len(m["files"]) == 110 and m["complete"] is False and not (tmp_path / "s1/ground_truth").exists()
    res = CliRunner().invoke(main, ["verify", "--no-dp-check", str(tmp_path / "s1")])
    assert res.exit_code == 4 and "ground_truth/truth.json: missing" in res.output
    n, _ = _run(tmp_path)  # the re-run takes no shot, writes the ground truth, then marks the session complete
    assert n == 0 and json.loads((tmp_path / "s1/manifest.json").read_text())["complete"] is True
    assert (tmp_path / "s1/ground_truth/cam1_depth_mm.png").is_file()
    from dp5k_common.io import new_file_mode

    mode = new_file_mode()  # the folder and its files follow the umask (mkdtemp / mkstemp would leave 0700 / 0600)
    assert (tmp_path / "s1/ground_truth").stat().st_mode & 0o777 == mode | (mode & 0o444) >> 2
    assert (tmp_path / "s1/ground_truth/truth.json").stat().st_mode & 0o777 == mode
    assert not list((tmp_path / "s1").glob(".ground_truth*"))
    res = CliRunner().invoke(main, ["verify", "--no-dp-check", str(tmp_path / "s1")])
    assert res.exit_code == 0 and "OK: 110 files" in res.output


def test_failed_autofocus_stops_the_scene_before_any_shot(tmp_path: Path) -> None:
    def af_fails(sim: SimRig) -> None:
        sim.bodies["cam1"].faults.af_result = "fail"

    with pytest.raises(DeviceError, match=r"^cam1 \(.*\): autofocus: autofocus at \(24, 16\) px failed") as err:
        _run(tmp_path, before=af_fails)
    assert "SIM5D4000002" in str(err.value)
    assert json.loads((tmp_path / "s1/manifest.json").read_text())["files"] == []
    assert not list((tmp_path / "s1").rglob("*.dng"))


def test_card_capture_scene_deletes_each_card_file_only_after_it_is_verified(tmp_path: Path) -> None:
    from dataclasses import replace

    card = replace(RigConfig(), capture_destination="card", delete_from_card=True)
    n, sim = _run(tmp_path, rig=card)
    assert n == 110 and verify_session(tmp_path / "s1").problems == []
    assert all(b.objects == {} and 0x100B in b.op_log and 0x9117 not in b.op_log for b in sim.bodies.values())

    held: dict[str, SimRig] = {}

    def dpraw_off(s: SimRig) -> None:
        s.bodies["cam1"].faults.dual_pixel_raw = False
        held["sim"] = s

    with pytest.raises(DeviceError, match="did not write a Dual Pixel RAW"):
        _run(tmp_path / "b", rig=card, before=dpraw_off)
    bodies = held["sim"].bodies  # the refused raw was not stored, so its card copy was kept; cam0's was deleted
    assert [o.name for o in bodies["cam1"].objects.values()] == ["IMG_0001.DNG"] and bodies["cam0"].objects == {}
