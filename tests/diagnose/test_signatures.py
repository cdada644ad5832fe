"""Signatures are separable by construction: on atlases built from analytic kernels, each physical change moves its
own effect's signature and no other's (a gain ramp never shows as a field-varying PSF, a bright rim never as a focus
error), and the kernels' moments behave as documented."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch

from dp5k_common.effects import EFFECT_NAMES
from dp5k_diagnose import atlas as A
from dp5k_diagnose import signatures as S
from dp5k_diagnose.config import DiagnoseConfig
from dp5k_diagnose.measure import noise_signature
from dp5k_diagnose.noise import NoiseMeasure

P = 6
"""Pairs of the synthetic atlases."""


@functools.lru_cache(maxsize=None)
def kernel(h: int, c: float, side: int, *, rim: float = 0.0, shift: tuple[float, float] = (0.0, 0.0), leak: float = 0.0,
           scale_y: float = 1.0, ss: int = 8) -> np.ndarray:
    """(2h+1)^2 one view's PSF of signed CoC ``c`` px: the half disc behind focus on the ``side`` (-1 left view, +1
    right view; mirrored in front of focus), radial weight ``1 + rim (rho/R)^2``, shifted by ``shift`` px, ``leak`` of
    the other half mixed in (crosstalk), squeezed in y by ``scale_y``; it sums to 1/2."""
    R = abs(c) / 2
    ss = max(ss, int(np.ceil(8 / max(R, 1e-3))))  # several samples across even a sub-pixel disc
    ss = min(ss, 48)
    u = (np.arange((2 * h + 1) * ss) + 0.5) / ss - (h + 0.5)
    X, Y = np.meshgrid(u - shift[0], u - shift[1])
    R = max(R, 1.0 / ss)
    q = (X**2 + (Y / scale_y) ** 2) / R**2
    disc = np.where(q <= 1, 1 + rim * q, 0.0)
    own = (side * np.sign(c if c != 0 else 1) * X) > 0
    w = disc * np.where(own, 1 - leak, leak)
    px = np.arange(-h, h + 1, dtype=np.float64)
    T = np.maximum(0.0, 1.0 - np.abs(px[:, None] - u[None, :]))  # bilinear splat: sub-pixel positions survive
    k = T @ w @ T.T
    return k / max(k.sum(), 1e-12) / 2


def view_kernels(key: A.Key, **kw) -> np.ndarray:
    """(2, 3, side, side) L and R kernels of a cell at its bin's CoC (the same in every channel)."""
    grid = A.Grid.of(key)
    c = kw.pop("coc_of")(key)
    gains = kw.pop("gains", (1.0, 1.0))
    k = np.stack([g * kernel(grid.h, c, side, **kw(key) if callable(kw) else kw) for side, g in zip((-1, +1), gains)])
    # back onto the block grid: each block's mean px value
    bs = grid.bs
    k = k.reshape(2, grid.side, bs, grid.side, bs).mean((2, 4))
    return np.repeat(k[:, None], 3, axis=1)


