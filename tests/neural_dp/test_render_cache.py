"""The base model's layered render is reused only where it cannot differ: the same batch, field and model state
(:data:`neural_dp.simulators.base.model._LAYERS_CACHE`), and a CoC map whose colour channels are equal is
rendered as one channel (:func:`neural_dp.simulators.base.render.render_layers`)."""

from __future__ import annotations

import pytest
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


def test_equal_colour_cocs_render_as_one_channel_to_the_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    from neural_dp.simulators.base import render as render_mod

    channels: list[int] = []
    index = render_mod._fractional_index
    monkeypatch.setattr(render_mod, "_fractional_index", lambda coc, nodes: (channels.append(coc.shape[1]), index(coc, nodes))[1])
    b = _batch()
    one = render_layers(b.sharp, b.coc_px, b.valid, _kernels, RenderConfig())
    three = render_layers(b.sharp, b.coc_px.expand(-1, 3, -1, -1).contiguous(), b.valid, _kernels, RenderConfig())
    assert all(torch.equal(x, y) for x, y in zip(one, three))
    assert channels == [1, 1]  # the equal 3-channel CoC went the one-channel way
    # a colour whose CoC differs is still rendered with its own CoC
    coc = b.coc_px.expand(-1, 3, -1, -1).clone()
    coc[:, 2] += 1.5
    blue = render_layers(b.sharp, coc, b.valid, _kernels, RenderConfig())
    assert float((blue[0][:, 2] - one[0][:, 2]).abs().max()) > 1e-3
    assert channels[-1] == 3


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


def test_one_view_alone_is_the_same_as_with_both() -> None:
    b = _batch(seed=2)
    both = render_layers(b.sharp, b.coc_px, b.valid, _kernels, RenderConfig())
    left = render_layers(b.sharp, b.coc_px, b.valid, _kernels, RenderConfig(), ("l",))
    right = render_layers(b.sharp, b.coc_px, b.valid, _kernels, RenderConfig(), ("r",))
    assert left[1] is None and right[0] is None
    assert torch.equal(left[0], both[0]) and torch.equal(right[1], both[1])
    assert float((both[0] - both[1]).abs().max()) > 1e-3  # the views differ: the right one is not the left one again


def test_a_crop_on_one_side_of_the_field_renders_as_the_three_node_blend(monkeypatch: pytest.MonkeyPatch) -> None:
    """The PSF that changes along field x is rendered at nodes -1, 0, 1 and blended; a crop right of the centre
    skips the two node views it does not weigh, and its views are still the blend of all three nodes."""
    from neural_dp.simulators.base.components import FieldVaryingPSF
    from neural_dp.simulators.base.model import FIELD_NODES_X

    b = _batch(seed=3)
    field = field_coords(2, 40, 56, "cpu")
    field[:, 0] = 0.2 + 0.35 * (field[:, 0] + 1)  # field x in [0.2, 0.9]
    fvp = FieldVaryingPSF()
    fvp.params.update(split_shift=0.2, coc_growth_at_corner=0.3)  # along x only (vignetting: the next test)
    model = BaseModel(rim_softness_px=0.6, components=[fvp])
    from neural_dp.simulators.base import model as model_mod

    asked: dict[float, tuple[str, ...]] = {}
    seen: list[float] = []  # the field x the component's PSF was asked at, as the kernels are built
    shape = fvp.shape
    monkeypatch.setattr(fvp, "shape", lambda *a: seen.append(fvp.field_x) or shape(*a))
    real = model_mod.render_layers_multi

    def spy(sharp, coc, valid, kernel_sets, cfg):
        def recording(fn, views):
            def at(nodes):
                out = fn(nodes)
                asked[seen[-1]] = views  # the field node the kernels were built at (the model sets it)
                return out
            return at
        return real(sharp, coc, valid, [(recording(fn, views), views) for fn, views in kernel_sets], cfg)

    monkeypatch.setattr(model_mod, "render_layers_multi", spy)
    with torch.enable_grad():
        got = model.render_layers_only(b, field)
    monkeypatch.setattr(model_mod, "render_layers_multi", real)
    assert asked == {-1.0: ("r",), 0.0: ("l", "r"), 1.0: ("l",)}  # four views of six
    coc = fvp.coc(b.coc_px.float(), b, field)
    from neural_dp.simulators.base.sharp import sharp_radiance

    sharp = sharp_radiance(b, model.sharp_deblur_iters, model.config)
    nodes = {}
    for x in FIELD_NODES_X:
        fvp.field_x = x
        nodes[x] = render_layers(sharp, coc, b.valid, model._kernel_fn(x * x), model.config)
    fvp.field_x = 0.0
    fx = field[:, :1]
    w = {-1.0: (-fx).clamp(min=0), 1.0: fx.clamp(min=0)}
    w[0.0] = 1 - w[-1.0] - w[1.0]
    want_l = sum(w[x] * nodes[x][0] for x in FIELD_NODES_X)
    want_r = sum(w[x] * nodes[-x if x else 0.0][1] for x in FIELD_NODES_X)
    # the field nodes' kernels are convolved together (zero-padded to one support, one FFT batch), each node
    # alone here: the same blur up to float32 rounding
    torch.testing.assert_close(got[0], want_l, atol=1e-6, rtol=0)
    torch.testing.assert_close(got[1], want_r, atol=1e-6, rtol=0)
    assert float((nodes[1.0][0] - nodes[0.0][0]).abs().max()) > 1e-3  # the nodes differ: the blend matters


