"""Thin-lens optics shared by the studio, processing and the simulators (paper Eq. 6 and Eq. 7).

Units are in the names: ``_mm`` millimetres (scene distances and sizes on the sensor alike),
``_px`` output-image pixels, ``_m`` metres.

Sign conventions (also in docs/conventions.md):

* The signed CoC ``C`` is the blur circle's **diameter** on the sensor. ``C > 0`` for points
  **behind** the focal plane (``d > F``), ``C < 0`` in front of it, ``C = 0`` in focus.
* For ``C > 0`` a point's light in the **left** DP view lands on the **left** half of its disc and in
  the **right** view on the right half, so behind focus the right view is displaced to the right of
  the left view (+x); in front of focus the halves swap. The right PSF is the hflip of the left
  (Eq. 2). The disc's radius is ``|C| / 2``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import BadInputError


def coc_diameter_mm(
    depth_mm: ArrayLike,
    focus_distance_mm: float,
    focal_length_mm: float,
    f_number: float,
) -> NDArray[np.float64]:
    r"""Signed circle-of-confusion diameter on the sensor, in mm (paper Eq. 6).

    .. math::
        C = \frac{f^2}{N d} \cdot \frac{d - F}{F - f}

    Args:
        depth_mm: object distance ``d`` (absolute depth along the optical axis), any shape, mm.
            Zero or negative entries are treated as invalid and give NaN.
        focus_distance_mm: focus distance ``F`` in mm, must exceed the focal length.
        focal_length_mm: thin-lens focal length ``f`` in mm (use :func:`thin_lens_focal_length_mm`
            to convert a pinhole focal length).
        f_number: ``N``, e.g. 1.8.

    Returns:
        Array of the input's shape, float64, signed diameter in mm (NaN where depth <= 0).

    Example:
        >>> float(coc_diameter_mm(2000.0, 2000.0, 85.0, 1.8))
        0.0
        >>> round(float(coc_diameter_mm(4000.0, 2000.0, 85.0, 1.8)), 4)
        1.0481
    """
    f = float(focal_length_mm)
    F = float(focus_distance_mm)
    N = float(f_number)
    if not (np.isfinite(F) and np.isfinite(f) and np.isfinite(N)) or N <= 0 or f <= 0 or F <= f:
        raise BadInputError(
            f"need focus distance > focal length > 0 and f-number > 0, got F={F} mm, f={f} mm, N={N}"
        )
    d = np.asarray(depth_mm, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = (f * f) / (N * d) * (d - F) / (F - f)
    return np.where(d > 0, c, np.nan)


def coc_diameter_px(
    depth_mm: ArrayLike,
    focus_distance_mm: float,
    focal_length_mm: float,
    f_number: float,
    pixel_pitch_mm: float,
) -> NDArray[np.float64]:
    """Signed CoC diameter in output pixels: Eq. 6 divided by the pixel pitch (what ``coc.tif`` stores).

    Example:
        >>> round(float(coc_diameter_px(4000.0, 2000.0, 85.0, 1.8, 36.0 / 1680)), 2)
        48.91
    """
    if not pixel_pitch_mm > 0:
        raise BadInputError(f"pixel pitch must be > 0 mm, got {pixel_pitch_mm}")
    return coc_diameter_mm(depth_mm, focus_distance_mm, focal_length_mm, f_number) / float(pixel_pitch_mm)


def thin_lens_focal_length_mm(pinhole_focal_length_mm: float, focus_distance_mm: float) -> float:
    r"""Thin-lens focal length from a pinhole focal length and the focus distance (paper Eq. 7).

    .. math::
        \frac{1}{f_{thin}} = \frac{1}{F} + \frac{1}{f_{pin}}

    The pinhole focal length is the thin lens's image distance for the in-focus plane.

    Example:
        >>> round(thin_lens_focal_length_mm(88.7, 2000.0), 2)
        84.93
    """
    f_pin = float(pinhole_focal_length_mm)
    F = float(focus_distance_mm)
    if not (f_pin > 0 and F > 0):
        raise BadInputError(f"need positive focal length and focus distance, got f_pin={f_pin}, F={F}")
    return 1.0 / (1.0 / F + 1.0 / f_pin)


def pinhole_focal_length_mm(thin_focal_length_mm: float, focus_distance_mm: float) -> float:
    """Inverse of :func:`thin_lens_focal_length_mm`: image distance ``v = 1 / (1/f - 1/F)`` in mm."""
    f = float(thin_focal_length_mm)
    F = float(focus_distance_mm)
    if not (0 < f < F):
        raise BadInputError(f"need 0 < focal length < focus distance, got f={f}, F={F}")
    return 1.0 / (1.0 / f - 1.0 / F)


