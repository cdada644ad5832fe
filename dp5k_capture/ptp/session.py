"""PTP sessions and transactions over a :class:`~dp5k_capture.ptp.transport.Transport`.

A transaction is Command (bulk OUT) -> optional Data (OUT or IN) -> Response (bulk IN). This module keeps
transaction ids (OpenSession uses id 0, each later transaction the next one), parses the bulk-IN side as a
stream split by ContainerLength (data and response may arrive in one read, a Response may replace the
Data container), skips stale responses, retries DeviceBusy within a bound, recovers a stalled pipe
(Get Device Status, Clear Halt, retry once) and turns response codes into typed errors that name the
device and the operation.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from dp5k_common.errors import DeviceError

from .codes import ContainerType, Op, Resp, name_of
from .container import HEADER_LEN, MAX_CONTAINER_BYTES, Container, Header, parse_header, parse_params
from .datasets import DeviceInfo, DevicePropDesc, ObjectInfo, StorageInfo, parse_u32_array
from .errors import DeviceBusyError, DisconnectedError, PTPTimeoutError, ProtocolError, ResponseError, StallError
from .transport import Transport

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionConfig:
    """Timeouts and bounds of a PTP session.

    Attributes:
        timeout_s: per-phase timeout.
        busy_retries: how many times a DeviceBusy (0x2019) answer is retried before giving up.
        busy_delay_s: first wait after DeviceBusy; doubles up to ``busy_delay_max_s``.
        stall_retries: how many times a transaction is retried after recovering a stalled pipe.
        max_data_bytes: the largest data phase accepted (longer claimed lengths are a ProtocolError).
        first_read: size of the first read of each container (one high-speed packet, as libgphoto2 does).
        chunk_read: size of the following reads of a long data phase.
        close_session: send CloseSession on close (False for bodies that break on it, e.g. the 5D Mark IV).
        open_attempts: OpenSession tries; between two, Device Reset (0x66) and a drain of stale bulk-IN data.
        drain_timeout_s: a drain read that waits this long for data ends the drain (the pipe is empty).
    """

    timeout_s: float = 5.0
    busy_retries: int = 30
    busy_delay_s: float = 0.05
    busy_delay_max_s: float = 1.0
    stall_retries: int = 1
    max_data_bytes: int = 256 << 20
    first_read: int = 512
    chunk_read: int = 1 << 20
    close_session: bool = True
    open_attempts: int = 3
    drain_timeout_s: float = 0.2


@dataclass(frozen=True)
class Result:
    """What a transaction returned: the response code and params and the IN data (if any)."""

    code: int
    params: tuple[int, ...]
    data: bytes = b""


class PTPSession:
    """One PTP session with one device.

    Args:
        transport: the wire (USB or the test seam).
        config: timeouts and bounds.
    """

    def __init__(self, transport: Transport, config: SessionConfig | None = None) -> None:
        self.transport = transport
        self.config = config or SessionConfig()
        self.name = transport.name
        self.session_id: int | None = None
        self._tid = 0
        self._pending = bytearray()
        self.op_log: list[int] = []
        self.unfinished_tid: int | None = None  # a transaction left mid-way (Ctrl-C, an error): close() cancels it

    # ------------------------------------------------------------------ low level
    def _next_tid(self) -> int:
        tid = self._tid
        self._tid = (self._tid + 1) & 0xFFFFFFFF
        return tid

    def _timeout_ms(self, timeout_s: float | None) -> int:
        return int(1000 * (timeout_s if timeout_s is not None else self.config.timeout_s))

    def _fill(self, need: int, size: int, timeout_ms: int) -> None:
        """Read from bulk IN until ``_pending`` holds ``need`` bytes (zero-length packets are skipped, bounded)."""
        empty = 0
        while len(self._pending) < need:
            chunk = self.transport.read(size, timeout_ms)
            if not chunk:
                empty += 1
                if empty > 4:
                    raise ProtocolError("device sent only zero-length packets", where=self.name)
                continue
            self._pending += chunk

    def _read_container(self, timeout_ms: int, expect_data: bool) -> tuple[Header, bytes]:
        """Read one whole container from the bulk-IN stream; returns its header and body bytes."""
        # a read shorter than one packet overflows when the device sends a full packet (USB 3: 1024 bytes)
        self._fill(HEADER_LEN, max(self.config.first_read, self.transport.max_packet), timeout_ms)
        peek = parse_header(self._pending, max_length=MAX_CONTAINER_BYTES, where=self.name)
        bound = self.config.max_data_bytes + HEADER_LEN if peek.type == ContainerType.DATA else HEADER_LEN + 20
        if peek.type == ContainerType.DATA and peek.length == 0xFFFFFFFF:
            return peek, self._read_until_short(timeout_ms)
        hdr = parse_header(self._pending, max_length=bound, where=self.name)
        while len(self._pending) < hdr.length:  # body arrives as it comes: nothing is pre-allocated from hdr.length
            want = min(self.config.chunk_read, hdr.length - len(self._pending))
            want = -(-want // self.transport.max_packet) * self.transport.max_packet
            self._fill(len(self._pending) + 1, want, timeout_ms)
        body = bytes(self._pending[HEADER_LEN : hdr.length])
        del self._pending[: hdr.length]
        return hdr, body

    def _read_until_short(self, timeout_ms: int) -> bytes:
        """Data of unknown length (0xFFFFFFFF): read until a short packet (bounded by ``max_data_bytes``)."""
        data = bytearray(self._pending[HEADER_LEN:])
        self._pending.clear()
        while True:
            chunk = self.transport.read(self.config.chunk_read, timeout_ms)
            data += chunk
            if len(data) > self.config.max_data_bytes:
                raise ProtocolError(f"data phase longer than the bound {self.config.max_data_bytes}", where=self.name)
            if len(chunk) < self.config.chunk_read:
                return bytes(data)

    def _once(self, op: int, params: tuple[int, ...], data_out: bytes | None, data_in: bool, tid: int, timeout_ms: int) -> Result:
        self._pending.clear()
        self.transport.write(Container(ContainerType.COMMAND, op, tid, params).pack(), timeout_ms)
        if data_out is not None:
            self.transport.write(Container(ContainerType.DATA, op, tid, (), data_out).pack(), timeout_ms)
        data = b""
        for _ in range(8):  # bounded: stale responses of earlier transactions are skipped
            hdr, body = self._read_container(timeout_ms, data_in)
            if hdr.type == ContainerType.DATA:
                if hdr.tid != tid or hdr.code != op:
                    raise ProtocolError(f"data container for op 0x{hdr.code:04X} tid {hdr.tid}, expected 0x{op:04X} tid {tid}", where=self.name)
                if not data_in:
                    raise ProtocolError(f"unexpected data phase for op 0x{op:04X}", where=self.name)
                data = body
                continue
            if hdr.type == ContainerType.RESPONSE:
                rparams = parse_params(hdr, body, where=self.name)
                if hdr.tid != tid:
                    log.debug("%s: skipping stale response tid %d (waiting for %d)", self.name, hdr.tid, tid)
                    continue
                return Result(hdr.code, rparams, data)
            raise ProtocolError(f"unexpected container type {hdr.type} on bulk IN", where=self.name)
        raise ProtocolError(f"no response with transaction id {tid}", where=self.name)

    def recover(self, step: str) -> None:
        """Recover a stalled pipe: Get Device Status, Clear Halt on both bulk endpoints, wait for OK."""
        log.warning("%s: %s: recovering a stalled pipe", self.name, step)
        try:
            self.transport.device_status()
        except StallError:
            pass
        self.transport.clear_halt()
        for _ in range(20):
            status = self.transport.device_status()
            if status == Resp.OK:
                self._pending.clear()
                return
            time.sleep(0.05)
        raise StallError(f"{step}: device status stayed 0x{status:04X} after clearing the halt", where=self.name)

    def transaction(
        self,
        op: int,
        params: tuple[int, ...] | list[int] = (),
        *,
        data_out: bytes | None = None,
        data_in: bool = False,
        timeout_s: float | None = None,
        ok: tuple[int, ...] = (Resp.OK,),
    ) -> Result:
        """Run one transaction; retries DeviceBusy and one stall; raises a typed error otherwise.

        Args:
            op: operation code.
            params: up to 5 u32 parameters.
            data_out: host -> device data phase.
            data_in: the operation has a device -> host data phase.
            ok: response codes accepted as success.
        """
        step = name_of(Op, op)
        if self.unfinished_tid is not None:  # the last transaction was cut off (Ctrl-C, an error mid-read): its
            self.abort_unfinished()  # data would answer this one, so cancel it and drain the pipe first
        timeout_ms = self._timeout_ms(timeout_s)
        delay = self.config.busy_delay_s
        stalls = 0
        busy = 0
        while True:
            tid = self._next_tid()
            self.op_log.append(op)
            try:
                self.unfinished_tid = tid
                res = self._once(op, tuple(params), data_out, data_in, tid, timeout_ms)
                self.unfinished_tid = None
            except StallError as exc:
                stalls += 1
                if stalls > self.config.stall_retries:
                    exc.message = f"{step}: {exc.message}"
                    raise
                self.recover(step)
                continue
            except PTPTimeoutError as exc:
                try:  # leave the pipe in a known state for the next transaction
                    self.transport.cancel(tid)
                except DeviceError:
                    pass
                raise PTPTimeoutError(f"{step}: {exc.message} after {timeout_ms / 1000:g} s", where=self.name) from exc
            except DeviceError as exc:
                if not exc.message.startswith(step):
                    exc.message = f"{step}: {exc.message}"
                raise
            if res.code == Resp.DEVICE_BUSY:
                busy += 1
                if busy > self.config.busy_retries:
                    raise DeviceBusyError(res.code, op, where=self.name)
                time.sleep(delay)
                delay = min(delay * 2, self.config.busy_delay_max_s)
                continue
            if res.code not in ok:
                raise ResponseError(res.code, op, where=self.name)
            return res

    # ------------------------------------------------------------------ standard operations
    def open_session(self, session_id: int = 1) -> None:
        """OpenSession with transaction id 0; SessionAlreadyOpen counts as success.

        A body whose last client died mid-transaction (killed, Ctrl-C, unplugged cable) may still hold a
        half-sent data phase, a halted pipe or an open session. As libgphoto2 does on open: clear the halts
        first; when OpenSession fails, send the Still Image class Device Reset (0x66), drain the stale bulk-IN
        data in big reads until a read times out, and try again (``open_attempts`` in all).
        """
        try:
            self.transport.clear_halt()
        except DisconnectedError:
            raise
        except DeviceError as exc:
            log.debug("%s: clear halt before OpenSession: %s", self.name, exc)
        for attempt in range(1, self.config.open_attempts + 1):
            self._tid = 0
            try:
                self.transaction(Op.OPEN_SESSION, (session_id,), ok=(Resp.OK, Resp.SESSION_ALREADY_OPEN))
                break
            except DisconnectedError:
                raise
            except DeviceError as exc:
                if attempt == self.config.open_attempts:
                    exc.message = f"{exc.message} (after {attempt} tries, each after a Device Reset and a drain)"
                    raise
                log.warning("%s: OpenSession failed (%s): Device Reset, draining stale data, retrying", self.name, exc.message)
                self.transport.device_reset()
                self.drain()
        self.unfinished_tid = None
        self.session_id = session_id

    def drain(self) -> int:
        """Read and drop what the device still has queued on bulk IN, in ``chunk_read`` reads (1 MiB: a stale
        GetPartialObject chunk goes in one read, not 2,000 of 512 bytes) until one times out; bounded by
        ``max_data_bytes``. Returns the number of bytes dropped."""
        self._pending.clear()
        dropped = 0
        timeout_ms = self._timeout_ms(self.config.drain_timeout_s)
        while dropped <= self.config.max_data_bytes:
            try:
                chunk = self.transport.read(self.config.chunk_read, timeout_ms)
            except PTPTimeoutError:
                break
            if not chunk:
                break
            dropped += len(chunk)
        if dropped:
            log.warning("%s: dropped %d bytes of stale bulk-IN data", self.name, dropped)
        return dropped

    def abort_unfinished(self) -> None:
        """Cancel (0x64) a transaction left mid-way (Ctrl-C during a download) and drain its data, so the
        next transaction starts on a clean pipe. Errors are logged: this runs while closing."""
        tid = self.unfinished_tid
        if tid is None:
            return
        self.unfinished_tid = None
        try:
            self.transport.cancel(tid)
            self.drain()
        except DeviceError as exc:
            log.warning("%s: cancelling the interrupted transaction %d: %s", self.name, tid, exc)

    def close_session(self) -> None:
        """CloseSession, unless the config says this body must never get it."""
        if self.session_id is not None and self.config.close_session:
            self.transaction(Op.CLOSE_SESSION)
        self.session_id = None

    def get_device_info(self) -> DeviceInfo:
        return DeviceInfo.parse(self.transaction(Op.GET_DEVICE_INFO, data_in=True).data, where=self.name)

    def get_storage_ids(self) -> list[int]:
        return parse_u32_array(self.transaction(Op.GET_STORAGE_IDS, data_in=True).data, where=self.name, what="StorageIDs")

    def get_storage_info(self, storage_id: int) -> StorageInfo:
        return StorageInfo.parse(self.transaction(Op.GET_STORAGE_INFO, (storage_id,), data_in=True).data, where=self.name)

    def get_object_handles(self, storage_id: int = 0xFFFFFFFF, ofc: int = 0, parent: int = 0) -> list[int]:
        res = self.transaction(Op.GET_OBJECT_HANDLES, (storage_id, ofc, parent), data_in=True)
        return parse_u32_array(res.data, where=self.name, what="ObjectHandles")

    def get_object_info(self, handle: int) -> ObjectInfo:
        return ObjectInfo.parse(self.transaction(Op.GET_OBJECT_INFO, (handle,), data_in=True).data, where=self.name)

    def get_object(self, handle: int, timeout_s: float | None = None) -> bytes:
        return self.transaction(Op.GET_OBJECT, (handle,), data_in=True, timeout_s=timeout_s).data

    def get_partial_object(self, handle: int, offset: int, max_bytes: int) -> bytes:
        res = self.transaction(Op.GET_PARTIAL_OBJECT, (handle, offset, max_bytes), data_in=True)
        if res.params and res.params[0] != len(res.data):
            raise ProtocolError(f"GetPartialObject says {res.params[0]} bytes, sent {len(res.data)}", where=self.name)
        return res.data

    def delete_object(self, handle: int) -> None:
        self.transaction(Op.DELETE_OBJECT, (handle, 0))

    def get_device_prop_desc(self, prop: int) -> DevicePropDesc:
        return DevicePropDesc.parse(self.transaction(Op.GET_DEVICE_PROP_DESC, (prop,), data_in=True).data, where=self.name)

    def get_device_prop_value(self, prop: int) -> bytes:
        return self.transaction(Op.GET_DEVICE_PROP_VALUE, (prop,), data_in=True).data

    def cancel(self) -> None:
        """Still Image class request Cancel for the last transaction."""
        self.transport.cancel((self._tid - 1) & 0xFFFFFFFF)

    def reset(self) -> None:
        """Still Image class request Device Reset; the session is closed by the device."""
        self.transport.device_reset()
        self.session_id = None
        self._pending.clear()

    def device_status(self) -> int:
        return self.transport.device_status()
