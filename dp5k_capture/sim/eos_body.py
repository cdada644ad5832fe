"""A simulated Canon EOS 5D Mark IV: one PTP operation handler shared by the USB and PTP/IP framings.

It answers the operations dp5k's client and libgphoto2 use (standard PTP plus the EOS remote-capture
set), keeps the EOS properties and their allowed lists, queues GetEvent records, and on a release
renders one exposure through an injected :class:`BodyOptics` (the virtual studio, or a trivial scene in
unit tests) at the current aperture, shutter, ISO and focus. Quirks of the real body are kept: the raw
DeviceInfo reports VendorExtensionID 6, and after CloseSession every operation answers
OperationNotSupported (libgphoto2 ``PTP_DONT_CLOSE_SESSION``).

**Autofocus repeatability.** The first AF of a body lands on the subject at the AF point (how far the lens
truly focuses from what the body records is the studio's ``focus_offset`` effect). Every later AF, and the
lens of a body that was re-created (a new in-process ``--sim`` run: the bodies of the last run are gone),
lands ``AF_SCATTER_REL`` (0.3-1.0 %) of the distance in front of or behind it, drawn from a generator seeded
by ``af_seed`` (the studio seed), ``run``, the serial and the AF count: AF twice and the focus differs, as on a
real lens.
FocusMode (0xD108) can be set to MF (3) by the PC unless ``BodyFaults.focus_mode_fixed``; in MF, DoAf fails
(the AF state says failed) and no release refocuses.
"""

from __future__ import annotations

import logging
import random
import struct
import zlib
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..ptp import eos_events as ev
from ..ptp.codes import (
    AV_CODES,
    CAPTURE_DEST_CARD,
    CAPTURE_DEST_PC,
    ISO_CODES,
    OFC_ASSOCIATION,
    OFC_DNG,
    EOS_BATTERY_LEVELS,
    FOCUS_MODE_MF,
    EosEvent,
    EosProp,
    Op,
    Resp,
    av_code,
    iso_code,
    tv_code,
    tv_seconds,
    AV_FROM_CODE,
    ISO_FROM_CODE,
    TV_CODES,
)
from ..ptp.datasets import DeviceInfo, DevicePropDesc, ObjectInfo, StorageInfo, Writer
from ..ptp.olc import FOCUS_FAILED, FOCUS_IN_FOCUS, OLC_FOCUS_BIT, OLC_PROPS, pack_olc

log = logging.getLogger(__name__)

STORAGE_ID = 0x00010001
RAW_FORMAT = (6, 0, 4)  # ImageFormat entry: kind 6 = RAW, size 0 = L, compression 4 = lossless
CARD_SHOTS = 900  # AvailableShots the simulated card has room for
CARD_BYTES = 64_000_000_000  # a 64 GB card ...
CARD_FREE_BYTES = 60_000_000_000  # ... with 60 GB free before this session's files
BATTERY_PERCENT = 75
AF_SCATTER_REL = (0.003, 0.010)  # |focus distance error| of a repeated AF, relative (see the module docstring)
FOCUS_MODE_ONE_SHOT = 0
CARD_IMAGE_FOLDER = 0x9010_0000  # DCIM/100CANON on the card
CARD_FOLDERS = {0x9000_0000: ("DCIM", 0), CARD_IMAGE_FOLDER: ("100CANON", 0x9000_0000)}  # handle -> (name, parent)
OLC_VERSION = 0xB  # OLC field layout of the 5Ds generation (the 5D Mark IV's own version is not recorded)
DATA_OUT_OPS = frozenset({Op.EOS_SET_DEVICE_PROP_VALUE_EX, Op.SET_DEVICE_PROP_VALUE})


@dataclass(frozen=True)
class ExposureSettings:
    """What the body knows when its shutter opens."""

    serial: str
    f_number: float
    shutter_s: float
    iso: int
    focus_point_px: tuple[float, float] | None
    focus_distance_m: float | None
    dual_pixel_raw: bool
    sequence: int


class BodyOptics(Protocol):
    """What the body needs from the world: autofocus at a point and the file bytes of one exposure."""

    def autofocus_m(self, serial: str, point_px: tuple[float, float]) -> float: ...
    def expose(self, settings: ExposureSettings) -> bytes: ...


