"""Shared fixtures: simulated bodies on the simulated USB bus (the real pyusb/PTP/EOS client code runs)."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
import usb.core

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

from dp5k_capture.canon import CaptureTiming, EosCamera  # noqa: E402
from dp5k_capture.ptp.session import PTPSession, SessionConfig  # noqa: E402
from dp5k_capture.ptp.transport import UsbTransport  # noqa: E402
from dp5k_capture.sim.eos_body import SimulatedEOS  # noqa: E402
from dp5k_capture.sim.usb_backend import SimUsbBackend  # noqa: E402
from dp5k_capture.sim.usb_device import SimUsbPtpDevice  # noqa: E402
from dp5k_capture.sim.world import FlatOptics  # noqa: E402

FAST = CaptureTiming(prop_echo_s=1.0, object_s=2.0, poll_s=0.0, keepalive_s=10.0, af_settle_s=0.0, focus_s=1.0)
FAST_SESSION = SessionConfig(timeout_s=0.5, busy_delay_s=0.001, busy_delay_max_s=0.002)


class Body:
    """A simulated body plus the client objects talking to it through pyusb."""

    def __init__(self, serial: str = "SIM0001", pid: int = 0x3281) -> None:
        self.optics = FlatOptics((48, 32))
        self.core = SimulatedEOS(serial, self.optics)
        self.usb = SimUsbPtpDevice(self.core, pid=pid)
        self.backend = SimUsbBackend([self.usb])
        self.device = usb.core.find(backend=self.backend, idVendor=0x04A9)
        self.transport = UsbTransport(self.device, f"body {serial}")
        self.session = PTPSession(self.transport, FAST_SESSION)
        self.camera = EosCamera(self.session, (self.device.idVendor, self.device.idProduct), FAST)


@pytest.fixture
def body() -> Iterator[Body]:
    yield Body()
