"""Containers, datasets and EOS event records: round trips, and bounded parsing of hostile bytes."""

from __future__ import annotations

import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dp5k_capture.ptp import eos_events as ev
from dp5k_capture.ptp.codes import ContainerType, EosEvent, EosProp, av_code, iso_code, tv_code
from dp5k_capture.ptp.container import Container, parse_container, parse_header
from dp5k_capture.ptp.datasets import DeviceInfo, DevicePropDesc, ObjectInfo, StorageInfo, parse_u32_array
from dp5k_capture.ptp.errors import ProtocolError


def test_canon_exposure_codes_match_libgphoto2_tables() -> None:
    assert [av_code(f) for f in (1.8, 2, 2.8, 4, 5.6, 22)] == [0x15, 0x18, 0x20, 0x28, 0x30, 0x50]
    assert av_code(16) == 0x48  # not f/22
    assert tv_code(1 / 60) == 0x68 and tv_code(1.0) == 0x38 and tv_code(1 / 8000) == 0xA0
    assert iso_code(100) == 0x48 and iso_code(6400) == 0x78
    with pytest.raises(ValueError):
        av_code(1.7)


def test_command_container_bytes_match_the_recorded_sx200_open_session() -> None:
    # umockdev recording, first bulk OUT URB: OpenSession(1), transaction id 0
    assert Container(ContainerType.COMMAND, 0x1002, 0, (1,)).pack().hex() == "10000000010002100000000001000000"
    c = parse_container(bytes.fromhex("0C0000000300012000000000"))
    assert (c.type, c.code, c.tid, c.params) == (ContainerType.RESPONSE, 0x2001, 0, ())


def test_dataset_round_trips() -> None:
    info = DeviceInfo(vendor_extension_id=6, operations=[0x1001, 0x9110], manufacturer="Canon Inc.",
                      model="Canon EOS 5D Mark IV", serial_number="00ab")
    assert DeviceInfo.parse(info.pack()) == info
    oi = ObjectInfo(storage_id=0x10001, object_format=0x3811, compressed_size=123, filename="IMG_0001.DNG")
    assert ObjectInfo.parse(oi.pack()) == oi
    si = StorageInfo(3, 2, 0, 1 << 36, 1 << 35, 900, "SD", "EOS_DIGITAL")
    assert StorageInfo.parse(si.pack()) == si
    dpd = DevicePropDesc(0x5001, 2, False, 100, 80, 2, [0, 50, 100])
    assert DevicePropDesc.parse(dpd.pack()) == dpd


def test_eos_event_records_parse() -> None:
    data = (ev.pack_prop_value(EosProp.APERTURE, 0x15) + ev.pack_avail_list(EosProp.ISO, [0x48, 0x50])
            + ev.pack_prop_value(EosProp.SERIAL_NUMBER, "012021000417")
            + ev.pack_request_object_transfer(0x90000001, 0x3811, 4242, "IMG_0001.DNG")
            + ev.pack_object_added_ex(0x90000002, 0x10001, 0x3811, 77, 0x90000000, "IMG_0002.DNG")
            + ev.pack_image_format_value(EosProp.IMAGE_FORMAT, 6, 0, 4) + ev.pack_camera_status(1) + ev.TERMINATOR
            + b"trailing garbage after the terminator is ignored")
    recs = ev.parse_events(data)
    assert [r.code for r in recs] == [EosEvent.PROP_VALUE_CHANGED, EosEvent.AVAIL_LIST_CHANGED, EosEvent.PROP_VALUE_CHANGED,
                                      EosEvent.REQUEST_OBJECT_TRANSFER, EosEvent.OBJECT_ADDED_EX, EosEvent.PROP_VALUE_CHANGED,
                                      EosEvent.CAMERA_STATUS_CHANGED]
    assert recs[0].value == 0x15 and recs[1].values == [0x48, 0x50] and recs[2].value == "012021000417"
    assert (recs[3].handle, recs[3].size, recs[3].filename) == (0x90000001, 4242, "IMG_0001.DNG")
    assert (recs[4].handle, recs[4].size, recs[4].filename) == (0x90000002, 77, "IMG_0002.DNG")
    assert recs[5].value == 0x060004 and recs[6].status == 1


def test_untrusted_lengths_are_bounded_before_allocation() -> None:
    # a 4-byte buffer claiming 2^32-1 array elements, a container claiming 3 GiB, a record claiming 1 GiB
    with pytest.raises(ProtocolError, match="does not fit"):
        parse_u32_array(struct.pack("<I", 0xFFFFFFFF))
    with pytest.raises(ProtocolError, match="exceeds the bound"):
        parse_header(struct.pack("<IHHI", 3 << 30, 2, 0x1009, 1), max_length=1 << 20)
    with pytest.raises(ProtocolError, match="size"):
        ev.parse_events(struct.pack("<II", 1 << 30, EosEvent.PROP_VALUE_CHANGED) + b"\0" * 8)
    with pytest.raises(ProtocolError, match="does not fit"):
        ev.parse_events(struct.pack("<IIIII", 20, EosEvent.AVAIL_LIST_CHANGED, 0xD101, 3, 0xFFFFFFFF))


_settings = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_settings
@given(st.binary(max_size=512))
def test_parsers_never_crash_on_random_bytes(blob: bytes) -> None:
    for parse in (DeviceInfo.parse, ObjectInfo.parse, StorageInfo.parse, DevicePropDesc.parse, parse_u32_array,
                  ev.parse_events, parse_container):
        try:
            parse(blob)
        except ProtocolError:
            pass


@_settings
@given(st.lists(st.tuples(st.sampled_from([0xC189, 0xC18A, 0xC181, 0xC186, 0xC18B, 0xC182, 0x1234]),
                          st.binary(max_size=48), st.integers(-8, 8)), max_size=6))
def test_event_parser_survives_malformed_records(records: list[tuple[int, bytes, int]]) -> None:
    """Well-framed records with random bodies and wrong sizes: only ProtocolError, never beyond the buffer."""
    data = b"".join(struct.pack("<II", max(0, 8 + len(body) + skew), code) + body for code, body, skew in records)
    try:
        recs = ev.parse_events(data)
    except ProtocolError:
        return
    assert len(recs) <= len(records)


@_settings
@given(st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFF), st.integers(0, 0xFFFF), st.binary(max_size=40))
def test_container_header_fuzz(length: int, ctype: int, code: int, body: bytes) -> None:
    blob = struct.pack("<IHHI", length, ctype, code, 7) + body
    try:
        c = parse_container(blob, max_length=1 << 16)
    except ProtocolError:
        return
    assert c.pack() == blob
