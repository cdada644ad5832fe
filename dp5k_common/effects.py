"""The vocabulary of physical DP effects, shared by the studio (which plants them) and diagnose
(which names them). Neither side imports the other; both import these names."""

from __future__ import annotations

EFFECT_NAMES: tuple[str, ...] = (
    "lr_gain_imbalance",
    "field_varying_psf",
    "chromatic_defocus",
    "disparity_scale",
    "focus_offset",
    "psf_profile",
    "front_back_asymmetry",
    "misregistration",
    "noise",
)
"""Every effect name, in a fixed order. ``"none"`` is diagnose's answer when no effect is found."""

NO_EFFECT = "none"
