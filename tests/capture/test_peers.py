"""Cross-checks against implementations no one on the project wrote (marker ``peer``).

* real libgphoto2 (PyPI ``gphoto2`` wheel) drives the simulated body over PTP/IP through a full Canon EOS
  remote capture;
* umockdev replays a recorded real Canon camera (PowerShot SX200 IS) into our pyusb client;
* the PyPI ``epson-projector`` client drives the simulated EB-U42 over its serial (pty) path.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.peer

REPO = Path(__file__).resolve().parents[2]
SX200 = REPO.parent / "shared" / "data" / "umockdev-canon-sx200"


def test_libgphoto2_captures_from_the_simulated_body(tmp_path: Path) -> None:
    gp = pytest.importorskip("gphoto2")
    proc = subprocess.Popen([sys.executable, "-m", "dp5k_capture.sim.ptpip", "--state-dir", str(tmp_path)], cwd=REPO)
    try:
        for _ in range(200):
            if (tmp_path / "port").exists() or proc.poll() is not None:
                break
            time.sleep(0.05)
        port = int((tmp_path / "port").read_text())
        cam = gp.Camera()
        abilities = gp.CameraAbilitiesList()
        abilities.load()
        cam.set_abilities(abilities[abilities.lookup_model("PTP/IP Camera")])
        ports = gp.PortInfoList()
        ports.load()
        cam.set_port_info(ports[ports.lookup_path(f"ptpip:127.0.0.1:{port}:{port}")])  # event port too
        cam.init()
        cfg = cam.get_config()
        ap = cfg.get_child_by_name("aperture")
        choices = [ap.get_choice(i) for i in range(ap.count_choices())]
        assert choices[0] == "1.8" and choices[-1] == "22" and "2.8" in choices  # parsed our AvailListChanged
        target = cam.get_single_config("capturetarget")  # libgphoto2 keeps this setting in ~/.gphoto/settings
        target.set_value("Internal RAM")
        cam.set_single_config("capturetarget", target)
        for name, first, last in (("iso", "100", "12800"), ("shutterspeed", "30", "1/8000")):
            w = cfg.get_child_by_name(name)
            vals = [w.get_choice(i) for i in range(w.count_choices())]
            assert (vals[0], vals[-1]) == (first, last), (name, vals)
        for name, value in (("aperture", "2.8"), ("iso", "100"), ("shutterspeed", "1/60")):
            w = cam.get_single_config(name)
            w.set_value(value)
            cam.set_single_config(name, w)
        path = cam.capture(gp.GP_CAPTURE_IMAGE)
        cfile = cam.file_get(path.folder, path.name, gp.GP_FILE_TYPE_NORMAL)
        data = bytes(cfile.get_data_and_size())
        cam.exit()
        assert data == (tmp_path / "last_object.bin").read_bytes()
        import rawpy

        (tmp_path / "got.dng").write_bytes(data)
        with rawpy.imread(str(tmp_path / "got.dng")) as r:  # the downloaded file is a raw LibRaw opens
            assert r.raw_image_visible.shape == (64, 96)
        import tifffile

        with tifffile.TiffFile(tmp_path / "got.dng") as tf:  # the body exposed at what libgphoto2 set
            meta = json.loads(tf.pages[0].description)
        assert (meta["f_number"], meta["iso"], meta["shutter_s"]) == (2.8, 100, pytest.approx(1 / 60))
        ops = [int(x, 16) for x in (tmp_path / "ops.txt").read_text().split()]
        assert ops[:3] == [0x1002, 0x1001, 0x9114]  # libgphoto2's order: OpenSession, GetDeviceInfo, SetRemoteMode
        for op in (0x9115, 0x9116, 0x9110, 0x911A, 0x9128, 0x9129, 0x101B, 0x9117, 0x9160):
            assert op in ops, hex(op)
    finally:
        proc.kill()
        proc.wait()


def test_libgphoto2_card_capture_returns_the_file_from_the_simulated_card(tmp_path: Path) -> None:
    """Capture to the memory card: libgphoto2 finds the new image through ObjectAddedEx and GetObjectInfo (DCIM/100CANON
    folders included) and downloads it with GetObject, in seconds (it used to poll for 90 s)."""
    gp = pytest.importorskip("gphoto2")
    proc = subprocess.Popen([sys.executable, "-m", "dp5k_capture.sim.ptpip", "--state-dir", str(tmp_path)], cwd=REPO)
    try:
        for _ in range(200):
            if (tmp_path / "port").exists() or proc.poll() is not None:
                break
            time.sleep(0.05)
        port = int((tmp_path / "port").read_text())
        cam = gp.Camera()
        abilities = gp.CameraAbilitiesList()
        abilities.load()
        cam.set_abilities(abilities[abilities.lookup_model("PTP/IP Camera")])
        ports = gp.PortInfoList()
        ports.load()
        cam.set_port_info(ports[ports.lookup_path(f"ptpip:127.0.0.1:{port}:{port}")])
        cam.init()
        w = cam.get_single_config("capturetarget")
        w.set_value("Memory card")
        cam.set_single_config("capturetarget", w)
        t0 = time.monotonic()
        path = cam.capture(gp.GP_CAPTURE_IMAGE)
        cfile = cam.file_get(path.folder, path.name, gp.GP_FILE_TYPE_NORMAL)  # keep it alive while its data is copied
        data = bytes(cfile.get_data_and_size())
        took_s = time.monotonic() - t0
        w.set_value("Internal RAM")  # back to libgphoto2's default (it persists this setting)
        cam.set_single_config("capturetarget", w)
        cam.exit()
        assert path.folder == "/store_00010001/DCIM/100CANON" and path.name.startswith("IMG_0001.")
        assert data == (tmp_path / "last_object.bin").read_bytes() and took_s < 10.0
        ops = [int(x, 16) for x in (tmp_path / "ops.txt").read_text().split()]
        assert 0x1008 in ops and 0x1009 in ops and 0x9117 not in ops  # GetObjectInfo + GetObject, no PC transfer
    finally:
        proc.kill()
        proc.wait()


_UMOCK_CLIENT = """
import json
from dp5k_capture.devices import find_bodies
from dp5k_capture.ptp.transport import UsbTransport
from dp5k_capture.ptp.session import PTPSession
found = find_bodies()
s = PTPSession(UsbTransport(found[0].device, "sx200"))
s.open_session(1)
info = s.get_device_info()
handles = s.get_object_handles(0xFFFFFFFF, 0, 0xFFFFFFFF)  # the same URBs gphoto2 sent when recorded
print(json.dumps({"vid": found[0].vid, "pid": found[0].pid, "manufacturer": info.manufacturer, "model": info.model,
                  "vendor": info.vendor_extension_id, "ops": info.operations, "version": info.standard_version,
                  "handles": handles}))
