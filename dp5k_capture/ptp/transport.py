"""The USB side of PTP: one class that moves bytes over a Still Image interface with pyusb.

Finds the class-6 interface's bulk-OUT, bulk-IN and interrupt-IN endpoints, writes commands and data
(with a zero-length packet when a transfer is a multiple of wMaxPacketSize), reads, and issues the
Still Image class requests (Cancel 0x64, Device Reset 0x66, Get Device Status 0x67). pyusb/libusb
errors become typed dp5k errors that name the device: ENODEV -> :class:`DisconnectedError`, a timeout ->
:class:`PTPTimeoutError`, EPIPE -> :class:`StallError`, EACCES -> :class:`UsbAccessError` (names the device
node and the udev rule that fixes it), EBUSY -> :class:`UsbBusyError` (names who holds the body).

A bulk-IN read waits in slices of at most ``READ_SLICE_MS``: libusb's synchronous transfer does not return on
a signal, so one 20 s read would keep a Ctrl-C waiting 20 s; between slices Python sees it. A slice that
times out after part of the data arrived returns that part (pyusb keeps it), so slicing loses nothing.
"""

from __future__ import annotations

import errno as errno_mod
import struct
import time
from typing import Any, Protocol

import usb.core
import usb.util

from dp5k_common.errors import DeviceError

from ..usb_access import access_denied_message, busy_message, device_node, is_access_denied, is_busy
from .codes import PTP_INTERFACE_CLASS
from .errors import DisconnectedError, PTPTimeoutError, ProtocolError, StallError, UsbAccessError, UsbBusyError

REQ_CANCEL = 0x64
REQ_GET_EXTENDED_EVENT = 0x65
REQ_DEVICE_RESET = 0x66
REQ_GET_DEVICE_STATUS = 0x67
CANCEL_EVENT_CODE = 0x4001
READ_SLICE_MS = 500  # longest uninterruptible wait of one bulk-IN read: Ctrl-C is seen within about this


class Transport(Protocol):
    """What a :class:`~dp5k_capture.ptp.session.PTPSession` needs from the wire."""

    name: str
    max_packet: int

    def write(self, data: bytes, timeout_ms: int) -> None: ...
    def read(self, size: int, timeout_ms: int) -> bytes: ...
    def read_event(self, size: int, timeout_ms: int) -> bytes: ...
    def cancel(self, tid: int) -> None: ...
    def device_status(self) -> int: ...
    def device_reset(self) -> None: ...
    def clear_halt(self) -> None: ...


def map_usb_error(exc: BaseException, name: str, step: str, node: str | None = None) -> DeviceError:
    """Translate a pyusb exception into a dp5k device error naming ``name`` (device) and ``step``; permission
    and busy errors also name the device ``node`` (``/dev/bus/usb/BBB/DDD``) and what to do."""
    if isinstance(exc, usb.core.USBTimeoutError):
        return PTPTimeoutError(f"{step}: timed out", where=name)
    if is_access_denied(exc):
        return UsbAccessError(f"{step}: {access_denied_message(node or device_node(None, None))}", where=name)
    if is_busy(exc):
        return UsbBusyError(f"{step}: {busy_message(node or device_node(None, None))}", where=name)
    err = getattr(exc, "errno", None)
    backend = getattr(exc, "backend_error_code", None)
    if err == errno_mod.ENODEV or backend == -4 or "No such device" in str(exc):
        return DisconnectedError(f"{step}: device disconnected ({exc})", where=name)
    if err == errno_mod.EPIPE or backend == -9 or "Pipe error" in str(exc):
        return StallError(f"{step}: endpoint stalled ({exc})", where=name)
    if err == errno_mod.ETIMEDOUT or backend == -7:
        return PTPTimeoutError(f"{step}: timed out", where=name)
    return DeviceError(f"{step}: USB error ({exc})", where=name)


