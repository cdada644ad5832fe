"""The rig description (``rig.toml``): bodies by serial, focus points, projector port and exposure plan.

Example (all keys optional except the bodies' serials on a real rig)::

    capture_destination = "pc"     # or "card": the body writes to its card, the client downloads the new file
    delete_from_card = false       # "card": delete each card file after its download is verified

    [[body]]
    id = "cam0"
    serial = "012345678901"
    focus_point_px = [3360, 2240]

    [[body]]
    id = "cam1"
    serial = "012345678902"
    focus_point_px = [3360, 2240]

    [projector]
    port = "/dev/ttyUSB0"      # RS-232C, null-modem cable, 9600 8N1
    display_index = 1          # SDL display of the HDMI output
    source = "30"              # HDMI1

    [exposure]
    iso = 100
    dp_f_numbers = [1.8, 2.0, 2.8, 4.0, 5.6]
    dp_shutter_s_at_f1_8 = 0.002   # scaled by (N / 1.8)^2 to keep the exposure constant
    sharp_f_number = 22.0

    [timeouts]                 # seconds; libgphoto2-like defaults
    transaction_s = 20.0       # one USB transaction
    capture_s = 100.0          # release -> new raw announced
    settings_s = 10.0          # Av/Tv/ISO confirmed by the body
    focus_s = 10.0             # AF result
"""

from __future__ import annotations

import numpy as np

import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from dp5k_common.errors import BadInputError

from .ptp.codes import av_code, tv_code, tv_seconds

CAPTURE_DESTINATIONS = ("pc", "card")


@dataclass(frozen=True)
class BodyConfig:
    """One camera body. ``focus_point_px`` is in raw-image pixels (x, y).

    ``K`` (3x3, raw px) and ``dist`` (OpenCV k1, k2, p1, p2, k3) are the body's intrinsics prior for its
    focus setting (from a one-time many-view calibration, e.g. ``calib/`` on 20+ ChArUco views); they are
    copied into the manifest, and processing holds them fixed while the scene's 3 ChArUco pairs
    re-estimate the stereo R, T. Empty = unknown (processing then estimates them from the 3 views).
    """

    id: str
    serial: str = ""
    model: str = "Canon EOS 5D Mark IV"
    lens: str = "EF85mm f/1.8 USM"
    sensor_size_mm: tuple[float, float] = (36.0, 24.0)
    raw_size_px: tuple[int, int] = (6720, 4480)
    focus_point_px: tuple[int, int] = (3360, 2240)
    K: tuple[tuple[float, float, float], ...] = ()
    dist: tuple[float, ...] = ()


@dataclass(frozen=True)
class ProjectorConfig:
    """The projector: serial port for ESC/VP21 and the display that carries its HDMI input."""

    model: str = "EPSON EB-U42"
    port: str = "/dev/ttyUSB0"
    width: int = 1920
    height: int = 1200
    display_index: int = 1
    source: str = "30"
    settle_s: float = 0.15


@dataclass(frozen=True)
class ExposureConfig:
    """Exposure plan. Shutter times are rounded to Canon's 1/3-stop codes.

    ``dp_shutter_s_at_f1_8`` is scaled by ``(N / 1.8)^2`` so every DP aperture gets the same exposure.
    """

    iso: int = 100
    dp_f_numbers: tuple[float, ...] = (1.8, 2.0, 2.8, 4.0, 5.6)
    dp_shutter_s_at_f1_8: float = 1 / 500
    sharp_f_number: float = 22.0
    sharp_shutter_s: float = 1 / 4
    sl_f_number: float = 22.0
    sl_shutter_s: float = 1 / 4
    charuco_f_number: float = 22.0
    charuco_shutter_s: float = 1 / 4
    charuco_views: int = 3

    def dp_shutter_s(self, f_number: float) -> float:
        """Shutter for a DP aperture at constant exposure, rounded to the camera's nearest 1/3 stop."""
        return canon_shutter(self.dp_shutter_s_at_f1_8 * (f_number / 1.8) ** 2)


@dataclass(frozen=True)
class TimeoutConfig:
    """Time limits (seconds) of the body protocol (``[timeouts]`` in rig.toml). On expiry the error names the
    step and the body. Defaults follow libgphoto2 (20 s per USB transaction, ~100 s for a capture).

    Attributes:
        transaction_s: one PTP transaction phase (command, data, response) on USB.
        capture_s: after the release, until the body announces the new raw file.
        settings_s: until the body confirms (echoes) an aperture, shutter, ISO or other setting.
        focus_s: after DoAf, until the body reports its AF result (in focus, or failed).
    """

    transaction_s: float = 20.0
    capture_s: float = 100.0
    settings_s: float = 10.0
    focus_s: float = 10.0


