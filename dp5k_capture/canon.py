"""Canon EOS remote capture over a PTP session (the vendor extension, written here).

Sequence (after libgphoto2's camera_prepare_canon_eos_capture / trigger / download, see
docs/capture.md): OpenSession(1) with tid 0, GetDeviceInfo, SetRemoteMode(1), SetEventMode(1), GetEvent
until empty, capture destination PC (0xD11C=4) + PCHDDCapacity until AvailableShots > 0, image quality
RAW via SetDevicePropValueEx (0x9110). Focus once per scene in live view: EVFOutputDevice=PC, ZoomPosition(x, y),
DoAf, wait for the AF result (OLC focus info, after SetRequestOLCInfoGroup), AfCancel, live view off; then lock it
(FocusMode 0xD108 = MF where the body offers it). Each exposure: set Av/Tv/ISO and wait until GetEvent echoes them,
RemoteReleaseOn(3, 1) (full press, no AF) + RemoteReleaseOff(3), GetEvent until RequestObjectTransfer
(KeepDeviceOn every 10 s), GetPartialObject in 1 MiB chunks, TransferComplete; a release refused with StoreFull is a
:class:`CardFullError`. Images announced before this session (a killed client's) are kept in :attr:`EosCamera.stale`
for the caller to rescue. With capture to the card:
ObjectAddedEx, GetObjectInfo, GetPartialObject chunks, and DeleteObject only after the file is verified. Never CloseSession (a 5D
Mark IV answers OperationNotSupported to everything after it).
"""

from __future__ import annotations

import dataclasses
import logging
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dp5k_common.errors import DeviceError

from .ptp.codes import (
    CANON_VID,
    CAPTURE_DEST_CARD,
    CAPTURE_DEST_PC,
    FOCUS_MODE_MF,
    OFC_ASSOCIATION,
    EVF_OUTPUT_PC,
    EosEvent,
    EosProp,
    Op,
    Resp,
    av_code,
    iso_code,
    tv_code,
)
from .ptp.datasets import DeviceInfo
from .ptp.eos_events import EosRecord, parse_events
from .ptp.errors import CardFullError, ResponseError
from .ptp.olc import FOCUS_FAILED, FOCUS_IN_FOCUS, OLC_FIELD_SIZES, OLC_REQUEST_ALL
from .ptp.session import PTPSession
from .rig import TimeoutConfig

log = logging.getLogger(__name__)

CHUNK_BYTES = 1 << 20
FOCUS_MODE_AF = 0  # one-shot AF (FocusMode 0xD108), what DoAf needs
REMOTE_RELEASE_CARD_FULL = 7  # RemoteRelease (0x910F) result: card full (libgphoto2)
RAW_IMAGE_FORMAT = (6, 0, 4)  # kind RAW, size L, compression lossless
DONT_CLOSE_SESSION = {(CANON_VID, 0x3281)}  # EOS 5D Mark IV (libgphoto2 PTP_DONT_CLOSE_SESSION)


@dataclass(frozen=True)
class CaptureTiming:
    """Bounds of the capture loop.

    Attributes:
        prop_echo_s: how long to wait for GetEvent to confirm a setting (rig.toml ``[timeouts] settings_s``).
        object_s: how long to wait for the new object after a release (``capture_s``; libgphoto2: 90-100 s).
        poll_s: pause between GetEvent polls.
        keepalive_s: KeepDeviceOn interval while waiting.
        af_settle_s: wait after DoAf on a body that reports no AF result (no decodable OLC focus info).
        focus_s: how long to wait for the AF result after DoAf (``focus_s``).
    """

    prop_echo_s: float = 10.0
    object_s: float = 100.0
    poll_s: float = 0.02
    keepalive_s: float = 10.0
    af_settle_s: float = 0.5
    focus_s: float = 10.0

    @classmethod
    def from_timeouts(cls, t: TimeoutConfig) -> CaptureTiming:
        """The capture-loop bounds of rig.toml's ``[timeouts]``."""
        return cls(prop_echo_s=t.settings_s, object_s=t.capture_s, focus_s=t.focus_s)


@dataclass
class Download:
    """One downloaded object: its camera file name and bytes."""

    filename: str
    data: bytes
    handle: int
    on_card: bool = False


@dataclass
class EosState:
    """What GetEvent has told us so far."""

    props: dict[int, int | str] = field(default_factory=dict)
    avail: dict[int, list[int]] = field(default_factory=dict)
    busy: bool = False
    focus: int | None = None  # last AF state from OLC focus info: 0 searching, 1 in focus, 2 failed
    olc: bool = False  # SetRequestOLCInfoGroup was sent: settings and AF state come as OLCInfoChanged