@dataclass(frozen=True)
class Reply:
    """A handler's answer: response code, response params and (for data-in operations) the data."""

    code: int
    params: tuple[int, ...] = ()
    data: bytes | None = None


@dataclass
class BodyFaults:
    """Faults the body injects at the PTP level (USB-level faults live in the USB framing).

    Attributes:
        busy: op code -> how many times it answers DeviceBusy before it succeeds.
        dual_pixel_raw: False simulates a body whose DPRAW menu setting is off.
        card_full: RemoteRelease answers 7 / the release fails with StoreFull.
        af_result: what DoAf reports in OLC focus info: ``ok`` (in focus), ``fail`` (AF failed), ``silent`` (nothing).
        busy_rate: every operation in a session answers DeviceBusy with this probability (seeded ``rng``);
            ``busy_answers`` counts them.
        full_from_release: the release (counted over the body's life) that finds the card full, and every one
            after it (``--sim-faults full@K``); the card reports no free space once the next release would fail.
        focus_mode_fixed: the PC cannot set FocusMode (as on a body whose lens switch decides it).
    """

    busy: dict[int, int] = field(default_factory=dict)
    dual_pixel_raw: bool = True
    card_full: bool = False
    af_result: str = "ok"
    busy_rate: float = 0.0
    busy_answers: int = 0
    rng: random.Random = field(default_factory=lambda: random.Random(0))
    full_from_release: int | None = None
    focus_mode_fixed: bool = False


@dataclass
class _Object:
    handle: int
    name: str
    data: bytes
    on_card: bool


