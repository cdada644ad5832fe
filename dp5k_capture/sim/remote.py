"""The capture client's side of a simulated rig served by another process (:mod:`dp5k_capture.sim.server`).

:func:`connect_sim_rig` returns what a ``--sim`` capture needs: the rig (serials, projector port), a pyusb
backend whose devices forward every USB call to the server's bodies (the production transport, session
and EOS code run unchanged), the pattern window (a local headless one whose frames go down the HDMI cable,
a shared-memory framebuffer), the board positioner and the ground-truth writer. A server that goes away
looks like an unplugged body (ENODEV).
"""

from __future__ import annotations

import contextlib
import errno
import mmap
import os
import threading
from dataclasses import dataclass, replace
from multiprocessing.connection import Client, Connection
from pathlib import Path
from typing import Any

import numpy as np
import usb.core
from numpy.typing import NDArray

from dp5k_common.errors import DeviceError
from dp5k_common.io import new_file_mode

from ..display import PatternWindow
from ..rig import RigConfig
from .usb_backend import SimUsbBackend

SHM_DIR = "/dev/shm"  # where POSIX shared memory lives on Linux


class _Link:
    """One request/reply connection to the server, safe against Ctrl-C and shared by threads.

    Each request carries a sequence number and its reply echoes it. A call interrupted between sending and
    receiving (Ctrl-C at any moment, e.g. while a hung body is waited for) leaves its reply, or half of a
    message, in the socket: that connection is out of step, so the next call opens a fresh one to the
    server (the bodies live there and keep their state) instead of reading someone else's reply. A lock keeps
    the keep-alive thread and the main thread from interleaving on one socket.
    """

    def __init__(self, conn: Connection, where: str, socket_path: Path | None = None) -> None:
        self.conn = conn
        self.where = where
        self.socket_path = socket_path
        self._seq = 0
        self._out_of_step = False
        self._lock = threading.Lock()

    def _reconnect(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()
        if self.socket_path is None:
            raise usb.core.USBError("No such device (the link to the sim-rig server was interrupted)", None, errno.ENODEV)
        try:
            self.conn = Client(str(self.socket_path), family="AF_UNIX")
        except OSError as exc:
            raise usb.core.USBError("No such device (the sim-rig server went away)", None, errno.ENODEV) from exc
        self._out_of_step = False

    def call(self, *msg: Any) -> Any:
        with self._lock:
            if self._out_of_step:
                self._reconnect()
            self._seq += 1
            seq = self._seq
            try:
                self.conn.send(("call", seq, msg))
                while True:
                    got, reply = self.conn.recv()
                    if got == seq:
                        break
            except (EOFError, OSError) as exc:
                self._out_of_step = True
                raise usb.core.USBError("No such device (the sim-rig server went away)", None, errno.ENODEV) from exc
            except BaseException:  # Ctrl-C (or anything) between send and reply: this socket is out of step
                self._out_of_step = True
                raise
        if reply[0] == "ok":
            return reply[1]
        if reply[0] == "usb_timeout":
            raise usb.core.USBTimeoutError(reply[1], None, errno.ETIMEDOUT)
        if reply[0] == "usb_error":
            raise usb.core.USBError(reply[1], reply[3] if len(reply) > 3 else None, reply[2])
        raise DeviceError(f"sim-rig server: {reply[1]}", where=self.where)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()


class RemoteUsbDevice:
    """A body of the server, with the interface :class:`~dp5k_capture.sim.usb_backend.SimUsbBackend` drives."""

    def __init__(self, link: _Link, cam_id: str, vid: int, pid: int, bus: int, address: int, max_packet: int) -> None:
        self.link, self.cam_id = link, cam_id
        self.vid, self.pid, self.bus, self.address, self.max_packet = vid, pid, bus, address, max_packet

    def _usb(self, method: str, *args: Any) -> Any:
        return self.link.call("usb", self.cam_id, method, args)

    def bulk_out(self, data: bytes) -> int:
        return int(self._usb("bulk_out", bytes(data)))

    def bulk_in(self, size: int, timeout_ms: int | None = None) -> bytes:
        return bytes(self._usb("bulk_in", size))

    def interrupt_in(self, size: int, timeout_ms: int | None = None) -> bytes:
        return bytes(self._usb("interrupt_in", size))

    def open(self) -> None:
        self._usb("open")

    def claim(self) -> None:
        self._usb("claim")

    def control(self, req_type: int, req: int, value: int, index: int, data: bytes | int) -> bytes | int:
        return self._usb("control", req_type, req, value, index, data)

    def clear_halt(self, ep: int) -> None:
        self._usb("clear_halt", ep)

    def _check_present(self) -> None:
        self._usb("_check_present")


class HdmiWindow:
    """The client's headless :class:`PatternWindow`, its every frame copied into the server's HDMI framebuffer.

    The server's shared-memory segment is mapped straight from ``/dev/shm`` (Linux), not attached through
    ``multiprocessing.shared_memory``: Python 3.11 registers every attached segment with the resource tracker,
    which unlinks it when this client exits, and a Ctrl-C between attaching and unregistering would remove
    the server's framebuffer for every later client.
    """

    def __init__(self, width: int, height: int, shm_name: str) -> None:
        self.width, self.height = width, height
        fd = os.open(f"{SHM_DIR}/{shm_name.lstrip('/')}", os.O_RDWR)
        try:
            self._map = mmap.mmap(fd, width * height)
        finally:
            os.close(fd)
        self._hdmi: NDArray[np.uint8] = np.ndarray((height, width), np.uint8, buffer=self._map)
        self.window = PatternWindow(width, height, display_index=0, settle_s=0.0, headless=True)

    @property
    def shown(self) -> int | None:
        return self.window.shown

    def show(self, image: NDArray[np.uint8], tag: int | None = None) -> None:
        self.window.show(image, tag)
        self._hdmi[:] = self.window.frame()

    def frame(self) -> NDArray[np.uint8]:
        return self.window.frame()

    def close(self) -> None:
        self.window.close()
        del self._hdmi
        self._map.close()


class RemoteBoard:
    """The studio's hands on the server: place the ChArUco board in pose ``view`` or take it away."""

    def __init__(self, link: _Link) -> None:
        self.link = link

    def place(self, view: int) -> None:
        self.link.call("board", "place", (view,))

    def clear(self) -> None:
        self.link.call("board", "clear", ())


@dataclass
class RemoteSimRig:
    """A connected sim-rig server: what :func:`dp5k_capture.session_run.capture_scene` opens for ``--sim``."""

    rig: RigConfig
    backend: SimUsbBackend
    window: HdmiWindow
    board: RemoteBoard
    describe: dict[str, Any]
    link: _Link

    def write_ground_truth_once(self, session_dir: Path) -> Path:
        """``ground_truth/`` written by the server, with the mode this client's umask gives new files."""
        return Path(self.link.call("ground_truth", str(Path(session_dir).resolve()), new_file_mode()))

    def status(self) -> dict[str, Any]:
        return dict(self.link.call("status"))

    def close(self) -> None:
        self.link.close()


def connect_sim_rig(socket_path: Path, base: RigConfig | None = None, faults: str = "") -> RemoteSimRig:
    """Connect to the sim-rig server at ``socket_path``; arm ``faults`` (``--sim-faults``) if given.

    The rig keeps ``base``'s exposure plan and ids; bodies (serials, raw sizes, focus points, intrinsics) and
    the projector (its pty) come from the server.

    Raises:
        DeviceError: no server listens there.
    """
    where = f"sim-rig {socket_path}"
    try:
        conn = Client(str(socket_path), family="AF_UNIX")
    except OSError as exc:
        raise DeviceError(f"no simulated rig serves there ({exc.strerror or exc}); start one with "
                          "python -m dp5k_capture.sim.server --socket PATH", where=where) from exc
    link = _Link(conn, where, Path(socket_path))
    hello = link.call("hello")
    if faults:
        link.call("faults", faults)
    srv: RigConfig = hello["rig"]
    rig = replace(base or RigConfig(), bodies=srv.bodies, projector=srv.projector)
    devices = [RemoteUsbDevice(link, *d) for d in hello["bodies"]]
    window = HdmiWindow(rig.projector.width, rig.projector.height, hello["hdmi"])
    return RemoteSimRig(rig, SimUsbBackend(devices), window, RemoteBoard(link), hello["describe"], link)  # type: ignore[arg-type]


__all__ = ["RemoteSimRig", "connect_sim_rig", "RemoteUsbDevice", "HdmiWindow"]
