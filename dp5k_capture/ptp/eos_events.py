"""Canon EOS GetEvent (0x9116) records: a bounded parser (client) and packers (simulated body).

The data phase is a list of records ``u32 size (incl. these 8 bytes) | u32 code | body``, ended by the
terminator ``size=8, code=0``. Offsets below are from the record start (libgphoto2 ptp-pack.c):

* 0xC189 PropValueChanged: prop u32 @8, value @12 (u16 or u32 by property; ASCII for strings)
* 0xC18A AvailListChanged: prop u32 @8, type u32 @12 (3 = list), count u32 @16, values @20, 4 bytes each
* 0xC181 ObjectAddedEx: handle @8, storage @12, OFC u16 @16, size u32 @28, parent @32, filename @40
* 0xC186 RequestObjectTransfer: handle @8, OFC @12, size @20, filename @28
* 0xC18B CameraStatusChanged: status @8 (1 = busy)
* 0xC1A5 OLCInfoChanged: Av/Tv/ISO and the AF state (:mod:`dp5k_capture.ptp.olc`), decoded with the OLC
  version the body reported (property 0xD199), into PropValueChanged records and one record with ``focus``
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from .codes import IMAGE_FORMAT_PROPS, STRING_PROPS, U32_PROPS, EosEvent, EosProp
from .errors import ProtocolError
from .olc import parse_olc

MAX_RECORDS = 4096
MAX_LIST = 1024


@dataclass
class EosRecord:
    """One decoded event record; fields not used by its code stay None."""

    code: int
    prop: int | None = None
    value: int | str | None = None
    values: list[int] = field(default_factory=list)
    handle: int | None = None
    ofc: int | None = None
    size: int | None = None
    filename: str | None = None
    status: int | None = None
    focus: int | None = None


def _u32(rec: bytes, off: int) -> int:
    if off + 4 > len(rec):
        raise ProtocolError(f"event record of {len(rec)} bytes too short for a field at {off}")
    return struct.unpack_from("<I", rec, off)[0]


def _cstr(rec: bytes, off: int) -> str:
    if off > len(rec):
        raise ProtocolError(f"event record of {len(rec)} bytes too short for a name at {off}")
    return rec[off:].split(b"\x00", 1)[0].decode("ascii", errors="replace")


def _image_format(rec: bytes, off: int) -> int:
    """ImageFormat struct -> ``kind << 16 | size << 8 | compression`` of its first image (RAW = 0x060004)."""
    n = _u32(rec, off)
    if n not in (1, 2):
        raise ProtocolError(f"ImageFormat with {n} entries")
    kind, size, comp = _u32(rec, off + 8), _u32(rec, off + 12), _u32(rec, off + 16)
    return ((kind & 0xFF) << 16) | ((size & 0xFF) << 8) | (comp & 0xFF)


def parse_events(data: bytes, *, where: str | None = None, olc_version: int = 0) -> list[EosRecord]:
    """Decode a GetEvent data phase. Stops at the terminator or the end of the buffer.

    ``olc_version`` is the body's OLC version known so far (a PropValueChanged of 0xD199 in ``data``
    updates it for the records after it); OLCInfoChanged records of an unknown version are kept undecoded.

    Raises:
        ProtocolError: a record whose size is < 8 or runs past the buffer, or a malformed body.
    """
    out: list[EosRecord] = []
    pos = 0
    data = bytes(data)
    while pos + 8 <= len(data):
        size, code = struct.unpack_from("<II", data, pos)
        if size == 8 and code == 0:
            break
        if size < 8 or pos + size > len(data):
            raise ProtocolError(f"event record at byte {pos} has size {size} (buffer {len(data)})", where=where)
        if len(out) >= MAX_RECORDS:
            raise ProtocolError(f"more than {MAX_RECORDS} event records", where=where)
        rec = data[pos : pos + size]
        try:
            if code == EosEvent.OLC_INFO_CHANGED:
                out += _decode_olc(rec, olc_version)
            else:
                out.append(_decode(code, rec))
                if out[-1].prop == EosProp.OLC_INFO_VERSION and isinstance(out[-1].value, int):
                    olc_version = out[-1].value
        except ProtocolError as exc:
            raise ProtocolError(f"event 0x{code:04X} at byte {pos}: {exc.message}", where=where) from exc
        pos += size
    return out


def _decode_olc(rec: bytes, version: int) -> list[EosRecord]:
    info = parse_olc(rec, version)
    if info is None:
        return [EosRecord(EosEvent.OLC_INFO_CHANGED)]
    out = [EosRecord(EosEvent.PROP_VALUE_CHANGED, prop=prop, value=value) for prop, value in info.props.items()]
    if info.focus is not None:
        out.append(EosRecord(EosEvent.OLC_INFO_CHANGED, focus=info.focus))
    return out


def _decode(code: int, rec: bytes) -> EosRecord:
    if code == EosEvent.PROP_VALUE_CHANGED:
        prop = _u32(rec, 8)
        if prop in STRING_PROPS:
            return EosRecord(code, prop=prop, value=_cstr(rec, 12))
        if prop in IMAGE_FORMAT_PROPS:
            return EosRecord(code, prop=prop, value=_image_format(rec, 12))
        if prop in U32_PROPS:
            return EosRecord(code, prop=prop, value=_u32(rec, 12))
        if len(rec) < 14:
            raise ProtocolError("PropValueChanged without a value")
        return EosRecord(code, prop=prop, value=struct.unpack_from("<H", rec, 12)[0])
    if code == EosEvent.AVAIL_LIST_CHANGED:
        prop, _kind, count = _u32(rec, 8), _u32(rec, 12), _u32(rec, 16)
        if count > MAX_LIST or 20 + 4 * count > len(rec):
            raise ProtocolError(f"AvailListChanged of {count} values does not fit in {len(rec)} bytes")
        return EosRecord(code, prop=prop, values=list(struct.unpack_from(f"<{count}I", rec, 20)))
    if code == EosEvent.OBJECT_ADDED_EX:
        return EosRecord(code, handle=_u32(rec, 8), ofc=_u32(rec, 16) & 0xFFFF, size=_u32(rec, 28), filename=_cstr(rec, 40))
    if code == EosEvent.REQUEST_OBJECT_TRANSFER:
        return EosRecord(code, handle=_u32(rec, 8), ofc=_u32(rec, 12) & 0xFFFF, size=_u32(rec, 20), filename=_cstr(rec, 28))
    if code == EosEvent.CAMERA_STATUS_CHANGED:
        return EosRecord(code, status=_u32(rec, 8))
    if code == EosEvent.OBJECT_REMOVED:
        return EosRecord(code, handle=_u32(rec, 8))
    return EosRecord(code)


# ---------------------------------------------------------------------------------------- packers
TERMINATOR = struct.pack("<II", 8, 0)


def _record(code: int, body: bytes) -> bytes:
    return struct.pack("<II", 8 + len(body), code) + body


def pack_prop_value(prop: int, value: int | str) -> bytes:
    """PropValueChanged; integers as u32 slot (u16 props read the low half), strings NUL-terminated."""
    if isinstance(value, str):
        return _record(EosEvent.PROP_VALUE_CHANGED, struct.pack("<I", prop) + value.encode("ascii") + b"\x00")
    return _record(EosEvent.PROP_VALUE_CHANGED, struct.pack("<II", prop, value & 0xFFFFFFFF))


def pack_image_format_value(prop: int, kind: int, size: int, compression: int) -> bytes:
    """PropValueChanged for an ImageFormat property holding one image (e.g. RAW: kind 6, size 0, comp 4)."""
    body = struct.pack("<IIIIII", prop, 1, 0x10, kind, size, compression)
    return _record(EosEvent.PROP_VALUE_CHANGED, body)


def pack_avail_list(prop: int, values: list[int]) -> bytes:
    return _record(EosEvent.AVAIL_LIST_CHANGED, struct.pack(f"<III{len(values)}I", prop, 3, len(values), *values))


def pack_object_added_ex(handle: int, storage: int, ofc: int, size: int, parent: int, filename: str) -> bytes:
    body = bytearray(32)
    struct.pack_into("<IIH", body, 0, handle, storage, ofc)
    struct.pack_into("<II", body, 20, size, parent)
    return _record(EosEvent.OBJECT_ADDED_EX, bytes(body) + filename.encode("ascii") + b"\x00")


def pack_request_object_transfer(handle: int, ofc: int, size: int, filename: str) -> bytes:
    body = bytearray(20)
    struct.pack_into("<II", body, 0, handle, ofc)
    struct.pack_into("<I", body, 12, size)
    return _record(EosEvent.REQUEST_OBJECT_TRANSFER, bytes(body) + filename.encode("ascii") + b"\x00")


def pack_camera_status(status: int) -> bytes:
    return _record(EosEvent.CAMERA_STATUS_CHANGED, struct.pack("<I", status))
