"""The physical base model: signs, normalisation, occlusion, fitting, registry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dp5k_learn.batch import DPBatch
from neural_dp.simulators.base import BaseModel, PSFShape, field_coords, fit_parameters, half_disc_kernels


def make_batch(sharp: torch.Tensor, coc: torch.Tensor, left=None, right=None) -> DPBatch:
    B, _, H, W = sharp.shape
    return DPBatch(
        sharp=sharp, coc_px=coc, depth_mm=torch.full((B, 1, H, W), 1000.0), valid=torch.ones(B, 1, H, W, dtype=torch.bool),
        f_number=torch.full((B,), 2.0), focus_distance_mm=torch.full((B,), 1500.0), focal_length_mm=torch.full((B,), 50.0),
        pixel_pitch_mm=torch.full((B,), 0.05), focus_point_px=torch.zeros(B, 2), left=left, right=right,
    )


def centroid_x(img: torch.Tensor) -> float:
    g = img.mean(dim=(0, 1, 2))
    xs = torch.arange(g.numel(), dtype=g.dtype)
    return float((g * xs).sum() / g.sum())


@pytest.mark.parametrize("coc", [6.0, -6.0])
def test_behind_focus_right_view_is_right_of_left(coc: float) -> None:
    sharp = torch.zeros(1, 3, 33, 33)
    sharp[..., 16, 16] = 1.0
    left, right = BaseModel(rim_softness_px=0.0)(make_batch(sharp, torch.full((1, 1, 33, 33), coc)))
    sep = centroid_x(right) - centroid_x(left)
    ideal = 4 * abs(coc) / (3 * np.pi)  # docs/conventions.md: 4c/(3 pi)
    assert np.sign(sep) == np.sign(coc)
    assert abs(abs(sep) - ideal) < 0.15 * ideal


def test_right_psf_is_hflip_of_left_and_each_sums_to_one() -> None:
    one = torch.ones(())
    k = half_disc_kernels(PSFShape(torch.tensor([7.0, -3.0, 0.0]), one, one * 0.5, one * 0, one * 0, one))
    assert torch.allclose(k.sum((1, 2)), torch.ones(3), atol=1e-5)
    # coc < 0 mirrors the half: left PSF of -c equals right PSF (hflip) of +c at the same size
    k2 = half_disc_kernels(PSFShape(torch.tensor([3.0, -3.0]), one, one * 0.5, one * 0, one * 0, one))
    assert torch.allclose(k2[1], k2[0].flip(-1), atol=1e-6)
    # in focus the lens' residual blur (softness) is symmetric: no DP disparity; without it, a delta
    assert torch.allclose(k[2], k[2].flip(-1), atol=1e-6) and torch.allclose(k[2], k[2].flip(-2), atol=1e-6)
    k0 = half_disc_kernels(PSFShape(torch.tensor([0.0]), one, one * 0.0, one * 0, one * 0, one))[0]
    delta = torch.zeros_like(k0)
    delta[k0.shape[-1] // 2, k0.shape[-1] // 2] = 1.0
    assert torch.allclose(k0, delta, atol=1e-6)


@pytest.mark.parametrize("coc", [0.3, 0.6, 1.0, 2.0, 5.0])
def test_sub_pixel_discs_keep_their_dp_centroid(coc: float) -> None:
    """The left PSF's centroid is -2c/(3 pi) px at every size (box-pooling a sub-pixel half disc into the
    centre pixel would erase DP disparity below ~1.5 px); its horizontal variance is the disc's plus the
    linear-interpolation spread, never less than the disc's."""
    one = torch.ones(())
    k = half_disc_kernels(PSFShape(torch.tensor([coc]), one, one * 0.0, one * 0, one * 0, one))[0].double()
    x = torch.arange(k.shape[-1], dtype=torch.float64) - k.shape[-1] // 2
    cx = float((k.sum(0) * x).sum())
    assert cx == pytest.approx(-2 * coc / (3 * np.pi), abs=0.01 * max(coc, 1.0))
    var_x = float((k.sum(0) * (x - cx) ** 2).sum())
    assert var_x >= (coc / 2) ** 2 / 4 - (2 * coc / (3 * np.pi)) ** 2 - 1e-6


def test_uniform_image_stays_uniform_across_depth_edges_no_dark_seams() -> None:
    sharp = torch.full((1, 3, 40, 60), 0.6)
    coc = torch.full((1, 1, 40, 60), 9.0)
    coc[..., :, 20:40] = -7.0  # a near object in front of a far background
    left, right = BaseModel(rim_softness_px=1.0, gain=1.0)(make_batch(sharp, coc))
    assert torch.allclose(left, torch.full_like(left, 0.3), atol=1e-4)
    assert torch.allclose(left + right, torch.full_like(left, 0.6), atol=1e-4)