@functools.lru_cache(maxsize=None)
def build(effect: str | None) -> A.Atlas:
    """An atlas of view-sets ``measured`` (the ideal kernels changed by ``effect``) and ``model`` (ideal), with whole
    field bins from -13 to +13 px of CoC and zone cells over the 3 x 3 field."""
    keys = [(b, -1) for b in range(-12, 13) if b != 0 and abs(A.FINE.centre(b)) <= 15] + \
           [(b, z) for z in range(9) for b in (-3, -2, 2, 3)]
    cells = {}
    for key in keys:
        grid = A.Grid.of(key)
        c = (A.FINE if key[1] < 0 else A.COARSE).centre(key[0])
        zx, zy = A.zone_centre(key[1]) if key[1] >= 0 else (0.0, 0.0)

        def ks(changed: bool) -> tuple[np.ndarray, tuple[float, float]]:
            cc, kw, gains = c, {}, (1.0, 1.0)
            if changed and effect == "focus_offset":
                cc = c + 0.6
            if changed and effect == "psf_profile":
                kw["rim"] = 1.5
            if changed and effect == "front_back_asymmetry":
                kw["rim"] = 1.5 if c > 0 else -0.6
            if changed and effect == "misregistration":
                kw["shift"] = (1.0, -1.0)  # whole px: a sub-pixel shift of a splatted kernel also blurs it
            if changed and effect == "disparity_scale":
                kw["leak"] = 0.2
            if changed and effect == "field_varying_psf" and key[1] >= 0:
                kw["scale_y"] = 1.0 - 0.25 * abs(zy)  # squeezed radially at the top and bottom of the field
            if changed and effect == "lr_gain_imbalance":
                r = math.exp(0.08 + 0.1 * zx)
                gains = (2 * r / (1 + r), 2 / (1 + r))
            k = np.stack([g * kernel(grid.h, cc, side, **kw) for side, g in zip((-1, +1), gains)])
            bs = grid.bs
            k = k.reshape(2, grid.side, bs, grid.side, bs).mean((2, 4))
            return np.repeat(k[:, None], 3, axis=1), gains

        cell = A.Cell(key[0], key[1], grid, np.arange(P), np.full(P, 1000.0), np.full(P, 1000.0 * c), np.full((P, 3), 500.0))
        for name, changed in (("measured", True), ("model", False)):
            k, gains = ks(changed)
            cell.kernels[name] = k
            cell.influence[name] = np.zeros((P, 2, 3, grid.side, grid.side))
            cell.dc[name] = np.broadcast_to(np.array(gains)[None, :, None] * 250.0, (P, 2, 3)).copy()
            cell.noise_sd[name] = np.full((2, 3), 1e-4)
        cell.factor = torch.eye(grid.n, dtype=torch.float64).expand(3, grid.n, grid.n).contiguous() * 30.0
        cells[key] = cell
    weights = np.random.default_rng(0).multinomial(P, np.full(P, 1 / P), size=60).astype(np.float64)
    return A.Atlas(("measured", "model"), cells, [f"p{i}" for i in range(P)], weights)


def signatures(atlas: A.Atlas) -> dict[str, S.Signature]:
    p = S.Pairing(atlas, "measured", "model")
    cfg = DiagnoseConfig()
    out = [S.lr_gain_signature(atlas, p), S.field_signature(atlas, p), S.chromatic_signature(p, True), S.disparity_signature(p),
           S.focus_signature(p), S.profile_signature(atlas, p), S.front_back_signature(p), S.misregistration_signature(p),
           noise_signature(NoiseMeasure(True, 1.0, np.ones(50)), cfg)]
    return {s.effect: s for s in out}


@pytest.mark.parametrize("effect", [None, "lr_gain_imbalance", "misregistration", "disparity_scale", "focus_offset",
                                    "psf_profile", "front_back_asymmetry", "field_varying_psf"])
def test_each_change_moves_its_own_signature_only(effect: str | None) -> None:
    sigs = signatures(build(effect))
    assert set(sigs) == set(EFFECT_NAMES)
    differ = {e for e, s in sigs.items() if s.differs(0.05)}
    detail = {e: [(v.name, round(v.value, 4)) for v in s.values] for e, s in sigs.items()}
    assert differ == ({effect} if effect else set()), detail


def test_signature_values_are_the_planted_ones() -> None:
    s = signatures(build("misregistration"))["misregistration"]
    assert {v.name: round(v.value, 2) for v in s.values} == {"shift_x": 1.0, "shift_y": -1.0}
    s = signatures(build("focus_offset"))["focus_offset"]
    assert s.values[0].value == pytest.approx(0.6, abs=0.1)
    s = signatures(build("disparity_scale"))["disparity_scale"]
    assert s.values[0].value == pytest.approx(-0.4, abs=0.05)  # a leak of 0.2 each way leaves 0.6 of the split
    lr = {v.name: v.value for v in signatures(build("lr_gain_imbalance"))["lr_gain_imbalance"].values}
    assert lr["lr_log_ratio_centre"] == pytest.approx(0.08, abs=0.005) and lr["lr_log_ratio_per_x"] == pytest.approx(0.1, abs=0.01)


