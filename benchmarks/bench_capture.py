"""Capture-layer speed: PTP download through the real client code, event parsing, a whole simulated scene.

Prints a table. Targets: a 70 MB Dual Pixel RAW (the 5D Mark IV's size) crosses the client's PTP layer (pyusb,
containers, 1 MiB GetPartialObject, simulated body included) at >= 100 MB/s on the dev machine, so a scene's
110 raws (~7.7 GB on the rig) cost the client ~1 min and the rig is bound by the camera and cable; GetEvent
parsing > 50k records/s; a simulated demo scene (110 files, studio scale 60) well under a minute; a flat-world
scene with the bodies in a sim-rig server process within 2x the same scene with in-process bodies.

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
from run_info import record_result


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


def _flat_scene_in_process(out: str) -> None:
    """The peer of the served scene: the same flat world and client code, the bodies in this process."""
    from dp5k_capture.capture import RigDevices, run_scene
    from dp5k_capture.devices import open_bodies
    from dp5k_capture.escvp21 import EpsonProjector, EscVp21Timing
    from dp5k_capture.rawsession import RawSessionWriter
    from dp5k_capture.sim.server import FLAT_RAW_SIZE_PX
    from dp5k_capture.sim.world import make_sim_rig, write_ground_truth_once

    sim = make_sim_rig(raw_size_px=FLAT_RAW_SIZE_PX)
    try:
        writer = RawSessionWriter(out, "flat", sim.rig, "dng", extra={"simulated": True})
        proj = EpsonProjector(sim.rig.projector.port, timing=EscVp21Timing(poll_s=0.05))
        assert sim.window is not None
        devices = RigDevices(open_bodies(sim.rig, backend=sim.backend), proj, sim.window, sim.optics)
        try:
            run_scene(sim.rig, devices, writer, before_complete=lambda d: write_ground_truth_once(sim.optics, d))
        finally:
            devices.close()
    finally:
        sim.close()


def bench_served_scene() -> list[tuple[str, float, str]]:
    """A whole flat-world scene with the bodies in a sim-rig server process (every USB call crosses a Unix
    socket) against the same scene with the bodies in-process (the floor)."""
    import subprocess
    import sys
    from pathlib import Path

    from dp5k_capture.session_run import SimSpec, capture_scene
    from dp5k_capture.rig import RigConfig

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        _flat_scene_in_process(tmp)
        floor = time.perf_counter() - t0
        sock = Path(tmp) / "rig.sock"
        server = subprocess.Popen([sys.executable, "-m", "dp5k_capture.sim.server", "--socket", str(sock), "--world", "flat"],
                                  stdout=subprocess.DEVNULL)
        try:
            while not sock.exists():
                time.sleep(0.05)
            t0 = time.perf_counter()
            capture_scene("served", Path(tmp), RigConfig(), sim=SimSpec(server=sock))
            served = time.perf_counter() - t0
        finally:
            server.terminate()
            server.wait(10)
    return [("flat scene, bodies in-process (110 files; floor)", floor, "s"),
            ("flat scene, bodies in a sim-rig server (--sim-rig)", served, "s")]


def main_() -> None:
    import datetime
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip() or "?"
    print(f"{datetime.datetime.now().isoformat(timespec='seconds')}  commit {commit}  {os.cpu_count()} cores")
    print(f"{'benchmark':<52} {'value':>12}  unit       load (1 min)")
    rows = []
    for bench in (bench_download, bench_events, bench_scene, bench_served_scene):
        out = bench()
        for name, value, unit in out if isinstance(out, list) else [out]:
            print(f"{name:<52} {value:>12.1f}  {unit:<10} {os.getloadavg()[0]:.1f}")
            rows.append([name, f"{value:.1f}", unit, f"{os.getloadavg()[0]:.1f}"])
    record_result("speed-capture", "Capture layer: PTP download, event parsing, a simulated scene",
                  ["benchmark", "value", "unit", "load (1 min)"], rows)


if __name__ == "__main__":
    main_()