class UsbTransport:
    """PTP bulk/interrupt pipes of one USB Still Image device (a pyusb :class:`usb.core.Device`).

    Args:
        device: the pyusb device (real libusb backend, umockdev, or the simulated backend).
        name: how errors name the device (e.g. ``"cam0 (Canon EOS 5D Mark IV, serial 0123)"``).
    """

    def __init__(self, device: usb.core.Device, name: str | None = None) -> None:
        self.device = device
        self.name = name or f"usb {device.idVendor:04x}:{device.idProduct:04x}"
        self.node = device_node(getattr(device, "bus", None), getattr(device, "address", None))
        try:
            cfg = device.get_active_configuration()
        except usb.core.USBError as first:
            if is_access_denied(first) or is_busy(first):
                raise map_usb_error(first, self.name, "open", self.node) from first
            try:
                device.set_configuration()
            except usb.core.USBError as exc:
                raise map_usb_error(exc, self.name, "set configuration", self.node) from exc
            cfg = device.get_active_configuration()
        intf = usb.util.find_descriptor(cfg, bInterfaceClass=PTP_INTERFACE_CLASS)
        if intf is None:
            raise ProtocolError("no Still Image (class 6) interface", where=self.name)
        self.interface = intf.bInterfaceNumber

        def ep(direction: int, kind: int) -> Any:
            return usb.util.find_descriptor(
                intf,
                custom_match=lambda e: usb.util.endpoint_direction(e.bEndpointAddress) == direction
                and usb.util.endpoint_type(e.bmAttributes) == kind,
            )

        self.ep_out = ep(usb.util.ENDPOINT_OUT, usb.util.ENDPOINT_TYPE_BULK)
        self.ep_in = ep(usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_BULK)
        self.ep_int = ep(usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_INTR)
        if self.ep_out is None or self.ep_in is None:
            raise ProtocolError("Still Image interface lacks bulk IN/OUT endpoints", where=self.name)
        self.max_packet = int(self.ep_in.wMaxPacketSize)
        try:
            if device.is_kernel_driver_active(self.interface):
                device.detach_kernel_driver(self.interface)
        except (NotImplementedError, usb.core.USBError):
            pass
        try:
            usb.util.claim_interface(device, self.interface)
        except usb.core.USBError as exc:
            raise map_usb_error(exc, self.name, "claim interface", self.node) from exc

    def write(self, data: bytes, timeout_ms: int) -> None:
        try:
            n = self.ep_out.write(data, timeout_ms)
            if n != len(data):
                raise DeviceError(f"bulk OUT wrote {n} of {len(data)} bytes", where=self.name)
            if data and len(data) % int(self.ep_out.wMaxPacketSize) == 0:
                self.ep_out.write(b"", timeout_ms)  # zero-length packet ends the transfer
        except usb.core.USBError as exc:
            raise map_usb_error(exc, self.name, "bulk OUT") from exc

    def read(self, size: int, timeout_ms: int) -> bytes:
        """One bulk-IN transfer of at most ``size`` bytes within ``timeout_ms``, waited for in slices."""
        return self._sliced(self.ep_in, size, timeout_ms, "bulk IN")

    def read_event(self, size: int, timeout_ms: int) -> bytes:
        if self.ep_int is None:
            return b""
        try:
            return self._sliced(self.ep_int, size, timeout_ms, "interrupt IN")
        except PTPTimeoutError:
            return b""

    def _sliced(self, ep: Any, size: int, timeout_ms: int, step: str) -> bytes:
        deadline = time.monotonic() + max(int(timeout_ms), 1) / 1000.0
        while True:
            left_ms = int((deadline - time.monotonic()) * 1000.0)
            try:
                return bytes(ep.read(size, max(1, min(READ_SLICE_MS, left_ms))))
            except usb.core.USBTimeoutError as exc:
                if left_ms <= READ_SLICE_MS:
                    raise map_usb_error(exc, self.name, step) from exc
            except usb.core.USBError as exc:
                raise map_usb_error(exc, self.name, step, self.node) from exc

    def _ctrl(self, req_type: int, req: int, data: Any, step: str) -> Any:
        try:
            return self.device.ctrl_transfer(req_type, req, 0, self.interface, data, 2000)
        except usb.core.USBError as exc:
            raise map_usb_error(exc, self.name, step, self.node) from exc

    def cancel(self, tid: int) -> None:
        """Class request Cancel (0x64): data = CancellationCode 0x4001 (u16) + TransactionID (u32)."""
        self._ctrl(0x21, REQ_CANCEL, struct.pack("<HI", CANCEL_EVENT_CODE, tid), "cancel request")

    def device_status(self) -> int:
        """Class request Get Device Status (0x67): returns the PTP response code it reports."""
        raw = bytes(self._ctrl(0xA1, REQ_GET_DEVICE_STATUS, 20, "get device status"))
        if len(raw) < 4:
            raise ProtocolError(f"device status of {len(raw)} bytes", where=self.name)
        return struct.unpack_from("<H", raw, 2)[0]

    def device_reset(self) -> None:
        """Class request Device Reset (0x66): the device closes the session and clears its pipes."""
        self._ctrl(0x21, REQ_DEVICE_RESET, None, "device reset request")

    def clear_halt(self) -> None:
        """Clear the halt (stall) on both bulk endpoints."""
        for ep in (self.ep_in, self.ep_out):
            try:
                self.device.clear_halt(ep.bEndpointAddress)
            except usb.core.USBError as exc:
                raise map_usb_error(exc, self.name, "clear halt") from exc

    def close(self) -> None:
        try:
            usb.util.release_interface(self.device, self.interface)
            usb.util.dispose_resources(self.device)
        except usb.core.USBError:
            pass
