"""The Neural DP Simulator: inputs, the left/right mirror at model level, tiled inference."""

from __future__ import annotations

from dataclasses import replace

import torch

from dp5k_learn.batch import DPBatch
from neural_dp.model import ModelConfig, UNetKPN, normalize_depth
from neural_dp.simulators.neural import NeuralDPSimulator, model_inputs


def _batch(H: int = 40, W: int = 56, B: int = 1) -> DPBatch:
    g = torch.Generator().manual_seed(0)
    depth = 500 + 4000 * torch.rand(B, 1, H, W, generator=g)
    valid = torch.rand(B, 1, H, W, generator=g) > 0.1
    z = torch.zeros(B)
    return DPBatch(sharp=torch.rand(B, 3, H, W, generator=g), coc_px=torch.randn(B, 1, H, W, generator=g) * 5,
                   depth_mm=depth * valid, valid=valid, f_number=z + 1.8, focus_distance_mm=z + 2000,
                   focal_length_mm=z + 85, pixel_pitch_mm=z + 0.02, focus_point_px=torch.zeros(B, 2))


def test_depth_input_is_minmax_with_invalid_minus_one() -> None:
    b = _batch()
    d = normalize_depth(b.depth_mm, b.valid)
    assert float(d[b.valid].min()) == 0.0 and float(d[b.valid].max()) == 1.0
    assert bool((d[~b.valid] == -1).all())
    x = model_inputs(b, 10.0)
    assert x.shape == (1, 5, 40, 56)
    torch.testing.assert_close(x[:, 3:4][b.valid], (b.coc_px / 10.0)[b.valid])


def test_model_kernel_shifting_left_view_left_shifts_right_view_right() -> None:
    net = UNetKPN(ModelConfig(base_channels=4, levels=2))
    with torch.no_grad():
        bias = torch.zeros_like(net.head.bias)
        bias[2 * 5 + 4] = 60.0  # left kernel = delta at (row 2, col 4): gathers x + 2, moves content left
        net.head.bias.copy_(bias)
        net.view_gain.fill_(1.0)
    net.eval()
    sharp = torch.zeros(1, 3, 16, 24)
    sharp[..., 8, 12] = 1.0
    left, right = net(sharp, torch.zeros(1, 5, 16, 24))
    assert left[0, 0].argmax().item() == 8 * 24 + 10
    assert right[0, 0].argmax().item() == 8 * 24 + 14


def test_tiled_inference_equals_whole_image() -> None:
    """BatchNorm in eval mode is local, so tiles with enough margin reproduce the whole-image output."""
    torch.manual_seed(0)
    cfg = ModelConfig(base_channels=4, levels=2, tile_px=0)
    sim = NeuralDPSimulator(cfg)
    with torch.no_grad():
        torch.nn.init.normal_(sim.net.head.weight, std=0.3)
    sim.eval()
    b = _batch(70, 90)
    with torch.no_grad():
        whole = sim(b)
        sim.cfg = replace(cfg, tile_px=32, tile_margin_px=32)
        tiled = sim(b)
    torch.testing.assert_close(tiled[0], whole[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(tiled[1], whole[1], atol=1e-5, rtol=0)


def test_per_channel_kernels_option() -> None:
    sim = NeuralDPSimulator(ModelConfig(base_channels=4, levels=2, kernel_per_channel=True))
    sim.eval()
    with torch.no_grad():
        weights, _, _ = sim.net.predict(torch.rand(2, 5, 16, 16))
        left, right = sim(_batch(20, 28, B=2))
    assert weights.shape == (2, 3, 25, 16, 16)
    torch.testing.assert_close(weights.sum(2), torch.ones(2, 3, 16, 16))
    assert left.shape == right.shape == (2, 3, 20, 28)
