"""``--sim-faults`` text -> faults armed on the simulated bodies.

Grammar: comma-separated items ``[CAM.]NAME@K`` or ``[CAM.]NAME=P``; without ``CAM.`` an item applies to
every body. Downloads are counted per body from 1 (each raw file the body sends from offset 0).

=================  ===================================================================================
``disconnect@K``   the body vanishes from USB halfway through its K-th raw download (ENODEV, sticky)
``stall@K``        bulk IN stalls when its K-th raw download starts (the client recovers and retries)
``hang@K``         the body stops sending halfway through its K-th raw download and never answers that
                   read (only meaningful with a sim-rig server: the client is then killed or Ctrl-C'd)
``busy=P``         every operation answers DeviceBusy with probability P (0..1)
=================  ===================================================================================

Example: ``disconnect@37,busy=0.1`` or ``cam1.hang@5``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from dp5k_common.errors import BadInputError

_ITEM = re.compile(r"(?:(?P<cam>[A-Za-z0-9_-]+)\.)?(?P<name>[a-z]+)(?:@(?P<k>\d+)|=(?P<p>[0-9.]+))")
DOWNLOAD_FAULTS = ("disconnect", "stall", "hang")


@dataclass(frozen=True)
class BodyFaultPlan:
    """Faults of one body. ``*_at_download``: 1-based raw download number, None = never."""

    disconnect_at_download: int | None = None
    stall_at_download: int | None = None
    hang_at_download: int | None = None
    busy_rate: float = 0.0


def parse_sim_faults(spec: str, camera_ids: tuple[str, ...]) -> dict[str, BodyFaultPlan]:
    """Parse ``spec`` for the bodies ``camera_ids``; an empty spec gives no faults.

    Raises:
        BadInputError: an item that does not parse, an unknown fault or body, a rate outside 0..1.
    """
    plans: dict[str, dict[str, float | int]] = {c: {} for c in camera_ids}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        m = _ITEM.fullmatch(item)
        if m is None:
            raise BadInputError(f"fault {item!r} is not NAME@K or NAME=P (e.g. disconnect@37,busy=0.1)", where="--sim-faults")
        cams = [m["cam"]] if m["cam"] else list(camera_ids)
        unknown = [c for c in cams if c not in plans]
        if unknown:
            raise BadInputError(f"fault {item!r}: no body {unknown[0]!r} (bodies: {', '.join(camera_ids)})", where="--sim-faults")
        name = m["name"]
        if name in DOWNLOAD_FAULTS and m["k"] is not None and int(m["k"]) >= 1:
            value: float | int = int(m["k"])
            key = f"{name}_at_download"
        elif name == "busy" and m["p"] is not None:
            value = float(m["p"])
            if not 0.0 <= value <= 1.0:
                raise BadInputError(f"fault {item!r}: the busy rate must lie in 0..1", where="--sim-faults")
            key = "busy_rate"
        else:
            raise BadInputError(f"fault {item!r}: use disconnect@K, stall@K, hang@K (K >= 1) or busy=P", where="--sim-faults")
        for c in cams:
            plans[c][key] = value
    return {c: BodyFaultPlan(**kw) for c, kw in plans.items()}  # type: ignore[arg-type]


__all__ = ["BodyFaultPlan", "parse_sim_faults"]
