"""Canon EOS OLCInfoChanged (0xC1A5) GetEvent records: exposure values and the AF result.

After SetRequestOLCInfoGroup (0x913D) a body reports Av/Tv/ISO changes and its focus state in these
records (possibly only there). Layout (libgphoto2 ptp-pack.c, facts only): ``u32 size | u32 code | u32 len
(size - 8 or size - 4) | u16 mask | u16 ?`` then, for each mask bit 0..12 that is set, in bit order, one
field whose byte size depends on the body's OLC version (property 0xD199):

* bit 0x0002 Tv: the Tv code is field byte 5;  bit 0x0004 Av: field byte 4;  bit 0x0008 ISO: field byte 3
* bit 0x0100 focus info: field byte 4 is the AF state: 0 idle / searching, 1 in focus, 2 failed

Only versions whose field sizes are known (0x7 .. 0xF) are decoded; others are left to PropValueChanged.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .codes import EosEvent, EosProp
from .errors import ProtocolError

OLC_REQUEST_ALL = 0x1FFF  # the group mask libgphoto2 requests
OLC_FIELD_BITS = 13
# field byte sizes for mask bits 0x0001 .. 0x1000, by OLC version
_SIZES_7 = (2, 6, 5, 4, 4, 6, 7, 4, 6, 5, 5, 8, 1)
_SIZES_8 = (2, 6, 5, 4, 4, 6, 7, 4, 6, 7, 7, 8, 1)
_SIZES_B = (2, 6, 5, 4, 4, 6, 8, 4, 6, 5, 5, 9, 1)
_SIZES_F = (2, 7, 6, 4, 4, 6, 8, 4, 6, 5, 5, 9, 1)
OLC_FIELD_SIZES: dict[int, tuple[int, ...]] = {7: _SIZES_7, 8: _SIZES_8, 9: _SIZES_8, 0xA: _SIZES_8, 0xB: _SIZES_B,
                                               0xC: _SIZES_B, 0xD: _SIZES_B, 0xE: _SIZES_B, 0xF: _SIZES_F}
# mask bit -> (property, byte of the field holding its code)
OLC_PROPS = {0x0002: (EosProp.SHUTTER_SPEED, 5), 0x0004: (EosProp.APERTURE, 4), 0x0008: (EosProp.ISO, 3)}
OLC_FOCUS_BIT = 0x0100
FOCUS_IN_FOCUS = 1
FOCUS_FAILED = 2


@dataclass(frozen=True)
class OlcInfo:
    """What one OLCInfoChanged record says: property codes changed, and the AF state if reported."""

    props: dict[int, int]
    focus: int | None


def parse_olc(rec: bytes, version: int) -> OlcInfo | None:
    """Decode one OLCInfoChanged record (``rec`` includes its 8-byte header); None if ``version`` is unknown.

    Raises:
        ProtocolError: a record too short for its mask, or whose length field disagrees with its size.
    """
    sizes = OLC_FIELD_SIZES.get(version)
    if sizes is None:
        return None
    if len(rec) < 16:
        raise ProtocolError(f"OLCInfoChanged of {len(rec)} bytes")
    length, mask = struct.unpack_from("<IH", rec, 8)
    if length not in (len(rec) - 8, len(rec) - 4):
        raise ProtocolError(f"OLCInfoChanged length {length} in a record of {len(rec)} bytes")
    props: dict[int, int] = {}
    focus = None
    off = 16
    for j in range(OLC_FIELD_BITS):
        bit = 1 << j
        if not mask & bit:
            continue
        if off + sizes[j] > len(rec):
            raise ProtocolError(f"OLCInfoChanged field 0x{bit:04X} runs past the record ({len(rec)} bytes)")
        field = rec[off : off + sizes[j]]
        if bit in OLC_PROPS:
            prop, at = OLC_PROPS[bit]
            props[prop] = field[at]
        elif bit == OLC_FOCUS_BIT:
            focus = field[4]
        off += sizes[j]
    return OlcInfo(props, focus)


def pack_olc(version: int, props: dict[int, int] | None = None, focus: int | None = None) -> bytes:
    """An OLCInfoChanged record as a body of OLC ``version`` sends it (simulated body)."""
    sizes = OLC_FIELD_SIZES[version]
    by_bit = {bit: (prop, at) for bit, (prop, at) in OLC_PROPS.items()}
    mask, fields = 0, b""
    for j in range(OLC_FIELD_BITS):
        bit = 1 << j
        field = bytearray(sizes[j])
        if bit in by_bit and props and by_bit[bit][0] in props:
            prop, at = by_bit[bit]
            field[0:2] = b"\x01\x01"
            field[at] = props[prop] & 0xFF
        elif bit == OLC_FOCUS_BIT and focus is not None:
            field[4] = focus
        else:
            continue
        mask |= bit
        fields += bytes(field)
    size = 16 + len(fields)
    return struct.pack("<IIIHH", size, EosEvent.OLC_INFO_CHANGED, size - 8, mask, 0) + fields


__all__ = ["OlcInfo", "parse_olc", "pack_olc", "OLC_REQUEST_ALL", "FOCUS_IN_FOCUS", "FOCUS_FAILED", "OLC_FIELD_SIZES"]
