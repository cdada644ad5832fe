"""What ``dp5k devices`` says about each Canon body and EPSON projector it can see.

Per body: model, serial, device node, permission state, battery, card free space and who holds it. A body
this user may open is probed read-only in a short PTP session (DeviceInfo, StorageInfo, the battery from
the EOS BatteryPower property 0xD111 or PTP BatteryLevel 0x5001), then left as found (event and remote mode
off, no CloseSession on a 5D Mark IV). Per serial port: permission state and holder; the projector's own
port (from ``rig.toml``, or the simulated one) is asked over ESC/VP21 for its serial number, power and lamp
hours. A projector has no battery or card.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dp5k_common.errors import DeviceError

from .devices import FoundBody
from .escvp21 import EpsonProjector, EscVp21Timing
from .ptp.codes import BATTERY_LEVEL_PROP, EOS_BATTERY_LEVELS, EosEvent, EosProp, Op
from .ptp.eos_events import parse_events
from .ptp.errors import UsbAccessError, UsbBusyError
from .ptp.session import PTPSession, SessionConfig
from .ptp.transport import UsbTransport
from .usb_access import RELEASE_HINT, access_denied_message, holder_text, holders, node_permissions

PROBE_SESSION = SessionConfig(timeout_s=3.0, busy_retries=5)
POWER_STATES = {"00": "standby", "01": "on", "02": "warming up", "03": "cooling down", "04": "standby (network on)",
                "05": "abnormal standby", "09": "A/V standby"}


@dataclass
class BodyReport:
    """One Canon body as ``dp5k devices`` lists it (``?`` where it could not be read, and why in ``note``)."""

    found: FoundBody
    model: str = "?"
    serial: str = "?"
    permission: str = "ok"
    battery: str = "?"
    card: str = "?"
    held_by: str = "nobody"
    note: str = ""

    def lines(self) -> list[str]:
        head = f"{self.model}  serial {self.serial}  ({self.found.vid:04x}:{self.found.pid:04x} at {self.found.node})"
        body = f"permission {self.permission} | battery {self.battery} | card {self.card} | held by: {self.held_by}"
        return [head, f"    {body}"] + ([f"    {self.note}"] if self.note else [])


def _held_by(node: str) -> str:
    found = [h for h in holders(node) if h.pid != os.getpid()]
    return ", ".join(h.describe() for h in found) if found else "nobody"


def _battery(session: PTPSession, props: dict[int, Any], device_props: list[int], operations: list[int]) -> str:
    eos = props.get(EosProp.BATTERY_POWER)
    if isinstance(eos, int):
        return EOS_BATTERY_LEVELS.get(eos, f"unknown (0x{eos:X})")
    if BATTERY_LEVEL_PROP in device_props and Op.GET_DEVICE_PROP_DESC in operations:
        desc = session.get_device_prop_desc(BATTERY_LEVEL_PROP)
        lo, hi = (desc.values[0], desc.values[1]) if desc.form == 1 and len(desc.values) >= 2 else (0, 100)
        return f"{round(100 * (desc.current - lo) / max(hi - lo, 1))}%"
    return "not reported"


def _card(session: PTPSession, operations: list[int]) -> str:
    ids = session.get_storage_ids() if Op.GET_STORAGE_IDS in operations else []
    if not ids:
        return "no card"
    parts = []
    for sid in ids:
        info = session.get_storage_info(sid)
        parts.append(f"{info.free_bytes / 1e9:.1f} GB free ({info.free_images} shots)"
                     + (f" of {info.max_capacity / 1e9:.1f} GB" if info.max_capacity else ""))
    return ", ".join(parts)


def probe_body(found: FoundBody, config: SessionConfig = PROBE_SESSION) -> BodyReport:
    """Read model, serial, battery and card of one found body, or say why not (permission, holder)."""
    rep = BodyReport(found, model=found.product or "Canon (model unreadable)", serial=found.serial or "?")
    if found.permission == "denied":
        rep.permission = f"DENIED on {found.node}" + (f" ({p})" if (p := node_permissions(found.node)) else "")
        rep.held_by = _held_by(found.node)
        rep.note = access_denied_message(found.node)
        return rep
    try:
        transport = UsbTransport(found.device, f"{found.vid:04x}:{found.pid:04x} at {found.node}")
    except UsbBusyError as exc:
        rep.held_by = holder_text(found.node)
        rep.note = f"its interface is claimed (Resource busy): {RELEASE_HINT}"
        return rep
    except UsbAccessError as exc:
        rep.permission = f"DENIED on {found.node}"
        rep.note = exc.message
        return rep
    except DeviceError as exc:
        rep.note = f"could not open: {exc.message}"
        return rep
    session = PTPSession(transport, config)
    try:
        session.open_session(1)
        info = session.get_device_info()
        rep.model, rep.serial = info.model or rep.model, found.serial or info.serial_number or "?"
        props: dict[int, Any] = {}
        eos = Op.EOS_GET_EVENT in info.operations and Op.EOS_SET_EVENT_MODE in info.operations
        if eos:  # EOS properties (battery) come only as events, after remote + event mode
            session.transaction(Op.EOS_SET_REMOTE_MODE, (1,))
            session.transaction(Op.EOS_SET_EVENT_MODE, (1,))
            for rec in parse_events(session.transaction(Op.EOS_GET_EVENT, data_in=True).data, where=transport.name):
                if rec.code == EosEvent.PROP_VALUE_CHANGED and rec.prop is not None:
                    props[rec.prop] = rec.value
        rep.battery = _battery(session, props, info.properties, info.operations)
        rep.card = _card(session, info.operations)
        if eos:
            session.transaction(Op.EOS_SET_EVENT_MODE, (0,))
            session.transaction(Op.EOS_SET_REMOTE_MODE, (0,))
    except DeviceError as exc:
        rep.note = f"could not read it: {exc.one_line()}"
    finally:
        session.abort_unfinished()  # never CloseSession: a 5D Mark IV breaks after it
        transport.close()
    return rep


@dataclass
class PortReport:
    """One serial port: permission, holder, and (for the projector's port) what the projector says."""

    port: str
    description: str
    permission: str = "ok"
    held_by: str = "nobody"
    projector: str = ""

    def lines(self) -> list[str]:
        out = [f"{self.port}  {self.description}".rstrip(), f"    permission {self.permission} | held by: {self.held_by}"]
        return out + ([f"    {self.projector}"] if self.projector else [])


def probe_port(port: str, description: str, *, query: bool, timing: EscVp21Timing | None = None) -> PortReport:
    """Permission and holder of a serial port; with ``query``, ask the EPSON projector on it (ESC/VP21)."""
    rep = PortReport(port, description)
    if Path(port).exists() and not os.access(port, os.R_OK | os.W_OK):
        rep.permission = (f"DENIED ({node_permissions(port)}): add yourself to its group, e.g. "
                          "sudo usermod -aG dialout $USER, and log in again")
    rep.held_by = _held_by(os.path.realpath(port)) if Path(port).exists() else "nobody"
    if not query:
        return rep
    try:
        with EpsonProjector(port, timing=timing or EscVp21Timing(default_s=1.0)) as proj:
            proj.hello()
            serial, power = proj.query("SNO"), proj.power_state()
            try:
                lamp = f", lamp {int(proj.query('LAMP'))} h"
            except (DeviceError, ValueError):
                lamp = ""
        rep.projector = f"EPSON projector (ESC/VP21): serial {serial}, power {power} ({POWER_STATES.get(power, '?')}){lamp}"
    except DeviceError as exc:
        rep.projector = f"no ESC/VP21 answer: {exc.message} (a null-modem cable? RS-232C enabled in the projector menu?)"
    return rep


__all__ = ["BodyReport", "PortReport", "probe_body", "probe_port"]
