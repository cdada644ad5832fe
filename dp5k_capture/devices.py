"""Device discovery and opening: Canon bodies by USB vendor id and serial number, the projector's port.

The 5D Mark IV's DeviceInfo reports VendorExtensionID 6 (not Canon's 0xB), so Canon is recognised by USB
vendor id 0x04A9 and the body by the USB iSerialNumber string (checked against DeviceInfo and ``rig.toml``).
Reading that string needs the device open; a device this user may not open (no udev rule) is still listed,
with its device node and ``permission = "denied"``, so a missing body is explained rather than "not found".
The pyusb backend is injected (``backend``): libusb on the rig, the simulated bus in tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import usb.core
import usb.util
from serial.tools import list_ports

from dp5k_common.errors import DeviceError

from .canon import CaptureTiming, EosCamera
from .ptp.codes import CANON_VID, PTP_INTERFACE_CLASS
from .ptp.errors import UsbAccessError
from .ptp.session import PTPSession, SessionConfig
from .ptp.transport import UsbTransport, map_usb_error
from .rig import RigConfig
from .usb_access import access_denied_message, device_node, is_access_denied


@dataclass
class FoundBody:
    """A Canon PTP device on USB."""

    vid: int
    pid: int
    serial: str
    product: str
    bus: int | None
    address: int | None
    device: Any
    permission: str = "ok"  # "ok", or "denied": the device node cannot be opened by this user
    problem: str = ""  # why the strings could not be read (other than permission)

    @property
    def node(self) -> str:
        """The device node, ``/dev/bus/usb/BBB/DDD``."""
        return device_node(self.bus, self.address)

    def line(self) -> str:
        perm = "" if self.permission == "ok" else f"  NO PERMISSION on {self.node}"
        return f"{self.vid:04x}:{self.pid:04x} at {self.node}  serial {self.serial or '?'}  {self.product}{perm}".rstrip()


def _is_ptp(dev: usb.core.Device) -> bool:
    try:
        for cfg in dev:
            if usb.util.find_descriptor(cfg, bInterfaceClass=PTP_INTERFACE_CLASS) is not None:
                return True
    except usb.core.USBError:
        return False
    return False


def find_bodies(backend: Any = None) -> list[FoundBody]:
    """Every Canon (VID 0x04A9) USB device with a Still Image interface."""
    try:
        devs = list(usb.core.find(find_all=True, idVendor=CANON_VID, backend=backend) or [])
    except usb.core.NoBackendError as exc:
        raise DeviceError(f"no libusb backend ({exc}); install libusb-1.0", where="usb") from exc
    out = []
    for dev in devs:
        if not _is_ptp(dev):
            continue
        serial = product = problem = ""
        permission = "ok"
        try:  # pyusb's Device.langids hides why strings fail; asking for them directly shows EACCES
            usb.util.get_langids(dev)
            serial = usb.util.get_string(dev, dev.iSerialNumber) or "" if dev.iSerialNumber else ""
            product = usb.util.get_string(dev, dev.iProduct) or "" if dev.iProduct else ""
        except usb.core.USBError as exc:
            if is_access_denied(exc):
                permission = "denied"
            else:
                problem = str(exc)
        except (ValueError, NotImplementedError) as exc:
            problem = str(exc)
        out.append(FoundBody(dev.idVendor, dev.idProduct, serial, product, dev.bus, dev.address, dev, permission, problem))
    return out


def serial_ports() -> list[str]:
    """Serial ports on this machine (candidates for the projector's RS-232C adapter)."""
    return [f"{p.device}  {p.description}" for p in list_ports.comports()]


def _denied_text(denied: list[FoundBody]) -> str:
    """One line for Canon devices whose serial this user cannot read (no permission on their nodes)."""
    first = denied[0]
    more = "" if len(denied) == 1 else f" (and {', '.join(f.node for f in denied[1:])})"
    return f"Canon {first.vid:04x}:{first.pid:04x}, serial unreadable: {access_denied_message(first.node)}{more}"


def open_body(found: FoundBody, cam_id: str, config: SessionConfig | None = None, timing: CaptureTiming | None = None,
              *, destination: str = "pc", delete_from_card: bool = False) -> EosCamera:
    """Open a PTP session on a found body and put it into EOS remote mode (capture to ``destination``)."""
    name = f"{cam_id} ({found.product or 'Canon'} serial {found.serial or '?'})"
    transport = UsbTransport(found.device, name)
    cam = EosCamera(PTPSession(transport, config), (found.vid, found.pid), timing, destination=destination,
                    delete_from_card=delete_from_card)
    cam.cam_id, cam.serial = cam_id, found.serial
    info = cam.open()
    if found.serial and info.serial_number and not info.serial_number.endswith(found.serial):
        raise DeviceError(f"DeviceInfo serial {info.serial_number} does not match USB serial {found.serial}", where=name)
    return cam


def open_bodies(rig: RigConfig, backend: Any = None, config: SessionConfig | None = None,
                timing: CaptureTiming | None = None) -> dict[str, EosCamera]:
    """Open the rig's two bodies, matched by serial number (in rig order if no serials are configured), capturing to
    the rig's ``capture_destination``."""
    found = find_bodies(backend)
    listing = "; ".join(f.line() for f in found) or "none"
    denied = [f for f in found if f.permission == "denied"]
    chosen: dict[str, FoundBody] = {}
    for i, b in enumerate(rig.bodies):
        if b.serial:
            match = [f for f in found if f.serial == b.serial]
            if not match:
                if denied:
                    raise UsbAccessError(f"body with serial {b.serial} not found among the Canon bodies this user may "
                                         f"open; {_denied_text(denied)}", where=b.id)
                raise DeviceError(f"body with serial {b.serial} not found on USB (found: {listing})", where=b.id)
            chosen[b.id] = match[0]
        else:
            if denied:
                raise UsbAccessError(f"cannot tell the bodies apart: {_denied_text(denied)}", where=b.id)
            if len(found) != len(rig.bodies):
                raise DeviceError(f"rig.toml gives no serials and {len(found)} Canon bodies are connected (found: {listing})", where=b.id)
            chosen[b.id] = found[i]
    cams: dict[str, EosCamera] = {}
    try:
        for cam_id, f in chosen.items():
            try:
                cams[cam_id] = open_body(f, cam_id, config, timing, destination=rig.capture_destination,
                                         delete_from_card=rig.delete_from_card)
            except usb.core.USBError as exc:
                raise map_usb_error(exc, cam_id, "open", f.node) from exc
    except BaseException:
        for cam in cams.values():
            cam.close()
        raise
    return cams
