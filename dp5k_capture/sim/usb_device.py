"""USB framing of the simulated body: PTP bulk containers in and out, class requests, USB faults.

:class:`SimUsbPtpDevice` turns bulk-OUT bytes into operations for a :class:`SimulatedEOS` and queues the
data and response containers on bulk IN, one USB transfer per container (a read never spans two). It also
answers the Still Image class requests and string descriptors, and injects USB faults on request:
disconnect after N bytes of bulk IN, stalls, DeviceBusy storms (via the body), short, garbled and
malformed containers. Like a real body, it keeps what it was sending when its client dies: a new client
first reads that stale half-sent data phase, until a Cancel (0x64) or Device Reset (0x66) clears it.

Errors carry libusb's error codes as pyusb's libusb1 backend raises them (``errno`` and
``backend_error_code``): no permission on the device node (``access_denied``: EACCES, -3, as without a udev
rule), an interface claimed by another process (``held_by``: EBUSY, -6, as while gvfs or gphoto2 holds
the body), a disconnect (ENODEV, -4), a stall (EPIPE, -9). With ``blocking``, a bulk-IN read that has nothing
to return waits out its timeout with SIGINT held back, as libusb's synchronous transfer does (it retries
its poll on EINTR), so a Ctrl-C is seen only when the read returns.
"""

from __future__ import annotations

import errno
import signal
import struct
import time
from collections import deque
from dataclasses import dataclass

import usb.core

from ..ptp.codes import CANON_VID, EOS_5D_MARK_IV_PID, ContainerType, Op, Resp
from ..ptp.container import HEADER, HEADER_LEN
from .eos_body import DATA_OUT_OPS, SimulatedEOS
from .fault_spec import BodyFaultPlan

EP_IN, EP_OUT, EP_INT = 0x81, 0x02, 0x83
# errno -> libusb error code (libusb.h), as pyusb's libusb1 backend pairs them in USBError
LIBUSB_CODES = {errno.EIO: -1, errno.EACCES: -3, errno.ENODEV: -4, errno.EBUSY: -6, errno.ETIMEDOUT: -7,
                errno.EOVERFLOW: -8, errno.EPIPE: -9}


@dataclass
class UsbFaults:
    """USB-level faults (each fires once, then clears itself unless noted).

    Attributes:
        disconnect_after_in_bytes: after this many more bulk-IN bytes the device vanishes (ENODEV, sticky).
        stall_in: stall the next N bulk-IN reads (EPIPE) until the host clears the halt.
        garble_next_in: flip the container type of the next bulk-IN container to 7.
        short_next_in: cut the next bulk-IN container to 5 bytes (a short packet, then nothing).
        bad_length_next_in: claim a 3 GiB length in the next data container's header.
        drop_next_response: the next response container never comes (the host times out).
    """

    disconnect_after_in_bytes: int | None = None
    stall_in: int = 0
    garble_next_in: bool = False
    short_next_in: bool = False
    bad_length_next_in: bool = False
    drop_next_response: bool = False


class SimHang(Exception):
    """The body stopped sending in the middle of a data phase (``hang@K``): this read is never answered."""


