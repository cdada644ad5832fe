"""PTP and Canon EOS codes (ISO 15740; Canon vendor extension as in libgphoto2's ptp.h).

Only the codes dp5k uses or must recognise. Exposure encodings: Canon Av/Tv/ISO codes (u16).
"""

from __future__ import annotations

import math
from enum import IntEnum


class ContainerType(IntEnum):
    COMMAND = 1
    DATA = 2
    RESPONSE = 3
    EVENT = 4


class Op(IntEnum):
    """Operation codes: standard 0x1xxx, Canon EOS 0x91xx."""

    GET_DEVICE_INFO = 0x1001
    OPEN_SESSION = 0x1002
    CLOSE_SESSION = 0x1003
    GET_STORAGE_IDS = 0x1004
    GET_STORAGE_INFO = 0x1005
    GET_OBJECT_HANDLES = 0x1007
    GET_OBJECT_INFO = 0x1008
    GET_OBJECT = 0x1009
    DELETE_OBJECT = 0x100B
    INITIATE_CAPTURE = 0x100E
    GET_DEVICE_PROP_DESC = 0x1014
    GET_DEVICE_PROP_VALUE = 0x1015
    SET_DEVICE_PROP_VALUE = 0x1016
    GET_PARTIAL_OBJECT = 0x101B
    EOS_GET_STORAGE_IDS = 0x9101
    EOS_GET_STORAGE_INFO = 0x9102
    EOS_REMOTE_RELEASE = 0x910F
    EOS_SET_DEVICE_PROP_VALUE_EX = 0x9110
    EOS_SET_REMOTE_MODE = 0x9114
    EOS_SET_EVENT_MODE = 0x9115
    EOS_GET_EVENT = 0x9116
    EOS_TRANSFER_COMPLETE = 0x9117
    EOS_PC_HDD_CAPACITY = 0x911A
    EOS_SET_UI_LOCK = 0x911B
    EOS_RESET_UI_LOCK = 0x911C
    EOS_KEEP_DEVICE_ON = 0x911D
    EOS_REQUEST_DEVICE_PROP_VALUE = 0x9127
    EOS_REMOTE_RELEASE_ON = 0x9128
    EOS_REMOTE_RELEASE_OFF = 0x9129
    EOS_SET_REQUEST_OLC_INFO_GROUP = 0x913D
    EOS_DO_AF = 0x9154
    EOS_ZOOM_POSITION = 0x9159
    EOS_AF_CANCEL = 0x9160


class Resp(IntEnum):
    """Response codes (ISO 15740 table)."""

    OK = 0x2001
    GENERAL_ERROR = 0x2002
    SESSION_NOT_OPEN = 0x2003
    INVALID_TRANSACTION_ID = 0x2004
    OPERATION_NOT_SUPPORTED = 0x2005
    PARAMETER_NOT_SUPPORTED = 0x2006
    INCOMPLETE_TRANSFER = 0x2007
    INVALID_STORAGE_ID = 0x2008
    INVALID_OBJECT_HANDLE = 0x2009
    DEVICE_PROP_NOT_SUPPORTED = 0x200A
    INVALID_OBJECT_FORMAT_CODE = 0x200B
    STORE_FULL = 0x200C
    OBJECT_WRITE_PROTECTED = 0x200D
    STORE_READ_ONLY = 0x200E
    ACCESS_DENIED = 0x200F
    NO_THUMBNAIL_PRESENT = 0x2010
    SELF_TEST_FAILED = 0x2011
    PARTIAL_DELETION = 0x2012
    STORE_NOT_AVAILABLE = 0x2013
    SPECIFICATION_BY_FORMAT_UNSUPPORTED = 0x2014
    NO_VALID_OBJECT_INFO = 0x2015
    INVALID_CODE_FORMAT = 0x2016
    UNKNOWN_VENDOR_CODE = 0x2017
    CAPTURE_ALREADY_TERMINATED = 0x2018
    DEVICE_BUSY = 0x2019
    INVALID_PARENT_OBJECT = 0x201A
    INVALID_DEVICE_PROP_FORMAT = 0x201B
    INVALID_DEVICE_PROP_VALUE = 0x201C
    INVALID_PARAMETER = 0x201D
    SESSION_ALREADY_OPEN = 0x201E
    TRANSACTION_CANCELLED = 0x201F
    SPECIFICATION_OF_DESTINATION_UNSUPPORTED = 0x2020


