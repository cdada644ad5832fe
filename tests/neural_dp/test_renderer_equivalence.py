"""Equivalence of the optimised renderers with their reference implementations (``tests/reference``): the layered
peers (``layered_peer_render``), ray tracing (``raytrace_render``) and the base model's layers and kernels
(``base_model_render``), compared on small scenes to 1e-4: the test fails if an optimisation changes what a
simulator renders.
"""

from __future__ import annotations

import pytest
import torch

from dp5k_learn.batch import DPBatch
from neural_dp import kernels
from neural_dp.simulators import peer_layers
from neural_dp.simulators.base import BaseModel
from neural_dp.simulators.base.components import ChromaticDefocus, PSFProfile
from neural_dp.simulators.base.psf import _half_disc_kernel
from neural_dp.simulators.base.render import RenderConfig, render_layers
from neural_dp.simulators.butterworth import ButterworthSimulator, butterworth_psf
from neural_dp.simulators.disk import TranslatingDiskSimulator, translating_disk_psf
from neural_dp.simulators.peer_layers import render_layered
from neural_dp.simulators.raytrace import RayTracingSimulator, render_raytrace

from ..reference import base_model_render, layered_peer_render, raytrace_render


# ---- scenes ---------------------------------------------------------------------------------------------

def _scene(B: int, H: int, W: int, coc_lo: float, coc_hi: float, dtype: torch.dtype, seed: int = 0) -> DPBatch:
    """Textured sharp image; CoC a smooth ramp from ``coc_lo`` to ``coc_hi`` with a near block (depth edges,
    occlusion) and a few invalid pixels."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H, dtype=dtype), torch.linspace(0, 1, W, dtype=dtype), indexing="ij")
    tex = 0.5 + 0.3 * torch.sin(23 * xx + 3 * torch.arange(3, dtype=dtype).view(3, 1, 1)) * torch.cos(17 * yy)
    sharp = (tex[None] + 0.1 * torch.rand(B, 3, H, W, generator=g, dtype=dtype)).clamp(0, 1)
    coc = (coc_lo + (coc_hi - coc_lo) * (0.7 * xx + 0.3 * yy))[None, None].expand(B, 1, H, W).clone()
    coc[:, :, H // 4 : H // 2, W // 3 : W // 2] = coc_lo + 0.13  # a near object: a depth edge in front
    coc += 0.3 * torch.rand(B, 1, H, W, generator=g, dtype=dtype)  # continuous CoC values, not on layer centres
    valid = torch.rand(B, 1, H, W, generator=g) > 0.05
    z = torch.zeros(B, dtype=dtype)
    return DPBatch(sharp=sharp, coc_px=coc, depth_mm=torch.full_like(coc, 1500.0), valid=valid, f_number=z + 2.0,
                   focus_distance_mm=z + 1500, focal_length_mm=z + 50, pixel_pitch_mm=z + 0.05,
                   focus_point_px=torch.zeros(B, 2))


TOL = 1e-4
"""Largest allowed difference to the reference, on images in [0, 1] (issue 22: outputs stay the same)."""


# ---- peers ------------------------------------------------------------------------------------------------

SMALL_TILES = {"TILE_MIN_PX": 12, "TILE_SIDE_PER_KERNEL_PX": 0, "TILES_PER_CHUNK": 3}
LAYER_PATHS = {
    "auto": {},
    "direct_and_tiles": {"FRAME_FFT_COST_RATIO": float("inf"), **SMALL_TILES},
    "direct_and_frame_fft": {"FRAME_FFT_COST_RATIO": 0.0},
    "fft_tiles_only": {"DIRECT_MAX_PX": 0, "FRAME_FFT_COST_RATIO": float("inf"), **SMALL_TILES},
    "fft_frame_only": {"DIRECT_MAX_PX": 0, "FRAME_FFT_COST_RATIO": 0.0},
}
"""Settings of peer_layers that force each convolution path (direct on a layer's box, FFT of the tiles
holding a layer's pixels, several tiles per layer and chunk, spectra accumulated on the frame grid)."""


@pytest.mark.parametrize("path", list(LAYER_PATHS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["disk", "butterworth"])
def test_layered_peers_equal_reference(name: str, dtype: torch.dtype, path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    for attr, value in LAYER_PATHS[path].items():
        monkeypatch.setattr(peer_layers if attr == "FRAME_FFT_COST_RATIO" else kernels, attr, value)
    b = _scene(2, 40, 56, -19.0, 26.0, dtype)
    sim, psf = ((TranslatingDiskSimulator(), translating_disk_psf) if name == "disk"
                else (ButterworthSimulator(), butterworth_psf))
    left, right = sim(b)
    ref_l, ref_r = layered_peer_render.render_layered(b.sharp, b.coc_px, b.valid, psf)
    assert left.dtype == dtype
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_layered_peers_equal_reference_with_coarser_layers() -> None:
    b = _scene(1, 32, 48, -12.0, 15.0, torch.float64, seed=3)
    left, right = render_layered(b.sharp, b.coc_px, b.valid, translating_disk_psf, step_px=2.5)
    ref_l, ref_r = layered_peer_render.render_layered(b.sharp, b.coc_px, b.valid, translating_disk_psf, step_px=2.5)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


# ---- ray tracing --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_raytrace_equals_reference(dtype: torch.dtype) -> None:
    b = _scene(2, 36, 50, -13.0, 17.0, dtype, seed=1)
    left, right = RayTracingSimulator()(b)
    ref_l, ref_r = raytrace_render.render_raytrace(b.sharp, b.coc_px, b.valid)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_raytrace_equals_reference_with_capped_aperture_grid() -> None:
    b = _scene(1, 30, 40, -15.0, 12.0, torch.float64, seed=2)
    left, right = render_raytrace(b.sharp, b.coc_px, b.valid, max_points_side=8)
    ref_l, ref_r = raytrace_render.render_raytrace(b.sharp, b.coc_px, b.valid, max_points_side=8)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_raytrace_equals_reference_whatever_the_thread_count() -> None:
    """Image row bands are rendered on several threads (8 bands here); the result must not depend on how many."""
    b = _scene(1, 64, 30, -9.0, 11.0, torch.float64, seed=4)
    ref_l, ref_r = raytrace_render.render_raytrace(b.sharp, b.coc_px, b.valid)
    one = render_raytrace(b.sharp, b.coc_px, b.valid, threads=1)
    more = render_raytrace(b.sharp, b.coc_px, b.valid, threads=3)  # at most numba's pool size
    for left, right in (one, more):
        torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
        torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)
    assert torch.equal(one[0], more[0]) and torch.equal(one[1], more[1])


RAYTRACE_COCS = [0.0, 0.3, -0.7, 1.0, 1.999, 2.0, 2.001, -3.9999, 4.0, 4.0001, 5.5, -7.99, 8.0, 8.01, -9.5,
                 10.0, 13.7, -16.0001, 19.999, 23.4]
"""CoCs (px) on both sides of the even integers where the aperture grid's side steps, and beyond a cap of 8."""


@pytest.mark.parametrize("max_points_side", [8, 64])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_raytrace_equals_reference_across_grid_sides_and_the_cap(dtype: torch.dtype, max_points_side: int) -> None:
    """Every pixel its own CoC drawn from RAYTRACE_COCS (depth edges everywhere): the compiled kernel's grid
    side, mirrored rows and cut profiles must give the reference's splat for each, including capped grids whose
    rays land more than 1 px apart."""
    g = torch.Generator().manual_seed(6)
    B, H, W = 2, 40, 52
    coc = torch.tensor(RAYTRACE_COCS, dtype=dtype)[torch.randint(len(RAYTRACE_COCS), (B, 1, H, W), generator=g)]
    sharp = torch.rand(B, 3, H, W, generator=g, dtype=dtype)
    valid = torch.rand(B, 1, H, W, generator=g) > 0.05
    left, right = render_raytrace(sharp, coc, valid, max_points_side=max_points_side)
    ref_l, ref_r = raytrace_render.render_raytrace(sharp, coc, valid, max_points_side=max_points_side)
    assert left.dtype == right.dtype == dtype
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_raytrace_equals_reference_on_a_one_pixel_wide_image() -> None:
    """A 1-px axis: rays landing beyond it are lost, as in the reference (no clamping onto the only column)."""
    b = _scene(1, 20, 1, -6.0, 7.0, torch.float64, seed=5)
    left, right = render_raytrace(b.sharp, b.coc_px, b.valid)
    ref_l, ref_r = raytrace_render.render_raytrace(b.sharp, b.coc_px, b.valid)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


# ---- base model ---------------------------------------------------------------------------------------------

BASE_PATHS = {"auto": {}, "fft_tiles_only": {"DIRECT_MAX_PX": 0, **SMALL_TILES}}
"""Settings of neural_dp.kernels that force the base renderer's nodes through each convolution path."""


@pytest.mark.parametrize("path", list(BASE_PATHS))
@pytest.mark.parametrize("coc_range", [(-6.0, 8.0), (-30.0, 41.0)])
def test_base_layers_equal_reference(coc_range: tuple[float, float], path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Small blurs (direct convolutions only) and large ones (FFT nodes, the node spacing ladder)."""
    for attr, value in BASE_PATHS[path].items():
        monkeypatch.setattr(kernels, attr, value)
    b = _scene(2, 48, 64, *coc_range, torch.float32, seed=4)
    model = BaseModel(rim_softness_px=0.7)
    cfg = model.config
    kfn = model._kernel_fn(0.0)
    coc = b.coc_px.float()
    left, right = render_layers(b.sharp, coc, b.valid, kfn, cfg)
    ref_l, ref_r = base_model_render.render_layers(b.sharp, coc, b.valid, kfn, cfg)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


@pytest.mark.parametrize("path", list(BASE_PATHS))
def test_base_layers_equal_reference_per_channel_psfs_and_cocs(path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Per-channel kernels (a PSF component with chromatic CoCs): the 6-channel path."""
    for attr, value in BASE_PATHS[path].items():
        monkeypatch.setattr(kernels, attr, value)
    b = _scene(1, 40, 52, -20.0, 24.0, torch.float32, seed=5)
    chroma = ChromaticDefocus()
    chroma.params = {"focal_shift_r_mm": 0.4, "focal_shift_b_mm": -0.3}
    prof = PSFProfile()
    prof.params = {"rim_gain": 1.5}
    model = BaseModel(rim_softness_px=0.4, components=[chroma, prof])
    coc = torch.cat([b.coc_px + 1.5, b.coc_px, b.coc_px - 1.2], dim=1).float()
    kfn = model._kernel_fn(0.0)
    left, right = render_layers(b.sharp, coc, b.valid, kfn, model.config)
    ref_l, ref_r = base_model_render.render_layers(b.sharp, coc, b.valid, kfn, model.config)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_base_full_disc_layers_equal_reference() -> None:
    """Symmetric kernels (the sharp frame's own blur, sharp_radiance): the right view reuses the left one."""
    from neural_dp.simulators.base.psf import full_disc_kernels

    b = _scene(2, 40, 52, -9.0, 7.0, torch.float32, seed=6)
    cfg = RenderConfig()
    kfn = lambda nodes: full_disc_kernels(nodes, cfg.supersample)  # noqa: E731
    left, right = render_layers(b.sharp, b.coc_px, b.valid, kfn, cfg)
    ref_l, ref_r = base_model_render.render_layers(b.sharp, b.coc_px, b.valid, kfn, cfg)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


@pytest.mark.parametrize("node", [
    (0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0), (0.7, 1.0, 0.5, 0.0, 0.0, 1.0, 0.0), (-3.2, 1.0, 0.5, 0.0, 1.5, 1.0, 0.3),
    (12.5, 1.1, 1.2, -0.4, 0.2, 0.8, 1.0), (-41.0, 1.0, 0.5, 0.0, 0.0, 1.0, 0.0), (73.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.5),
])
def test_base_kernels_equal_reference(node: tuple[float, ...]) -> None:
    """The half-disc kernels (softening and pixel sampling now as band-matrix products) equal the
    conv2d-built ones."""
    torch.testing.assert_close(_half_disc_kernel(*node, supersample=4), base_model_render.half_disc_kernel(*node, supersample=4),
                               atol=1e-8, rtol=1e-5)
