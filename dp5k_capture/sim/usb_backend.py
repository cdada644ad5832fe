"""A pyusb backend (``usb.backend.IBackend``) whose devices are simulated PTP cameras.

``usb.core.find(backend=SimUsbBackend([...]))`` returns ordinary :class:`usb.core.Device` objects, so
dp5k's transport, discovery and session code run unchanged; only libusb is replaced. Descriptors follow
the real layout: one configuration, interface 0 class 6/1/1, bulk IN 0x81, bulk OUT 0x02, interrupt IN
0x83 (8-byte packets).
"""

from __future__ import annotations

import array
from types import SimpleNamespace
from typing import Any

import usb.backend
import usb.core

from .usb_device import EP_IN, EP_INT, EP_OUT, SimUsbPtpDevice


class SimUsbBackend(usb.backend.IBackend):
    """pyusb backend over a list of :class:`SimUsbPtpDevice`."""

    def __init__(self, devices: list[SimUsbPtpDevice]) -> None:
        super().__init__()
        self.devices = list(devices)

    def enumerate_devices(self) -> Any:
        return iter(self.devices)

    def get_device_descriptor(self, dev: SimUsbPtpDevice) -> Any:
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0, bDeviceProtocol=0,
            bMaxPacketSize0=64, idVendor=dev.vid, idProduct=dev.pid, bcdDevice=0x0001, iManufacturer=1,
            iProduct=2, iSerialNumber=3, bNumConfigurations=1, address=dev.address, bus=dev.bus,
            port_number=1, port_numbers=(1,), speed=3,
        )

    def get_configuration_descriptor(self, dev: SimUsbPtpDevice, config: int) -> Any:
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=39, bNumInterfaces=1, bConfigurationValue=1,
                               iConfiguration=0, bmAttributes=0xC0, bMaxPower=1, extra_descriptors=[])

    def get_interface_descriptor(self, dev: SimUsbPtpDevice, intf: int, alt: int, config: int) -> Any:
        if intf != 0 or alt != 0:
            raise IndexError("no such interface")
        return SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=3,
                               bInterfaceClass=6, bInterfaceSubClass=1, bInterfaceProtocol=1, iInterface=0,
                               extra_descriptors=[])

    def get_endpoint_descriptor(self, dev: SimUsbPtpDevice, ep: int, intf: int, alt: int, config: int) -> Any:
        table = [(EP_IN, 2, dev.max_packet, 0), (EP_OUT, 2, dev.max_packet, 0), (EP_INT, 3, 8, 9)]
        addr, attrs, size, interval = table[ep]
        return SimpleNamespace(bLength=7, bDescriptorType=5, bEndpointAddress=addr, bmAttributes=attrs,
                               wMaxPacketSize=size, bInterval=interval, bRefresh=0, bSynchAddress=0,
                               extra_descriptors=[])

    def open_device(self, dev: SimUsbPtpDevice) -> SimUsbPtpDevice:
        dev.open()  # EACCES without permission on the device node (no udev rule)
        return dev

    def close_device(self, dev_handle: SimUsbPtpDevice) -> None:
        pass

    def set_configuration(self, dev_handle: SimUsbPtpDevice, config_value: int) -> None:
        dev_handle._check_present()

    def get_configuration(self, dev_handle: SimUsbPtpDevice) -> int:
        return 1

    def set_interface_altsetting(self, dev_handle: SimUsbPtpDevice, intf: int, altsetting: int) -> None:
        pass

    def claim_interface(self, dev_handle: SimUsbPtpDevice, intf: int) -> None:
        dev_handle.claim()  # EBUSY while another process holds the interface

    def release_interface(self, dev_handle: SimUsbPtpDevice, intf: int) -> None:
        pass

    def is_kernel_driver_active(self, dev_handle: SimUsbPtpDevice, intf: int) -> bool:
        return False

    def bulk_write(self, dev_handle: SimUsbPtpDevice, ep: int, intf: int, data: array.array, timeout: int) -> int:
        return dev_handle.bulk_out(bytes(data))

    def bulk_read(self, dev_handle: SimUsbPtpDevice, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        chunk = dev_handle.bulk_in(len(buff) * buff.itemsize, timeout)
        memoryview(buff).cast("B")[: len(chunk)] = chunk
        return len(chunk)

    def intr_read(self, dev_handle: SimUsbPtpDevice, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        chunk = dev_handle.interrupt_in(len(buff), timeout)
        memoryview(buff).cast("B")[: len(chunk)] = chunk
        return len(chunk)

    def ctrl_transfer(self, dev_handle: SimUsbPtpDevice, bmRequestType: int, bRequest: int, wValue: int,
                      wIndex: int, data: array.array, timeout: int) -> int:
        if bmRequestType & 0x80:
            out = dev_handle.control(bmRequestType, bRequest, wValue, wIndex, len(data))
            assert isinstance(out, bytes)
            memoryview(data).cast("B")[: len(out)] = out
            return len(out)
        res = dev_handle.control(bmRequestType, bRequest, wValue, wIndex, bytes(data))
        return int(res) if isinstance(res, int) else len(res)

    def clear_halt(self, dev_handle: SimUsbPtpDevice, ep: int) -> None:
        dev_handle.clear_halt(ep)

    def reset_device(self, dev_handle: SimUsbPtpDevice) -> None:
        dev_handle._check_present()