def test_moments_of_an_ideal_split_and_of_profiles() -> None:
    h, c = 12, 16.0
    ideal = np.stack([kernel(h, c, -1), kernel(h, c, +1)])
    m = S.moments(ideal, c / 2 + 2.5)
    assert m.gap == pytest.approx(4 * c / (3 * math.pi), rel=0.03)
    assert m.efficiency == pytest.approx(1.0, abs=0.03)
    assert m.profile == pytest.approx(9 / 8, abs=0.01)  # a flat disc: E[r^2] / E[r]^2 = (R^2/2) / (2R/3)^2
    rim = S.moments(np.stack([kernel(h, c, -1, rim=2.0), kernel(h, c, +1, rim=2.0)]), c / 2 + 2.5)
    centre = S.moments(np.stack([kernel(h, c, -1, rim=-0.8), kernel(h, c, +1, rim=-0.8)]), c / 2 + 2.5)
    assert rim.profile < m.profile < centre.profile
    brighter = S.moments(ideal * np.array([1.3, 0.8])[:, None, None], c / 2 + 2.5)
    for attr in ("cx", "gap", "size", "efficiency", "profile"):  # the views' gains cancel from every moment
        assert float(getattr(brighter, attr)) == pytest.approx(float(getattr(m, attr)), abs=1e-9)


def test_a_focus_error_that_scales_with_each_pair_is_read_at_the_mean_pair() -> None:
    """A relative focus error moves each pair's CoC by ``(1/k - 1)`` times its CoC at infinity, so pairs focused near
    shift more; far background (large CoC behind focus) comes mostly from them. With the pairs' scales the signature
    reads the shift at the mean pair; a constant offset would read the spread between bins as a growth with |CoC|."""
    scale = np.array([0.5, 0.5, 0.5, 1.5, 1.5, 1.5])  # per pair: its CoC at infinity (any unit)
    beta = 0.5  # px of CoC per unit of scale
    keys = [(b, -1) for b in range(-12, 13) if b != 0 and abs(A.FINE.centre(b)) <= 15]
    cells = {}
    for key in keys:
        grid = A.Grid.of(key)
        c = A.FINE.centre(key[0])
        near = 0.9 if c < 4.0 else 0.1  # far background (CoC >= 4 px behind focus) mostly from the pairs focused near
        pixels = np.where(scale < 1, 1000.0 * near, 1000.0 * (1 - near))
        s_cell = float((pixels * scale).sum() / pixels.sum())
        cell = A.Cell(key[0], key[1], grid, np.arange(P), pixels, pixels * c, np.full((P, 3), 500.0))
        for name, cc in (("measured", c + beta * s_cell), ("model", c)):
            k = np.stack([kernel(grid.h, cc, side) for side in (-1, +1)])
            k = k.reshape(2, grid.side, grid.bs, grid.side, grid.bs).mean((2, 4))
            cell.kernels[name] = np.repeat(k[:, None], 3, axis=1)
            cell.influence[name] = np.zeros((P, 2, 3, grid.side, grid.side))
            cell.dc[name] = np.full((P, 2, 3), 250.0)
            cell.noise_sd[name] = np.full((2, 3), 1e-4)
        cell.factor = torch.eye(grid.n, dtype=torch.float64).expand(3, grid.n, grid.n).contiguous() * 30.0
        cells[key] = cell
    weights = np.random.default_rng(0).multinomial(P, np.full(P, 1 / P), size=60).astype(np.float64)
    atlas = A.Atlas(("measured", "model"), cells, [f"p{i}" for i in range(P)], weights)
    p = S.Pairing(atlas, "measured", "model", pair_scales={"coc_at_infinity_px": scale, "aperture_px": np.ones(P)})
    mean_scale = sum(float((c.pixels * scale).sum()) for c in cells.values()) / sum(float(c.pixels.sum()) for c in cells.values())
    f = S.focus_signature(p)
    assert f.values[0].value == pytest.approx(beta * mean_scale, abs=0.08), f.values[0].value  # 0.39; a constant offset reads 0.19
    assert not S.chromatic_signature(p, True).differs(0.05)  # the same shift in every channel is no colour error


def test_the_gap_slope_is_the_curves_own_and_missing_where_flat() -> None:
    c = np.array([-6.0, -3.0, -1.0, -0.4, 0.3, 1.0, 3.0, 6.0])
    gap = np.where(np.abs(c) < 0.8, 0.0, 0.4 * c)
    slope = S.gap_slope(c[::-1], gap[::-1])[::-1]  # any order
    assert slope[0] == pytest.approx(0.4) and slope[-1] == pytest.approx(0.4)
    assert np.isnan(slope[3]) and np.isnan(slope[4])  # flat near focus: says nothing about where the gap vanishes