def test_occlusion_near_layer_covers_far_blur() -> None:
    """A sharp near object (coc 0) must not be overwritten by the blurred far background's light."""
    sharp = torch.zeros(1, 3, 40, 60)
    sharp[..., :, :30] = 1.0
    coc = torch.full((1, 1, 40, 60), 12.0)
    coc[..., :, 30:] = 0.0  # dark sharp object in focus ... but it is FARTHER than nothing: make it near
    # near = most negative CoC: use -0.1 for the dark in-focus object, +12 (far, blurred) for the bright part
    coc[..., :, 30:] = -0.1
    left, right = BaseModel(rim_softness_px=0.0)(make_batch(sharp, coc))
    # the near dark object stays dark right next to the edge (blurred far light does not spill over it)
    assert float((left + right)[..., :, 31:34].max()) < 0.05
    # while the far bright region is darkened near the edge by the near object's blur? (no: it is sharp)
    assert float((left + right)[..., :, 10:20].min()) > 0.95


def test_surface_split_between_two_nodes_stays_opaque() -> None:
    """A near surface whose CoC lies halfway between two nodes is split 50/50 between them; the two halves
    join the transmittance together, so none of the bright far background shows through its middle (a plain
    over-composite of the halves lets m (1 - m) = 25 % of it through)."""
    sharp = torch.ones(1, 3, 40, 80)
    sharp[..., :, 25:55] = 0.0  # dark near surface in the middle
    coc = torch.full((1, 1, 40, 80), 10.0)  # bright far background, its blur reaching 5 px into the surface
    coc[..., :, 25:55] = -1.125  # halfway between the nodes -1.25 and -1.0
    left, right = BaseModel(rim_softness_px=0.0)(make_batch(sharp, coc))
    assert float((left + right)[..., 2:-2, 27:53].max()) < 1e-3  # 2 px inside its edges: its own blur is opaque there
    assert float((left + right)[..., :, :12].min()) > 0.99


def test_direct_and_fft_blurs_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """Small kernels are applied by direct convolution on each node's bounding box, large ones by FFT:
    forcing every node through the FFT path gives the same views."""
    import neural_dp.kernels as kernels_mod
    import neural_dp.simulators.base.render as base_mod

    rng = np.random.default_rng(1)
    sharp = torch.from_numpy(rng.uniform(0, 1, (2, 3, 40, 56)).astype(np.float32))
    coc = torch.linspace(-5, 9, 56).expand(2, 1, 40, 56).contiguous()
    coc[..., 10:25, 15:30] = -7.0
    model = BaseModel(rim_softness_px=0.4)
    mixed = model(make_batch(sharp, coc))
    assert any(2 * base_mod._support(k) + 1 <= kernels_mod.DIRECT_MAX_PX for k in model._kernel_fn(0.0)(torch.tensor([0.0, 1.0, 2.0])))
    monkeypatch.setattr(kernels_mod, "DIRECT_MAX_PX", 0)
    fft_only = model(make_batch(sharp, coc))
    for a, b in zip(mixed, fft_only):
        assert torch.allclose(a, b, atol=1e-5)


def test_fit_recovers_softness_and_gain() -> None:
    rng = np.random.default_rng(0)
    sharp = torch.from_numpy(rng.uniform(0.1, 0.9, (2, 3, 48, 64)).astype(np.float32))
    sharp = torch.nn.functional.avg_pool2d(sharp, 3, 1, 1)
    coc = torch.linspace(-8, 8, 64).expand(2, 1, 48, 64).contiguous()
    truth = BaseModel(rim_softness_px=1.5, gain=1.3)
    left, right = truth(make_batch(sharp, coc))
    model = BaseModel()
    params = model.fit([make_batch(sharp, coc, left, right)])
    assert set(params) == {"rim_softness_px", "gain"}
    assert abs(params["gain"] - 1.3) < 0.01
    assert abs(params["rim_softness_px"] - 1.5) < 0.2


def test_registry_serves_the_base_model() -> None:
    from neural_dp.registry import get_simulator

    sim = get_simulator("base")
    assert isinstance(sim, BaseModel) and sim.name == "base"


def test_fit_parameters_rejects_nothing_and_keeps_bounds() -> None:
    sharp = torch.rand(1, 3, 24, 24)
    coc = torch.full((1, 1, 24, 24), 4.0)
    l, r = BaseModel(rim_softness_px=0.5, gain=2.0)(make_batch(sharp, coc))
    m = BaseModel()
    m.bounds["gain"] = (0.1, 1.5)
    fit_parameters(m, [(m, "gain")], [make_batch(sharp, coc, l, r)])
    assert m.params["gain"] <= 1.5


