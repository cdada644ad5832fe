"""Raw session layout: plan counts, atomic never-overwrite writes, resume bookkeeping, verify, disk full."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest

from dp5k_capture import rawsession
from dp5k_capture.rawsession import CaptureStorageError, RawSessionWriter, plan_scene, verify_session
from dp5k_capture.rig import RigConfig, load_rig
from dp5k_common.errors import BadInputError


def test_plan_has_the_papers_counts() -> None:
    shots = plan_scene(RigConfig())
    kinds = [s.kind for s in shots]
    per_body = {k: kinds.count(k) for k in ("dp", "sharp", "charuco", "sl")}
    assert per_body == {"dp": 5, "sharp": 1, "charuco": 3, "sl": 46}  # x2 bodies: 10 + 2 + 6 + 92
    assert [s.stem for s in shots if s.kind == "dp"] == ["dp_f1.8", "dp_f2", "dp_f2.8", "dp_f4", "dp_f5.6"]
    assert [s.stem for s in shots if s.kind == "sharp"] == ["sharp_f22"]
    dp = [s for s in shots if s.kind == "dp"]
    exposure = [s.shutter_s / s.f_number**2 for s in dp]  # constant exposure within 1/3 stop
    assert max(exposure) / min(exposure) < 2 ** (1 / 3) + 1e-9


def test_rig_toml(tmp_path: Path) -> None:
    p = tmp_path / "rig.toml"
    p.write_text('[[body]]\nid = "cam0"\nserial = "A1"\nfocus_point_px = [10, 20]\n[[body]]\nid = "cam1"\nserial = "B2"\n'
                 '[projector]\nport = "/dev/ttyS9"\n[exposure]\niso = 200\n')
    rig = load_rig(p)
    assert rig.bodies[0].focus_point_px == (10, 20) and rig.projector.port == "/dev/ttyS9" and rig.exposure.iso == 200
    p.write_text('[projector]\nprot = "x"\n')
    with pytest.raises(BadInputError, match="unknown key 'prot'"):
        load_rig(p)
    p.write_text('[exposure]\ndp_f_numbers = [1.7]\n')
    with pytest.raises(BadInputError, match="f/1.7"):
        load_rig(p)


def test_rig_toml_timeouts(tmp_path: Path) -> None:
    from dp5k_capture.canon import CaptureTiming

    p = tmp_path / "rig.toml"
    assert (RigConfig().timeouts.transaction_s, RigConfig().timeouts.capture_s) == (20.0, 100.0)  # libgphoto2-like
    p.write_text("[timeouts]\ntransaction_s = 30\nfocus_s = 4.5\nsettings_s = 2\n")
    t = load_rig(p).timeouts
    assert (t.transaction_s, t.capture_s, t.settings_s, t.focus_s) == (30, 100.0, 2, 4.5)
    timing = CaptureTiming.from_timeouts(t)
    assert (timing.prop_echo_s, timing.object_s, timing.focus_s) == (2, 100.0, 4.5)
    for bad, why in (("focus_s = -1", "focus_s must be a positive"), ("capture_s = \"long\"", "capture_s must be"),
                     ("af_s = 3", "unknown key 'af_s'")):
        p.write_text(f"[timeouts]\n{bad}\n")
        with pytest.raises(BadInputError, match=why):
            load_rig(p)


def _writer(tmp_path: Path) -> tuple[RawSessionWriter, RigConfig]:
    rig = RigConfig()
    return RawSessionWriter(tmp_path, "s1", rig, "dng"), rig


def test_files_are_recorded_and_never_overwritten(tmp_path: Path) -> None:
    w, rig = _writer(tmp_path)
    shot = plan_scene(rig)[3]
    entry = w.add("cam0", shot, b"raw-bytes", {"camera_filename": "IMG_0001.DNG"})
    assert entry["path"] == "cam0/dp_f1.8.dng" and entry["size"] == 9 and entry["f_number"] == 1.8
    assert len(entry["sha256"]) == 64 and "timestamp" in entry
    assert w.done("cam0", shot)
    with pytest.raises(BadInputError, match="never overwritten"):
        w.add("cam0", shot, b"other", {})
    assert (tmp_path / "s1/cam0/dp_f1.8.dng").read_bytes() == b"raw-bytes"
    assert not [p for p in (tmp_path / "s1/cam0").iterdir() if p.name.startswith(".")]  # no temp left
    # a new writer (next run) sees the recorded file
    w2 = RawSessionWriter(tmp_path, "s1", rig, "dng")
    assert w2.done("cam0", shot)


def test_orphan_file_from_a_crash_is_adopted_not_overwritten(tmp_path: Path) -> None:
    w, rig = _writer(tmp_path)
    shot = plan_scene(rig)[4]
    (tmp_path / "s1/cam1").mkdir(parents=True)
    (tmp_path / "s1/cam1/dp_f2.dng").write_bytes(b"completed before the crash")
    entry = w.add("cam1", shot, b"new capture", {})
    assert (tmp_path / "s1/cam1/dp_f2.dng").read_bytes() == b"completed before the crash"
    assert entry["size"] == len(b"completed before the crash")


def test_check_failure_leaves_nothing(tmp_path: Path) -> None:
    w, rig = _writer(tmp_path)
    shot = plan_scene(rig)[0]

    def refuse(path: Path) -> None:
        raise BadInputError("not DP", where=path)

    with pytest.raises(BadInputError):
        w.add("cam0", shot, b"x", {}, check=refuse)
    assert not list((tmp_path / "s1/cam0").iterdir()) and not w.done("cam0", shot)


def test_disk_full_keeps_completed_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    w, rig = _writer(tmp_path)
    shots = plan_scene(rig)
    w.add("cam0", shots[0], b"first", {})

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(rawsession.os, "fsync", full)
    with pytest.raises(CaptureStorageError, match="disk full; completed files were kept") as err:
        w.add("cam0", shots[1], b"second", {})
    assert "cam0/charuco_1.dng" in str(err.value)
    monkeypatch.undo()
    assert sorted(p.name for p in (tmp_path / "s1/cam0").iterdir()) == ["charuco_0.dng"]
    w2 = RawSessionWriter(tmp_path, "s1", rig, "dng")
    assert w2.done("cam0", shots[0]) and not w2.done("cam0", shots[1])


def test_verify_finds_tampering_and_gaps(tmp_path: Path) -> None:
    w, rig = _writer(tmp_path)
    for s in plan_scene(rig):
        for b in ("cam0", "cam1"):
            w.add(b, s, f"{b}/{s.stem}".encode(), {})
    w.set_focus_point("cam0", (1, 2))
    w.set_focus_point("cam1", (3, 4))
    w.finish(rig)
    assert json.loads((tmp_path / "s1/manifest.json").read_text())["complete"] is True
    rep = verify_session(tmp_path / "s1", check_dual_pixel=False)
    assert rep.problems == [] and rep.counts == {"charuco": 6, "dp": 10, "sharp": 2, "sl": 92}
    (tmp_path / "s1/cam1/sl_07.dng").write_bytes(b"cam1/sl_08")  # same size, other bytes
    (tmp_path / "s1/cam0/dp_f2.dng").unlink()
    rep = verify_session(tmp_path / "s1", check_dual_pixel=False)
    assert "cam1/sl_07.dng: SHA-256 mismatch" in rep.problems and "cam0/dp_f2.dng: missing" in rep.problems
    assert "sl: 91 verified files, expected 92" in rep.problems
    with pytest.raises(BadInputError, match="already captured and complete"):
        RawSessionWriter(tmp_path, "s1", rig, "dng")
    with pytest.raises(BadInputError, match="scene name"):
        RawSessionWriter(tmp_path, "../evil", rig, "dng")


def test_files_follow_the_umask_and_stale_temporaries_go(tmp_path: Path) -> None:
    import os
    import stat

    old = os.umask(0o022)
    try:
        w, rig = _writer(tmp_path)
        shot = plan_scene(rig)[0]
        w.add("cam0", shot, b"raw bytes", {})
        for p in (tmp_path / "s1/manifest.json", tmp_path / "s1/cam0/charuco_0.dng"):
            assert stat.S_IMODE(p.stat().st_mode) == 0o644, p  # not 0600: readable like a camera's files
        os.umask(0o027)
        w.add("cam1", shot, b"raw bytes", {})
        assert stat.S_IMODE((tmp_path / "s1/cam1/charuco_0.dng").stat().st_mode) == 0o640
    finally:
        os.umask(old)
    # what a SIGKILL leaves under temporary names is removed when the scene is opened again
    (tmp_path / "s1/.manifest.json.abc123.json").write_text("{")
    (tmp_path / "s1/cam0/.sl_07.dng.xyz.dng").write_bytes(b"half")
    RawSessionWriter(tmp_path, "s1", rig, "dng")
    assert sorted(p.name for p in (tmp_path / "s1").rglob(".*")) == []
    assert (tmp_path / "s1/cam0/charuco_0.dng").read_bytes() == b"raw bytes"


def test_a_quarantine_move_cut_off_by_a_kill_is_completed_on_reopen(tmp_path: Path) -> None:
    """The manifest records a move before the rename: a kill in between leaves the file in place but no longer
    listed; reopening finishes the move instead of adopting the set-aside file as a fresh capture."""
    w, rig = _writer(tmp_path)
    shot = plan_scene(rig)[3]
    w.add("cam0", shot, b"old focus", {})

    def killed(src: Path, dest: Path) -> None:
        raise KeyboardInterrupt

    w._move = killed  # type: ignore[method-assign]
    with pytest.raises(KeyboardInterrupt):
        w.quarantine("cam0/dp_f1.8.dng", "focus moved")
    assert (tmp_path / "s1/cam0/dp_f1.8.dng").is_file()  # still in place after the kill
    w2 = RawSessionWriter(tmp_path, "s1", rig, "dng")
    assert not (tmp_path / "s1/cam0/dp_f1.8.dng").exists() and not w2.done("cam0", shot)
    assert (tmp_path / "s1/quarantine/run1/cam0/dp_f1.8.dng").read_bytes() == b"old focus"
    assert w2.run == 2 and [r["run"] for r in w2.manifest["runs"]] == [1, 2]
    w2.add("cam0", shot, b"new focus", {})  # the re-shot file takes its place; the old one stays set aside
    assert (tmp_path / "s1/cam0/dp_f1.8.dng").read_bytes() == b"new focus"
    report = verify_session(tmp_path / "s1", check_dual_pixel=False)
    assert not [p for p in report.problems if "quarantine" in p]
    (tmp_path / "s1/quarantine/run1/cam0/dp_f1.8.dng").write_bytes(b"tampered")
    report = verify_session(tmp_path / "s1", check_dual_pixel=False)
    assert "quarantine/run1/cam0/dp_f1.8.dng: changed since it was set aside (size or SHA-256)" in report.problems
