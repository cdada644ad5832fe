"""The PTP session over pyusb against the simulated body: transactions, typed errors and USB faults."""

from __future__ import annotations

import pytest

from dp5k_capture.ptp.codes import Op, Resp
from dp5k_capture.ptp.errors import (
    DeviceBusyError,
    DisconnectedError,
    ProtocolError,
    PTPTimeoutError,
    ResponseError,
    StallError,
)
from dp5k_capture.ptp.session import PTPSession
from dp5k_capture.ptp.transport import UsbTransport
from dp5k_capture.sim.eos_body import CARD_IMAGE_FOLDER as IMAGE_FOLDER

from .conftest import Body


def test_standard_operations(body: Body) -> None:
    s = body.session
    info = s.get_device_info()  # allowed outside a session
    assert info.manufacturer == "Canon Inc." and info.model == "Canon EOS 5D Mark IV"
    assert info.vendor_extension_id == 6  # what a real 5D Mark IV reports: Canon is identified by USB VID
    s.open_session()
    assert s.get_storage_ids() == [0x00010001]
    assert s.get_storage_info(0x00010001).label == "EOS_DIGITAL"
    desc = s.get_device_prop_desc(0x5001)
    assert (desc.current, desc.form, desc.values) == (75, 1, [0, 100, 1])
    assert s.get_device_prop_value(0x5001) == bytes([75])
    with pytest.raises(ResponseError) as err:
        s.get_device_prop_desc(0xD101)
    assert err.value.code == Resp.DEVICE_PROP_NOT_SUPPORTED and "body SIM0001" in str(err.value)
    # a card capture gives an object to list, describe, get and delete
    body.core.props[0xD11C] = 2
    assert body.core.handle(Op.EOS_REMOTE_RELEASE_ON, (3, 1)).code == Resp.OK
    assert len(s.get_object_handles(0x00010001)) == 3  # DCIM, DCIM/100CANON and the image
    handles = s.get_object_handles(0x00010001, 0, IMAGE_FOLDER)
    assert len(handles) == 1 and s.get_object_handles(0x00010001, 0, 0xFFFFFFFF) == [0x9000_0000]  # root: DCIM
    oi = s.get_object_info(handles[0])
    data = s.get_object(handles[0])
    assert len(data) == oi.compressed_size and data == body.core.last_object_bytes
    assert s.get_partial_object(handles[0], 10, 20) == data[10:30]
    s.delete_object(handles[0])
    assert s.get_object_handles(0x00010001, 0, IMAGE_FOLDER) == []
    # a Response instead of the Data container (error in the data phase) is a typed error
    with pytest.raises(ResponseError, match="INVALID_OBJECT_HANDLE"):
        s.get_object(handles[0])


def test_transaction_ids_and_session_already_open(body: Body) -> None:
    s = body.session
    s.open_session()
    first = s._tid
    s.get_device_info()
    assert s._tid == first + 1
    s.open_session()  # SessionAlreadyOpen counts as success; OpenSession always uses tid 0
    assert s.session_id == 1


def test_busy_storm_is_retried_within_the_bound(body: Body) -> None:
    s = body.session
    s.open_session()
    body.core.faults.busy[Op.GET_STORAGE_IDS] = 5
    assert s.get_storage_ids() == [0x00010001]
    assert s.op_log.count(Op.GET_STORAGE_IDS) == 6
    body.core.faults.busy[Op.GET_STORAGE_IDS] = 1000
    with pytest.raises(DeviceBusyError) as err:
        s.get_storage_ids()
    assert "body SIM0001" in str(err.value) and "0x1004" in str(err.value)
    assert s.op_log.count(Op.GET_STORAGE_IDS) == 6 + s.config.busy_retries + 1


def test_stalled_pipe_is_recovered_and_the_transaction_retried(body: Body) -> None:
    s = body.session
    s.open_session()
    body.usb.faults.stall_in = 1
    assert s.get_storage_ids() == [0x00010001]
    assert not body.usb.halted
    body.usb.faults.stall_in = 5  # keeps stalling: stops after the bound with a named error
    with pytest.raises(StallError) as err:
        s.get_storage_ids()
    assert str(err.value).startswith("body SIM0001: GET_STORAGE_IDS: bulk IN: endpoint stalled")


def test_disconnect_in_the_middle_of_a_transfer(body: Body) -> None:
    s = body.session
    s.open_session()
    body.core.props[0xD11C] = 2
    body.core.handle(Op.EOS_REMOTE_RELEASE_ON, (3, 1))
    handle = s.get_object_handles(0xFFFFFFFF, 0, IMAGE_FOLDER)[0]
    body.usb.faults.disconnect_after_in_bytes = body.usb.in_bytes + 700  # inside GetObject's data phase
    with pytest.raises(DisconnectedError) as err:
        s.get_object(handle)
    assert str(err.value).startswith("body SIM0001: GET_OBJECT: ") and "disconnected" in str(err.value)


