"""Canon EOS remote capture through the real client code against the simulated body."""

from __future__ import annotations

import struct

import pytest

from dp5k_capture.canon import CaptureTiming, EosCamera
from dp5k_capture.ptp.codes import Op
from dp5k_capture.ptp.session import PTPSession
from dp5k_common.errors import DeviceError

from .conftest import FAST, FAST_SESSION, Body


def test_open_puts_the_body_in_remote_capture_to_pc_raw(body: Body) -> None:
    info = body.camera.open()
    assert info.vendor_extension_id == 6
    core = body.core
    assert core.op_log[:6] == [Op.OPEN_SESSION, Op.GET_DEVICE_INFO, Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_EVENT_MODE,
                               Op.EOS_SET_REQUEST_OLC_INFO_GROUP, Op.EOS_GET_EVENT]  # libgphoto2's order
    assert (core.remote_mode, core.event_mode, core.olc_mask) == (1, 1, 0x1FFF)
    assert core.props[0xD11C] == 4 and core.props[0xD11B] > 0  # capture to PC, AvailableShots > 0
    assert core.image_format == (6, 0, 4)  # full-size RAW
    assert body.camera.state.avail[0xD101][0] == 0x15  # the lens opens to f/1.8


def test_exposure_settings_are_sent_as_setdevicepropvalueex(body: Body) -> None:
    sent: list[bytes] = []
    handle = body.core.handle

    def spy(op, params, data=None):  # noqa: ANN001, ANN202
        if op == Op.EOS_SET_DEVICE_PROP_VALUE_EX:
            sent.append(data)
        return handle(op, params, data)

    body.core.handle = spy  # type: ignore[method-assign]
    body.core.props[0xD102], body.core.props[0xD103] = 0x60, 0x58  # start at 1/30 s, ISO 400
    body.camera.open()
    sent.clear()
    body.camera.set_exposure(2.8, 1 / 60, 100)
    body.camera.set_aperture(22)
    # byte-identical to what real libgphoto2 sends (notes section 2.5)
    assert [p.hex() for p in sent] == ["0c00000001d1000020000000", "0c00000002d1000068000000", "0c00000003d1000048000000",
                                       "0c00000001d1000050000000"]
    assert body.core.props[0xD101] == 0x50


def test_aperture_outside_the_lens_range_is_refused(body: Body) -> None:
    body.camera.open()
    body.core.avail[0xD101] = [c for c in body.core.avail[0xD101] if c >= 0x18]  # a lens that stops at f/2
    body.camera.state.avail[0xD101] = body.core.avail[0xD101]
    with pytest.raises(DeviceError, match="aperture f/1.8: value 0x15 is not offered"):
        body.camera.set_aperture(1.8)


def test_focus_once_then_capture_without_refocus(body: Body) -> None:
    cam = body.camera
    cam.open()
    cam.focus_at((30, 10))
    assert body.core.focus_point_px == (30.0, 10.0)
    focus = body.core.focus_distance_m
    assert focus == pytest.approx(body.optics.autofocus_m("x", (30, 10)))
    assert body.core.props[0xD1B0] == 0  # live view off again
    dl = cam.capture(1.8, 1 / 500, 100)
    assert dl.data == body.core.last_object_bytes and dl.filename == "IMG_0001.DNG"
    assert body.core.objects == {}  # TransferComplete freed the body's buffer
    log = body.core.op_log
    i = log.index(Op.EOS_REMOTE_RELEASE_ON)
    assert log[i : i + 2] == [Op.EOS_REMOTE_RELEASE_ON, Op.EOS_REMOTE_RELEASE_OFF]
    assert Op.GET_PARTIAL_OBJECT in log and Op.EOS_TRANSFER_COMPLETE in log
    s = body.optics.exposures[-1]
    assert (s.f_number, s.shutter_s, s.iso, s.focus_distance_m) == (1.8, 1 / 500, 100, focus)
    cam.capture(5.6, 1 / 50, 100)
    assert body.optics.exposures[-1].focus_distance_m == focus  # all apertures at the same focus


def test_release_busy_storm_and_keepalive(body: Body) -> None:
    cam = body.camera
    cam.open()
    cam.timing = CaptureTiming(prop_echo_s=1, object_s=2, poll_s=0, keepalive_s=0, af_settle_s=0)
    body.core.faults.busy[Op.EOS_REMOTE_RELEASE_ON] = 4
    dl = cam.capture(4.0, 1 / 125, 100)
    assert dl.data == body.core.last_object_bytes
    assert body.core.op_log.count(Op.EOS_REMOTE_RELEASE_ON) == 5
    assert Op.EOS_KEEP_DEVICE_ON in body.core.op_log


@pytest.mark.parametrize("delete", [False, True])
def test_card_capture_is_downloaded_then_deleted_only_when_asked(body: Body, delete: bool) -> None:
    cam = EosCamera(body.session, (0x04A9, 0x3281), FAST, destination="card", delete_from_card=delete)
    body.core.props[0xD11C] = 4  # the body starts in PC mode: open() switches it to its card
    cam.open()
    assert body.core.props[0xD11C] == 2 and Op.EOS_PC_HDD_CAPACITY not in body.core.op_log
    dl = cam.capture(2.0, 1 / 250, 100)
    assert dl.data == body.core.last_object_bytes and dl.on_card and dl.filename == "IMG_0001.DNG"
    assert Op.GET_OBJECT_INFO in body.core.op_log and Op.EOS_TRANSFER_COMPLETE not in body.core.op_log
    assert dl.handle in body.core.objects  # still on the card until the caller has verified the file
    handles = body.session.get_object_handles(0x00010001, 0, 0)
    names = [body.session.get_object_info(h).filename for h in handles]
    assert names == ["DCIM", "100CANON", "IMG_0001.DNG"]  # the card's folders, then the image
    cam.release_card_copy(dl)
    assert (dl.handle in body.core.objects) is not delete and (Op.DELETE_OBJECT in body.core.op_log) is delete


