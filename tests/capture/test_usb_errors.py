"""Day-one USB problems explain themselves, through the injected pyusb backend (the simulated bus raises what
libusb raises: EACCES/-3 without a udev rule, EBUSY/-6 while another process holds the body): the device node and
the fix, the holder, a full card on which body and what was kept, the right rig.toml key for a timeout, and
``dp5k devices`` listing what matters for each device."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_capture import usb_access
from dp5k_capture.devices import find_bodies, open_bodies
from dp5k_capture.ptp.errors import CardFullError, UsbAccessError, UsbBusyError
from dp5k_capture.rig import RigConfig
from dp5k_capture.sim.fault_spec import BodyFaultPlan
from dp5k_capture.sim.world import SimRig, make_sim_rig
from dp5k_cli import main
from dp5k_common.errors import DeviceError

from .conftest import FAST, FAST_SESSION, client_run

CAM0_NODE, CAM1_NODE = "/dev/bus/usb/001/010", "/dev/bus/usb/001/011"


def _faulty(spec: str) -> SimRig:
    return make_sim_rig(RigConfig(), raw_size_px=(48, 32), warmup_s=0.05, faults=spec)


def test_no_permission_names_the_device_node_and_the_udev_rule() -> None:
    sim = _faulty("cam1.denied")
    try:
        found = {f.node: f for f in find_bodies(sim.backend)}
        assert (found[CAM1_NODE].permission, found[CAM1_NODE].serial) == ("denied", "")  # listed, serial unreadable
        with pytest.raises(UsbAccessError) as err:
            open_bodies(sim.rig, backend=sim.backend, config=FAST_SESSION, timing=FAST)
    finally:
        sim.close()
    msg = str(err.value)
    assert msg.startswith("cam1: body with serial SIM5D4000002 not found among the Canon bodies this user may open; ")
    assert f"no permission to open {CAM1_NODE}" in msg and "no udev rule" in msg
    assert ("dp5k devices --udev-rule | sudo tee /etc/udev/rules.d/60-dp5k.rules && sudo udevadm control --reload-rules "
            "&& sudo udevadm trigger, then unplug and replug the body") in msg
    assert "\n" not in err.value.one_line() and "found: 04a9:3281" not in msg


def test_the_shipped_udev_rule_is_package_data_and_printed_for_tee() -> None:
    rule = usb_access.udev_rule_path()
    assert rule.is_file() and rule.parent.name == "udev" and rule.parent.parent.name == "dp5k_capture"
    assert '"dp5k_capture" = ["udev/*.rules"]' in (Path(__file__).parents[2] / "pyproject.toml").read_text()
    res = CliRunner().invoke(main, ["devices", "--udev-rule"])
    assert res.exit_code == 0 and res.output == rule.read_text()
    rules = [line for line in res.output.splitlines() if line and not line.startswith("#")]
    assert rules == ['ACTION=="add|change", SUBSYSTEM=="usb", ENV{DEVTYPE}=="usb_device", ATTR{idVendor}=="04a9", '
                     'MODE="0660", GROUP="plugdev", TAG+="uaccess"']


def test_a_body_held_by_another_process_names_the_usual_holders() -> None:
    sim = _faulty("cam0.held")
    try:
        with pytest.raises(UsbBusyError) as err:
            open_bodies(sim.rig, backend=sim.backend, config=FAST_SESSION, timing=FAST)
    finally:
        sim.close()
    msg = str(err.value)
    assert msg.startswith("cam0 (Canon EOS 5D Mark IV serial SIM5D4000001): claim interface: /dev/bus/usb/001/010 is busy "
                          "(Resource busy): held by another process")
    for holder in ("gvfs-gphoto2-volume-monitor", "gphoto2", "another dp5k"):
        assert holder in msg
    assert "systemctl --user stop gvfs-gphoto2-volume-monitor.service" in msg


def _fake_proc(root: Path, pid: int, comm: str, cmdline: str, node: str) -> None:
    (root / str(pid) / "fd").mkdir(parents=True)
    (root / str(pid) / "comm").write_text(comm + "\n")
    (root / str(pid) / "cmdline").write_text(cmdline.replace(" ", "\0") + "\0")
    os.symlink(node, root / str(pid) / "fd" / "7")
    os.symlink("/dev/null", root / str(pid) / "fd" / "0")


def test_the_holder_is_named_where_proc_shows_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _fake_proc(tmp_path, 4242, "gvfs-gphoto2-vo", "/usr/libexec/gvfs-gphoto2-volume-monitor", CAM0_NODE)
    _fake_proc(tmp_path, 5151, "python3", "/usr/bin/python3 -m dp5k_cli capture --scene s2", CAM1_NODE)
    (tmp_path / "self").mkdir()  # not a pid: skipped
    monkeypatch.setattr(usb_access, "PROC_ROOT", tmp_path)
    sim = _faulty("held")
    try:
        with pytest.raises(UsbBusyError, match=r"held by gvfs-gphoto2-vo \(pid 4242: /usr/libexec/gvfs-gphoto2-volume-monitor\); "
                                               r"quit it"):
            open_bodies(sim.rig, backend=sim.backend, config=FAST_SESSION, timing=FAST)
    finally:
        sim.close()
    text = usb_access.holder_text(CAM1_NODE)
    assert text == "another dp5k (pid 5151: /usr/bin/python3 -m dp5k_cli capture --scene s2)"


def test_holders_are_read_from_the_real_proc(tmp_path: Path) -> None:
    held = tmp_path / "node"
    held.write_text("")
    with held.open() as fh:
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"], stdin=fh)
    try:
        found = usb_access.holders(str(held))
        assert [h.pid for h in found] == [child.pid] and "time.sleep(30)" in found[0].cmdline
    finally:
        child.kill()
        child.wait()


def test_a_full_card_says_which_body_and_what_was_kept(tmp_path: Path) -> None:
    sim = _faulty("")
    try:
        sim.usb_devices["cam1"].arm(BodyFaultPlan(full_at_release=5))  # cam1's 5th release: dp_f2
        with pytest.raises(CardFullError) as err:
            client_run(sim, tmp_path)
    finally:
        sim.close()
    line = err.value.one_line()
    assert line == (f"card full on cam1 (serial SIM5D4000002): dp_f2: the body refused the release (StoreFull 0x200C); "
                    f"kept: 9 completed files in {tmp_path / 's1'}, none deleted from the card; free space on the card "
                    "(or swap it) and run the same command again to resume")
    assert "0x200C)" in line and "STORE_FULL" not in line and err.value.exit_code == 5


def test_a_full_card_in_dp5k_devices_and_the_cli_line(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["devices", "--sim", "--sim-faults", "cam1.full@1"])
    assert res.exit_code == 0, res.output
    cam1 = res.output.split("cam1: ", 1)[1]
    assert "card 0.0 GB free (0 shots) of 64.0 GB" in cam1.splitlines()[1]


def test_the_new_image_timeout_names_capture_s() -> None:
    from dp5k_capture.ptp.codes import Resp
    from dp5k_capture.sim.eos_body import Reply

    from .conftest import Body

    body = Body()
    body.camera.open()
    body.core._expose = lambda: Reply(Resp.OK)  # type: ignore[method-assign]  # released, but no image ever comes
    with pytest.raises(DeviceError, match=r"wait for the new image: no confirmation from the body within 2 s "
                                          r"\(rig.toml \[timeouts\] capture_s\)"):
        body.camera.capture(4.0, 1 / 60, 100)


def test_dp5k_devices_lists_serial_model_permission_battery_card_and_holder() -> None:
    res = CliRunner().invoke(main, ["devices", "--sim"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0] == "Canon bodies (2):"
    assert lines[1] == f"  cam0: Canon EOS 5D Mark IV  serial SIM5D4000001  (04a9:3281 at {CAM0_NODE})"
    assert lines[2] == "      permission ok | battery 75% | card 60.0 GB free (900 shots) of 64.0 GB | held by: nobody"
    assert lines[3].startswith("  cam1: Canon EOS 5D Mark IV  serial SIM5D4000002")
    assert lines[5] == "EPSON projector: serial ports (1):" and "simulated EPSON EB-U42" in lines[6]
    assert lines[7] == "      permission ok | held by: nobody"
    assert lines[8].startswith("      EPSON projector (ESC/VP21): serial X5DS0000001, power 04")
    res = CliRunner().invoke(main, ["devices", "--sim", "--sim-faults", "cam1.denied,cam0.held"])
    assert res.exit_code == 0, res.output
    cam0, cam1 = res.output.split("  cam0: ", 1)[1], res.output.split("serial ?  (04a9:3281 at /dev/bus/usb/001/011)", 1)[1]
    assert "battery ? | card ? | held by: another process (usually gvfs-gphoto2-volume-monitor" in cam0.splitlines()[1]
    assert cam1.splitlines()[1].startswith(f"      permission DENIED on {CAM1_NODE} | battery ? | card ?")
    assert "install dp5k's rule: dp5k devices --udev-rule | sudo tee" in cam1.splitlines()[2]


def test_cli_capture_without_permission_is_one_line(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(tmp_path / "raw"), "--sim",
                                    "--sim-faults", "cam1.denied"])
    assert res.exit_code == 5, res.output
    [line] = [x for x in res.output.splitlines() if x.startswith("dp5k: error:")]
    assert line.startswith(f"dp5k: error: cam1: body with serial ") and f"no permission to open {CAM1_NODE}" in line
    assert "Traceback" not in res.output
