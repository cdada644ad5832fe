"""ESC/VP21 driver against the simulated EB-U42 on a pseudo-terminal (pyserial's real serial path)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from dp5k_capture.escvp21 import EpsonProjector, EscVp21Timing, ProjectorError
from dp5k_capture.sim.projector import SimulatedEBU42
from dp5k_common.errors import DeviceError, DeviceTimeoutError


@pytest.fixture
def sim() -> Iterator[SimulatedEBU42]:
    s = SimulatedEBU42(warmup_s=0.3, cooldown_s=0.1)
    yield s
    s.stop()


def _driver(path: str, **kw: float) -> EpsonProjector:
    return EpsonProjector(path, timing=EscVp21Timing(poll_s=0.02, **kw))


def test_start_up_waits_through_warm_up(sim: SimulatedEBU42) -> None:
    proj = _driver(sim.serve_pty())
    assert proj.port.baudrate == 9600 and proj.port.bytesize == 8 and proj.port.parity == "N"
    t0 = time.monotonic()
    proj.prepare()
    assert time.monotonic() - t0 >= 0.3  # waited for the lamp
    assert (sim.power(), sim.source, sim.muted) == ("01", "30", False)
    assert sim.log[:3] == ["", "PWR?", "PWR ON"] and "PWR?" in sim.log[3:]
    proj.blank(True)
    assert sim.muted and sim.lit_image() is None
    proj.close()


def test_commands_during_warm_up_answer_err(sim: SimulatedEBU42) -> None:
    proj = _driver(sim.serve_pty())
    proj.command("PWR ON")
    with pytest.raises(ProjectorError, match=r"'SOURCE 30' refused \(ERR\)") as err:
        proj.command("SOURCE 30")
    assert "projector (/dev/pts/" in str(err.value)
    assert proj.power_state() == "02"


def test_err_reply_and_unknown_command(sim: SimulatedEBU42) -> None:
    proj = _driver(sim.serve_pty())
    proj.prepare()
    with pytest.raises(ProjectorError, match="FOO 1"):
        proj.command("FOO 1")
    sim.faults.err_next = 1
    with pytest.raises(ProjectorError):
        proj.set_source("30")
    proj.set_source("A0")
    assert sim.source == "A0"


def test_silent_projector_times_out(sim: SimulatedEBU42) -> None:
    proj = _driver(sim.serve_pty(), default_s=0.2)
    sim.faults.silent = True
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeoutError, match="'PWR\\?': no ':' prompt within 0.2 s"):
        proj.power_state()
    assert time.monotonic() - t0 < 1.0


def test_warm_up_that_never_ends_is_bounded(sim: SimulatedEBU42) -> None:
    sim.warmup_s = 100.0
    proj = _driver(sim.serve_pty(), warmup_s=0.2)
    with pytest.raises(DeviceTimeoutError, match="still warm-up after 0.2 s"):
        proj.power_on()


def test_bad_port_is_a_device_error() -> None:
    with pytest.raises(DeviceError, match="cannot open serial port"):
        EpsonProjector("/nonexistent/ttyUSB9")


def test_lit_image_follows_power_source_and_mute(sim: SimulatedEBU42) -> None:
    import numpy as np

    frame = np.full((4, 4), 200, np.uint8)
    sim.hdmi = lambda: frame
    assert sim.lit_image() is None  # standby
    proj = _driver(sim.serve_pty())
    proj.prepare()
    assert sim.lit_image() is frame
    proj.command("SOURCE 52")
    assert sim.lit_image() is None  # not on HDMI


def test_power_off_waits_through_cool_down(sim: SimulatedEBU42) -> None:
    proj = _driver(sim.serve_pty())
    proj.prepare()
    proj.power_off(wait=False)
    assert proj.power_state() == "03"
    with pytest.raises(ProjectorError):
        proj.command("PWR ON")  # not accepted during cool-down
    proj.power_on()
    proj.power_off()
    assert sim.power() == "04" and proj.power_state() == "04"