def test_a_cut_pupil_renders_as_the_bilinear_blend_of_the_field_grid_nodes_it_weighs(monkeypatch: pytest.MonkeyPatch) -> None:
    """Cat's-eye vignetting cuts the pupil along the field vector, so its PSF changes along y too: the views are
    the bilinear blend of renders on the 3 x 3 grid of field nodes, each node's cut at ``vignetting`` (x, y a)
    with ``a`` the frame's half-height over its half-width; a crop in the upper right quadrant renders only
    the 8 node views it weighs of 18, and the y nodes differ (the cut's y part is rendered, not dropped)."""
    from neural_dp.simulators.base import model as model_mod
    from neural_dp.simulators.base.components import FieldVaryingPSF
    from neural_dp.simulators.base.model import FIELD_NODES_X, FIELD_NODES_Y
    from neural_dp.simulators.base.sharp import sharp_radiance

    b = _batch(seed=4)
    field = field_coords(2, 40, 56, "cpu", origin=(62, 0), full_size=(120, 80))  # x in [0.04, 0.97], y in [-1, -0.01]
    unit = 79 / 119
    fvp = FieldVaryingPSF()
    fvp.params.update(vignetting=0.5)
    model = BaseModel(rim_softness_px=0.6, components=[fvp])
    asked: dict[tuple[float, float], tuple[str, ...]] = {}
    seen: list[tuple[float, float]] = []  # the field node the component's PSF was asked at, as the kernels are built
    shape = fvp.shape
    monkeypatch.setattr(fvp, "shape", lambda *a: seen.append((fvp.field_x, round(fvp.field_y, 4))) or shape(*a))
    real = model_mod.render_layers_multi

    def spy(sharp, coc, valid, kernel_sets, cfg):
        def recording(fn, views):
            def at(nodes):
                out = fn(nodes)
                asked[seen[-1]] = views
                return out
            return at
        return real(sharp, coc, valid, [(recording(fn, views), views) for fn, views in kernel_sets], cfg)

    monkeypatch.setattr(model_mod, "render_layers_multi", spy)
    with torch.enable_grad():
        got = model.render_layers_only(b, field)
    monkeypatch.setattr(model_mod, "render_layers_multi", real)
    up, mid = round(-unit, 4), 0.0
    assert asked == {(-1.0, up): ("r",), (0.0, up): ("l", "r"), (1.0, up): ("l",),
                     (-1.0, mid): ("r",), (0.0, mid): ("l", "r"), (1.0, mid): ("l",)}
    sharp = sharp_radiance(b, model.sharp_deblur_iters, model.config)
    nodes = {}
    for x in FIELD_NODES_X:
        for y in FIELD_NODES_Y:
            fvp.field_x, fvp.field_y = x, y * unit
            nodes[(x, y)] = render_layers(sharp, b.coc_px.float(), b.valid, model._kernel_fn(x * x), model.config)
    fvp.field_x = fvp.field_y = 0.0

    def tent(t: torch.Tensor) -> dict[float, torch.Tensor]:
        w = {-1.0: (-t).clamp(min=0), 1.0: t.clamp(min=0)}
        w[0.0] = 1 - w[-1.0] - w[1.0]
        return w

    wx, wy = tent(field[:, :1]), tent(field[:, 1:2])
    grid = [(x, y) for x in FIELD_NODES_X for y in FIELD_NODES_Y]
    want_l = sum(wx[x] * wy[y] * nodes[(x, y)][0] for x, y in grid)
    want_r = sum(wx[x] * wy[y] * nodes[(-x if x else 0.0, y)][1] for x, y in grid)
    torch.testing.assert_close(got[0], want_l, atol=1e-6, rtol=0)
    torch.testing.assert_close(got[1], want_r, atol=1e-6, rtol=0)
    assert float((nodes[(0.0, -1.0)][0] - nodes[(0.0, 0.0)][0]).abs().max()) > 1e-3  # a cut from above changes the PSF


def test_a_pupil_cut_along_y_mirrors_the_psf_vertically() -> None:
    """The cut's y part: the left-view PSF with the cutting circle at (dx, dy) is the vertical mirror of the
    one at (dx, -dy) (the split line is vertical, so a cut from below is a cut from above mirrored), and the
    circle centred at dy > 0 keeps the pupil's lower part (pupil y > 0), which lands below the chief ray behind
    focus and above it in front: the PSF's centroid moves by sign(c) along y."""
    from neural_dp.simulators.base.psf import _pushforward_kernel

    for c in (6.0, -9.0):
        down = _pushforward_kernel(c, 1.0, 0.3, 0.0, 0.0, 1.0, clip_dx=0.2, clip_dy=0.5)
        up = _pushforward_kernel(c, 1.0, 0.3, 0.0, 0.0, 1.0, clip_dx=0.2, clip_dy=-0.5)
        torch.testing.assert_close(down, up.flip(0), atol=1e-6, rtol=0)
        n = down.shape[0]
        ys = torch.arange(n, dtype=torch.float32) - n // 2
        centroid_y = float((down.sum(1) * ys).sum())
        assert centroid_y * (1 if c > 0 else -1) > 0.1 * abs(c) / 2, centroid_y


def test_field_y_units_are_each_frames_half_height_over_its_half_width() -> None:
    """Crops of a 120 x 80 and a 200 x 100 frame in one batch: each item's unit is its own frame's (79/119 and
    99/199), read from its field's steps, whatever the crop's place and size."""
    from neural_dp.simulators.base.field import field_y_units

    a = field_coords(1, 40, 56, "cpu", origin=(62, 0), full_size=(120, 80))
    b = field_coords(1, 40, 56, "cpu", origin=(10, 30), full_size=(200, 100))
    units = field_y_units(torch.cat([a, b]))
    torch.testing.assert_close(units, torch.tensor([79 / 119, 99 / 199]), atol=1e-5, rtol=0)
    assert float(field_y_units(field_coords(2, 1, 56, "cpu"))[0]) == 1.0  # a one-row crop: no y step to read
