"""Tiled Neural DP inference: the halo is the network's receptive radius, and tiles stitch to the whole image."""

from __future__ import annotations

import pytest
import torch

from dp5k_learn.batch import DPBatch
from neural_dp.model import ModelConfig, UNetKPN
from neural_dp.simulators.neural import NeuralDPSimulator, model_inputs


def _batch(H: int, W: int) -> DPBatch:
    g = torch.Generator().manual_seed(0)
    depth = 500 + 4000 * torch.rand(1, 1, H, W, generator=g)
    valid = torch.rand(1, 1, H, W, generator=g) > 0.1
    z = torch.zeros(1)
    return DPBatch(sharp=torch.rand(1, 3, H, W, generator=g), coc_px=torch.randn(1, 1, H, W, generator=g) * 5,
                   depth_mm=depth * valid, valid=valid, f_number=z + 1.8, focus_distance_mm=z + 2000,
                   focal_length_mm=z + 85, pixel_pitch_mm=z + 0.02, focus_point_px=torch.zeros(1, 2))


@pytest.mark.parametrize(("levels", "radius"), [(2, 26), (3, 58), (4, 122)])
def test_receptive_radius_is_the_measured_reach_of_the_network(levels: int, radius: int) -> None:
    """The analytic radius equals the farthest input column that moves some output of a column, over every
    position of the column within one pooling period (the worst case is what a tile's halo must cover)."""
    torch.manual_seed(levels)
    net = UNetKPN(ModelConfig(base_channels=4, levels=levels, norm="none")).eval()
    torch.nn.init.normal_(net.head.weight, std=0.5)
    assert net.receptive_radius_px == radius
    H, W = 2 * net.multiple, 2 * radius + 3 * net.multiple
    sharp = torch.rand(1, 3, H, W)
    inputs = torch.rand(1, 5, H, W).requires_grad_()
    left, right = net(sharp, inputs)
    reach = 0
    for x in range(radius + net.multiple, radius + 2 * net.multiple):
        (grad,) = torch.autograd.grad((left[..., x] + right[..., x]).sum(), inputs, retain_graph=True)
        cols = torch.nonzero(grad.abs().sum(dim=(0, 1, 2)) > 0).flatten()
        reach = max(reach, x - int(cols.min()), int(cols.max()) - x)
    assert reach == radius


def test_tiled_paper_depth_network_equals_whole_image() -> None:
    """4 levels (the paper's depth; few channels to stay fast): 64 px tiles, each with the 128 px halo the
    receptive radius asks for, stitched to within 1e-4 of one whole-image pass; the image is large enough
    that interior tiles are cut on all four sides. Weights drawn to keep activations at unit scale through
    the depth (PyTorch's default init shrinks them ~2x per conv, which hides a short halo): a 96 px halo,
    the old default, is then off by 5e-4, none by 0.4."""
    torch.manual_seed(0)
    sim = NeuralDPSimulator(ModelConfig(base_channels=4, levels=4, tile_px=64))
    with torch.no_grad():
        for conv in sim.net.modules():
            if isinstance(conv, torch.nn.Conv2d):
                torch.nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
        torch.nn.init.normal_(sim.net.head.weight, std=0.3)
    sim.eval()
    b = _batch(330, 340)  # not multiples of 16: the edge tiles are padded like the whole image
    with torch.no_grad():
        tiled = sim(b)
        whole = sim.net(b.sharp, model_inputs(b, sim.cfg.coc_scale_px))
    assert float((whole[0] - b.sharp).abs().max()) > 0.5  # the network does change the image
    torch.testing.assert_close(tiled[0], whole[0], atol=1e-4, rtol=0)
    torch.testing.assert_close(tiled[1], whole[1], atol=1e-4, rtol=0)


def test_group_norm_network_runs_untiled() -> None:
    """GroupNorm normalises over the whole image, so tiles would change the output: such a network is not tiled."""
    torch.manual_seed(0)
    sim = NeuralDPSimulator(ModelConfig(base_channels=4, levels=2, norm="group", tile_px=32))
    with torch.no_grad():
        torch.nn.init.normal_(sim.net.head.weight, std=0.3)
    sim.eval()
    b = _batch(96, 128)
    with torch.no_grad():
        out = sim(b)
        whole = sim.net(b.sharp, model_inputs(b, sim.cfg.coc_scale_px))
    torch.testing.assert_close(out[0], whole[0], atol=1e-6, rtol=0)
