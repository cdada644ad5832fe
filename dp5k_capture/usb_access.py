"""Day-one USB problems explained: which device node, why it cannot be opened, who holds it, how to fix it.

On Linux a USB device is the character device ``/dev/bus/usb/BBB/DDD`` (bus, address). Without a udev rule
it belongs to root: libusb's open fails with LIBUSB_ERROR_ACCESS (EACCES), pyusb then cannot read even the
serial number. While another process has claimed the PTP interface (GNOME's gvfs-gphoto2-volume-monitor,
a ``gphoto2`` command or mount, another dp5k), claiming it fails with LIBUSB_ERROR_BUSY (EBUSY). This module
names the node, reads who holds it from ``/proc/<pid>/fd`` where the kernel lets us (our own processes,
or all with root), and says how to fix it (dp5k's udev rule, shipped as package data).
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import stat
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

USB_DEVFS = "/dev/bus/usb"
PROC_ROOT = Path("/proc")  # where holders are looked up (tests point it at a fake tree)
UDEV_RULE_NAME = "60-dp5k.rules"
UDEV_RULE_DEST = f"/etc/udev/rules.d/{UDEV_RULE_NAME}"
USUAL_HOLDERS = "gvfs-gphoto2-volume-monitor (GNOME's camera automount), a gphoto2 command or gphotofs mount, or another dp5k"
LIBUSB_ERROR_ACCESS = -3
LIBUSB_ERROR_BUSY = -6


def device_node(bus: int | None, address: int | None) -> str:
    """``/dev/bus/usb/BBB/DDD`` of a USB device (``?`` when the backend does not say)."""
    if bus is None or address is None:
        return f"{USB_DEVFS}/?"
    return f"{USB_DEVFS}/{int(bus):03d}/{int(address):03d}"


def udev_rule_path() -> Path:
    """The udev rules file shipped with dp5k (``dp5k_capture/udev/60-dp5k.rules``)."""
    return Path(str(resources.files("dp5k_capture") / "udev" / UDEV_RULE_NAME))


def udev_install_commands() -> str:
    """The shell commands that install the shipped rule (one line, for error messages and docs)."""
    return (f"dp5k devices --udev-rule | sudo tee {UDEV_RULE_DEST} && sudo udevadm control --reload-rules "
            "&& sudo udevadm trigger, then unplug and replug the body")


def is_access_denied(exc: BaseException) -> bool:
    """A pyusb/libusb error that means: no permission on the device node."""
    return getattr(exc, "errno", None) == errno.EACCES or getattr(exc, "backend_error_code", None) == LIBUSB_ERROR_ACCESS


def is_busy(exc: BaseException) -> bool:
    """A pyusb/libusb error that means: another process has claimed the interface (or a kernel driver has)."""
    return getattr(exc, "errno", None) == errno.EBUSY or getattr(exc, "backend_error_code", None) == LIBUSB_ERROR_BUSY


def node_permissions(node: str) -> str | None:
    """``crw-rw-r-- root:root`` of an existing device node, None if it does not exist here."""
    try:
        st = os.stat(node)
    except OSError:
        return None
    try:
        owner = pwd.getpwuid(st.st_uid).pw_name
    except KeyError:
        owner = str(st.st_uid)
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    return f"{stat.filemode(st.st_mode)} {owner}:{group}"


@dataclass(frozen=True)
class Holder:
    """A process that has a device node open: its pid, short name (``comm``) and command line."""

    pid: int
    name: str
    cmdline: str

    def describe(self) -> str:
        what = "another dp5k" if "dp5k" in self.cmdline or self.name.startswith("dp5k") else self.name
        return f"{what} (pid {self.pid}: {self.cmdline or self.name})"


def holders(node: str, proc: Path | None = None) -> list[Holder]:
    """Processes with ``node`` open, found through ``/proc/<pid>/fd/*`` links.

    Only processes whose fd folder this user may read are seen (its own; all of them for root); the
    others are skipped silently. ``proc`` defaults to :data:`PROC_ROOT`.
    """
    found: list[Holder] = []
    try:
        pids = [e for e in os.scandir(proc or PROC_ROOT) if e.name.isdigit()]
    except OSError:
        return found
    for entry in pids:
        fd_dir = Path(entry.path) / "fd"
        try:
            links = list(os.scandir(fd_dir))
        except OSError:
            continue
        for fd in links:
            try:
                target = os.readlink(fd.path)
            except OSError:
                continue
            if target == node:
                found.append(Holder(int(entry.name), _read_text(Path(entry.path) / "comm"),
                                    _read_text(Path(entry.path) / "cmdline").replace("\0", " ").strip()))
                break
    return found


def _read_text(path: Path) -> str:
    try:
        return path.read_text(errors="replace").strip()
    except OSError:
        return ""


def access_denied_message(node: str) -> str:
    """What to say when the device node cannot be opened: the node, its permissions, the fix."""
    perms = node_permissions(node)
    shown = f"{node} ({perms})" if perms else node
    return (f"no permission to open {shown}: this user may not use the body over USB (no udev rule for Canon "
            f"04a9); install dp5k's rule: {udev_install_commands()}")


def holder_text(node: str, proc: Path | None = None) -> str:
    """Who holds ``node`` (other than this process): the processes /proc shows, else the usual suspects."""
    found = [h for h in holders(node, proc) if h.pid != os.getpid()]
    if found:
        return ", ".join(h.describe() for h in found)
    return f"another process (usually {USUAL_HOLDERS}; /proc shows none of this user's processes on it)"


RELEASE_HINT = ("quit it (gvfs: systemctl --user stop gvfs-gphoto2-volume-monitor.service, or unmount the camera in "
                "the file manager; gphoto2: end the command or fusermount -u the gphotofs mount) and run again")


def busy_message(node: str, proc: Path | None = None) -> str:
    """What to say when the interface is claimed by someone else: the holder if /proc shows it, else the usual ones."""
    return f"{node} is busy (Resource busy): held by {holder_text(node, proc)}; {RELEASE_HINT}"


__all__ = ["Holder", "holders", "device_node", "udev_rule_path", "udev_install_commands", "is_access_denied", "is_busy",
           "access_denied_message", "busy_message", "holder_text", "RELEASE_HINT", "node_permissions", "USUAL_HOLDERS", "UDEV_RULE_NAME"]
