"""Exposure of imported views measured on load (format v1 wants ``left + right`` = the full-aperture blur of
``sharp``, all on one linear scale; docs/data-format.md).

Converters do not agree on the scale of DP views: Canon DPP writes each view as a full-brightness image (so
``left + right`` is twice the combined frame), a raw pipeline writes the photodiode sums (``left + right`` =
combined), and the sharp f/22 frame has its own exposure. So nothing is assumed: on linear images, the gain
that brings ``left + right`` to the combined frame and the gain that brings ``sharp`` to it are ratios of mean
signal over the pixels unsaturated in every image (blur keeps the mean, so the ratios hold for blurred and
sharp frames alike). How well ``views_gain * (left + right)`` reproduces the combined frame pixel by pixel is
returned too: a large residual says the transfer curve (``--curve``) or the views are not what they claim.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError

SATURATED = 0.98
"""Linear value (of 1) above which a pixel is taken as clipped and left out of the ratios."""
CURVE_RESIDUAL_WARN = 0.03
"""``combined_residual`` above which the transfer curve is taken not to linearise the images (an import warning;
``--strict`` refuses the scene). Linearised right, the studio's sRGB layouts give 0.4 % (8-bit) and less."""
CURVE_BETTER_BY = 3.0
"""... or when the other curve (srgb <-> linear) leaves this many times less (:func:`linearity_warning`)."""
CURVE_RESIDUAL_FLOOR = 0.001
"""Residuals below this are fine whatever the other curve gives (quantisation, noise)."""


@dataclass(frozen=True)
class Exposure:
    """Measured gains (unitless) and the combined-frame check.

    Attributes:
        views_gain: multiply left and right by this (``mean(combined) / mean(left + right)``; 1 without a
            combined frame).
        sharp_gain: multiply sharp by this (``mean(combined) / mean(sharp)``, or ``mean(left + right) /
            mean(sharp)`` without a combined frame).
        combined_residual: median |views_gain (left + right) - combined| / mean(combined) over the unclipped
            pixels (NaN without a combined frame).
        pixels: how many pixels entered the ratios.
        headroom: a common factor (<= 1) applied to all three on top of the gains, so that the 99.9th
            percentile of ``left + right`` and of ``sharp`` stays within the 16-bit range (format v1 stores
            [0, 1]); 1 unless the views were written at full brightness each.
    """

    views_gain: float
    sharp_gain: float
    combined_residual: float
    pixels: int
    headroom: float = 1.0

    def apply(self, left: NDArray[np.floating], right: NDArray[np.floating], sharp: NDArray[np.floating]
              ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """(left, right, sharp) on the common linear scale, float32."""
        v, s = self.views_gain * self.headroom, self.sharp_gain * self.headroom
        return ((np.asarray(left) * v).astype(np.float32), (np.asarray(right) * v).astype(np.float32),
                (np.asarray(sharp) * s).astype(np.float32))

    def to_json(self) -> dict[str, float | int | None]:
        """For params.json (``combined_residual`` None without a combined frame)."""
        resid = self.combined_residual if np.isfinite(self.combined_residual) else None
        return {"views_gain": self.views_gain, "sharp_gain": self.sharp_gain, "headroom": self.headroom,
                "combined_residual": resid, "pixels": self.pixels}


def measure_exposure(left: NDArray[np.floating], right: NDArray[np.floating], sharp: NDArray[np.floating],
                     combined: NDArray[np.floating] | None = None, where: str = "") -> Exposure:
    """Gains that put left, right and sharp on the combined frame's linear scale (see the module docstring).

    Args:
        left, right, sharp, combined: (H, W, 3) linear images of one capture (combined optional).
        where: named in errors.

    Raises:
        BadInputError: a frame is black where the others are not, or every pixel is clipped.
    """
    imgs = [left, right, sharp] + ([] if combined is None else [combined])
    ok = np.ones(np.shape(left)[:2], bool)
    for a in imgs:
        ok &= np.asarray(a).max(-1) < SATURATED
    if ok.mean() < 0.05:
        raise BadInputError(f"{100 * (1 - ok.mean()):.0f} % of the pixels are clipped; cannot measure the exposure",
                            where=where or None)
    lr = float(np.asarray(left)[ok].sum() + np.asarray(right)[ok].sum())
    sh = float(np.asarray(sharp)[ok].sum())
    if lr <= 0 or sh <= 0:
        raise BadInputError("a view or the sharp frame is black; cannot measure the exposure", where=where or None)
    views = np.asarray(left, np.float32) + np.asarray(right, np.float32)
    if combined is None:
        g, sg, resid = 1.0, lr / sh, float("nan")
    else:
        c = float(np.asarray(combined)[ok].sum())
        if c <= 0:
            raise BadInputError("the combined frame is black; cannot measure the exposure", where=where or None)
        g, sg = c / lr, c / sh
        resid = float(np.median(np.abs(g * views - np.asarray(combined))[ok]) / (c / (ok.sum() * 3)))
    peak = max(float(np.percentile((g * views).max(-1), 99.9)), float(np.percentile((sg * np.asarray(sharp)).max(-1), 99.9)))
    return Exposure(g, sg, resid, int(ok.sum()), min(1.0, 1.0 / peak) if peak > 0 else 1.0)


def linearity_warning(left: NDArray[np.floating], right: NDArray[np.floating], sharp: NDArray[np.floating],
                      combined: NDArray[np.floating], curve: str, residual: float) -> str | None:
    """A warning when ``curve`` does not linearise the images, measured on the combined frame: in linear light
    ``left + right`` is the combined frame times one gain. The images are re-encoded with ``curve`` and read with
    the other one (srgb <-> linear), and the residual (``Exposure.combined_residual``) of both readings compared.
    Where the views are alike a power-law curve is nearly absorbed by the gain (a wrong curve left 0.28 % on the
    studio's 16-bit layout), but the right curve fits to the quantisation (0.001 %): so the warning comes when the
    residual is above :data:`CURVE_RESIDUAL_WARN`, or when the other curve fits :data:`CURVE_BETTER_BY` times better
    (and this one leaves more than :data:`CURVE_RESIDUAL_FLOOR`); None when fine.

    Args:
        left, right, sharp, combined: (H, W, 3) images already linearised with ``curve``.
        curve: the curve they were read with (``srgb`` or ``linear``).
        residual: their measured ``combined_residual``.
    """
    if not np.isfinite(residual) or residual <= CURVE_RESIDUAL_FLOOR:
        return None
    from dp5k_common.transfer import linear_to_srgb, srgb_to_linear

    other = "linear" if curve == "srgb" else "srgb"

    def reread(img: NDArray[np.floating]) -> NDArray[np.floating]:
        return linear_to_srgb(img) if curve == "srgb" else srgb_to_linear(np.clip(np.asarray(img, np.float32), 0, 1))

    try:
        alt = measure_exposure(reread(left), reread(right), reread(sharp), reread(combined)).combined_residual
    except BadInputError:
        alt = float("nan")
    better = bool(alt * CURVE_BETTER_BY < residual)
    if residual <= CURVE_RESIDUAL_WARN and not better:
        return None
    advice = (f"; read as {other} it is {100 * alt:.3g} %: the images are probably {other} (--curve {other}, or "
              f"\"curve\": \"{other}\" in a generic optics.json)" if better
              else f" ({100 * alt:.3g} % read as {other}: the views may not add up to the combined frame)")
    return (f"left + right does not reproduce the combined frame: median residual {100 * residual:.3g} % of its mean "
            f"with the {curve} curve, so it does not linearise these images" + advice)
