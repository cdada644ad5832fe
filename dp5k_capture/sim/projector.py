"""A simulated EPSON EB-U42 that answers ESC/VP21 on a pseudo-terminal or a TCP socket.

The state machine follows the ESC/VP21 guide: in standby only ``PWR ON`` / ``PWR?`` (and, with network
standby, queries) are accepted; ``PWR ON`` starts a warm-up (``PWR=02``) that ends in ``PWR=01``; commands
other than ``PWR?`` during warm-up and cool-down answer ``ERR``; unknown commands answer ``ERR``. What the
projector throws on the scene is its HDMI input while it is on, on the HDMI source and not muted
(:meth:`SimulatedEBU42.lit_image`); otherwise black.
"""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

SOURCES = {"30": "HDMI1", "A0": "HDMI2", "1F": "Computer", "11": "Computer RGB", "41": "Video", "52": "USB", "53": "LAN"}


@dataclass
class ProjectorFaults:
    """Faults: ``silent`` = abnormal state, no ':' ever; ``err_next`` = answer ERR to the next N commands."""

    silent: bool = False
    err_next: int = 0


class SimulatedEBU42:
    """ESC/VP21 state machine of an EB-U42 (1920 x 1200).

    Args:
        warmup_s: warm-up duration after PWR ON (the real lamp takes ~30 s).
        cooldown_s: cool-down after PWR OFF.
        hdmi: returns the image on the HDMI input (the pattern window's framebuffer), or None.
        network_standby: standby mode 04 (queries accepted) instead of 00.
    """

    WIDTH, HEIGHT = 1920, 1200

    def __init__(self, warmup_s: float = 0.3, cooldown_s: float = 0.2,
                 hdmi: Callable[[], NDArray[np.uint8] | None] | None = None, network_standby: bool = True) -> None:
        self.warmup_s, self.cooldown_s = warmup_s, cooldown_s
        self.hdmi = hdmi
        self.network_standby = network_standby
        self.faults = ProjectorFaults()
        self._standby = "04" if network_standby else "00"
        self._state = self._standby
        self._until = 0.0
        self.source = "30"
        self.muted = False
        self.log: list[str] = []
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()

    # ------------------------------------------------------------------ state
    def power(self) -> str:
        now = time.monotonic()
        if self._state == "02" and now >= self._until:
            self._state = "01"
        elif self._state == "03" and now >= self._until:
            self._state = self._standby
        return self._state

    def lit_image(self) -> NDArray[np.uint8] | None:
        """The image on the scene now (None = dark)."""
        if self.power() != "01" or self.muted or self.source not in ("30", "A0") or self.hdmi is None:
            return None
        return self.hdmi()

    def answer(self, line: str) -> bytes | None:
        """The reply to one command line (without CR); None = say nothing (abnormal state)."""
        with self._lock:
            self.log.append(line)
            if self.faults.silent:
                return None
            cmd = line.strip()
            if cmd == "":
                return b":"
            if self.faults.err_next > 0:
                self.faults.err_next -= 1
                return b"ERR\r:"
            state = self.power()
            if cmd == "PWR?":
                return f"PWR={state}\r:".encode()
            if cmd == "PWR ON":
                if state in ("00", "04"):
                    self._state, self._until = "02", time.monotonic() + self.warmup_s
                    return b":"
                return b":" if state in ("01", "02") else b"ERR\r:"
            if state in ("00", "02", "03") or (state == "04" and not cmd.endswith("?")):
                return b"ERR\r:"
            if cmd == "PWR OFF":
                self._state, self._until = "03", time.monotonic() + self.cooldown_s
                return b":"
            if cmd == "SOURCE?":
                return f"SOURCE={self.source}\r:".encode()
            if cmd.startswith("SOURCE "):
                code = cmd.split(" ", 1)[1].upper()
                if code not in SOURCES or state != "01":
                    return b"ERR\r:"
                self.source = code
                return b":"
            if cmd == "MUTE?":
                return f"MUTE={'ON' if self.muted else 'OFF'}\r:".encode()
            if cmd in ("MUTE ON", "MUTE OFF") and state == "01":
                self.muted = cmd.endswith("ON")
                return b":"
            if cmd == "ERR?":
                return b"ERR=00\r:"
            if cmd == "LAMP?":
                return b"LAMP=1234\r:"
            if cmd == "SNO?":
                return b"SNO=X5DS0000001\r:"
            return b"ERR\r:"

    def _serve(self, read: Callable[[], bytes], write: Callable[[bytes], None]) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            try:
                chunk = read()
            except OSError:
                return
            if chunk is None:
                continue
            if chunk == b"":
                return
            buf += chunk
            while b"\r" in buf:
                line, _, rest = bytes(buf).partition(b"\r")
                buf = bytearray(rest)
                reply = self.answer(line.decode("ascii", errors="replace"))
                if reply is not None:
                    try:
                        write(reply)
                    except OSError:
                        return

    # ------------------------------------------------------------------ transports
    def serve_pty(self) -> str:
        """Serve on a new pseudo-terminal; returns the slave device path for pyserial."""
        master, slave = os.openpty()
        tty.setraw(slave)
        path = os.ttyname(slave)
        self._slave_fd = slave  # keep the slave open so the master never sees EOF between clients

        def read() -> bytes:
            import select

            r, _, _ = select.select([master], [], [], 0.1)
            return os.read(master, 256) if r else None  # type: ignore[return-value]

        t = threading.Thread(target=self._serve, args=(read, lambda b: os.write(master, b)), daemon=True)
        t.start()
        self._threads.append(t)
        self._fds = [master, slave]
        return path

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=1.0)
        for fd in getattr(self, "_fds", []):
            try:
                os.close(fd)
            except OSError:
                pass
        if hasattr(self, "_srv"):
            self._srv.close()
