"""The studio's raw sensor, the reference: a Dual Pixel RAW sampled from the two photodiodes' radiance (RGGB mosaic,
quantum efficiency, shot noise, read noise, 14-bit clipping).

A readable version of :func:`dp5k_studio.sensor.expose_raw` (the whole mosaic built with ``np.take_along_axis``);
the package's version (the mosaic sliced site by site) must give the same frames bit for bit from the same random
generator (``tests/studio/test_reference_equivalence.py``). Not a test module.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError
from dp5k_studio.sensor import DEFAULT_SENSOR, SensorModel


def bayer_channel_index(H: int, W: int) -> NDArray[np.int8]:
    """(H, W) channel of each RGGB site: 0 = R at (even, even), 1 = G, 2 = B at (odd, odd)."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.where((yy % 2 == 0) & (xx % 2 == 0), 0, np.where((yy % 2 == 1) & (xx % 2 == 1), 2, 1)).astype(np.int8)


def mosaic(rgb: NDArray[np.floating]) -> NDArray[np.float64]:
    """(H, W, 3) -> (H, W) RGGB mosaic (each site keeps its own channel)."""
    H, W = rgb.shape[:2]
    ch = bayer_channel_index(H, W)
    return np.take_along_axis(np.asarray(rgb, dtype=np.float64), ch[:, :, None].astype(np.int64), axis=2)[:, :, 0]


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
    qe = np.asarray(sensor.qe_rgb)
    scale = sensor.q_e_per_s * shutter_s / (f_number**2)
    g = sensor.gain_e_per_dn(iso)
    sig = sensor.read_sigma_dn(iso) * read_sigma_factor
    elec = []
    for view in (left_rgb, right_rgb):
        lam = np.maximum(mosaic(np.asarray(view) * qe[None, None, :]) * scale, 0.0)
        k = float(shot_var_factor)
        e = rng.poisson(lam / k).astype(np.float64) * k if k != 1.0 else rng.poisson(lam).astype(np.float64)
        elec.append(e)
    e_l, e_r = elec
    H, W = e_l.shape
    main = sensor.black_level + (e_l + e_r) / g + rng.normal(0.0, sig, (H, W))
    aux = sensor.black_level + e_l / g + rng.normal(0.0, sig, (H, W))
    to16 = lambda a: np.clip(np.rint(a), 0, sensor.white_level).astype(np.uint16)  # noqa: E731
    return to16(main), to16(aux)