class SimulatedEOS:
    """The PTP core of one simulated body.

    Args:
        serial: the body serial (EOS property 0xD1AF, DeviceInfo and USB iSerialNumber).
        optics: the world the body photographs.
        vendor_extension_id: what DeviceInfo reports (6 like the real 5D Mark IV over USB).
        lens_name: reported LensName; apertures offered are those of an EF 85mm f/1.8.
        af_seed: seeds the AF scatter (the studio seed).
        run: how many runs of this scene came before this body was made (in-process ``--sim`` makes new bodies
            each run; a run > 0 means the lens was focused by a body of an earlier run, wherever that AF landed).
        lens_point_px: where a re-created body's lens was last focused (its scene focus point, raw px).
    """

    MODEL = "Canon EOS 5D Mark IV"

    def __init__(
        self,
        serial: str,
        optics: BodyOptics,
        *,
        vendor_extension_id: int = 6,
        lens_name: str = "EF85mm f/1.8 USM",
        faults: BodyFaults | None = None,
        af_seed: int = 0,
        run: int = 0,
        lens_point_px: tuple[float, float] | None = None,
    ) -> None:
        self.serial = serial
        self.optics = optics
        self.vendor_extension_id = vendor_extension_id
        self.faults = faults or BodyFaults()
        self.session_open = False
        self.broken = False  # after CloseSession, like the real body
        self.remote_mode = 0
        self.event_mode = 0
        self.olc_mask = 0  # SetRequestOLCInfoGroup: Av/Tv/ISO and the AF state then come only as OLCInfoChanged
        self.events: list[bytes] = []
        self.objects: dict[int, _Object] = {}
        self._next_handle = 0x9000_0001
        self.sequence = 0
        self.focus_point_px: tuple[float, float] | None = None
        self.focus_distance_m: float | None = None
        self.af_seed, self.run = int(af_seed), int(run)
        self.af_count = 0  # AFs of this body (the first lands on the subject, later ones scatter)
        self.lens_point_px = lens_point_px
        self.releases = 0
        self.pressed = 0
        self.op_log: list[int] = []
        self.last_object_bytes: bytes = b""
        apertures = [c for f, c in sorted(AV_CODES.items()) if 1.8 <= f <= 22.0]
        self.avail: dict[int, list[int]] = {
            EosProp.APERTURE: apertures,
            EosProp.SHUTTER_SPEED: sorted(TV_CODES),  # 30 s .. 1/8000 s in 1/3 stops
            EosProp.ISO: sorted(ISO_CODES.values()),
            EosProp.CAPTURE_DESTINATION: [CAPTURE_DEST_CARD, CAPTURE_DEST_PC],
            EosProp.FOCUS_MODE: [FOCUS_MODE_ONE_SHOT, FOCUS_MODE_MF],  # not offered while faults.focus_mode_fixed
        }
        self.props: dict[int, int | str] = {
            EosProp.APERTURE: av_code(4.0),
            EosProp.SHUTTER_SPEED: tv_code(1 / 60),
            EosProp.ISO: iso_code(100),
            EosProp.AUTO_EXPOSURE_MODE: 3,  # M
            EosProp.DRIVE_MODE: 0,
            EosProp.FOCUS_MODE: FOCUS_MODE_ONE_SHOT,
            EosProp.BATTERY_POWER: next(c for c, t in EOS_BATTERY_LEVELS.items() if t == f"{BATTERY_PERCENT}%"),
            EosProp.CAPTURE_DESTINATION: CAPTURE_DEST_CARD,
            EosProp.AVAILABLE_SHOTS: CARD_SHOTS,  # room on the card (capture to card is the power-on setting)
            EosProp.EVF_OUTPUT_DEVICE: 0,
            EosProp.OLC_INFO_VERSION: OLC_VERSION,
            EosProp.SERIAL_NUMBER: serial,
            EosProp.LENS_NAME: lens_name,
        }
        self.image_format: tuple[int, int, int] = (1, 0, 3)  # JPEG L fine until the client asks for RAW
        self._dumped = False

    # ------------------------------------------------------------------ helpers
    def device_info(self) -> DeviceInfo:
        ops = sorted({int(o) for o in Op if o not in (Op.INITIATE_CAPTURE, Op.SET_DEVICE_PROP_VALUE)} | {0x9108})
        return DeviceInfo(
            standard_version=100, vendor_extension_id=self.vendor_extension_id, vendor_extension_version=100,
            vendor_extension_desc="", functional_mode=0, operations=ops,
            events=[0x4002, 0x4006, 0x400D, 0xC101],
            properties=[0x5001],  # EOS properties (0xD1xx) are listed by GetDeviceInfoEx only, as on real bodies
            capture_formats=[OFC_DNG], image_formats=[OFC_DNG, 0x3801],
            manufacturer="Canon Inc.", model=self.MODEL, device_version="1-1.2.0", serial_number=self.serial.rjust(32, "0"),
        )

    def _queue_prop(self, prop: int) -> None:
        value = self.props[prop]
        bit = {p: b for b, (p, _) in OLC_PROPS.items()}.get(prop)
        if bit is not None and self.olc_mask & bit:
            self.events.append(pack_olc(OLC_VERSION, {prop: int(value)}))
            return
        self.events.append(ev.pack_prop_value(prop, value))

    def _queue_dump(self) -> None:
        for prop, value in self.props.items():  # values first: libgphoto2 drops an AvailList for a property it has not seen yet
            self.events.append(ev.pack_prop_value(prop, value))
        for prop, values in self.avail.items():
            if prop == EosProp.FOCUS_MODE and self.faults.focus_mode_fixed:
                continue  # the lens switch decides: the PC is offered no choice
            self.events.append(ev.pack_avail_list(prop, values))
        self.events.append(ev.pack_image_format_value(EosProp.IMAGE_FORMAT, *self.image_format))
        self._dumped = True

    def settings(self) -> ExposureSettings:
        return ExposureSettings(
            serial=self.serial,
            f_number=AV_FROM_CODE[int(self.props[EosProp.APERTURE])],
            shutter_s=tv_seconds(int(self.props[EosProp.SHUTTER_SPEED])),
            iso=ISO_FROM_CODE[int(self.props[EosProp.ISO])],
            focus_point_px=self.focus_point_px,
            focus_distance_m=self.focus_distance_m,
            dual_pixel_raw=self.faults.dual_pixel_raw and self.image_format == RAW_FORMAT,
            sequence=self.sequence,
        )

    def _autofocus(self, point_px: tuple[float, float] | None = None) -> None:
        """One AF at ``point_px`` (default: the live-view AF frame): the first on the subject, later ones scattered."""
        point = point_px or self.focus_point_px
        if point is None:
            return
        subject_m = float(self.optics.autofocus_m(self.serial, point))
        self.focus_distance_m = subject_m * (1.0 + self._af_error())
        self.af_count += 1

    def _af_error(self) -> float:
        """Relative error of this AF: 0 for the body's first, else 0.3-1.0 % in front of or behind the subject."""
        if self.af_count == 0 and self.run == 0:
            return 0.0
        rng = np.random.default_rng([self.af_seed, self.run, zlib.crc32(self.serial.encode()), self.af_count])
        return float(rng.uniform(*AF_SCATTER_REL) * rng.choice((-1.0, 1.0)))

    def _read_only(self) -> set[int]:
        fixed = {EosProp.AVAILABLE_SHOTS, EosProp.BATTERY_POWER, EosProp.OLC_INFO_VERSION, EosProp.AUTO_EXPOSURE_MODE}
        return fixed | ({EosProp.FOCUS_MODE} if self.faults.focus_mode_fixed else set())

    def card_is_full(self) -> bool:
        """No room for the next image (``card_full``, or the next release is ``full_from_release``)."""
        full_from = self.faults.full_from_release
        return self.faults.card_full or (full_from is not None and self.releases + 1 >= full_from)

    def _expose(self) -> Reply:
        if self.card_is_full():
            return Reply(Resp.STORE_FULL)
        self.releases += 1
        if self.focus_distance_m is None:  # the lens sits wherever it was left: AF'd by an earlier run of this body
            self._autofocus(self.focus_point_px or self.lens_point_px)
        self.sequence += 1
        data = self.optics.expose(self.settings())
        handle = self._next_handle
        self._next_handle += 1
        ext = "DNG" if self.image_format[0] == 6 else "JPG"
        name = f"IMG_{self.sequence:04d}.{ext}"
        on_card = self.props[EosProp.CAPTURE_DESTINATION] != CAPTURE_DEST_PC
        self.objects[handle] = _Object(handle, name, data, on_card)
        self.last_object_bytes = data
        self.events.append(ev.pack_camera_status(1))
        if on_card:
            self.events.append(ev.pack_object_added_ex(handle, STORAGE_ID, OFC_DNG, len(data), CARD_IMAGE_FOLDER, name))
        else:
            self.events.append(ev.pack_request_object_transfer(handle, OFC_DNG, len(data), name))
        self.events.append(ev.pack_camera_status(0))
        return Reply(Resp.OK)

    # ------------------------------------------------------------------ the handler
    def handle(self, op: int, params: tuple[int, ...], data: bytes | None = None) -> Reply:
        """Answer one operation (params already decoded; ``data`` is the host->device data phase)."""
        self.op_log.append(op)
        if self.broken:
            return Reply(Resp.OPERATION_NOT_SUPPORTED)
        if op == Op.GET_DEVICE_INFO:
            return Reply(Resp.OK, data=self.device_info().pack())
        if op == Op.OPEN_SESSION:
            if self.session_open:
                return Reply(Resp.SESSION_ALREADY_OPEN)
            if not params or params[0] == 0:
                return Reply(Resp.INVALID_PARAMETER)
            self.session_open = True
            return Reply(Resp.OK)
        if not self.session_open:
            return Reply(Resp.SESSION_NOT_OPEN)
        if self.faults.busy_rate > 0 and self.faults.rng.random() < self.faults.busy_rate:
            self.faults.busy_answers += 1
            return Reply(Resp.DEVICE_BUSY)
        remaining = self.faults.busy.get(op, 0)
        if remaining > 0:
            self.faults.busy[op] = remaining - 1
            return Reply(Resp.DEVICE_BUSY)
        fn = getattr(self, f"_op_{op:04x}", None)
        if fn is None:
            return Reply(Resp.OPERATION_NOT_SUPPORTED)
        p = tuple(params) + (0,) * (5 - len(params))
        return fn(p, data)

    # standard operations
    def _op_1003(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        self.session_open = False
        self.broken = True  # "2016 EOS cameras ... report 0x2005 on all following opcodes"
        return Reply(Resp.OK)

    def _op_1004(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        return Reply(Resp.OK, data=Writer().array(4, [STORAGE_ID]).bytes())

    _op_9101 = _op_1004

    def _op_1005(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if p[0] != STORAGE_ID:
            return Reply(Resp.INVALID_STORAGE_ID)
        used = sum(len(o.data) for o in self.objects.values() if o.on_card)
        free = 0 if self.card_is_full() else max(CARD_FREE_BYTES - used, 0)
        shots = 0 if self.card_is_full() else max(CARD_SHOTS - sum(o.on_card for o in self.objects.values()), 0)
        info = StorageInfo(3, 2, 0, CARD_BYTES, free, shots, "SD", "EOS_DIGITAL")
        return Reply(Resp.OK, data=info.pack())

    _op_9102 = _op_1005

    def _op_1007(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """GetObjectHandles(storage, format, parent): parent 0xFFFFFFFF = the card's root, 0 = every object."""
        if p[0] not in (STORAGE_ID, 0xFFFFFFFF):
            return Reply(Resp.INVALID_STORAGE_ID)
        tree = [(h, parent) for h, (_, parent) in CARD_FOLDERS.items()]
        tree += [(h, CARD_IMAGE_FOLDER) for h, o in self.objects.items() if o.on_card]
        if p[2] == 0xFFFFFFFF:
            handles = [h for h, parent in tree if parent == 0]
        elif p[2] == 0:
            handles = [h for h, _ in tree]
        else:
            handles = [h for h, parent in tree if parent == p[2]]
        return Reply(Resp.OK, data=Writer().array(4, handles).bytes())

    def _object(self, handle: int) -> _Object | None:
        return self.objects.get(handle)

    def _op_1008(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """GetObjectInfo of a card folder (DCIM, DCIM/100CANON) or of an image (on the card or in SDRAM)."""
        if p[0] in CARD_FOLDERS:
            name, parent = CARD_FOLDERS[p[0]]
            info = ObjectInfo(storage_id=STORAGE_ID, object_format=OFC_ASSOCIATION, parent=parent,
                              association_type=1, filename=name, capture_date="20261121T200000")
            return Reply(Resp.OK, data=info.pack())
        obj = self._object(p[0])
        if obj is None:
            return Reply(Resp.INVALID_OBJECT_HANDLE)
        info = ObjectInfo(storage_id=STORAGE_ID if obj.on_card else 0, object_format=OFC_DNG, compressed_size=len(obj.data),
                          parent=CARD_IMAGE_FOLDER if obj.on_card else 0, filename=obj.name, capture_date="20261121T200000")
        return Reply(Resp.OK, data=info.pack())

    def _op_1009(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        obj = self._object(p[0])
        return Reply(Resp.INVALID_OBJECT_HANDLE) if obj is None else Reply(Resp.OK, data=obj.data)

    def _op_101b(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        obj = self._object(p[0])
        if obj is None:
            return Reply(Resp.INVALID_OBJECT_HANDLE)
        chunk = obj.data[p[1] : p[1] + p[2]]
        return Reply(Resp.OK, (len(chunk),), chunk)

    def _op_100b(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if self.objects.pop(p[0], None) is None:
            return Reply(Resp.INVALID_OBJECT_HANDLE)
        self.events.append(struct.pack("<III", 12, EosEvent.OBJECT_REMOVED, p[0]))
        return Reply(Resp.OK)

    def _op_9117(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        obj = self.objects.get(p[0])
        if obj is None or obj.on_card:
            return Reply(Resp.INVALID_OBJECT_HANDLE)
        del self.objects[p[0]]  # released from the body's SDRAM
        return Reply(Resp.OK)

    def _op_1014(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if p[0] == 0x5001:  # BatteryLevel, u8 range 0..100
            return Reply(Resp.OK, data=DevicePropDesc(0x5001, 2, False, 100, BATTERY_PERCENT, 1, [0, 100, 1]).pack())
        return Reply(Resp.DEVICE_PROP_NOT_SUPPORTED)

    def _op_1015(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if p[0] == 0x5001:
            return Reply(Resp.OK, data=bytes([BATTERY_PERCENT]))
        return Reply(Resp.DEVICE_PROP_NOT_SUPPORTED)

    # EOS operations
    def _op_9110(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if data is None or len(data) < 12:
            return Reply(Resp.INVALID_DEVICE_PROP_FORMAT)
        size, prop = struct.unpack_from("<II", data, 0)
        if size != len(data):
            return Reply(Resp.INVALID_DEVICE_PROP_FORMAT)
        if prop in (EosProp.IMAGE_FORMAT, EosProp.IMAGE_FORMAT_CF, EosProp.IMAGE_FORMAT_SD):
            if size != 28 or struct.unpack_from("<I", data, 8)[0] != 1:
                return Reply(Resp.INVALID_DEVICE_PROP_VALUE)
            self.image_format = struct.unpack_from("<III", data, 16)
            self.events.append(ev.pack_image_format_value(prop, *self.image_format))
            return Reply(Resp.OK)
        if prop not in self.props or isinstance(self.props[prop], str) or prop in self._read_only():
            return Reply(Resp.DEVICE_PROP_NOT_SUPPORTED)
        value = struct.unpack_from("<I", data, 8)[0]
        if prop in self.avail and value not in self.avail[prop]:
            return Reply(Resp.INVALID_DEVICE_PROP_VALUE)
        self.props[prop] = value
        self._queue_prop(prop)
        if prop == EosProp.CAPTURE_DESTINATION:  # the card's room, or 0 until the PC announces its (PCHDDCapacity)
            self.props[EosProp.AVAILABLE_SHOTS] = CARD_SHOTS if value == CAPTURE_DEST_CARD else 0
            self._queue_prop(EosProp.AVAILABLE_SHOTS)
        return Reply(Resp.OK)

    def _op_9108(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """GetDeviceInfoEx: u32 size, then u32-count arrays of events, properties and an unknown list."""
        events = [int(e) for e in EosEvent]
        props = sorted(int(k) for k in self.props) + [int(EosProp.IMAGE_FORMAT)]
        body = Writer().array(4, events).array(4, props).array(4, []).bytes()
        return Reply(Resp.OK, data=struct.pack("<I", 4 + len(body)) + body)

    def _op_9114(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        self.remote_mode = p[0]
        return Reply(Resp.OK)

    def _op_9115(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """SetEventMode: switching it on (each new client does) starts with a dump of every property."""
        self.event_mode = p[0]
        if p[0]:
            self._queue_dump()
        return Reply(Resp.OK)

    def _op_9116(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if not self._dumped:
            self._queue_dump()
        out = b"".join(self.events) + ev.TERMINATOR
        self.events.clear()
        return Reply(Resp.OK, data=out)

    def _op_911a(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if self.props[EosProp.CAPTURE_DESTINATION] == CAPTURE_DEST_PC:
            self.props[EosProp.AVAILABLE_SHOTS] = 9999
            self._queue_prop(EosProp.AVAILABLE_SHOTS)
        return Reply(Resp.OK)

    def _ok(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        return Reply(Resp.OK)

    _op_911b = _op_911c = _op_911d = _op_9160 = _ok

    def _op_9127(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        if p[0] in self.props:
            self._queue_prop(p[0])
        return Reply(Resp.OK)

    def _op_9159(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """ZoomPosition(x, y): moves the live-view AF frame; here in raw-image pixels."""
        self.focus_point_px = (float(p[0]), float(p[1]))
        return Reply(Resp.OK)

    def _op_9154(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """DoAf: focus at the AF frame (only in live view, like the real body); the AF state goes to OLC focus info."""
        if not int(self.props[EosProp.EVF_OUTPUT_DEVICE]) & 2:
            return Reply(Resp.GENERAL_ERROR)
        report = self.olc_mask & OLC_FOCUS_BIT and self.faults.af_result != "silent"
        ok = self.faults.af_result == "ok" and self.props[EosProp.FOCUS_MODE] != FOCUS_MODE_MF  # MF: the lens does not AF
        if report:
            self.events.append(pack_olc(OLC_VERSION, focus=0))
        if ok:
            self._autofocus()
        if report:
            self.events.append(pack_olc(OLC_VERSION, focus=FOCUS_IN_FOCUS if ok else FOCUS_FAILED))
        return Reply(Resp.OK)

    def _op_913d(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        """SetRequestOLCInfoGroup(mask)."""
        self.olc_mask = p[0]
        return Reply(Resp.OK)

    def _op_9128(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        button, no_af = p[0], p[1]
        if button not in (1, 2, 3):
            return Reply(Resp.INVALID_PARAMETER)
        if not no_af and self.props[EosProp.FOCUS_MODE] != 3:
            self._autofocus()
        self.pressed = button
        if button in (2, 3):
            return self._expose()
        return Reply(Resp.OK)

    def _op_9129(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        self.pressed = 0
        return Reply(Resp.OK)

    def _op_910f(self, p: tuple[int, ...], data: bytes | None) -> Reply:
        res = self._expose()
        return Reply(Resp.OK, (7 if res.code == Resp.STORE_FULL else 0,))