def _studio_slanted_plane(coc_from: float, coc_to: float, f_number: float):
    """A noise-free studio render of a checkerboard plane whose CoC runs ``coc_from..coc_to`` px across x,
    with its sharp frame rendered at f/22 as format v1 says."""
    from dp5k_studio.dataset import pair_from_rgbd
    from dp5k_studio.dp_optics import LensSetting, coc_channels_px

    H, W, f, F, pitch = 48, 112, 50.0, 1500.0, 36.0 / 160
    yy, xx = np.mgrid[0:H, 0:W]
    radiance = np.where(((xx // 6) + (yy // 6)) % 2 == 0, 0.8, 0.2).astype(np.float32)[:, :, None].repeat(3, 2)
    zs = np.linspace(300.0, 2e5, 400000)
    coc_of_z = coc_channels_px(zs[None, :], LensSetting(f, f_number, F, pitch))[0, :, 1]
    depth = np.repeat(np.interp(np.linspace(coc_from, coc_to, W), coc_of_z, zs)[None, :], H, 0)
    rp = pair_from_rgbd(radiance, depth, f_number=f_number, focus_distance_mm=F, focal_length_mm=f, pixel_pitch_mm=pitch,
                        noise=False, sharp_is_pinhole=True)
    img = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]  # noqa: E731
    batch = make_batch(img(rp.sharp), torch.from_numpy(rp.coc_px)[None, None].float(), img(rp.left), img(rp.right))
    batch.f_number = torch.tensor([f_number])
    batch.sharp_f_number = torch.tensor([float(rp.extra["sharp_f_number"])])
    return batch


@pytest.mark.parametrize("coc_range", [(-8.0, -2.0), (2.0, 8.0)])
def test_sharp_frames_own_f22_blur_is_undone(coc_range: tuple[float, float]) -> None:
    """Rendering from the f/22 frame as if it were a pinhole image leaves its own blur (a disc 2.8/22 of the
    DP disc) in both views; undoing it brings the base model to a few times closer to the studio."""
    batch = _studio_slanted_plane(*coc_range, f_number=2.8)
    assert float(batch.sharp_f_number[0]) == 22.0

    def error(iters: int) -> float:
        left, right = BaseModel(0.0, 1.0, sharp_deblur_iters=iters).render(batch)
        crop = (slice(None), slice(None), slice(16, -16), slice(16, -16))
        return float(((left - batch.left)[crop] ** 2 + (right - batch.right)[crop] ** 2).sum().sqrt())

    pinhole, undone = error(0), error(2)
    assert undone < 0.35 * pinhole, (pinhole, undone)


def test_an_all_in_focus_sharp_image_is_not_deblurred() -> None:
    """``sharp_f_number = 0`` marks a sharp image that is the radiance itself (synthetic pairs)."""
    batch = _studio_slanted_plane(2.0, 8.0, f_number=2.8)
    batch.sharp_f_number = torch.zeros(1)
    a = BaseModel(0.0, 1.0, sharp_deblur_iters=2).render(batch)
    b = BaseModel(0.0, 1.0, sharp_deblur_iters=0).render(batch)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_radiance_cache_is_bounded_and_keyed_by_the_batch(monkeypatch: pytest.MonkeyPatch) -> None:
    """The deblurred sharp image is cached per batch (fits render one batch many times) within a byte bound;
    a different batch never gets another's result."""
    from neural_dp.simulators.base import sharp as base_mod

    from neural_dp.simulators.base.cache import TensorCache

    batches = [make_batch(torch.rand(1, 3, 24, 32, generator=torch.Generator().manual_seed(k)), torch.full((1, 1, 24, 32), 12.0))
               for k in range(3)]
    one_entry = 3 * 24 * 32 * 4  # one radiance (bytes)
    monkeypatch.setattr(base_mod, "_RADIANCE_CACHE", TensorCache(one_entry))
    first = [base_mod.sharp_radiance(b).clone() for b in batches]
    assert len(base_mod._RADIANCE_CACHE) == 1
    assert not torch.equal(first[0], batches[0].sharp)  # a 12 px CoC at f/2 means 1.1 px discs at f/22
    for b, x in zip(batches, first):
        assert torch.equal(base_mod.sharp_radiance(b), x)


@pytest.mark.parametrize("coc", [0.6, 1.3, 3.0])
def test_pixel_box_integrates_the_psf_over_pixel_areas(coc: float) -> None:
    """pixel_box = 1 samples the PSF through a 1-px box: a half disc inside the centre pixel stays there
    (centroid 0 for c = 0.6, where the triangle keeps -2c/(3 pi)); large discs hardly differ; a blend is
    linear in pixel_box; c = 0 stays the identity."""
    one = torch.ones(())

    def kernel(c: float, beta: float) -> torch.Tensor:
        return half_disc_kernels(PSFShape(torch.tensor([c]), one, one * 0.0, one * 0, one * 0, one, one * beta))[0].double()

    def cx(k: torch.Tensor) -> float:
        x = torch.arange(k.shape[-1], dtype=torch.float64) - k.shape[-1] // 2
        return float((k.sum(0) * x).sum())

    tent, box, mid = kernel(coc, 0.0), kernel(coc, 1.0), kernel(coc, 0.5)
    assert float(box.sum()) == pytest.approx(1.0, abs=1e-6)
    if coc < 1.0:
        assert cx(box) == pytest.approx(0.0, abs=1e-6) and cx(tent) == pytest.approx(-2 * coc / (3 * np.pi), abs=0.01)
    else:
        assert abs(cx(box)) < abs(cx(tent))  # pixel-area integration pulls light to the centre pixel
    assert torch.allclose(mid, (tent + box) / 2, atol=1e-6)
    k0 = kernel(0.0, 1.0)
    assert float(k0[k0.shape[-1] // 2, k0.shape[-1] // 2]) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("truth_box", [0.0, 1.0])
def test_fit_base_finds_how_the_data_samples_its_psfs(truth_box: float) -> None:
    """Views rendered with triangle (0) or box (1) pixel sampling, fine texture, CoC 0.3-3 px, nominal
    noise: diagnose's base fit recovers the sampling, with no rim softness in either case."""
    from dp5k_diagnose.data import Sample
    from dp5k_diagnose.fitting import fit_base

    g = torch.Generator().manual_seed(3)
    B, H, W = 4, 48, 64
    sharp = 0.1 + 0.8 * torch.rand(B, 3, H, W, generator=g)
    coc = torch.linspace(0.3, 3.0, W).expand(B, 1, H, W).clone()
    coc[:, :, : H // 2] *= -1
    b = make_batch(sharp, coc)
    b.sharp_f_number = torch.zeros(B)
    fld = field_coords(B, H, W)
    with torch.no_grad():
        left, right = BaseModel(rim_softness_px=0.0, pixel_box=truth_box).render(b, fld)
    noisy = [v + torch.sqrt(2e-5 * v + 1e-6) * torch.randn(v.shape, generator=g) for v in (left, right)]
    base = fit_base([Sample(dataclasses.replace(b, left=noisy[0], right=noisy[1]), fld)], iters=6)
    assert base.params["pixel_box"] == pytest.approx(truth_box, abs=0.15)
    assert base.params["rim_softness_px"] < 0.1


def test_scored_values_are_the_masked_entries_and_follow_an_in_place_change() -> None:
    """The fits' residuals gather the scored entries by a flat index kept per score map: the same entries in the
    same order as the boolean mask, measured again when the map changes in place, forgotten with the map."""
    import gc
    from types import SimpleNamespace

    from neural_dp.simulators.base import fit as fitting

    g = torch.Generator().manual_seed(0)
    score = torch.rand(2, 1, 9, 11, generator=g) > 0.5
    sample = SimpleNamespace(score=score)
    e = torch.rand(2, 6, 9, 11, generator=g)
    assert torch.equal(fitting.scored_values(sample, e), e[score.expand(-1, 6, -1, -1)])
    score[1, 0, 4] = ~score[1, 0, 4]  # in place: the index must not be the old one
    assert torch.equal(fitting.scored_values(sample, e), e[score.expand(-1, 6, -1, -1)])
    key = id(score)
    assert key in fitting._SCORED_INDEX
    del sample, score
    gc.collect()
    assert key not in fitting._SCORED_INDEX


def test_a_pupil_cut_below_the_axis_is_the_mirror_of_the_cut_above_it() -> None:
    """A node whose pupil is cut at ``clip_dy < 0`` is served as the y-flip of the node at ``+clip_dy``: it must
    equal the kernel built directly for that cut (which is not symmetric in y, so a flip along x or no flip
    fails)."""
    from neural_dp.simulators.base import psf

    psf._KERNEL_CACHE.clear()
    one = torch.ones(())
    nodes = torch.tensor([-9.0, 4.0, 12.5])
    shape = psf.PSFShape(coc_px=nodes, scale=one, softness_px=one * 0.6, rim2=one * 0.1, rim4=one * 0.0, split=one, pixel_box=one * 0.3,
                         clip_dx=one * 0.2, clip_dy=one * -0.35)
    got = psf.half_disc_kernels(shape, 4)
    direct = psf.stack_centred([psf._pushforward_kernel(float(c), 1.0, 0.6, 0.1, 0.0, 1.0, 0.3, 0.0, 0.2, 0.0, -0.35) for c in nodes])
    assert float((direct - direct.flip(-2)).abs().max()) > 1e-3  # the cut is not symmetric in y
    torch.testing.assert_close(got, direct, atol=1e-7, rtol=0)