@pytest.mark.parametrize("fault", ["garble_next_in", "bad_length_next_in"])
def test_garbled_and_malformed_containers_are_protocol_errors(body: Body, fault: str) -> None:
    s = body.session
    s.open_session()
    setattr(body.usb.faults, fault, True)
    with pytest.raises(ProtocolError) as err:
        s.get_device_info()
    assert "body SIM0001" in str(err.value)
    assert s.get_storage_ids() == [0x00010001]  # the next transaction works again


def test_short_packet_and_lost_response_time_out_cleanly(body: Body) -> None:
    s = body.session
    s.open_session()
    body.usb.faults.short_next_in = True
    with pytest.raises((PTPTimeoutError, ProtocolError)) as err:
        s.get_storage_ids()
    assert "GET_STORAGE_IDS" in str(err.value)
    body.usb.faults.drop_next_response = True
    with pytest.raises(PTPTimeoutError, match="GET_STORAGE_IDS: .*timed out"):
        s.get_storage_ids()
    assert s.get_storage_ids() == [0x00010001]


class _MergedReads:
    """A transport seam that returns data + response in one read (what libgphoto2's vcamera does)."""

    def __init__(self, inner: UsbTransport, dev) -> None:  # noqa: ANN001
        self.inner, self.dev, self.name, self.max_packet = inner, dev, inner.name, inner.max_packet

    def write(self, data: bytes, timeout_ms: int) -> None:
        self.inner.write(data, timeout_ms)

    def read(self, size: int, timeout_ms: int) -> bytes:
        out = bytearray()
        while self.dev._in and len(out) < size:
            out += self.dev.bulk_in(size - len(out))
        return bytes(out) if out else self.inner.read(size, timeout_ms)

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self.inner, name)


def test_data_and_response_in_one_read_and_stale_responses(body: Body) -> None:
    s = PTPSession(_MergedReads(body.transport, body.usb), body.session.config)
    s.open_session()
    assert s.get_device_info().model == "Canon EOS 5D Mark IV"
    # a stale response of an older transaction is skipped
    body.usb._queue_response(Resp.OK, 0, ())
    assert s.get_storage_ids() == [0x00010001]


def test_class_requests(body: Body) -> None:
    s = body.session
    s.open_session()
    assert s.device_status() == Resp.OK
    s.cancel()
    s.reset()
    assert not body.core.session_open and s.session_id is None


class _RandomWire:
    """A transport whose bulk IN delivers arbitrary bytes in arbitrary chunks, then times out."""

    name = "fuzz body"
    max_packet = 512

    def __init__(self, chunks: list[bytes]) -> None:
        self.chunks = list(chunks)

    def write(self, data: bytes, timeout_ms: int) -> None:
        pass

    def read(self, size: int, timeout_ms: int) -> bytes:
        if not self.chunks:
            raise PTPTimeoutError("bulk IN: timed out", where=self.name)
        c = self.chunks.pop(0)
        if len(c) > size:
            self.chunks.insert(0, c[size:])
            c = c[:size]
        return c

    def cancel(self, tid: int) -> None:
        pass


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from dp5k_common.errors import DeviceError  # noqa: E402


@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(max_size=64), max_size=6), st.booleans())
def test_session_survives_garbled_streams(chunks: list[bytes], data_in: bool) -> None:
    """Whatever arrives on bulk IN, a transaction ends in a result or a DeviceError naming the device."""
    from dp5k_capture.ptp.session import SessionConfig

    s = PTPSession(_RandomWire(chunks), SessionConfig(max_data_bytes=1 << 16, busy_retries=2, busy_delay_s=0.0))
    try:
        s.transaction(Op.GET_DEVICE_INFO, data_in=data_in)
    except DeviceError as exc:
        assert "fuzz body" in str(exc)


def test_superspeed_packets_never_overflow_the_read_buffer() -> None:
    """USB 3 bodies send 1024-byte packets: every read must be a whole number of packets."""
    b = Body()
    b.usb.max_packet = 1024
    from dp5k_capture.ptp.transport import UsbTransport as _T

    s = PTPSession(_T(b.device, "usb3 body"), b.session.config)
    assert s.transport.max_packet == 1024
    s.open_session()
    assert s.get_device_info().model == "Canon EOS 5D Mark IV"
    b.core.props[0xD11C] = 2
    b.core.handle(Op.EOS_REMOTE_RELEASE_ON, (3, 1))
    h = s.get_object_handles(0xFFFFFFFF, 0, IMAGE_FOLDER)[0]
    assert s.get_object(h) == b.core.last_object_bytes
