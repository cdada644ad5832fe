"""Each peer simulator against its defining property, on small cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dp5k_learn.batch import DPBatch
from neural_dp.simulators.butterworth import ButterworthParams, butterworth_highpass, butterworth_psf, butterworth_ring
from neural_dp.simulators.disk import translating_disk_psf
from neural_dp.simulators.peer_layers import render_layered
from neural_dp.simulators.raytrace import render_raytrace
from neural_dp.registry import PEERS, get_simulator


def _centroid_x(h: np.ndarray) -> float:
    k = h.shape[1]
    return float((h.sum(0) * (np.arange(k) - k // 2)).sum() / h.sum())


def _batch(sharp: torch.Tensor, coc: torch.Tensor, valid: torch.Tensor | None = None) -> DPBatch:
    B = sharp.shape[0]
    z = torch.zeros(B)
    return DPBatch(
        sharp=sharp, coc_px=coc, depth_mm=torch.full_like(coc, 1000.0),
        valid=torch.ones_like(coc, dtype=torch.bool) if valid is None else valid,
        f_number=z + 1.8, focus_distance_mm=z + 2000, focal_length_mm=z + 85, pixel_pitch_mm=z + 0.02,
        focus_point_px=torch.zeros(B, 2),
    )


# ---- translating disk -------------------------------------------------------------------------------

@pytest.mark.parametrize("coc", [6.0, 11.0, -9.0])
def test_disk_support_mass_and_side(coc: float) -> None:
    h = translating_disk_psf(coc)
    r = abs(coc) / 2
    k = h.shape[0]
    yy, xx = np.mgrid[:k, :k] - k // 2
    assert h.sum() == pytest.approx(0.5)
    # support: nothing outside the disk of radius r (pixel corners farther than r carry nothing)
    assert h[np.hypot(np.abs(xx) - 0.5, np.abs(yy) - 0.5) > r].sum() == 0.0
    # left view of a point behind focus lies on the left half of the disk, in front: the right half
    cx = _centroid_x(h)
    assert (cx < -0.2 * r) if coc > 0 else (cx > 0.2 * r)


def test_disk_is_linear_ramp_along_each_row() -> None:
    h = translating_disk_psf(20.0)  # r = 10
    row = h[10, 2:-2]  # centre row, well inside the disk: weights fall linearly with x
    d2 = np.diff(row, 2)
    assert np.abs(d2).max() < 1e-3 * row.max()
    assert (np.diff(row) < 0).all()
    # left + right is symmetric (the full-aperture kernel) and right is the mirror image
    full = h + h[:, ::-1]
    np.testing.assert_allclose(full, full[:, ::-1])


def test_disk_in_focus_is_identity() -> None:
    assert translating_disk_psf(0.4).shape == (1, 1)


# ---- Butterworth ------------------------------------------------------------------------------------

def test_butterworth_frequency_response() -> None:
    d = np.array([0.0, 0.5, 1.0, 2.0, 10.0])
    for n in (3, 6, 9):
        b = butterworth_highpass(d, 1.0, n)
        assert b[0] == 0.0 and b[2] == pytest.approx(0.5)  # half power at the cut-off
        assert b[3] == pytest.approx(4.0**n / (1 + 4.0**n))
        assert b[4] == pytest.approx(1.0, abs=1e-5)
    # higher order, sharper transition
    assert butterworth_highpass(np.array([0.8]), 1.0, 9)[0] < butterworth_highpass(np.array([0.8]), 1.0, 3)[0]


def test_butterworth_ring_is_beta_in_centre_one_at_rim() -> None:
    ring = butterworth_ring(10, order=3, cut_off_factor=2.5, beta=0.1)
    assert ring[10, 10] == pytest.approx(0.1)
    # rescaled over the k x k array: the corner (largest radius) maps to 1
    b = butterworth_highpass(np.array([10.0, 10 * math.sqrt(2)]), 20 / 2.5, 3)
    assert ring[10, 0] == pytest.approx(0.1 + 0.9 * b[0] / b[1])
    assert ring[10, 0] > 0.8 and (np.diff(ring[10, :11]) < 0).all()  # a ring: rising toward the rim
    assert ring[0, 0] == 0.0  # outside the circle


def test_butterworth_psf_mass_side_and_size() -> None:
    h = butterworth_psf(12.0)  # radius 6 -> k = 13, padded by the Gaussian
    assert h.sum() == pytest.approx(0.5)
    assert h.shape[0] >= 13
    assert _centroid_x(h) < -1.0
    assert _centroid_x(butterworth_psf(-12.0)) > 1.0
    np.testing.assert_allclose(butterworth_psf(-12.0), h[:, ::-1])
    assert butterworth_psf(0.0).shape[0] >= 3  # their rule: CoC 0 becomes 1


# ---- ray tracing ------------------------------------------------------------------------------------

def test_raytrace_point_source_energy_symmetry_and_centroid() -> None:
    H, W, c = 41, 41, 16.0
    x = torch.zeros(1, 1, H, W, dtype=torch.float64)
    x[..., 20, 20] = 1.0
    coc = torch.full((1, 1, H, W), c, dtype=torch.float64)
    left, right = render_raytrace(x, coc, torch.ones_like(coc, dtype=torch.bool))
    assert float(left.sum() + right.sum()) == pytest.approx(1.0, abs=1e-9)  # energy conserved
    assert float(left.sum()) == pytest.approx(0.5, abs=1e-9)
    torch.testing.assert_close(right[0, 0], left[0, 0].flip(1))  # right = hflip(left) about the point
    xs = torch.arange(W, dtype=torch.float64) - 20
    cx = float((left[0, 0].sum(0) * xs).sum() / left.sum())
    assert cx == pytest.approx(-4 * (c / 2) / (3 * math.pi), rel=0.05)  # half-disk centroid 4r/(3 pi)
    support = (left + right)[0, 0] > 1e-9
    yy, xx = torch.meshgrid(xs, xs, indexing="ij")
    assert not support[torch.hypot(xx, yy) > c / 2 + 1.5].any()


def test_raytrace_front_of_focus_swaps_halves() -> None:
    x = torch.zeros(1, 1, 31, 31, dtype=torch.float64)
    x[..., 15, 15] = 1.0
    coc = torch.full((1, 1, 31, 31), -10.0, dtype=torch.float64)
    left, _ = render_raytrace(x, coc, torch.ones_like(coc, dtype=torch.bool))
    assert float((left[0, 0].sum(0) * (torch.arange(31) - 15)).sum()) > 0


# ---- the layered scheme and all peers ---------------------------------------------------------------

@pytest.mark.parametrize("name", PEERS)
def test_uniform_image_stays_uniform_across_depth_layers(name: str) -> None:
    """No dark seams at layer boundaries or borders: coverage normalisation keeps a flat field flat."""
    H, W = 32, 48
    sharp = torch.full((1, 3, H, W), 0.6, dtype=torch.float64)
    coc = torch.linspace(-12, 12, W, dtype=torch.float64).view(1, 1, 1, W).expand(1, 1, H, W).contiguous()
    left, right = get_simulator(name)(_batch(sharp, coc))
    torch.testing.assert_close(left + right, sharp, atol=1e-9, rtol=0)


def test_layered_without_normalisation_would_show_seams() -> None:
    """The property the normalisation buys: un-normalised mask-then-blur darkens layer edges."""
    H, W = 16, 40
    sharp = torch.ones(1, 3, H, W, dtype=torch.float64)
    coc = torch.where(torch.arange(W) < 20, 2.0, 14.0).double().view(1, 1, 1, W).expand(1, 1, H, W).contiguous()
    left, right = render_layered(sharp, coc, torch.ones_like(coc, dtype=torch.bool), translating_disk_psf)
    assert float((left + right).min()) == pytest.approx(1.0)
    # the same sums without the denominator dip below 1 next to the boundary
    from neural_dp.kernels import convolve_same
    m_near = (coc < 5).double()
    psf_near, psf_far = (torch.as_tensor(translating_disk_psf(c)) for c in (2.0, 14.0))
    full = lambda p: p + p.flip(1)  # noqa: E731
    raw = convolve_same(m_near, full(psf_near)) + convolve_same(1 - m_near, full(psf_far))
    assert float(raw[0, 0, 8, 10:30].min()) < 0.95


@pytest.mark.parametrize("name", PEERS)
def test_peer_disparity_sign_follows_convention(name: str) -> None:
    """Behind focus the right view is displaced to the right of the left view (+x)."""
    H, W = 24, 64
    x = torch.zeros(1, 3, H, W, dtype=torch.float64)
    x[..., :, 32:] = 1.0  # a vertical edge
    for c, sign in ((10.0, 1.0), (-10.0, -1.0)):
        left, right = get_simulator(name)(_batch(x, torch.full((1, 1, H, W), c, dtype=torch.float64)))
        lp, rp = left[0, 0, 12], right[0, 0, 12]
        # location of the half-maximum crossing of each view
        xl = float((lp < lp.max() / 2).sum())
        xr = float((rp < rp.max() / 2).sum())
        assert sign * (xr - xl) > 1.0, (name, c, xl, xr)


def test_peers_run_batched_on_float32() -> None:
    torch.manual_seed(0)
    sharp = torch.rand(2, 3, 20, 30)
    coc = torch.randn(2, 1, 20, 30) * 4
    valid = torch.rand(2, 1, 20, 30) > 0.1
    for name in PEERS:
        left, right = get_simulator(name)(_batch(sharp, coc, valid))
        assert left.shape == sharp.shape and left.dtype == torch.float32 and torch.isfinite(left).all()
