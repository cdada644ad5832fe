"""The pieces of a capture run that the scene sequence and the resume checks share: one device step, one shot of
one body (with its in-flight record and a full card explained), the Dual Pixel check, and keeping the bodies
awake while the operator handles the board."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from dp5k_common.errors import BadInputError, DeviceError, DP5KError

from .canon import Download, EosCamera
from .ptp.codes import EosEvent
from .ptp.eos_events import EosRecord
from .ptp.errors import CardFullError
from .rawsession import RawSessionWriter, Shot

log = logging.getLogger(__name__)

KEEPALIVE_DEFAULT_S = 10.0  # KeepDeviceOn interval (s) when there are no bodies to take it from


def step(name: str, fn: Callable[..., object], *args: object) -> object:
    """Run ``fn(*args)``; a dp5k error gets ``name`` (the step) in front of its message."""
    try:
        return fn(*args)
    except DP5KError as exc:
        exc.message = f"{name}: {exc.message}"
        raise


def dual_pixel_check(where: str) -> Callable[[Path], None]:
    """A file check that refuses raws that are not two-frame Dual Pixel RAW (names ``where``)."""

    def check(path: Path) -> None:
        from dp5k_common.rawfile import read_dual_pixel

        try:
            read_dual_pixel(path)
        except BadInputError as exc:
            raise DeviceError(
                f"the body did not write a Dual Pixel RAW ({exc.message}); enable Shooting menu > Dual Pixel RAW "
                "with quality RAW on this body; the scene stops here", where=where) from exc

    return check


def in_flight_recorder(writer: RawSessionWriter, cam_id: str, stem: str) -> Callable[[EosRecord], None]:
    """Records an announced image (handle, name, size) before its download, so a reopen after a kill finds it."""

    def record(rec: EosRecord) -> None:
        writer.set_in_flight(cam_id, {"handle": rec.handle, "filename": rec.filename, "size": rec.size, "shot": stem,
                                      "on_card": rec.code == EosEvent.OBJECT_ADDED_EX})

    return record


def capture_one(cam: EosCamera, cam_id: str, stem: str, f_number: float, shutter_s: float, iso: int,
                writer: RawSessionWriter) -> Download:
    """Release ``cam`` and download the new raw, its handle recorded meanwhile; a full card becomes one line that
    names the body and what was kept."""
    try:
        return cam.capture(f_number, shutter_s, iso, announced=in_flight_recorder(writer, cam_id, stem))
    except CardFullError as exc:
        raise card_full(cam, cam_id, stem, writer) from exc


def card_full(cam: EosCamera, cam_id: str, stem: str, writer: RawSessionWriter) -> CardFullError:
    """``card full on cam0 (serial ...)``: which shot, what the session kept, what to do."""
    kept = len(writer.manifest["files"])
    card = ("; this scene's files stay on the card too (delete_from_card = false)"
            if cam.destination == "card" and not cam.delete_from_card else "")
    return CardFullError(f"card full on {cam_id} (serial {cam.serial or '?'}): {stem}: the body refused the release "
                         f"(StoreFull 0x200C); kept: {kept} completed files in {writer.dir}, none deleted from the card{card}; "
                         "free space on the card (or swap it) and run the same command again to resume")


def shoot(cam: EosCamera, cam_id: str, shot: Shot, writer: RawSessionWriter, check_dp: bool) -> None:
    """Capture one planned file of one body and store it (verified, atomically); errors name the shot."""
    try:
        dl = capture_one(cam, cam_id, shot.stem, shot.f_number, shot.shutter_s, shot.iso, writer)
        meta = {"camera_filename": dl.filename, "focus_point_px": list(cam.focus_point_px or ())}
        writer.add(cam_id, shot, dl.data, meta, check=dual_pixel_check(cam.name) if check_dp else None)
        cam.release_card_copy(dl)  # capture to card: delete the card file only now that it is verified and stored
    except CardFullError:
        raise
    except DP5KError as exc:
        if not exc.message.startswith(shot.stem):
            exc.message = f"{shot.stem}: {exc.message}"
        raise


@contextmanager
def keep_bodies_awake(bodies: Iterable[EosCamera]) -> Iterator[None]:
    """While the operator is prompted (the main thread waits for Enter), send KeepDeviceOn to each body every
    ``keepalive_s`` from a helper thread, so no body powers down. The bodies are idle meanwhile: only this
    thread talks to them. A failure is logged; the next shot reports the body's state."""
    cams = list(bodies)
    stop = threading.Event()

    def run() -> None:
        interval_s = min((c.timing.keepalive_s for c in cams), default=KEEPALIVE_DEFAULT_S)
        while not stop.wait(interval_s):
            for cam in cams:
                try:
                    cam.keep_alive()
                except DP5KError as exc:
                    log.warning("%s: keep-alive while waiting for the operator: %s", cam.name, exc)

    thread = threading.Thread(target=run, name="keep-bodies-awake", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


__all__ = ["step", "dual_pixel_check", "capture_one", "card_full", "shoot", "keep_bodies_awake", "in_flight_recorder"]
