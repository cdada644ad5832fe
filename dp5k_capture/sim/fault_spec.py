"""``--sim-faults`` text -> faults armed on the simulated bodies.

Grammar: comma-separated items ``[CAM.]NAME@K``, ``[CAM.]NAME=P`` or ``[CAM.]NAME``; without ``CAM.`` an item
applies to every body. Downloads and releases are counted per body from 1 (a raw download is each raw file
the body sends from offset 0).

=================  ===================================================================================
``disconnect@K``   the body vanishes from USB halfway through its K-th raw download (ENODEV, sticky)
``stall@K``        bulk IN stalls when its K-th raw download starts (the client recovers and retries)
``hang@K``         the body stops sending halfway through its K-th raw download and never answers that
                   read (only meaningful with a sim-rig server: the client is then killed or Ctrl-C'd)
``full@K``         the card has room for K-1 more images: the K-th release and all later ones answer
                   StoreFull (0x200C), and the card reports no free space from then on (at once for K = 1)
``busy=P``         every operation answers DeviceBusy with probability P (0..1)
``denied``         the body's USB device node cannot be opened by this user (EACCES: no udev rule)
``held``           another process has claimed the body's interface (EBUSY: gvfs, gphoto2, another dp5k)
=================  ===================================================================================

Example: ``disconnect@37,busy=0.1``, ``cam1.hang@5`` or ``cam1.denied``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from dp5k_common.errors import BadInputError

_ITEM = re.compile(r"(?:(?P<cam>[A-Za-z0-9_-]+)\.)?(?P<name>[a-z]+)(?:@(?P<k>\d+)|=(?P<p>[0-9.]+))?")
DOWNLOAD_FAULTS = ("disconnect", "stall", "hang")
FLAG_FAULTS = ("denied", "held")


@dataclass(frozen=True)
class BodyFaultPlan:
    """Faults of one body. ``*_at_download``: 1-based raw download number, None = never."""

    disconnect_at_download: int | None = None
    stall_at_download: int | None = None
    hang_at_download: int | None = None
    full_at_release: int | None = None
    busy_rate: float = 0.0
    denied: bool = False
    held: bool = False


def parse_sim_faults(spec: str, camera_ids: tuple[str, ...]) -> dict[str, BodyFaultPlan]:
    """Parse ``spec`` for the bodies ``camera_ids``; an empty spec gives no faults.

    Raises:
        BadInputError: an item that does not parse, an unknown fault or body, a rate outside 0..1.
    """
    plans: dict[str, dict[str, float | int | bool]] = {c: {} for c in camera_ids}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        m = _ITEM.fullmatch(item)
        if m is None or (m["k"] is None and m["p"] is None and m["name"] not in FLAG_FAULTS):
            raise BadInputError(f"fault {item!r} is not NAME@K, NAME=P or denied/held (e.g. disconnect@37,busy=0.1)",
                                where="--sim-faults")
        cams = [m["cam"]] if m["cam"] else list(camera_ids)
        unknown = [c for c in cams if c not in plans]
        if unknown:
            raise BadInputError(f"fault {item!r}: no body {unknown[0]!r} (bodies: {', '.join(camera_ids)})", where="--sim-faults")
        name = m["name"]
        if name in DOWNLOAD_FAULTS and m["k"] is not None and int(m["k"]) >= 1:
            value: float | int | bool = int(m["k"])
            key = f"{name}_at_download"
        elif name == "full" and m["k"] is not None and int(m["k"]) >= 1:
            value, key = int(m["k"]), "full_at_release"
        elif name in FLAG_FAULTS and m["k"] is None and m["p"] is None:
            value, key = True, name
        elif name == "busy" and m["p"] is not None:
            value = float(m["p"])
            if not 0.0 <= value <= 1.0:
                raise BadInputError(f"fault {item!r}: the busy rate must lie in 0..1", where="--sim-faults")
            key = "busy_rate"
        else:
            raise BadInputError(f"fault {item!r}: use disconnect@K, stall@K, hang@K, full@K (K >= 1), busy=P, denied or held",
                                where="--sim-faults")
        for c in cams:
            plans[c][key] = value
    return {c: BodyFaultPlan(**kw) for c, kw in plans.items()}  # type: ignore[arg-type]


__all__ = ["BodyFaultPlan", "parse_sim_faults"]