def test_never_close_session_on_a_5d_mark_iv() -> None:
    b = Body()
    b.camera.open()
    b.camera.close()
    assert Op.CLOSE_SESSION not in b.core.op_log
    assert not b.core.broken and (b.core.remote_mode, b.core.event_mode) == (0, 0)
    other = Body(pid=0x3299)  # a body without the quirk gets CloseSession
    other.camera.open()
    other.camera.close()
    assert other.core.op_log[-1] == Op.CLOSE_SESSION


def test_a_non_canon_device_is_refused() -> None:
    b = Body()
    cam = EosCamera(PTPSession(b.transport, FAST_SESSION), (0x1234, 0x0001))
    with pytest.raises(DeviceError, match="not a Canon body"):
        cam.open()
    assert struct.pack("<H", 0x04A9)  # Canon's VID is the identity, not DeviceInfo's vendor id


def test_olc_records_decode_libgphoto2s_samples() -> None:
    """Field bytes as libgphoto2 logged them from real bodies (Tv 01 01 98 10 00 60, Av 01 01 5b 30 30, ISO 01 01 00 78)."""
    from dp5k_capture.ptp.eos_events import parse_events
    from dp5k_capture.ptp.olc import pack_olc, parse_olc

    fields = bytes.fromhex("010198100060" "01015b3030" "01010078")
    rec = struct.pack("<IIIHH", 16 + len(fields), 0xC1A5, 8 + len(fields), 0x000E, 0) + fields
    info = parse_olc(rec, 0xB)
    assert info is not None and info.props == {0xD102: 0x60, 0xD101: 0x30, 0xD103: 0x78} and info.focus is None
    assert parse_olc(rec, 0x30) is None  # a version whose layout is unknown is left undecoded
    for version in (7, 8, 0xB, 0xF):
        again = parse_olc(pack_olc(version, {0xD101: 0x28, 0xD103: 0x48}, focus=2), version)
        assert again is not None and again.props == {0xD101: 0x28, 0xD103: 0x48} and again.focus == 2
    # the OLC version arrives as a property in the same GetEvent data, before the OLC record
    version_rec = struct.pack("<IIII", 16, 0xC189, 0xD199, 0xB)
    recs = parse_events(version_rec + rec + struct.pack("<II", 8, 0))
    assert [(r.prop, r.value) for r in recs[1:]] == [(0xD102, 0x60), (0xD101, 0x30), (0xD103, 0x78)]


def test_settings_are_confirmed_from_olc_events_only(body: Body) -> None:
    """After SetRequestOLCInfoGroup the simulated body reports Av/Tv/ISO only in OLCInfoChanged: the client confirms from it."""
    import dp5k_capture.sim.eos_body as eb

    got: list[bytes] = []
    handle = body.core.handle

    def spy(op, params, data=None):  # noqa: ANN001, ANN202
        reply = handle(op, params, data)
        if op == Op.EOS_GET_EVENT:
            got.append(reply.data)
        return reply

    body.core.handle = spy  # type: ignore[method-assign]
    body.camera.open()
    got.clear()
    body.camera.set_aperture(2.8)
    codes = [struct.unpack_from("<II", d, 0) for d in got if len(d) > 8]
    assert codes == [(16 + 5, 0xC1A5)] and body.camera.state.props[0xD101] == 0x20  # one OLC record (Av field: 5 bytes)
    body.core._queue_prop = lambda prop: None  # type: ignore[method-assign]  # a body that stays silent
    with pytest.raises(DeviceError, match=r"body SIM0001: set aperture f/4: no confirmation from the body within 1 s "
                                          r"\(rig.toml \[timeouts\] settings_s\)"):
        body.camera.set_aperture(4.0)
    assert eb.OLC_VERSION == 0xB


@pytest.mark.parametrize("result", ["fail", "silent"])
def test_failed_or_silent_autofocus_is_a_device_fault_naming_the_body(body: Body, result: str) -> None:
    body.camera.open()
    body.core.faults.af_result = result
    why = "failed: the body found no focus" if result == "fail" else r"AF result: no confirmation .* \[timeouts\] focus_s"
    with pytest.raises(DeviceError, match=rf"^body SIM0001: autofocus at \(30, 10\) px.*{why}"):
        body.camera.focus_at((30, 10))
    assert body.core.props[0xD1B0] == 0 and body.core.op_log[-4:].count(Op.EOS_AF_CANCEL) == 1  # AF cancelled, live view off
    assert body.camera.focus_point_px is None
    body.core.faults.af_result = "ok"
    body.camera.focus_at((30, 10))  # confirmed this time
    assert body.camera.state.focus == 1 and body.core.focus_distance_m is not None


def test_bodies_get_keep_alive_while_the_operator_is_prompted(body: Body) -> None:
    import dataclasses
    import time

    from dp5k_capture.capture import OperatorBoard, keep_bodies_awake

    body.camera.timing = dataclasses.replace(FAST, keepalive_s=0.05)
    body.camera.open()
    before = body.core.op_log.count(Op.EOS_KEEP_DEVICE_ON)
    board = OperatorBoard(lambda msg: time.sleep(0.4))  # the operator takes a while to press Enter
    with keep_bodies_awake([body.camera]):
        board.place(0)
    sent = body.core.op_log.count(Op.EOS_KEEP_DEVICE_ON) - before
    assert sent >= 3
    time.sleep(0.15)
    assert body.core.op_log.count(Op.EOS_KEEP_DEVICE_ON) - before == sent  # stopped with the prompt
