"""PTP USB bulk containers (ISO 15740 / USB Still Image Capture Device Definition).

Layout (little-endian): ``u32 length | u16 type | u16 code | u32 transaction_id | payload``; the 12-byte
header is followed by 0-5 u32 parameters (command, response), the dataset bytes (data) or 0-3
parameters (event). Parsing is bounded: a container's length is checked against ``max_length`` before
anything is allocated for it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

from .codes import ContainerType
from .errors import ProtocolError

HEADER = struct.Struct("<IHHI")
HEADER_LEN = HEADER.size  # 12 bytes
MAX_PARAMS = 5
MAX_CONTAINER_BYTES = 0xFFFFFFFF  # 0xFFFFFFFF also means "unknown length" (> 4 GiB objects)


@dataclass(frozen=True)
class Header:
    """A decoded container header. ``length`` counts header + payload, bytes."""

    length: int
    type: int
    code: int
    tid: int


@dataclass(frozen=True)
class Container:
    """A whole container: header fields plus params (command/response/event) or payload (data)."""

    type: int
    code: int
    tid: int
    params: tuple[int, ...] = ()
    payload: bytes = field(default=b"", repr=False)

    def pack(self) -> bytes:
        """Encode to bytes (parameters for non-data containers, payload for data)."""
        if self.type == ContainerType.DATA:
            body = bytes(self.payload)
        else:
            if len(self.params) > MAX_PARAMS:
                raise ValueError(f"at most {MAX_PARAMS} parameters, got {len(self.params)}")
            body = struct.pack(f"<{len(self.params)}I", *(p & 0xFFFFFFFF for p in self.params))
        return HEADER.pack(HEADER_LEN + len(body), int(self.type), int(self.code), int(self.tid)) + body


def parse_header(buf: bytes | bytearray | memoryview, *, max_length: int, where: str | None = None) -> Header:
    """Decode the 12-byte header at the start of ``buf``.

    Raises:
        ProtocolError: fewer than 12 bytes, length < 12 or > ``max_length``, or an unknown type.
    """
    if len(buf) < HEADER_LEN:
        raise ProtocolError(f"short container: {len(buf)} bytes, need a 12-byte header", where=where)
    length, ctype, code, tid = HEADER.unpack_from(bytes(buf[:HEADER_LEN]))
    if length < HEADER_LEN:
        raise ProtocolError(f"container length {length} is smaller than its header", where=where)
    if length > max_length:
        raise ProtocolError(f"container length {length} exceeds the bound {max_length}", where=where)
    if ctype not in (1, 2, 3, 4):
        raise ProtocolError(f"unknown container type {ctype}", where=where)
    return Header(length, ctype, code, tid)


def parse_params(header: Header, body: bytes, *, where: str | None = None) -> tuple[int, ...]:
    """The u32 parameters of a command/response/event container body (``length - 12`` bytes).

    Raises:
        ProtocolError: body not a whole number of u32, or more than 5 parameters.
    """
    n, rest = divmod(len(body), 4)
    if rest or n > MAX_PARAMS:
        raise ProtocolError(f"container body of {len(body)} bytes is not 0-5 u32 parameters", where=where)
    return struct.unpack(f"<{n}I", body)


def parse_container(buf: bytes, *, max_length: int = 1 << 20, where: str | None = None) -> Container:
    """Decode one complete container occupying all of ``buf``."""
    hdr = parse_header(buf, max_length=max_length, where=where)
    if hdr.length != len(buf):
        raise ProtocolError(f"container says {hdr.length} bytes but {len(buf)} arrived", where=where)
    body = bytes(buf[HEADER_LEN:])
    if hdr.type == ContainerType.DATA:
        return Container(hdr.type, hdr.code, hdr.tid, (), body)
    return Container(hdr.type, hdr.code, hdr.tid, parse_params(hdr, body, where=where))
