"""Typed PTP errors. All are :class:`DeviceError` s that name the device and the step (``where``)."""

from __future__ import annotations

from dp5k_common.errors import DeviceError, DeviceTimeoutError

from .codes import Resp, name_of


class ProtocolError(DeviceError):
    """Bytes from the device do not form a valid container, dataset or event record."""


class ResponseError(DeviceError):
    """The device answered an operation with a response code other than OK.

    Attributes:
        code: the PTP response code (e.g. 0x2019 DeviceBusy).
        op: the operation code it answered.
    """

    def __init__(self, code: int, op: int, *, where: str | None = None) -> None:
        self.code = int(code)
        self.op = int(op)
        super().__init__(f"operation 0x{op:04X} answered {name_of(Resp, code)} (0x{code:04X})", where=where)


class DeviceBusyError(ResponseError):
    """DeviceBusy (0x2019) persisted past the retry bound."""


class DisconnectedError(DeviceError):
    """The USB device went away (unplugged, powered off) in the middle of a step."""


class StallError(DeviceError):
    """An endpoint stalled (EPIPE) and recovery did not bring it back."""


class PTPTimeoutError(DeviceTimeoutError):
    """The device did not answer a phase of a transaction within its timeout."""


class UsbAccessError(DeviceError):
    """The USB device node cannot be opened: this user lacks permission (no udev rule)."""


class UsbBusyError(DeviceError):
    """Another process (or a kernel driver) has claimed the body's PTP interface."""


class CardFullError(DeviceError):
    """The body's card is full (StoreFull 0x200C, or RemoteRelease result 7)."""