@dataclass(frozen=True)
class RigConfig:
    """The whole rig.

    ``capture_destination``: ``pc`` (the body sends each raw straight to the PC, nothing on the card) or ``card``
    (the body writes it to its card; the client downloads the new card file, and deletes it after a verified
    download when ``delete_from_card``).
    """

    bodies: tuple[BodyConfig, ...] = (BodyConfig("cam0"), BodyConfig("cam1"))
    projector: ProjectorConfig = field(default_factory=ProjectorConfig)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    aux_view: str = "left"
    timeouts: TimeoutConfig = field(default_factory=TimeoutConfig)
    capture_destination: str = "pc"
    delete_from_card: bool = False


def canon_shutter(shutter_s: float) -> float:
    """The exposure time the body will really use for a request (via its Tv code)."""
    return tv_seconds(tv_code(shutter_s))


def _build(cls: type, data: dict[str, Any], where: str) -> Any:
    known = {f.name: f for f in fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in known:
            raise BadInputError(f"unknown key {key!r} (known: {', '.join(sorted(known))})", where=where)
        kwargs[key] = tuple(value) if isinstance(value, list) else value
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise BadInputError(str(exc), where=where) from exc


def load_rig(path: str | Path) -> RigConfig:
    """Read and validate ``rig.toml``.

    Raises:
        BadInputError: missing file, TOML syntax error, unknown keys, invalid apertures/shutters.
    """
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text())
    except FileNotFoundError as exc:
        raise BadInputError("rig file not found", where=path) from exc
    except tomllib.TOMLDecodeError as exc:
        raise BadInputError(f"not valid TOML ({exc})", where=path) from exc
    bodies = tuple(_build(BodyConfig, b, f"{path} [[body]]") for b in raw.pop("body", [])) or RigConfig().bodies
    projector = _build(ProjectorConfig, raw.pop("projector", {}), f"{path} [projector]")
    exposure = _build(ExposureConfig, raw.pop("exposure", {}), f"{path} [exposure]")
    timeouts = _build(TimeoutConfig, raw.pop("timeouts", {}), f"{path} [timeouts]")
    aux_view = raw.pop("aux_view", "left")
    destination = raw.pop("capture_destination", "pc")
    delete = raw.pop("delete_from_card", False)
    if raw:
        raise BadInputError(f"unknown sections or keys {sorted(raw)}", where=path)
    rig = RigConfig(bodies, projector, exposure, aux_view, timeouts, destination, delete)
    validate_rig(rig, str(path))
    return rig


def validate_rig(rig: RigConfig, where: str = "rig") -> None:
    """Check ids, apertures (Canon Av codes exist), shutters (Tv range) and the aux view."""
    ids = [b.id for b in rig.bodies]
    if len(ids) != 2 or len(set(ids)) != 2:
        raise BadInputError(f"the rig needs two bodies with distinct ids, got {ids}", where=where)
    e = rig.exposure
    try:
        for f in (*e.dp_f_numbers, e.sharp_f_number, e.sl_f_number, e.charuco_f_number):
            av_code(f)
        for s in (e.dp_shutter_s_at_f1_8, e.sharp_shutter_s, e.sl_shutter_s, e.charuco_shutter_s):
            tv_code(s)
        for f in e.dp_f_numbers:
            tv_code(e.dp_shutter_s(f))
    except ValueError as exc:
        raise BadInputError(str(exc), where=where) from exc
    for b in rig.bodies:
        if b.K and (np.shape(b.K) != (3, 3) or not np.isfinite(np.asarray(b.K, float)).all()):
            raise BadInputError(f"body {b.id}: K must be a finite 3x3 matrix in raw px", where=where)
        if b.dist and (len(b.dist) not in (4, 5, 8) or not np.isfinite(np.asarray(b.dist, float)).all()):
            raise BadInputError(f"body {b.id}: dist must hold 4, 5 or 8 finite OpenCV coefficients", where=where)
    if rig.capture_destination not in CAPTURE_DESTINATIONS:
        raise BadInputError(f"capture_destination must be one of {', '.join(CAPTURE_DESTINATIONS)}, got {rig.capture_destination!r}", where=where)
    if not isinstance(rig.delete_from_card, bool):
        raise BadInputError(f"delete_from_card must be true or false, got {rig.delete_from_card!r}", where=where)
    if rig.aux_view not in ("left", "right"):
        raise BadInputError(f"aux_view must be left or right, got {rig.aux_view!r}", where=where)
    if not (math.isfinite(e.iso) and e.iso > 0):
        raise BadInputError(f"bad ISO {e.iso}", where=where)
    for f in fields(TimeoutConfig):
        limit = getattr(rig.timeouts, f.name)
        if not (isinstance(limit, (int, float)) and math.isfinite(limit) and limit > 0):
            raise BadInputError(f"[timeouts] {f.name} must be a positive number of seconds, got {limit!r}", where=where)
