"""Capture-layer speed: PTP download through the real client code, event parsing, a whole simulated scene.

Prints a table. Targets: a 70 MB Dual Pixel RAW (the 5D Mark IV's size) crosses the client's PTP layer (pyusb,
containers, 1 MiB GetPartialObject, simulated body included) at >= 100 MB/s on the dev machine, so a scene's
110 raws (~7.7 GB on the rig) cost the client ~1 min and the rig is bound by the camera and cable; GetEvent
parsing > 50k records/s; a simulated demo scene (110 files, studio scale 60) well under a minute.

    .venv/bin/python benchmarks/bench_capture.py
"""

from __future__ import annotations

import os
import tempfile
import time

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import usb.core

from dp5k_capture.canon import CaptureTiming, EosCamera
from dp5k_capture.ptp import eos_events as ev
from dp5k_capture.ptp.session import PTPSession, SessionConfig
from dp5k_capture.ptp.transport import UsbTransport
from dp5k_capture.sim.eos_body import SimulatedEOS
from dp5k_capture.sim.usb_backend import SimUsbBackend
from dp5k_capture.sim.usb_device import SimUsbPtpDevice


class _BigFile:
    def __init__(self, nbytes: int) -> None:
        self.data = os.urandom(nbytes)

    def autofocus_m(self, serial: str, point: tuple[float, float]) -> float:
        return 2.0

    def expose(self, settings: object) -> bytes:
        return self.data


def bench_download(nbytes: int = 70 << 20) -> tuple[str, float, str]:
    core = SimulatedEOS("BENCH", _BigFile(nbytes))
    dev = usb.core.find(backend=SimUsbBackend([SimUsbPtpDevice(core, max_packet=1024)]), idVendor=0x04A9)
    cam = EosCamera(PTPSession(UsbTransport(dev), SessionConfig()), (dev.idVendor, dev.idProduct),
                    CaptureTiming(poll_s=0.0, af_settle_s=0.0))
    cam.open()
    t0 = time.perf_counter()
    dl = cam.capture(2.8, 1 / 100, 100)
    dt = time.perf_counter() - t0
    assert dl.data == core.last_object_bytes
    return "DPRAW download (70 MB, 1 MiB GetPartialObject)", nbytes / dt / 1e6, "MB/s"


def bench_events(n: int = 20000) -> tuple[str, float, str]:
    blob = b"".join(ev.pack_prop_value(0xD101, 0x15) for _ in range(n // 2))
    blob += b"".join(ev.pack_avail_list(0xD103, [0x48, 0x50, 0x58]) for _ in range(n // 2)) + ev.TERMINATOR
    t0 = time.perf_counter()
    count = 0
    for i in range(0, n, 4000):  # parse in realistic GetEvent-sized batches
        count += len(ev.parse_events(blob[: 4000 * 16] + ev.TERMINATOR))
    dt = time.perf_counter() - t0
    return "GetEvent record parsing", count / dt, "records/s"


def bench_scene() -> tuple[str, float, str]:
    from click.testing import CliRunner

    from dp5k_cli import main

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = CliRunner().invoke(main, ["-q", "capture", "--scene", "demo01", "--out", tmp, "--sim"])
        dt = time.perf_counter() - t0
        assert res.exit_code == 0, res.output
    return "simulated scene demo01 (110 files, scale 60)", dt, "s"


def main_() -> None:
    rows = [bench_download(), bench_events(), bench_scene()]
    print(f"{'benchmark':<52} {'value':>12}  unit")
    for name, value, unit in rows:
        print(f"{name:<52} {value:>12.1f}  {unit}")


if __name__ == "__main__":
    main_()
