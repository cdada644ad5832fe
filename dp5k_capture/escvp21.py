"""EPSON ESC/VP21 projector control over RS-232C with pyserial (9600 8N1, CR-terminated ASCII).

The projector answers every command with ``":"`` when it is ready; queries answer ``KEY=VALUE\\r:``,
refused commands ``ERR\\r:``. In an abnormal state (lamp failure, over-temperature) no colon comes, so a
timeout is fatal. Worst-case times (ESC/VP21 guide, section 5): PWR ON 40 s (up to 100 s on a third lamp
ignition), PWR OFF 10-50 s, SOURCE 5 s, others 3 s.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import serial

from dp5k_common.errors import DeviceError, DeviceTimeoutError

log = logging.getLogger(__name__)

POWER_STATES = {
    "00": "standby (network off)", "01": "on", "02": "warm-up", "03": "cool-down",
    "04": "standby (network on)", "05": "abnormal standby", "09": "A/V standby",
}
SOURCE_HDMI1 = "30"
SOURCE_HDMI2 = "A0"


class ProjectorError(DeviceError):
    """The projector answered ERR (command refused or not possible in its current state)."""


@dataclass(frozen=True)
class EscVp21Timing:
    """Per-command timeouts (s) and the warm-up bound."""

    power_on_s: float = 100.0
    power_off_s: float = 50.0
    source_s: float = 5.0
    default_s: float = 3.0
    warmup_s: float = 120.0
    poll_s: float = 1.0


class EpsonProjector:
    """ESC/VP21 driver for an EPSON EB-U42 (or any business projector of the family).

    Args:
        url: a pyserial port or URL (``/dev/ttyUSB0``, a pty path, ``socket://host:port``).
        name: how errors name the device.
        timing: command timeouts.
    """

    def __init__(self, url: str, name: str = "projector", timing: EscVp21Timing | None = None) -> None:
        self.url = url
        self.name = f"{name} ({url})"
        self.timing = timing or EscVp21Timing()
        try:
            self.port = serial.serial_for_url(url, baudrate=9600, bytesize=8, parity="N", stopbits=1,
                                              xonxoff=False, rtscts=False, timeout=0.1)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"cannot open serial port ({exc})", where=self.name) from exc

    def close(self) -> None:
        self.port.close()

    def __enter__(self) -> EpsonProjector:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _timeout_for(self, cmd: str) -> float:
        t = self.timing
        if cmd == "PWR ON":
            return t.power_on_s
        if cmd == "PWR OFF":
            return t.power_off_s
        if cmd.startswith("SOURCE "):
            return t.source_s
        return t.default_s

    def command(self, cmd: str, timeout_s: float | None = None) -> str:
        """Send ``cmd`` + CR, read up to the ':' prompt; returns the reply without prompt (may be '').

        Raises:
            ProjectorError: the projector answered ``ERR``.
            DeviceTimeoutError: no ':' within the command's timeout (abnormal state or cable).
        """
        timeout_s = self._timeout_for(cmd) if timeout_s is None else timeout_s
        try:
            self.port.reset_input_buffer()
            self.port.write(cmd.encode("ascii") + b"\r")
            self.port.flush()
            reply = bytearray()
            deadline = time.monotonic() + timeout_s
            while not reply.endswith(b":"):
                if time.monotonic() > deadline:
                    raise DeviceTimeoutError(f"{cmd!r}: no ':' prompt within {timeout_s:g} s (got {bytes(reply)!r})", where=self.name)
                chunk = self.port.read(self.port.in_waiting or 1)
                reply += chunk
                if len(reply) > 4096:
                    raise DeviceError(f"{cmd!r}: reply longer than 4096 bytes without a prompt", where=self.name)
        except serial.SerialException as exc:
            raise DeviceError(f"{cmd!r}: serial error ({exc})", where=self.name) from exc
        text = reply[:-1].decode("ascii", errors="replace").strip("\r\n ")
        if text == "ERR":
            raise ProjectorError(f"{cmd!r} refused (ERR)", where=self.name)
        return text

    def query(self, key: str) -> str:
        """``KEY?`` -> the value of ``KEY=VALUE``."""
        text = self.command(f"{key}?")
        head, sep, value = text.partition("=")
        if not sep or head.strip() != key:
            raise DeviceError(f"{key}?: unexpected reply {text!r}", where=self.name)
        return value.strip()

    def hello(self) -> None:
        """A bare CR; the projector answers ':' (connection check)."""
        self.command("", timeout_s=self.timing.default_s)

    def power_state(self) -> str:
        """``PWR?`` code: 00/04 standby, 01 on, 02 warm-up, 03 cool-down, 05 abnormal standby."""
        return self.query("PWR")

    def error_code(self) -> str:
        return self.query("ERR")

    def power_on(self) -> None:
        """Power on (after any cool-down) and wait through the warm-up until ``PWR?`` reads 01."""
        state = self.power_state()
        deadline = time.monotonic() + self.timing.power_off_s
        while state == "03":  # PWR ON is refused until the cool-down has finished
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(f"still cooling down after {self.timing.power_off_s:g} s", where=self.name)
            time.sleep(self.timing.poll_s)
            state = self.power_state()
        if state == "05":
            raise DeviceError(f"abnormal standby (error {self._safe_error()}); check lamp and temperature", where=self.name)
        if state != "01":
            if state != "02":
                self.command("PWR ON")
            deadline = time.monotonic() + self.timing.warmup_s
            while (state := self.power_state()) != "01":
                if state == "05":
                    raise DeviceError(f"power on failed: abnormal standby (error {self._safe_error()})", where=self.name)
                if time.monotonic() > deadline:
                    raise DeviceTimeoutError(f"still {POWER_STATES.get(state, state)} after {self.timing.warmup_s:g} s", where=self.name)
                time.sleep(self.timing.poll_s)

    def _safe_error(self) -> str:
        try:
            return self.error_code()
        except DeviceError:
            return "unknown"

    def power_off(self, wait: bool = True) -> None:
        """Power off; with ``wait``, poll ``PWR?`` through the cool-down (03) until standby (00/04)."""
        self.command("PWR OFF")
        deadline = time.monotonic() + self.timing.power_off_s
        while wait and (state := self.power_state()) not in ("00", "04"):
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(f"still {POWER_STATES.get(state, state)} {self.timing.power_off_s:g} s after PWR OFF", where=self.name)
            time.sleep(self.timing.poll_s)

    def set_source(self, code: str = SOURCE_HDMI1) -> None:
        self.command(f"SOURCE {code}")
        if self.query("SOURCE").upper() != code.upper():
            raise DeviceError(f"source did not switch to {code}", where=self.name)

    def blank(self, on: bool) -> None:
        """A/V mute on (blank, black screen) or off (show the HDMI input)."""
        self.command(f"MUTE {'ON' if on else 'OFF'}")

    def prepare(self, source: str = SOURCE_HDMI1) -> None:
        """The capture start-up: hello, power on with warm-up, HDMI source, unblank."""
        self.hello()
        self.power_on()
        self.set_source(source)
        self.blank(False)
