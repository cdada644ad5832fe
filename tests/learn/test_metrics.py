"""Masked metrics and losses: pinned to scikit-image / hand computations, and honest about the mask."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from dp5k_learn.losses import dp_loss, masked_charbonnier, masked_gradient_charbonnier
from dp5k_learn.metrics import masked_mae, masked_psnr, masked_ssim


def _pair(seed: int = 0, H: int = 48, W: int = 64) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    g = rng.uniform(0, 1, (1, 3, H, W))
    p = np.clip(g + rng.normal(0, 0.05, g.shape), 0, 1)
    return torch.from_numpy(p), torch.from_numpy(g)


def test_ssim_equals_skimage_wang_settings_on_full_mask() -> None:
    p, g = _pair()
    ones = torch.ones(1, 1, *p.shape[-2:], dtype=torch.bool)
    ours = float(masked_ssim(p, g, ones)[0])
    ref = structural_similarity(
        p[0].permute(1, 2, 0).numpy(), g[0].permute(1, 2, 0).numpy(), data_range=1.0, channel_axis=-1,
        gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    )
    assert ours == pytest.approx(ref, abs=1e-6)


def test_psnr_and_mae_equal_references_on_full_mask() -> None:
    p, g = _pair(1)
    ones = torch.ones(1, 1, *p.shape[-2:])
    ref = peak_signal_noise_ratio(g.numpy(), p.numpy(), data_range=1.0)
    assert float(masked_psnr(p, g, ones)[0]) == pytest.approx(ref, abs=1e-6)
    assert float(masked_mae(p, g, ones)[0]) == pytest.approx(float((p - g).abs().mean()), abs=1e-9)


def test_masked_metrics_ignore_garbage_in_invalid_pixels() -> None:
    p, g = _pair(2)
    mask = torch.ones(1, 1, *p.shape[-2:], dtype=torch.bool)
    mask[..., :, 40:] = False
    spoiled = p.clone()
    spoiled[..., :, 40:] = 1.0 - g[..., :, 40:]  # a terrible prediction where depth is invalid
    for fn in (masked_mae, masked_psnr, masked_ssim):
        assert float(fn(spoiled, g, mask)[0]) == pytest.approx(float(fn(p, g, mask)[0]), abs=1e-12)
    # ...while an unmasked metric would see it.
    full = torch.ones_like(mask)
    assert float(masked_psnr(spoiled, g, full)[0]) < float(masked_psnr(p, g, full)[0]) - 3


def test_ssim_mask_is_eroded_by_the_window_radius() -> None:
    p, g = _pair(3)
    mask = torch.ones(1, 1, *p.shape[-2:], dtype=torch.bool)
    mask[..., 20, 30] = False
    spoiled = p.clone()
    spoiled[..., 20, 30] = 1.0 - g[..., 20, 30]
    # the one invalid pixel removes every window that touches it, so the spoil is invisible
    assert float(masked_ssim(spoiled, g, mask)[0]) == pytest.approx(float(masked_ssim(p, g, mask)[0]), abs=1e-12)


def test_perfect_prediction() -> None:
    _, g = _pair(4)
    m = torch.ones(1, 1, *g.shape[-2:])
    assert float(masked_ssim(g, g, m)[0]) == pytest.approx(1.0)
    assert float(masked_mae(g, g, m)[0]) == 0.0
    assert float(masked_psnr(g, g, m)[0]) > 150


def test_charbonnier_is_masked_mean_of_sqrt_d2_eps2() -> None:
    p, g = _pair(5)
    m = torch.zeros(1, 1, *p.shape[-2:])
    m[..., :10, :] = 1
    d = (p - g)[..., :10, :]
    expected = torch.sqrt(d**2 + 1e-6).mean()
    assert float(masked_charbonnier(p, g, m)) == pytest.approx(float(expected), rel=1e-9)
    # charbonnier, not kornia's Barron c=1 (which is ~d^2/2): a 0.1 offset costs ~0.1
    assert float(masked_charbonnier(g + 0.1, g, torch.ones_like(m))) == pytest.approx(0.1, rel=1e-3)


def test_gradient_term_sees_edges_not_offsets_and_respects_mask() -> None:
    _, g = _pair(6)
    m = torch.ones(1, 1, *g.shape[-2:])
    assert float(masked_gradient_charbonnier(g + 0.2, g, m)) == pytest.approx(1e-3, rel=1e-6)
    blurred = torch.nn.functional.avg_pool2d(g, 3, 1, 1)
    assert float(masked_gradient_charbonnier(blurred, g, m)) > 0.05
    # a difference only across the mask edge is not penalised
    step = g.clone()
    step[..., :, 32:] += 0.5
    m2 = m.clone()
    m2[..., :, 32:] = 0
    assert float(masked_gradient_charbonnier(step, g, m2)) == pytest.approx(1e-3, rel=1e-6)


def test_dp_loss_is_zero_gradient_at_optimum_and_differentiable() -> None:
    p, g = _pair(7)
    p = p.clone().requires_grad_(True)
    m = torch.ones(1, 1, *g.shape[-2:])
    loss = dp_loss(p, p, g, g, m)
    loss.backward()
    assert p.grad is not None and float(p.grad.abs().sum()) > 0