"""


@pytest.mark.skipif(shutil.which("umockdev-run") is None, reason="umockdev-run not installed (apt package umockdev)")
@pytest.mark.skipif(not (SX200 / "canon-powershot-sx200.ioctl").is_file(),
                    reason=f"recorded Canon trace not found at {SX200} (the CI checkout has shared/ beside the repo)")
def test_pyusb_client_reads_a_recorded_real_canon_camera() -> None:
    cmd = ["umockdev-run", "-d", str(SX200 / "canon-powershot-sx200.umockdev"),
           "-i", f"/dev/bus/usb/001/011={SX200 / 'canon-powershot-sx200.ioctl'}", "--", sys.executable, "-c", _UMOCK_CLIENT]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert res.returncode == 0, res.stderr[-2000:]
    info = json.loads(res.stdout.strip().splitlines()[-1])
    assert (info["vid"], info["pid"]) == (0x04A9, 0x31C0)
    assert info["manufacturer"] == "Canon Inc." and info["model"] == "Canon PowerShot SX200 IS"
    assert info["vendor"] == 6 and info["version"] == 100  # vendor id 6, like the 5D Mark IV: Canon known by VID
    assert len(info["ops"]) == 52 and 0x1001 in info["ops"] and 0x9001 in info["ops"]
    assert info["handles"] == [0x00080000]  # the card's root folder, from the camera's own bytes


def test_epson_projector_client_drives_the_simulated_eb_u42() -> None:
    pytest.importorskip("epson_projector")
    from epson_projector.projector_serial import ProjectorSerial

    from dp5k_capture.sim.projector import SimulatedEBU42

    sim = SimulatedEBU42(warmup_s=0.3)
    path = sim.serve_pty()

    async def drive() -> dict[str, object]:
        p = ProjectorSerial(path)
        out: dict[str, object] = {"open": await p.async_init()}
        out["pwr0"] = await p.get_property("PWR", 3)
        out["source_standby"] = await p.send_command("SOURCE 30", 3)  # refused in standby: ERR -> False
        await p.send_command("PWR ON", 40)
        out["warm"] = await p.get_property("PWR", 3)
        t0 = time.monotonic()
        while await p.get_property("PWR", 3) != "01" and time.monotonic() - t0 < 5:
            await asyncio.sleep(0.05)
        out["pwr1"] = await p.get_property("PWR", 3)
        out["src"] = await p.send_command("SOURCE A0", 5)
        out["src?"] = await p.get_property("SOURCE", 3)
        out["bad"] = await p.send_command("FOO 1", 3)
        out["sno"] = await p.get_property("SNO", 3)
        p.close()
        return out

    try:
        out = asyncio.run(drive())
    finally:
        sim.stop()
    assert out["open"] is True and out["pwr0"] == "04" and out["source_standby"] is False
    assert out["warm"] == "02" and out["pwr1"] == "01"
    assert out["src?"] == "A0" and sim.source == "A0" and out["bad"] is False and out["sno"]
