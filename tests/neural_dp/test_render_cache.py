"""The base model's layered render is reused only where it cannot differ: the same batch, field and model state
(:data:`neural_dp.simulators.base.model._LAYERS_CACHE`), and a CoC map whose colour channels are equal is
rendered as one channel (:func:`neural_dp.simulators.base.render.render_layers`)."""

from __future__ import annotations

import torch

from dp5k_learn.batch import DPBatch
from neural_dp.simulators.base import BaseModel
from neural_dp.simulators.base.components import ChromaticDefocus, PSFProfile
from neural_dp.simulators.base.field import field_coords
from neural_dp.simulators.base.psf import PSFShape, half_disc_kernels
from neural_dp.simulators.base.render import RenderConfig, render_layers


def _batch(B: int = 2, H: int = 40, W: int = 56, seed: int = 0) -> DPBatch:
    g = torch.Generator().manual_seed(seed)
    sharp = torch.rand(B, 3, H, W, generator=g)
    coc = -6.0 + 14.0 * torch.rand(B, 1, H, W, generator=g)
    z = torch.zeros(B)
    return DPBatch(sharp=sharp, coc_px=coc, depth_mm=torch.full_like(coc, 1500.0), valid=torch.ones(B, 1, H, W, dtype=torch.bool),
                   f_number=z + 2.0, focus_distance_mm=z + 1500, focal_length_mm=z + 50, pixel_pitch_mm=z + 0.005,
                   focus_point_px=torch.zeros(B, 2))


def _kernels(nodes: torch.Tensor) -> torch.Tensor:
    one = torch.ones(())
    return half_disc_kernels(PSFShape(nodes, one, one * 0.5, one * 0.0, one * 0.0, one), 4)[:, None]


def test_equal_colour_cocs_render_as_one_channel_to_the_bit() -> None:
    b = _batch()
    one = render_layers(b.sharp, b.coc_px, b.valid, _kernels, RenderConfig())
    three = render_layers(b.sharp, b.coc_px.expand(-1, 3, -1, -1).contiguous(), b.valid, _kernels, RenderConfig())
    assert all(torch.equal(x, y) for x, y in zip(one, three))
    # a colour whose CoC differs is still rendered with its own CoC
    coc = b.coc_px.expand(-1, 3, -1, -1).clone()
    coc[:, 2] += 1.5
    blue = render_layers(b.sharp, coc, b.valid, _kernels, RenderConfig())
    assert float((blue[0][:, 2] - one[0][:, 2]).abs().max()) > 1e-3


def test_a_chromatic_defocus_at_zero_renders_as_the_model_without_it() -> None:
    b = _batch()
    field = field_coords(2, 40, 56, "cpu")
    with torch.no_grad():
        plain = BaseModel(rim_softness_px=0.7).render(b, field)
        chroma = BaseModel(rim_softness_px=0.7, components=[ChromaticDefocus()]).render(b, field)
    assert all(torch.equal(x, y) for x, y in zip(plain, chroma))


def test_the_layered_render_is_reused_only_for_the_same_batch_field_and_state() -> None:
    b = _batch(seed=1)
    field = field_coords(2, 40, 56, "cpu")
    model = BaseModel(rim_softness_px=0.6, components=[PSFProfile()])
    with torch.no_grad():
        first = model.render_layers_only(b, field)
        again = model.render_layers_only(b, field)
        assert again[0] is first[0] and again[1] is first[1]  # the same state: the cached render
        # another model object in the same state gets the same render
        twin = BaseModel(rim_softness_px=0.6, components=[PSFProfile()])
        assert twin.render_layers_only(b, field)[0] is first[0]
        # a changed parameter renders anew, and differs
        model.component("psf_profile").params["rim_gain"] = 0.8
        rim = model.render_layers_only(b, field)
        assert rim[0] is not first[0] and float((rim[0] - first[0]).abs().max()) > 1e-4
        model.component("psf_profile").params["rim_gain"] = 0.0
        assert model.render_layers_only(b, field)[0] is first[0]
        # the batch changed in place: the cached render is stale and not used
        b.sharp.mul_(0.5)
        halved = model.render_layers_only(b, field)
        assert halved[0] is not first[0]
        assert torch.allclose(halved[0], first[0] * 0.5, atol=1e-5)
    # with autograd nothing is cached, and the render is the same
    with torch.enable_grad():
        fresh = model.render_layers_only(b, field)
    assert fresh[0] is not halved[0] and torch.allclose(fresh[0], halved[0], atol=1e-6)
