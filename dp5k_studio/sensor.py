"""The simulated Canon sensor: photons -> electrons (Poisson) -> DN (gain, read noise) -> 14-bit Bayer RGGB raw.

Units: radiance is the studio's linear relative unit (white paper under the studio lights ~ 0.85);
electrons per *full* DP pixel = ``radiance * qe_rgb[c] * Q_E_PER_S * shutter_s / N^2``. The pixel count of
a downscaled rig is treated as binning that keeps the per-pixel signal (documented approximation).

Gain from ISO: ``gain_e_per_dn = full_well_e / (white - black) * 100 / ISO``. Read noise: ``read_e`` electrons
before the ISO gain plus ``read_dn`` after it: ``sigma_DN^2 = (read_e / gain)^2 + read_dn^2``. Each photodiode
is sampled separately; ``main = left + right`` electrons, ``aux = left`` (Canon's Dual Pixel RAW layout).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError


@dataclass(frozen=True)
class SensorModel:
    """EOS 5D Mark IV-like sensor constants.

    Attributes:
        black_level: DN offset (14-bit).
        white_level: saturation DN (16383 for 14-bit).
        full_well_e: full well of a full DP pixel at ISO 100, electrons.
        read_e: read noise before the ISO amplifier, electrons RMS.
        read_dn: read noise after the amplifier (ADC), DN RMS.
        qe_rgb: relative channel sensitivities (R, G, B) to the studio's white light (as-shot WB = 1 / qe).
        q_e_per_s: electrons per second per unit radiance at f/1 (sets exposure).
    """

    black_level: int = 512
    white_level: int = 16383
    full_well_e: float = 67000.0
    read_e: float = 3.0
    read_dn: float = 2.0
    qe_rgb: tuple[float, float, float] = (0.55, 1.0, 0.75)
    q_e_per_s: float = 1.75e7

    def gain_e_per_dn(self, iso: int) -> float:
        """Electrons per DN at this ISO."""
        if not iso > 0:
            raise BadInputError(f"ISO must be > 0, got {iso}")
        return self.full_well_e / (self.white_level - self.black_level) * 100.0 / float(iso)

    def read_sigma_dn(self, iso: int) -> float:
        g = self.gain_e_per_dn(iso)
        return float(np.hypot(self.read_e / g, self.read_dn))

    @property
    def wb_gains(self) -> tuple[float, float, float]:
        return tuple(1.0 / q for q in self.qe_rgb)  # type: ignore[return-value]


DEFAULT_SENSOR = SensorModel()


@dataclass
class RawExposure:
    """One Dual Pixel RAW frame.

    Attributes:
        main: (H, W) uint16 Bayer RGGB, both photodiodes summed, black level included.
        aux: (H, W) uint16 Bayer RGGB, the LEFT photodiode only, black level included.
        black_level: DN offset of both frames.
        white_level: saturation DN.
        wb_gains: as-shot white balance (r, g, b) multipliers.
        metadata: camera, serial, f_number, focus_distance_m (recorded), shutter_s, iso, aux_view, effects...
    """

    main: NDArray[np.uint16]
    aux: NDArray[np.uint16]
    black_level: int
    white_level: int
    wb_gains: tuple[float, float, float]
    metadata: dict[str, Any] = field(default_factory=dict)

    def right(self) -> NDArray[np.int32]:
        """The right photodiode (main - aux, black level subtracted once), int32 DN above black."""
        return self.main.astype(np.int32) - self.aux.astype(np.int32)


def bayer_channel_index(H: int, W: int) -> NDArray[np.int8]:
    """(H, W) channel of each RGGB site: 0 = R at (even, even), 1 = G, 2 = B at (odd, odd)."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.where((yy % 2 == 0) & (xx % 2 == 0), 0, np.where((yy % 2 == 1) & (xx % 2 == 1), 2, 1)).astype(np.int8)


RGGB_SITES = ((0, 0, 0), (0, 1, 1), (1, 0, 1), (1, 1, 2))
"""(row parity, column parity, channel) of the four sites of the RGGB tile (:func:`bayer_channel_index`)."""


def mosaic(rgb: NDArray[np.floating], channel_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> NDArray[np.float64]:
    """(H, W, 3) -> (H, W) float64 RGGB mosaic: each site keeps its own channel, times that channel's gain
    (``mosaic(rgb * gain)`` with a quarter of the multiplications)."""
    a = np.asarray(rgb)
    out = np.empty(a.shape[:2], np.float64)
    for dy, dx, ch in RGGB_SITES:
        out[dy::2, dx::2] = a[dy::2, dx::2, ch].astype(np.float64) * float(channel_gain[ch])
    return out


def expose_raw(
    left_rgb: NDArray[np.floating],
    right_rgb: NDArray[np.floating],
    f_number: float,
    shutter_s: float,
    iso: int,
    rng: np.random.Generator,
    sensor: SensorModel = DEFAULT_SENSOR,
    shot_var_factor: float = 1.0,
    read_sigma_factor: float = 1.0,
) -> tuple[NDArray[np.uint16], NDArray[np.uint16]]:
    """Sample a Dual Pixel RAW from the two photodiodes' radiance.

    Args:
        left_rgb, right_rgb: (H, W, 3) radiance reaching each photodiode (each about half the light).
        f_number, shutter_s, iso: exposure.
        rng: random generator (shot and read noise).
        sensor: sensor constants.
        shot_var_factor: >1 inflates shot-noise variance (the ``noise`` effect), keeping the mean.
        read_sigma_factor: >1 inflates read noise.

    Returns:
        ``(main, aux)`` uint16 (H, W) RGGB frames, clipped to [0, white_level].
    """
    if not (f_number > 0 and shutter_s > 0):
        raise BadInputError(f"need f-number > 0 and shutter > 0 s, got N={f_number}, t={shutter_s}")
    scale = sensor.q_e_per_s * shutter_s / (f_number**2)
    g = sensor.gain_e_per_dn(iso)
    sig = sensor.read_sigma_dn(iso) * read_sigma_factor
    elec = []
    for view in (left_rgb, right_rgb):
        lam = np.maximum(mosaic(view, sensor.qe_rgb) * scale, 0.0)
        k = float(shot_var_factor)
        e = rng.poisson(lam / k).astype(np.float64) * k if k != 1.0 else rng.poisson(lam).astype(np.float64)
        elec.append(e)
    e_l, e_r = elec
    H, W = e_l.shape
    main = sensor.black_level + (e_l + e_r) / g + rng.normal(0.0, sig, (H, W))
    aux = sensor.black_level + e_l / g + rng.normal(0.0, sig, (H, W))
    to16 = lambda a: np.clip(np.rint(a), 0, sensor.white_level).astype(np.uint16)  # noqa: E731
    return to16(main), to16(aux)