class SimUsbPtpDevice:
    """One simulated USB PTP device (VID/PID of a 5D Mark IV by default) around a PTP core."""

    def __init__(self, core: SimulatedEOS, *, vid: int = CANON_VID, pid: int = EOS_5D_MARK_IV_PID,
                 bus: int = 1, address: int = 10, max_packet: int = 512, blocking: bool = False) -> None:
        self.core = core
        self.vid, self.pid, self.bus, self.address = vid, pid, bus, address
        self.max_packet = max_packet
        self.faults = UsbFaults()
        self.strings = {1: "Canon Inc.", 2: core.MODEL, 3: core.serial}
        self._out = bytearray()
        self._pending_cmd: tuple[int, int, tuple[int, ...]] | None = None
        self._in: deque[bytearray] = deque()
        self.gone = False
        self.halted = False
        self.in_bytes = 0
        self.resets = 0  # Still Image Device Reset requests received
        self.plan = BodyFaultPlan()
        self.downloads = 0  # raw files started (GetObject, or GetPartialObject at offset 0)
        self.hang_after_in_bytes: int | None = None
        self.blocking = blocking
        self.access_denied = False  # the device node is not ours (no udev rule): opening it fails (EACCES)
        self.held_by: str | None = None  # another process has claimed the PTP interface: claiming fails (EBUSY)

    # ------------------------------------------------------------------ faults
    def _usb_error(self, code: int, text: str) -> usb.core.USBError:
        return usb.core.USBError(text, LIBUSB_CODES.get(code), code)

    def _check_present(self) -> None:
        if self.gone:
            raise self._usb_error(errno.ENODEV, "No such device (it may have been disconnected)")

    def open(self) -> None:
        """libusb_open: needs read-write access to the device node."""
        self._check_present()
        if self.access_denied:
            raise self._usb_error(errno.EACCES, "Access denied (insufficient permissions)")

    def claim(self) -> None:
        """libusb_claim_interface: fails while another process holds the interface."""
        self.open()
        if self.held_by is not None:
            raise self._usb_error(errno.EBUSY, "Resource busy")

    def arm(self, plan: BodyFaultPlan) -> None:
        """Arm a ``--sim-faults`` plan: download faults count from now, ``full@K`` from the next release."""
        self.plan, self.downloads = plan, 0
        self.core.faults.busy_rate = plan.busy_rate
        self.core.faults.full_from_release = None if plan.full_at_release is None else self.core.releases + plan.full_at_release
        self.access_denied = plan.denied
        self.held_by = "another process" if plan.held else None

    def _block(self, timeout_ms: int | None) -> None:
        """Wait out a read's timeout like libusb's synchronous transfer: SIGINT is held back until it returns."""
        if not self.blocking or not timeout_ms:
            return
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            time.sleep(timeout_ms / 1000.0)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    # ------------------------------------------------------------------ bulk
    def bulk_out(self, data: bytes) -> int:
        self._check_present()
        if self.halted:
            raise self._usb_error(errno.EPIPE, "Pipe error")
        if not data:
            return 0  # zero-length packet
        self._out += data
        while len(self._out) >= HEADER_LEN:
            length, ctype, code, tid = HEADER.unpack_from(self._out)
            if length < HEADER_LEN or length > (64 << 20):
                self._out.clear()
                self._queue_response(Resp.GENERAL_ERROR, tid, ())
                return len(data)
            if len(self._out) < length:
                break
            body = bytes(self._out[HEADER_LEN:length])
            del self._out[:length]
            self._container(ctype, code, tid, body)
        return len(data)

    def _container(self, ctype: int, code: int, tid: int, body: bytes) -> None:
        if ctype == ContainerType.COMMAND:
            if len(body) % 4 or len(body) > 20:
                self._queue_response(Resp.GENERAL_ERROR, tid, ())
                return
            params = struct.unpack(f"<{len(body) // 4}I", body)
            if code in DATA_OUT_OPS:
                self._pending_cmd = (code, tid, params)
                return
            self._run(code, tid, params, None)
        elif ctype == ContainerType.DATA and self._pending_cmd is not None:
            op, ptid, params = self._pending_cmd
            self._pending_cmd = None
            if ptid != tid or op != code:
                self._queue_response(Resp.INVALID_TRANSACTION_ID, tid, ())
                return
            self._run(op, tid, params, body)
        else:
            self._queue_response(Resp.GENERAL_ERROR, tid, ())

    def _run(self, op: int, tid: int, params: tuple[int, ...], data: bytes | None) -> None:
        reply = self.core.handle(op, params, data)
        if reply.data is not None and reply.code == Resp.OK:
            if op == Op.GET_OBJECT or (op == Op.GET_PARTIAL_OBJECT and len(params) > 1 and params[1] == 0):
                self._arm_download_faults(HEADER_LEN + len(reply.data))
            self._in.append(bytearray(HEADER.pack(HEADER_LEN + len(reply.data), ContainerType.DATA, op, tid) + reply.data))
        if self.faults.drop_next_response:
            self.faults.drop_next_response = False
            return
        self._queue_response(reply.code, tid, reply.params)

    def _arm_download_faults(self, container_bytes: int) -> None:
        """Count a new raw download; arm the :class:`BodyFaultPlan` faults planned for it (halfway through)."""
        self.downloads += 1
        halfway = self.in_bytes + sum(len(c) for c in self._in) + container_bytes // 2
        if self.plan.disconnect_at_download == self.downloads:
            self.faults.disconnect_after_in_bytes = halfway
        if self.plan.hang_at_download == self.downloads:
            self.hang_after_in_bytes = halfway
        if self.plan.stall_at_download == self.downloads:
            self.faults.stall_in = 1

    def _queue_response(self, code: int, tid: int, params: tuple[int, ...]) -> None:
        body = struct.pack(f"<{len(params)}I", *params)
        self._in.append(bytearray(HEADER.pack(HEADER_LEN + len(body), ContainerType.RESPONSE, code, tid) + body))

    def bulk_in(self, size: int, timeout_ms: int | None = None) -> bytes:
        """One bulk-IN transfer of at most ``size`` bytes; ``timeout_ms`` matters only in blocking mode."""
        self._check_present()
        if self.faults.stall_in > 0 or self.halted:
            if self.faults.stall_in > 0:
                self.faults.stall_in -= 1
                self._in.clear()  # the device halts the pipe and drops the transaction it was sending
            self.halted = True
            raise self._usb_error(errno.EPIPE, "Pipe error")
        if not self._in:
            self._block(timeout_ms)
            raise usb.core.USBTimeoutError("Operation timed out", LIBUSB_CODES[errno.ETIMEDOUT], errno.ETIMEDOUT)
        cur = self._in[0]
        if self.faults.garble_next_in:
            self.faults.garble_next_in = False
            struct.pack_into("<H", cur, 4, 7)
        if self.faults.bad_length_next_in and cur[4] == ContainerType.DATA:
            self.faults.bad_length_next_in = False
            struct.pack_into("<I", cur, 0, 3 << 30)
        if self.faults.short_next_in:
            self.faults.short_next_in = False
            self._in.popleft()
            return bytes(cur[:5])
        if size % self.max_packet and len(cur) > size:  # libusb: a full packet into a shorter buffer overflows
            raise self._usb_error(errno.EOVERFLOW, "Overflow")
        n = min(size, len(cur))
        if self.hang_after_in_bytes is not None:
            left = self.hang_after_in_bytes - self.in_bytes
            if left <= 0:
                if self.blocking:  # in-process: the read waits out its timeout, the body never sends the rest
                    self._block(timeout_ms)
                    raise usb.core.USBTimeoutError("Operation timed out", LIBUSB_CODES[errno.ETIMEDOUT], errno.ETIMEDOUT)
                self.hang_after_in_bytes = None
                raise SimHang(f"{self.core.serial}: hanging in download {self.downloads}")
            n = min(n, left)
        if self.faults.disconnect_after_in_bytes is not None:
            left = self.faults.disconnect_after_in_bytes - self.in_bytes
            if left <= 0:
                self.gone = True
                self._check_present()
            n = min(n, left)
        out = bytes(cur[:n])
        del cur[:n]
        if not cur:
            self._in.popleft()
        self.in_bytes += n
        return out

    def interrupt_in(self, size: int, timeout_ms: int | None = None) -> bytes:
        self._check_present()
        self._block(timeout_ms)
        raise usb.core.USBTimeoutError("Operation timed out", LIBUSB_CODES[errno.ETIMEDOUT], errno.ETIMEDOUT)

    # ------------------------------------------------------------------ control
    def control(self, req_type: int, req: int, value: int, index: int, data: bytes | int) -> bytes | int:
        """Still Image class requests and GET_DESCRIPTOR(string); returns IN bytes or OUT length."""
        self._check_present()
        if req_type == 0x80 and req == 0x06 and value >> 8 == 3:  # string descriptor
            idx = value & 0xFF
            if idx == 0:
                return bytes([4, 3, 0x09, 0x04])
            text = self.strings.get(idx, "")
            raw = text.encode("utf-16-le")
            return (bytes([2 + len(raw), 3]) + raw)[: int(data)]
        if req_type == 0x21 and req == 0x64:  # Cancel
            self._in.clear()
            self._out.clear()
            self._pending_cmd = None
            return len(data) if isinstance(data, (bytes, bytearray)) else 0
        if req_type == 0x21 and req == 0x66:  # Device Reset
            self.resets += 1
            self._in.clear()
            self._out.clear()
            self._pending_cmd = None
            self.core.session_open = False
            return 0
        if req_type == 0xA1 and req == 0x67:  # Get Device Status
            code = Resp.TRANSACTION_CANCELLED if self.halted else Resp.OK
            return struct.pack("<HH", 4, code)
        raise self._usb_error(errno.EPIPE, "Pipe error")

    def clear_halt(self, ep: int) -> None:
        """CLEAR_FEATURE(ENDPOINT_HALT): the pipe runs again; data the body still holds stays queued."""
        self._check_present()
        self.halted = False

    def unplug(self) -> None:
        self.gone = True
