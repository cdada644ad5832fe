"""Canon EOS remote capture through the real client code against the simulated body."""

from __future__ import annotations

import struct

import pytest

from dp5k_capture.canon import CaptureTiming, EosCamera
from dp5k_capture.ptp.codes import Op
from dp5k_capture.ptp.session import PTPSession
from dp5k_common.errors import DeviceError

from .conftest import FAST_SESSION, Body


def test_open_puts_the_body_in_remote_capture_to_pc_raw(body: Body) -> None:
    info = body.camera.open()
    assert info.vendor_extension_id == 6
    core = body.core
    assert core.op_log[:5] == [Op.OPEN_SESSION, Op.GET_DEVICE_INFO, Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_EVENT_MODE, Op.EOS_GET_EVENT]
    assert (core.remote_mode, core.event_mode) == (1, 1)
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


def test_card_capture_is_downloaded_then_deleted(body: Body) -> None:
    cam = body.camera
    cam.open()
    cam.set_prop(0xD11C, 2, "capture destination card")
    dl = cam.capture(2.0, 1 / 250, 100)
    assert dl.data == body.core.last_object_bytes
    assert Op.DELETE_OBJECT in body.core.op_log and body.core.objects == {}


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