class Event(IntEnum):
    """Standard PTP event codes (interrupt pipe)."""

    CANCEL_TRANSACTION = 0x4001
    OBJECT_ADDED = 0x4002
    DEVICE_PROP_CHANGED = 0x4006
    CAPTURE_COMPLETE = 0x400D


class EosEvent(IntEnum):
    """Canon EOS GetEvent record codes."""

    REQUEST_GET_EVENT = 0xC101
    OBJECT_ADDED_EX = 0xC181
    OBJECT_REMOVED = 0xC182
    REQUEST_OBJECT_TRANSFER = 0xC186
    PROP_VALUE_CHANGED = 0xC189
    AVAIL_LIST_CHANGED = 0xC18A
    CAMERA_STATUS_CHANGED = 0xC18B
    WILL_SOON_SHUTDOWN = 0xC18D
    OLC_INFO_CHANGED = 0xC1A5


class EosProp(IntEnum):
    """Canon EOS device properties (set with SetDevicePropValueEx 0x9110)."""

    APERTURE = 0xD101
    SHUTTER_SPEED = 0xD102
    ISO = 0xD103
    EXP_COMPENSATION = 0xD104
    AUTO_EXPOSURE_MODE = 0xD105
    DRIVE_MODE = 0xD106
    FOCUS_MODE = 0xD108
    BATTERY_POWER = 0xD111
    AVAILABLE_SHOTS = 0xD11B
    CAPTURE_DESTINATION = 0xD11C
    IMAGE_FORMAT = 0xD120
    IMAGE_FORMAT_CF = 0xD121
    IMAGE_FORMAT_SD = 0xD122
    OLC_INFO_VERSION = 0xD199
    SERIAL_NUMBER = 0xD1AF
    EVF_OUTPUT_DEVICE = 0xD1B0
    LENS_NAME = 0xD1D8


U32_PROPS = frozenset({EosProp.FOCUS_MODE, EosProp.AVAILABLE_SHOTS, EosProp.CAPTURE_DESTINATION, EosProp.EVF_OUTPUT_DEVICE,
                       EosProp.OLC_INFO_VERSION})
"""EOS properties whose PropValueChanged value is a u32 (the others dp5k uses are u16)."""
STRING_PROPS = frozenset({EosProp.SERIAL_NUMBER, EosProp.LENS_NAME})
IMAGE_FORMAT_PROPS = frozenset({EosProp.IMAGE_FORMAT, EosProp.IMAGE_FORMAT_CF, EosProp.IMAGE_FORMAT_SD})

# EOS BatteryPower (0xD111, u16) -> charge, as libgphoto2 reads it (config.c, Canon EOS battery level)
EOS_BATTERY_LEVELS: dict[int, str] = {0: "low", 5: "25%", 1: "50%", 4: "75%", 2: "100%"}
BATTERY_LEVEL_PROP = 0x5001  # standard PTP BatteryLevel (u8 range)

CAPTURE_DEST_CARD = 2
CAPTURE_DEST_PC = 4
FOCUS_MODE_MF = 3
EVF_OUTPUT_PC = 2

OFC_DNG = 0x3811
OFC_CANON_CR2 = 0xB103
OFC_ASSOCIATION = 0x3001

CANON_VID = 0x04A9
EOS_5D_MARK_IV_PID = 0x3281
PTP_INTERFACE_CLASS = 6

