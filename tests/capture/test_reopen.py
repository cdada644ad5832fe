"""A body outlives its client: reopening after a client died mid-download, and closing after Ctrl-C.

The simulated body keeps the half-sent data phase queued when its client goes away, as a real one does, so
a new client's OpenSession first reads stale bytes ("unknown container type ..."). The client must recover
as libgphoto2 does: clear halts, Device Reset (0x66), drain, retry.
"""

from __future__ import annotations

import pytest
import usb.core

from dp5k_capture.canon import EosCamera
from dp5k_capture.ptp.codes import Op
from dp5k_capture.ptp.errors import ProtocolError
from dp5k_capture.ptp.session import PTPSession
from dp5k_capture.ptp.transport import UsbTransport
from dp5k_common.rawfile import read_dual_pixel

from .conftest import FAST, FAST_SESSION, Body


def _new_client(body: Body) -> EosCamera:
    """A second process's client: fresh pyusb device, transport, session and camera on the same body."""
    device = usb.core.find(backend=body.backend, idVendor=0x04A9)
    transport = UsbTransport(device, "body again")
    return EosCamera(PTPSession(transport, FAST_SESSION), (device.idVendor, device.idProduct), FAST)


def _interrupt_mid_download(body: Body, exc: BaseException) -> None:
    """Capture with the first client and let ``exc`` hit it after the first 512 bytes of the raw file."""
    cam = body.camera
    cam.open()
    cam.set_exposure(4.0, 1 / 60, 100)
    cam.release()
    rec = cam.wait_object()
    real_read = body.transport.read

    def read(size: int, timeout_ms: int) -> bytes:
        if size > 512:  # the first 512 bytes (header + start of the data phase) arrived; now the client dies
            raise exc
        return real_read(size, timeout_ms)

    body.transport.read = read  # type: ignore[method-assign]
    with pytest.raises(type(exc)):
        cam.download(rec)
    body.transport.read = real_read  # type: ignore[method-assign]
    assert len(body.usb._in[0]) > 4096  # the body still holds most of the raw file


def test_reopen_after_the_client_died_mid_download(body: Body) -> None:
    _interrupt_mid_download(body, SystemExit("killed"))  # the process ends: no close, nothing sent
    cam = _new_client(body)
    cam.open()  # stale data -> OpenSession fails -> Device Reset -> drain -> OpenSession again
    assert body.usb.resets == 1
    dl = cam.capture(2.8, 1 / 60, 100)
    assert read_dual_pixel_bytes(dl.data).main.shape == (32, 48)


def test_without_recovery_the_stale_data_breaks_open(body: Body) -> None:
    _interrupt_mid_download(body, SystemExit("killed"))
    cam = _new_client(body)
    cam.session.config = type(FAST_SESSION)(**{**FAST_SESSION.__dict__, "open_attempts": 1})
    with pytest.raises(ProtocolError, match="container type|data container"):
        cam.open()


def test_close_after_ctrl_c_mid_download_leaves_remote_mode(body: Body) -> None:
    _interrupt_mid_download(body, KeyboardInterrupt())
    body.camera.close()  # what RigDevices.close does on the way out of a Ctrl-C
    assert (body.core.remote_mode, body.core.event_mode) == (0, 0)
    assert Op.EOS_SET_REMOTE_MODE in body.core.op_log[-2:]
    assert not body.usb._in  # the interrupted transfer was cancelled and drained
    cam = _new_client(body)
    cam.open()
    assert body.usb.resets == 0  # nothing stale was left for the next client
    assert cam.capture(4.0, 1 / 60, 100).data


def read_dual_pixel_bytes(data: bytes):  # noqa: ANN201
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.dng"
        path.write_bytes(data)
        return read_dual_pixel(path)
