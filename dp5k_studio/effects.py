"""Physical DP effects of the studio's optics: named, parameterized, off by default.

Names come from :data:`dp5k_common.effects.EFFECT_NAMES` (diagnose uses the same vocabulary). Each effect
has a *strength* ``s >= 0``; ``s = 1`` is a documented "moderate" realistic magnitude taken from real
data (notes dp-simulators.md section 7), and the parameters scale with ``s`` as listed. ``x_n, y_n`` are
field coordinates normalized to [-1, 1] across the image (x right), ``r_n = sqrt(x_n^2 + y_n^2) / sqrt(2)``.

==========================  ==========================================================================
effect                      physics and parameters at strength s
==========================  ==========================================================================
lr_gain_imbalance           per-view gains ``g_L = 2 rho / (1 + rho)``, ``g_R = 2 / (1 + rho)`` with the L/R
                            ratio ``ln rho(x) = s (0.18 + 0.10 x_n - 0.06 y_n^2)``: ratio 1.20 at the centre,
                            1.09..1.32 across the field at s = 1 (Pixel 4: 1.18..1.24 scene means, 1.01..1.49
                            flat field). ``g_L + g_R = 2`` where the views agree, so in-focus brightness holds.
field_varying_psf           blur size grows with the field, ``c -> c (1 + 0.30 s r_n^2)`` (Pixel 4: sigma 4.8 px
                            centre vs 6.8 px edge), and the split softens off axis: on the left of the field
                            the left view receives ``kappa = 0.25 s max(0, -x_n)`` of the right half's light
                            (its PSF becomes a full ellipse), mirrored on the right.
chromatic_defocus           longitudinal chromatic aberration: per-channel thin-lens focal lengths
                            ``f_R = f + 0.04 s mm``, ``f_G = f``, ``f_B = f - 0.04 s mm`` with the sensor set for
                            green, so red and blue are defocused by ~1 px (1680 px wide, f/1.8) at the
                            focus distance and focus at slightly different depths.
disparity_scale             symmetric crosstalk between the two photodiodes: each view receives
                            ``kappa = 0.5 s / (1 + s)`` of the other half's light, so DP disparity shrinks by
                            ``1 - 2 kappa = 1 / (1 + s)`` (0.5 at s = 1; Canon's ~0.17 of the ideal split is
                            s ~ 5). Blur of left + right is unchanged.
focus_offset                the lens focuses at ``F_true = F_rec (1 + 0.05 s)`` while ``F_rec`` (the recorded
                            focus distance = depth at the focus point) is what params.json holds
                            (+5 % at s = 1: 2.70 m -> 2.84 m).
psf_profile                 the disc is not flat: radial weight ``1 + 1.5 s (rho / R)^4`` (bright rim,
                            "soap-bubble" bokeh), renormalized to the same energy.
front_back_asymmetry        spherical-aberration-like: behind focus (C > 0) the weight is
                            ``1 + 1.0 s (rho / R)^2`` (rim-heavy), in front of focus ``1 + 1.0 s (1 - (rho/R)^2)``
                            (centre-heavy) and front blur is ``1 + 0.10 s`` times larger.
misregistration             both DP views shifted against sharp/depth by ``(dx, dy) = s (0.0030 W, -0.0015 H)``
                            px of the output image (5.0, -1.7 px at 1680 x 1120; 0.86, -0.29 px at 288 x 192),
                            a band-limited (Fourier) shift that changes neither blur nor brightness (raw
                            route: only exposures below f/8, i.e. the DP captures, not the depth frames).
noise                       signal-dependent noise stronger than nominal: shot-noise variance x (1 + 3 s)
                            and read-noise sigma x (1 + s).
==========================  ==========================================================================
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from dp5k_common.effects import EFFECT_NAMES
from dp5k_common.errors import BadInputError


@dataclass(frozen=True)
class EffectSet:
    """Strengths of the planted effects (absent = off). Immutable; ``EffectSet()`` is the ideal lens.

    Attributes:
        strengths: effect name -> strength (>= 0).
    """

    strengths: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        clean: dict[str, float] = {}
        for name, s in dict(self.strengths).items():
            if name not in EFFECT_NAMES:
                raise BadInputError(f"unknown effect {name!r} (known: {', '.join(EFFECT_NAMES)})")
            s = float(s)
            if not (math.isfinite(s) and s >= 0):
                raise BadInputError(f"effect {name}: strength must be a finite number >= 0, got {s}")
            if s > 0:
                clean[name] = s
        object.__setattr__(self, "strengths", clean)

    @classmethod
    def of(cls, **strengths: float) -> EffectSet:
        """``EffectSet.of(misregistration=1.0, noise=0.5)``."""
        return cls(strengths)

    def s(self, name: str) -> float:
        """Strength of ``name`` (0.0 if off)."""
        if name not in EFFECT_NAMES:
            raise BadInputError(f"unknown effect {name!r}")
        return float(self.strengths.get(name, 0.0))

    def __bool__(self) -> bool:
        return bool(self.strengths)

    def names(self) -> list[str]:
        return [n for n in EFFECT_NAMES if n in self.strengths]

    def to_json(self, image_size: tuple[int, int] | None = None) -> dict[str, Any]:
        """``{name: {"strength": s, ...physical parameters}}`` for params.json / dataset.json (ground truth
        for tests; diagnose must never read it to decide)."""
        out: dict[str, Any] = {}
        for name in self.names():
            out[name] = {"strength": self.s(name), **effect_parameters(name, self.s(name), image_size)}
        return out


def effect_parameters(name: str, s: float, image_size: tuple[int, int] | None = None) -> dict[str, Any]:
    """The physical parameters of effect ``name`` at strength ``s`` (see the module table)."""
    if name == "lr_gain_imbalance":
        return {"lr_ratio_center": math.exp(0.18 * s), "log_ratio_coeffs": [0.18 * s, 0.10 * s, -0.06 * s]}
    if name == "field_varying_psf":
        return {"coc_growth_at_corner": 0.30 * s, "edge_leak": 0.25 * s}
    if name == "chromatic_defocus":
        return {"focal_shift_mm_rgb": [0.04 * s, 0.0, -0.04 * s]}
    if name == "disparity_scale":
        return {"crosstalk": 0.5 * s / (1.0 + s), "disparity_factor": 1.0 / (1.0 + s)}
    if name == "focus_offset":
        return {"focus_factor": 1.0 + 0.05 * s}
    if name == "psf_profile":
        return {"rim_gain": 1.5 * s, "rim_power": 4}
    if name == "front_back_asymmetry":
        return {"back_rim_gain": 1.0 * s, "front_center_gain": 1.0 * s, "front_size_factor": 1.0 + 0.10 * s}
    if name == "misregistration":
        out: dict[str, Any] = {"shift_frac": [0.0030 * s, -0.0015 * s]}
        if image_size is not None:
            out["shift_px"] = [0.0030 * s * image_size[0], -0.0015 * s * image_size[1]]
        return out
    if name == "noise":
        return {"shot_var_factor": 1.0 + 3.0 * s, "read_sigma_factor": 1.0 + s}
    raise BadInputError(f"unknown effect {name!r}")


def parse_effect(text: str) -> tuple[str, float]:
    """Parse ``"name=strength"`` (or just ``"name"`` = strength 1.0).

    Raises:
        BadInputError: unknown name or a strength that is not a number >= 0.
    """
    name, _, val = str(text).partition("=")
    name = name.strip()
    if name not in EFFECT_NAMES:
        raise BadInputError(f"unknown effect {name!r} in {text!r} (known: {', '.join(EFFECT_NAMES)})")
    try:
        s = float(val) if val.strip() else 1.0
    except ValueError as exc:
        raise BadInputError(f"effect strength in {text!r} is not a number") from exc
    if not (math.isfinite(s) and s >= 0):
        raise BadInputError(f"effect strength in {text!r} must be >= 0")
    return name, s


def parse_effects(texts: Iterable[str]) -> EffectSet:
    """``["noise=2", "misregistration"]`` -> EffectSet (a repeated name keeps the last strength)."""
    d: dict[str, float] = {}
    for t in texts:
        n, s = parse_effect(t)
        d[n] = s
    return EffectSet(d)