class EosCamera:
    """One Canon EOS body in remote mode.

    Args:
        session: an unopened PTP session on the body's transport.
        usb_id: (vendor, product) from the USB descriptor; identifies Canon (DeviceInfo says vendor 6).
        timing: bounds of the capture loop.
        destination: ``pc`` (raws go straight to the PC) or ``card`` (written to the card, then downloaded).
        delete_from_card: with ``card``, :meth:`release_card_copy` deletes the card file (after a verified download).
    """

    def __init__(self, session: PTPSession, usb_id: tuple[int, int] | None = None, timing: CaptureTiming | None = None,
                 *, destination: str = "pc", delete_from_card: bool = False) -> None:
        self.session = session
        self.destination = destination
        self.delete_from_card = delete_from_card
        self.usb_id = usb_id
        self.timing = timing or CaptureTiming()
        self.state = EosState()
        self.info: DeviceInfo | None = None
        self.name = session.name
        self._last_keepalive = time.monotonic()
        self.focus_point_px: tuple[int, int] | None = None
        self.pending: list[EosRecord] = []
        self.stale: list[EosRecord] = []  # images announced before this session (a killed client's): rescued by the caller
        self.cam_id = session.name  # the rig's id and the body serial, for messages (set by devices.open_body)
        self.serial = ""

    # ------------------------------------------------------------------ setup
    def open(self) -> DeviceInfo:
        """Open the session and put the body in remote + event mode, capture to PC, RAW quality."""
        self.session.open_session(1)
        self.info = self.session.get_device_info()
        if self.usb_id is not None and self.usb_id[0] != CANON_VID:
            raise DeviceError(f"not a Canon body (USB vendor 0x{self.usb_id[0]:04x})", where=self.name)
        if self.usb_id is None and "Canon" not in self.info.manufacturer:
            raise DeviceError(f"not a Canon body (manufacturer {self.info.manufacturer!r})", where=self.name)
        if self.usb_id in DONT_CLOSE_SESSION:
            self.session.config = dataclasses.replace(self.session.config, close_session=False)
        for op in (Op.EOS_SET_REMOTE_MODE, Op.EOS_SET_EVENT_MODE, Op.EOS_GET_EVENT, Op.EOS_SET_DEVICE_PROP_VALUE_EX,
                   Op.EOS_REMOTE_RELEASE_ON, Op.GET_PARTIAL_OBJECT):
            if op not in self.info.operations:
                raise DeviceError(f"body does not support operation 0x{op:04X} ({Op(op).name})", where=self.name)
        self.session.transaction(Op.EOS_SET_REMOTE_MODE, (1,))
        self.session.transaction(Op.EOS_SET_EVENT_MODE, (1,))
        if Op.EOS_SET_REQUEST_OLC_INFO_GROUP in self.info.operations:  # as libgphoto2: settings + AF come back as events
            self.session.transaction(Op.EOS_SET_REQUEST_OLC_INFO_GROUP, (OLC_REQUEST_ALL,))
            self.state.olc = True
        self.poll_events()
        if self.pending:  # announced to a client before us (killed mid-download): not a shot of ours
            log.info("%s: %d image(s) announced before this session: %s", self.name, len(self.pending),
                     ", ".join(r.filename or "?" for r in self.pending))
            self.stale, self.pending = list(self.pending), []
        if self.destination == "card":
            self.set_capture_to_card()
        else:
            self.set_capture_to_pc()
        self.set_raw_quality()
        return self.info

    def close(self) -> None:
        """Leave remote mode, also after Ctrl-C mid-transfer: Cancel the unfinished transaction and drain its
        data, then SetEventMode(0) and SetRemoteMode(0) (each tried even if the other fails). Never
        CloseSession on bodies that break on it."""
        self.session.abort_unfinished()
        for op, step in ((Op.EOS_SET_EVENT_MODE, "event mode off"), (Op.EOS_SET_REMOTE_MODE, "remote mode off")):
            try:
                self.session.transaction(op, (0,))
            except DeviceError as exc:
                log.warning("%s: %s failed: %s", self.name, step, exc)
        try:
            self.session.close_session()
        except DeviceError as exc:
            log.warning("%s: CloseSession failed: %s", self.name, exc)

    # ------------------------------------------------------------------ events
    def poll_events(self) -> list[EosRecord]:
        """One GetEvent; applies property changes to :attr:`state`; object events go to :attr:`pending`."""
        data = self.session.transaction(Op.EOS_GET_EVENT, data_in=True).data
        records = parse_events(data, where=self.name, olc_version=self._olc_version())
        for rec in records:
            if rec.code == EosEvent.OLC_INFO_CHANGED and rec.focus is not None:
                self.state.focus = rec.focus
            elif rec.code == EosEvent.PROP_VALUE_CHANGED and rec.prop is not None:
                self.state.props[rec.prop] = rec.value  # type: ignore[assignment]
            elif rec.code == EosEvent.AVAIL_LIST_CHANGED and rec.prop is not None:
                self.state.avail[rec.prop] = rec.values
            elif rec.code == EosEvent.CAMERA_STATUS_CHANGED:
                self.state.busy = rec.status == 1
            elif rec.code == EosEvent.REQUEST_OBJECT_TRANSFER or (rec.code == EosEvent.OBJECT_ADDED_EX and rec.ofc != OFC_ASSOCIATION):
                self.pending.append(rec)  # a new folder on the card (OFC association) is not an image
        return records

    def _olc_version(self) -> int:
        value = self.state.props.get(EosProp.OLC_INFO_VERSION, 0)
        return value if isinstance(value, int) else 0

    def reports_af_result(self) -> bool:
        """The body sends its AF state (OLC requested, and its OLC version is one we can decode)."""
        return self.state.olc and self._olc_version() in OLC_FIELD_SIZES

    def keep_alive(self) -> None:
        """KeepDeviceOn (0x911D) when the interval has passed."""
        now = time.monotonic()
        if now - self._last_keepalive >= self.timing.keepalive_s:
            self.session.transaction(Op.EOS_KEEP_DEVICE_ON)
            self._last_keepalive = now

    def _wait(self, what: str, done: Callable[[], bool], timeout_s: float, key: str = "settings_s") -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            self.poll_events()
            if done():
                return
            if time.monotonic() > deadline:
                raise DeviceError(f"{what}: no confirmation from the body within {timeout_s:g} s "
                                  f"(rig.toml [timeouts] {key})", where=self.name)
            self.keep_alive()
            time.sleep(self.timing.poll_s)

    # ------------------------------------------------------------------ properties
    def set_prop(self, prop: int, value: int, what: str) -> None:
        """SetDevicePropValueEx for an integer property; check the allowed list; wait for the echo."""
        allowed = self.state.avail.get(prop)
        if allowed is not None and value not in allowed:
            raise DeviceError(f"{what}: value 0x{value:X} is not offered by the body (allowed: {[hex(v) for v in allowed]})", where=self.name)
        payload = struct.pack("<III", 12, prop, value)
        self.session.transaction(Op.EOS_SET_DEVICE_PROP_VALUE_EX, data_out=payload)
        self._wait(f"set {what}", lambda: self.state.props.get(prop) == value, self.timing.prop_echo_s)

    def set_aperture(self, f_number: float) -> None:
        self.set_prop(EosProp.APERTURE, av_code(f_number), f"aperture f/{f_number:g}")

    def set_shutter(self, shutter_s: float) -> None:
        self.set_prop(EosProp.SHUTTER_SPEED, tv_code(shutter_s), f"shutter {shutter_s:g} s")

    def set_iso(self, iso: int) -> None:
        self.set_prop(EosProp.ISO, iso_code(iso), f"ISO {iso}")

    def set_exposure(self, f_number: float, shutter_s: float, iso: int) -> None:
        """Set Av, Tv and ISO (each only if it differs from what the body last reported)."""
        if self.state.props.get(EosProp.APERTURE) != av_code(f_number):
            self.set_aperture(f_number)
        if self.state.props.get(EosProp.SHUTTER_SPEED) != tv_code(shutter_s):
            self.set_shutter(shutter_s)
        if self.state.props.get(EosProp.ISO) != iso_code(iso):
            self.set_iso(iso)

    def set_capture_to_pc(self) -> None:
        """CaptureDestination = PC (4), PCHDDCapacity, then wait until AvailableShots > 0."""
        if self.state.props.get(EosProp.CAPTURE_DESTINATION) != CAPTURE_DEST_PC:
            self.set_prop(EosProp.CAPTURE_DESTINATION, CAPTURE_DEST_PC, "capture destination PC")
        self.session.transaction(Op.EOS_PC_HDD_CAPACITY, (0x0FFFFFFF, 0x1000, 1))
        self._wait("PC capture", lambda: int(self.state.props.get(EosProp.AVAILABLE_SHOTS, 0) or 0) > 0, self.timing.prop_echo_s)

    def set_capture_to_card(self) -> None:
        """CaptureDestination = the body's card value (the first offered value that is not PC, as libgphoto2
        picks it), then wait until AvailableShots > 0 (a card is in and has room)."""
        offered = [v for v in self.state.avail.get(EosProp.CAPTURE_DESTINATION, []) if v != CAPTURE_DEST_PC]
        card = offered[0] if offered else CAPTURE_DEST_CARD
        if self.state.props.get(EosProp.CAPTURE_DESTINATION) != card:
            self.set_prop(EosProp.CAPTURE_DESTINATION, card, "capture destination card")
        self._wait("card capture (is a card in, with room?)",
                   lambda: int(self.state.props.get(EosProp.AVAILABLE_SHOTS, 0) or 0) > 0, self.timing.prop_echo_s)

    def set_raw_quality(self) -> None:
        """ImageFormat = one full-size RAW (Dual Pixel RAW itself is a menu setting; files are verified)."""
        kind, size, comp = RAW_IMAGE_FORMAT
        payload = struct.pack("<IIIIIII", 28, EosProp.IMAGE_FORMAT, 1, 0x10, kind, size, comp)
        self.session.transaction(Op.EOS_SET_DEVICE_PROP_VALUE_EX, data_out=payload)
        want = (kind << 16) | (size << 8) | comp
        self._wait("image quality RAW", lambda: self.state.props.get(EosProp.IMAGE_FORMAT) == want, self.timing.prop_echo_s)

    # ------------------------------------------------------------------ focus
    def focus_at(self, point_px: tuple[int, int]) -> None:
        """Autofocus once at ``point_px`` (raw pixels) and confirm it: live view on, ZoomPosition, DoAf, wait for
        the body's AF result in its events (OLC focus info), AfCancel, live view off.

        Raises:
            DeviceError: the body reports a failed AF, or no result within ``focus_s`` (naming the body).
        """
        x, y = int(round(point_px[0])), int(round(point_px[1]))
        if self.state.props.get(EosProp.FOCUS_MODE) == FOCUS_MODE_MF and FOCUS_MODE_AF in self.state.avail.get(EosProp.FOCUS_MODE, []):
            self.set_prop(EosProp.FOCUS_MODE, FOCUS_MODE_AF, "focus mode AF (for this scene's autofocus)")
        self.set_prop(EosProp.EVF_OUTPUT_DEVICE, EVF_OUTPUT_PC, "live view on")
        self.session.transaction(Op.EOS_ZOOM_POSITION, (x, y))
        self.state.focus = None
        self.session.transaction(Op.EOS_DO_AF)
        try:
            if self.reports_af_result():
                self._wait(f"autofocus at ({x}, {y}) px: AF result", lambda: self.state.focus in (FOCUS_IN_FOCUS, FOCUS_FAILED),
                           self.timing.focus_s, "focus_s")
            else:
                log.warning("%s: the body reports no AF result (OLC version %d): waiting %g s after DoAf",
                            self.name, self._olc_version(), self.timing.af_settle_s)
                deadline = time.monotonic() + self.timing.af_settle_s
                while time.monotonic() < deadline:
                    self.poll_events()
                    time.sleep(self.timing.poll_s)
        except BaseException:
            self._end_af(quiet=True)  # AfCancel and live view off, without hiding what stopped the AF (Ctrl-C too)
            raise
        self._end_af()
        if self.state.focus == FOCUS_FAILED:
            raise DeviceError(f"autofocus at ({x}, {y}) px failed: the body found no focus there (low contrast, closer "
                              "than the lens focuses, or lens switch on MF); capture stops before any shot of this run", where=self.name)
        self.focus_point_px = (x, y)

    def _end_af(self, quiet: bool = False) -> None:
        """AfCancel, then live view off; ``quiet``: a failure is logged, not raised (an error is already in flight)."""
        try:
            self.session.transaction(Op.EOS_AF_CANCEL)
            self.set_prop(EosProp.EVF_OUTPUT_DEVICE, 0, "live view off")
        except DeviceError as exc:
            if not quiet:
                raise
            log.warning("%s: ending the AF after an interruption: %s", self.name, exc)

    def lock_focus(self) -> dict[str, object]:
        """Keep the focus of the last AF: FocusMode (0xD108) = MF where the body offers it, confirmed by its events.

        Whatever the body allows, dp5k never sends DoAf again for the scene and releases without AF
        (RemoteReleaseOn(3, 1)). Returns what the body reports: FocusMode before and after, how focus is held,
        the lens, the AF state.
        """
        before = self.state.props.get(EosProp.FOCUS_MODE)
        offered = self.state.avail.get(EosProp.FOCUS_MODE, [])
        if before == FOCUS_MODE_MF:
            how = "FocusMode 0xD108 already reads 3 (MF)"
        elif FOCUS_MODE_MF in offered:
            self.set_prop(EosProp.FOCUS_MODE, FOCUS_MODE_MF, "focus mode MF (focus lock)")
            how = "FocusMode 0xD108 set to 3 (MF) and confirmed by the body"
        else:
            how = "releases without AF only: the body offers no FocusMode MF to the PC (set the lens switch to MF)"
            log.warning("%s: the body does not let the PC set manual focus (FocusMode 0xD108 offers %s): focus is held by "
                        "releasing without AF; set the lens switch to MF now to be safe", self.name, offered or "nothing")
        return {"locked_by": how, "focus_mode_before": before, "focus_mode": self.state.props.get(EosProp.FOCUS_MODE),
                "af_state": {FOCUS_IN_FOCUS: "in focus", FOCUS_FAILED: "failed", None: "not reported"}.get(self.state.focus, str(self.state.focus)),
                "lens": self.state.props.get(EosProp.LENS_NAME)}

    # ------------------------------------------------------------------ capture
    def release(self) -> None:
        """Full press without AF, then release (RemoteReleaseOn(3, 1), RemoteReleaseOff(3))."""
        self.poll_events()
        if self.state.busy:
            self._wait("release", lambda: not self.state.busy, self.timing.object_s, "capture_s")
        try:
            self.session.transaction(Op.EOS_REMOTE_RELEASE_ON, (3, 1))
        except ResponseError as exc:
            if exc.code == Resp.STORE_FULL:
                raise CardFullError("the body refused the release: its card is full (StoreFull 0x200C)", where=self.name) from exc
            raise
        self.session.transaction(Op.EOS_REMOTE_RELEASE_OFF, (3,))

    def wait_object(self) -> EosRecord:
        """Poll GetEvent (with keep-alive) until the body announces the new object."""
        self._wait("wait for the new image", lambda: bool(self.pending), self.timing.object_s, "capture_s")
        return self.pending.pop(0)

    def download(self, rec: EosRecord) -> Download:
        """Download the announced object in 1 MiB GetPartialObject chunks.

        A PC capture ends with TransferComplete (the body frees its buffer). A card capture is first looked up
        with GetObjectInfo (its size on the card) and stays on the card: :meth:`release_card_copy` deletes it
        once the caller has verified and stored the file.
        """
        assert rec.handle is not None
        on_card = rec.code == EosEvent.OBJECT_ADDED_EX
        total = int(rec.size or 0)
        if on_card or total <= 0:
            info = self.session.get_object_info(rec.handle)
            if total > 0 and info.compressed_size != total:
                raise DeviceError(f"card file {info.filename}: ObjectInfo says {info.compressed_size} bytes, the event {total}", where=self.name)
            total = info.compressed_size
        buf = bytearray()
        while len(buf) < total:
            chunk = self.session.get_partial_object(rec.handle, len(buf), min(CHUNK_BYTES, total - len(buf)))
            if not chunk:
                raise DeviceError(f"download of {rec.filename}: body sent 0 bytes at offset {len(buf)}", where=self.name)
            buf += chunk
            self.keep_alive()
        if not on_card:
            self.session.transaction(Op.EOS_TRANSFER_COMPLETE, (rec.handle,))
        return Download(rec.filename or f"{rec.handle:08x}", bytes(buf), rec.handle, on_card)

    def release_card_copy(self, dl: Download) -> None:
        """Delete a downloaded card file if ``delete_from_card`` (call only after the download is verified)."""
        if dl.on_card and self.delete_from_card:
            self.session.delete_object(dl.handle)

    def capture(self, f_number: float, shutter_s: float, iso: int,
                announced: Callable[[EosRecord], None] | None = None) -> Download:
        """Set the exposure, release without refocusing and download the new raw file. ``announced(record)`` is
        called between the body's announcement and the download (the caller records the handle, so a reopen
        after a kill finds the image and frees the body of it)."""
        self.set_exposure(f_number, shutter_s, iso)
        self.release()
        rec = self.wait_object()
        if announced is not None:
            announced(rec)
        return self.download(rec)


__all__ = ["EosCamera", "CaptureTiming", "Download", "EosState"]
