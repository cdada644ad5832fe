"""Shared fixtures: simulated bodies on the simulated USB bus (the real pyusb/PTP/EOS client code runs)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
import usb.core

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

from dp5k_capture.canon import CaptureTiming, EosCamera  # noqa: E402
from dp5k_capture.capture import RigDevices, run_scene  # noqa: E402
from dp5k_capture.devices import open_bodies  # noqa: E402
from dp5k_capture.escvp21 import EpsonProjector, EscVp21Timing  # noqa: E402
from dp5k_capture.rawsession import RawSessionWriter  # noqa: E402
from dp5k_capture.rig import ProjectorConfig, RigConfig  # noqa: E402
from dp5k_capture.ptp.session import PTPSession, SessionConfig  # noqa: E402
from dp5k_capture.ptp.transport import UsbTransport  # noqa: E402
from dp5k_capture.sim.eos_body import SimulatedEOS  # noqa: E402
from dp5k_capture.sim.usb_backend import SimUsbBackend  # noqa: E402
from dp5k_capture.sim.usb_device import SimUsbPtpDevice  # noqa: E402
from dp5k_capture.sim.world import FlatOptics, SimRig, make_sim_rig, write_ground_truth_once  # noqa: E402

FAST = CaptureTiming(prop_echo_s=1.0, object_s=2.0, poll_s=0.0, keepalive_s=10.0, af_settle_s=0.0, focus_s=1.0)
FAST_SESSION = SessionConfig(timeout_s=0.5, busy_delay_s=0.001, busy_delay_max_s=0.002)


class Body:
    """A simulated body plus the client objects talking to it through pyusb."""

    def __init__(self, serial: str = "SIM0001", pid: int = 0x3281, blocking: bool = False) -> None:
        self.optics = FlatOptics((48, 32))
        self.core = SimulatedEOS(serial, self.optics)
        self.usb = SimUsbPtpDevice(self.core, pid=pid, blocking=blocking)
        self.backend = SimUsbBackend([self.usb])
        self.device = usb.core.find(backend=self.backend, idVendor=0x04A9)
        self.transport = UsbTransport(self.device, f"body {serial}")
        self.session = PTPSession(self.transport, FAST_SESSION)
        self.camera = EosCamera(self.session, (self.device.idVendor, self.device.idProduct), FAST)


@pytest.fixture
def body() -> Iterator[Body]:
    yield Body()


class _PatternCable:
    """A client's use of the simulated rig's pattern window: it draws, but the window stays (it is the projector's
    HDMI source in the simulated rig, which outlives the client)."""

    def __init__(self, window: object) -> None:
        self.window = window

    def show(self, image: object, tag: int | None = None) -> None:
        self.window.show(image, tag)  # type: ignore[attr-defined]

    def close(self) -> None:
        pass


def client_run(sim: SimRig, out: Path, scene: str = "s1", rig: RigConfig | None = None) -> int:
    """One capture client (what one ``dp5k capture`` run does) against the simulated rig ``sim``, whose bodies
    outlive it as real ones do; returns the files it wrote. ``rig`` overrides ``sim.rig`` (e.g. card capture)."""
    rig = rig or sim.rig
    writer = RawSessionWriter(out, scene, rig, "dng", extra={"simulated": True})
    proj = EpsonProjector(rig.projector.port, timing=EscVp21Timing(poll_s=0.01, default_s=0.5))
    devices = RigDevices({}, proj, _PatternCable(sim.window), sim.optics)  # type: ignore[arg-type]
    try:
        devices.bodies = open_bodies(rig, backend=sim.backend, config=FAST_SESSION, timing=FAST)
        return run_scene(rig, devices, writer, before_complete=lambda d: write_ground_truth_once(sim.optics, d))
    finally:
        devices.close()


def replug(sim: SimRig, cam: str) -> None:
    """Plug a body that vanished (a ``disconnect`` fault) back in, its faults cleared: the body kept its state."""
    from dp5k_capture.sim.fault_spec import BodyFaultPlan
    from dp5k_capture.sim.usb_device import UsbFaults

    dev = sim.usb_devices[cam]
    dev.gone, dev.faults = False, UsbFaults()
    dev.arm(BodyFaultPlan())


# an 8 x 4 px projector: 12 structured-light projections instead of 46, so a whole scene is 42 files
SMALL_RIG = RigConfig(projector=ProjectorConfig(width=8, height=4))


def small_sim_rig(run: int = 0) -> SimRig:
    """The simulated rig in this process: flat world (48 x 32 raw), :data:`SMALL_RIG`'s plan."""
    return make_sim_rig(SMALL_RIG, raw_size_px=(48, 32), warmup_s=0.05, run=run)


@pytest.fixture
def sim_rig() -> Iterator[SimRig]:
    """:func:`small_sim_rig`; its bodies outlive each :func:`client_run`."""
    sim = small_sim_rig()
    try:
        yield sim
    finally:
        sim.close()