# Canon EOS aperture codes (libgphoto2 config.c aperture table), f-number text -> code.
AV_CODES: dict[float, int] = {
    1.0: 0x08, 1.4: 0x10, 1.6: 0x13, 1.8: 0x15, 2.0: 0x18, 2.2: 0x1B, 2.5: 0x1D, 2.8: 0x20,
    3.2: 0x23, 3.5: 0x25, 4.0: 0x28, 4.5: 0x2B, 5.0: 0x2D, 5.6: 0x30, 6.3: 0x33, 7.1: 0x35,
    8.0: 0x38, 9.0: 0x3B, 10.0: 0x3D, 11.0: 0x40, 13.0: 0x43, 14.0: 0x45, 16.0: 0x48,
    18.0: 0x4B, 20.0: 0x4D, 22.0: 0x50, 25.0: 0x53, 29.0: 0x55, 32.0: 0x58,
}
AV_FROM_CODE: dict[int, float] = {v: k for k, v in AV_CODES.items()}

ISO_CODES: dict[int, int] = {100: 0x48, 200: 0x50, 400: 0x58, 800: 0x60, 1600: 0x68, 3200: 0x70, 6400: 0x78, 12800: 0x80}
ISO_FROM_CODE: dict[int, int] = {v: k for k, v in ISO_CODES.items()}


def av_code(f_number: float) -> int:
    """Canon Av code for a marked f-number (``f/1.8 -> 0x15``, ``f/22 -> 0x50``).

    >>> hex(av_code(1.8)), hex(av_code(22))
    ('0x15', '0x50')
    """
    key = round(float(f_number), 1)
    if key not in AV_CODES:
        raise ValueError(f"no Canon aperture code for f/{f_number}")
    return AV_CODES[key]


_TV_NOMINAL_S = (
    30, 25, 20, 15, 13, 10, 8, 6, 5, 4, 3.2, 2.5, 2, 1.6, 1.3, 1, 0.8, 0.6, 0.5, 0.4, 0.3,
    1 / 4, 1 / 5, 1 / 6, 1 / 8, 1 / 10, 1 / 13, 1 / 15, 1 / 20, 1 / 25, 1 / 30, 1 / 40, 1 / 50, 1 / 60, 1 / 80,
    1 / 100, 1 / 125, 1 / 160, 1 / 200, 1 / 250, 1 / 320, 1 / 400, 1 / 500, 1 / 640, 1 / 800, 1 / 1000,
    1 / 1250, 1 / 1600, 1 / 2000, 1 / 2500, 1 / 3200, 1 / 4000, 1 / 5000, 1 / 6400, 1 / 8000,
)
TV_CODES: dict[int, float] = dict(zip([c for c in range(0x10, 0xA1) if c % 8 in (0, 3, 5)], _TV_NOMINAL_S, strict=True))
"""Canon Tv code -> marked exposure time (s), 1/3-stop series 30 s (0x10) .. 1/8000 s (0xA0); rule 0x38 + 8 log2(1/t)."""


def tv_code(shutter_s: float) -> int:
    """Canon Tv code of the marked 1/3-stop time nearest to ``shutter_s`` (in stops).

    >>> hex(tv_code(1 / 60)), hex(tv_code(1.0)), hex(tv_code(1 / 125)), hex(tv_code(1 / 500))
    ('0x68', '0x38', '0x70', '0x80')
    """
    if not shutter_s > 0:
        raise ValueError(f"shutter time must be > 0 s, got {shutter_s}")
    if not 1 / 8000 / 1.2 <= shutter_s <= 30 * 1.2:
        raise ValueError(f"shutter time {shutter_s} s is outside 30 s .. 1/8000 s")
    return min(TV_CODES, key=lambda c: abs(math.log2(TV_CODES[c]) - math.log2(shutter_s)))


def tv_seconds(code: int) -> float:
    """Marked exposure time (s) of a Canon Tv code (``0x68 -> 1/60``)."""
    if code in TV_CODES:
        return float(TV_CODES[code])
    return float(2.0 ** (-(code - 0x38) / 8.0))


def iso_code(iso: int) -> int:
    """Canon ISO code (``100 -> 0x48``)."""
    if int(iso) not in ISO_CODES:
        raise ValueError(f"no Canon ISO code for ISO {iso}")
    return ISO_CODES[int(iso)]


def name_of(enum_type: type[IntEnum], code: int) -> str:
    """Readable name of a code, or its hex value if unknown."""
    try:
        return enum_type(code).name
    except ValueError:
        return f"0x{code:04X}"
