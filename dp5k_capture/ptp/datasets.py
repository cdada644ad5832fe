"""PTP datasets (DeviceInfo, ObjectInfo, StorageInfo, DevicePropDesc): bounded readers and writers.

Every length read from the device (string character counts, array element counts) is checked against
the bytes actually present before anything is allocated, so a garbled dataset raises
:class:`ProtocolError` instead of allocating gigabytes or crashing.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from .errors import ProtocolError

MAX_ARRAY_ELEMENTS = 1 << 20


class Reader:
    """Little-endian cursor over an untrusted byte buffer; every read is bounds-checked."""

    def __init__(self, data: bytes, *, where: str | None = None) -> None:
        self.data = bytes(data)
        self.pos = 0
        self.where = where

    def _take(self, n: int, what: str) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise ProtocolError(f"dataset truncated reading {what} at byte {self.pos} (need {n}, have {len(self.data) - self.pos})", where=self.where)
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def u8(self, what: str = "u8") -> int:
        return self._take(1, what)[0]

    def u16(self, what: str = "u16") -> int:
        return struct.unpack("<H", self._take(2, what))[0]

    def u32(self, what: str = "u32") -> int:
        return struct.unpack("<I", self._take(4, what))[0]

    def u64(self, what: str = "u64") -> int:
        return struct.unpack("<Q", self._take(8, what))[0]

    def string(self, what: str = "string") -> str:
        """PTP string: u8 character count (including the NUL), then UTF-16LE code units."""
        n = self.u8(what)
        if n == 0:
            return ""
        raw = self._take(2 * n, what)
        text = raw.decode("utf-16-le", errors="replace")
        return text.split("\x00", 1)[0]

    def array(self, width: int, what: str = "array") -> list[int]:
        """u32 element count, then that many little-endian integers of ``width`` bytes (2 or 4)."""
        n = self.u32(what)
        if n > MAX_ARRAY_ELEMENTS or n * width > len(self.data) - self.pos:
            raise ProtocolError(f"{what}: array of {n} elements does not fit in the {len(self.data) - self.pos} bytes left", where=self.where)
        fmt = {2: "H", 4: "I"}[width]
        return list(struct.unpack(f"<{n}{fmt}", self._take(n * width, what)))


class Writer:
    """Little-endian dataset builder (used by the simulated body and in tests)."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def u8(self, v: int) -> Writer:
        self.parts.append(struct.pack("<B", v))
        return self

    def u16(self, v: int) -> Writer:
        self.parts.append(struct.pack("<H", v))
        return self

    def u32(self, v: int) -> Writer:
        self.parts.append(struct.pack("<I", v & 0xFFFFFFFF))
        return self

    def u64(self, v: int) -> Writer:
        self.parts.append(struct.pack("<Q", v))
        return self

    def string(self, s: str) -> Writer:
        if not s:
            return self.u8(0)
        units = (s + "\x00").encode("utf-16-le")
        if len(units) // 2 > 255:
            raise ValueError("PTP strings hold at most 254 characters")
        self.parts.append(struct.pack("<B", len(units) // 2) + units)
        return self

    def array(self, width: int, values: list[int] | tuple[int, ...]) -> Writer:
        fmt = {2: "H", 4: "I"}[width]
        self.parts.append(struct.pack(f"<I{len(values)}{fmt}", len(values), *values))
        return self

    def bytes(self) -> bytes:
        return b"".join(self.parts)


@dataclass
class DeviceInfo:
    """ISO 15740 DeviceInfo dataset."""

    standard_version: int = 100
    vendor_extension_id: int = 0
    vendor_extension_version: int = 0
    vendor_extension_desc: str = ""
    functional_mode: int = 0
    operations: list[int] = field(default_factory=list)
    events: list[int] = field(default_factory=list)
    properties: list[int] = field(default_factory=list)
    capture_formats: list[int] = field(default_factory=list)
    image_formats: list[int] = field(default_factory=list)
    manufacturer: str = ""
    model: str = ""
    device_version: str = ""
    serial_number: str = ""

    @classmethod
    def parse(cls, data: bytes, *, where: str | None = None) -> DeviceInfo:
        r = Reader(data, where=where)
        return cls(
            r.u16("StandardVersion"), r.u32("VendorExtensionID"), r.u16("VendorExtensionVersion"),
            r.string("VendorExtensionDesc"), r.u16("FunctionalMode"), r.array(2, "OperationsSupported"),
            r.array(2, "EventsSupported"), r.array(2, "DevicePropertiesSupported"), r.array(2, "CaptureFormats"),
            r.array(2, "ImageFormats"), r.string("Manufacturer"), r.string("Model"), r.string("DeviceVersion"),
            r.string("SerialNumber"),
        )

    def pack(self) -> bytes:
        return (
            Writer().u16(self.standard_version).u32(self.vendor_extension_id).u16(self.vendor_extension_version)
            .string(self.vendor_extension_desc).u16(self.functional_mode).array(2, self.operations)
            .array(2, self.events).array(2, self.properties).array(2, self.capture_formats)
            .array(2, self.image_formats).string(self.manufacturer).string(self.model)
            .string(self.device_version).string(self.serial_number).bytes()
        )


@dataclass
class ObjectInfo:
    """ISO 15740 ObjectInfo dataset (the fields dp5k uses are named; the rest keep their defaults)."""

    storage_id: int = 0
    object_format: int = 0
    protection_status: int = 0
    compressed_size: int = 0
    thumb_format: int = 0
    thumb_compressed_size: int = 0
    thumb_width: int = 0
    thumb_height: int = 0
    image_width: int = 0
    image_height: int = 0
    image_bit_depth: int = 0
    parent: int = 0
    association_type: int = 0
    association_desc: int = 0
    sequence_number: int = 0
    filename: str = ""
    capture_date: str = ""
    modification_date: str = ""
    keywords: str = ""

    @classmethod
    def parse(cls, data: bytes, *, where: str | None = None) -> ObjectInfo:
        r = Reader(data, where=where)
        return cls(
            r.u32("StorageID"), r.u16("ObjectFormat"), r.u16("ProtectionStatus"), r.u32("ObjectCompressedSize"),
            r.u16("ThumbFormat"), r.u32("ThumbCompressedSize"), r.u32("ThumbPixWidth"), r.u32("ThumbPixHeight"),
            r.u32("ImagePixWidth"), r.u32("ImagePixHeight"), r.u32("ImageBitDepth"), r.u32("ParentObject"),
            r.u16("AssociationType"), r.u32("AssociationDesc"), r.u32("SequenceNumber"), r.string("Filename"),
            r.string("CaptureDate"), r.string("ModificationDate"), r.string("Keywords"),
        )

    def pack(self) -> bytes:
        return (
            Writer().u32(self.storage_id).u16(self.object_format).u16(self.protection_status)
            .u32(self.compressed_size).u16(self.thumb_format).u32(self.thumb_compressed_size)
            .u32(self.thumb_width).u32(self.thumb_height).u32(self.image_width).u32(self.image_height)
            .u32(self.image_bit_depth).u32(self.parent).u16(self.association_type).u32(self.association_desc)
            .u32(self.sequence_number).string(self.filename).string(self.capture_date)
            .string(self.modification_date).string(self.keywords).bytes()
        )


@dataclass
class StorageInfo:
    """ISO 15740 StorageInfo dataset."""

    storage_type: int = 3
    filesystem_type: int = 2
    access: int = 0
    max_capacity: int = 0
    free_bytes: int = 0
    free_images: int = 0
    description: str = ""
    label: str = ""

    @classmethod
    def parse(cls, data: bytes, *, where: str | None = None) -> StorageInfo:
        r = Reader(data, where=where)
        return cls(r.u16(), r.u16(), r.u16(), r.u64(), r.u64(), r.u32(), r.string(), r.string())

    def pack(self) -> bytes:
        return (
            Writer().u16(self.storage_type).u16(self.filesystem_type).u16(self.access).u64(self.max_capacity)
            .u64(self.free_bytes).u32(self.free_images).string(self.description).string(self.label).bytes()
        )


_INT_TYPES = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "q", 8: "Q"}


@dataclass
class DevicePropDesc:
    """DevicePropDesc for integer properties: code, datatype, get/set, default, current, form (enum/range)."""

    code: int
    datatype: int
    writable: bool
    default: int
    current: int
    form: int = 0  # 0 none, 1 range, 2 enumeration
    values: list[int] = field(default_factory=list)  # range: [min, max, step]; enum: the values

    @classmethod
    def parse(cls, data: bytes, *, where: str | None = None) -> DevicePropDesc:
        r = Reader(data, where=where)
        code, dtype, getset = r.u16("PropertyCode"), r.u16("DataType"), r.u8("GetSet")
        if dtype not in _INT_TYPES:
            raise ProtocolError(f"property 0x{code:04X}: datatype 0x{dtype:04X} is not an integer type", where=where)
        fmt = "<" + _INT_TYPES[dtype]
        width = struct.calcsize(fmt)

        def val(what: str) -> int:
            return struct.unpack(fmt, r._take(width, what))[0]

        default, current = val("FactoryDefault"), val("CurrentValue")
        form = r.u8("FormFlag")
        values: list[int] = []
        if form == 1:
            values = [val("Min"), val("Max"), val("Step")]
        elif form == 2:
            n = r.u16("NumberOfValues")
            if n * width > len(r.data) - r.pos:
                raise ProtocolError(f"property 0x{code:04X}: enumeration of {n} does not fit", where=where)
            values = [val("EnumValue") for _ in range(n)]
        return cls(code, dtype, bool(getset), default, current, form, values)

    def pack(self) -> bytes:
        fmt = "<" + _INT_TYPES[self.datatype]
        out = struct.pack("<HHB", self.code, self.datatype, int(self.writable))
        out += struct.pack(fmt, self.default) + struct.pack(fmt, self.current) + struct.pack("<B", self.form)
        if self.form == 1:
            out += b"".join(struct.pack(fmt, v) for v in self.values)
        elif self.form == 2:
            out += struct.pack("<H", len(self.values)) + b"".join(struct.pack(fmt, v) for v in self.values)
        return out


def parse_u32_array(data: bytes, *, where: str | None = None, what: str = "array") -> list[int]:
    """A u32 count followed by u32 values (GetStorageIDs, GetObjectHandles)."""
    return Reader(data, where=where).array(4, what)
