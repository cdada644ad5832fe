"""dp5k_testing/foreign_dp.py's own physics, checked without diagnose."""

from __future__ import annotations

import math

import numpy as np

from dp5k_testing.foreign_dp import EFFECT_DEFAULTS, ForeignOptics, ForeignScene, Planted, render_views


def _flat_wall_views(W: int = 96, H: int = 24, pad: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left and right views (rows of the green channel through the middle, divided by the ideal half's
    brightness) of a uniform wall behind focus with field_varying_psf planted, and the pixels' field x."""
    scene = ForeignScene(np.full((H + 2 * pad, W + 2 * pad, 3), 0.5), np.full((H + 2 * pad, W + 2 * pad), 3000.0), pad, (W // 2, H // 2))
    left, right = render_views(scene, ForeignOptics(50.0, 1.8, 1500.0, 0.05), Planted.of("field_varying_psf"))
    x = np.arange(W) / (W - 1) * 2 - 1
    return left[H // 2, :, 1] / 0.25, right[H // 2, :, 1] / 0.25, x


def test_the_moving_split_changes_each_views_light_smoothly_across_the_field() -> None:
    """The split line sits at 1.2 a (-x) disc radii, so the left view holds 2 A(1.2 a (-x)) of the ideal half's light
    (A: the disc's area share left of the line) and the right one the rest; it changes smoothly, with no step at
    the 9 field bands it is rendered at (nearest-band rendering stepped by about 0.10 of the view)."""
    left, right, x = _flat_wall_views()
    inner = slice(6, -6)  # away from the frame's border, where the blur meets the padding's edge
    s = np.clip(1.2 * EFFECT_DEFAULTS["field_varying_psf"] * -x, -1, 1)
    share = 1 + 2 * (s * np.sqrt(1 - s * s) + np.arcsin(s)) / math.pi
    np.testing.assert_allclose(left[inner], share[inner], atol=0.03)
    # the split moves light between the views, not in or out (the discretised disc holds about 1 % more than 2)
    total = (left + right)[inner]
    np.testing.assert_allclose(total, total.mean(), atol=0.015)
    assert abs(total.mean() - 2.0) < 0.03
    assert np.abs(np.diff(left[inner])).max() < 0.03
