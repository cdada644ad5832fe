"""Per-pixel kernel application and the DP mirror (Eq. 2's hflip)."""

from __future__ import annotations

import pytest
import torch

import torch.nn.functional as F

from neural_dp.kernels import _apply_kernels_unfold, apply_kernels, convolve_full, convolve_same, flip_lr


def _delta(B: int, K: int, H: int, W: int, i: int, j: int) -> torch.Tensor:
    w = torch.zeros(B, K * K, H, W, dtype=torch.float64)
    w[:, i * K + j] = 1.0
    return w


def test_shift_and_accumulate_equals_unfold_reference() -> None:
    torch.manual_seed(0)
    x = torch.rand(2, 3, 12, 17, dtype=torch.float64)
    w = torch.softmax(torch.randn(2, 25, 12, 17, dtype=torch.float64), 1)
    torch.testing.assert_close(apply_kernels(x, w), _apply_kernels_unfold(x, w))
    wc = torch.softmax(torch.randn(2, 3, 25, 12, 17, dtype=torch.float64), 2)
    torch.testing.assert_close(apply_kernels(x, wc), _apply_kernels_unfold(x, wc))


def test_gradcheck() -> None:
    torch.manual_seed(1)
    x = torch.rand(1, 2, 5, 6, dtype=torch.float64, requires_grad=True)
    w = torch.rand(1, 9, 5, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(apply_kernels, (x, w))


def test_kernel_that_shifts_left_view_left_shifts_right_view_right() -> None:
    """The deliberate choice against the released code's row-axis mirror: the mirror is along x."""
    x = torch.zeros(1, 1, 9, 15, dtype=torch.float64)
    x[..., 4, 7] = 1.0
    w_left = _delta(1, 5, 9, 15, 2, 4)  # gathers from x + 2: content moves 2 px LEFT
    left = apply_kernels(x, w_left)
    right = apply_kernels(x, flip_lr(w_left))
    assert left[0, 0].nonzero().tolist() == [[4, 5]]
    assert right[0, 0].nonzero().tolist() == [[4, 9]]
    # a row (y) mirror, as in the released code, would leave the two views identical here
    w_rowflip = w_left.view(1, 5, 5, 9, 15).flip(1).reshape(1, 25, 9, 15)
    assert torch.equal(apply_kernels(x, w_rowflip), left)


def test_flip_lr_is_an_involution_and_keeps_rows() -> None:
    w = torch.rand(2, 3, 25, 4, 4)
    assert torch.equal(flip_lr(flip_lr(w)), w)
    g = w.view(2, 3, 5, 5, 4, 4)
    torch.testing.assert_close(flip_lr(w).view(2, 3, 5, 5, 4, 4)[:, :, 1, 0], g[:, :, 1, 4])


def test_replicate_padding_keeps_constant_image_constant() -> None:
    x = torch.full((1, 3, 6, 7), 0.3)
    w = torch.softmax(torch.randn(1, 25, 6, 7), 1)
    torch.testing.assert_close(apply_kernels(x, w), x)


@pytest.mark.parametrize("k", [5, 31])
def test_convolve_same_is_true_convolution_both_paths(k: int) -> None:
    x = torch.zeros(1, 1, 40, 50, dtype=torch.float64)
    x[..., 20, 25] = 1.0
    psf = torch.zeros(k, k, dtype=torch.float64)
    psf[k // 2, 0] = 1.0  # mass at u = -k//2: content moves left
    out = convolve_same(x, psf)
    assert out[0, 0].argmax().item() == 20 * 50 + 25 - k // 2
    assert float(out.sum()) == pytest.approx(1.0)


@pytest.mark.parametrize("backend", ["opencv", "torch"])
def test_convolve_full_is_true_full_convolution(backend: str) -> None:
    """A delta lands at the PSF's centre offset, content follows the PSF's mass (u < 0 moves it left),
    and random images match ``conv2d`` with the flipped kernel, shared and per-channel PSFs."""
    x = torch.zeros(1, 1, 9, 11, dtype=torch.float64)
    x[..., 4, 5] = 1.0
    psf = torch.zeros(2, 5, 5, dtype=torch.float64)
    psf[0, 2, 0] = 1.0  # mass at u = -2
    psf[1, 2, 2] = 1.0  # identity
    out = convolve_full(x, psf, backend=backend)
    assert out.shape == (1, 2, 1, 13, 15)
    assert out[0, 1, 0].argmax().item() == (4 + 2) * 15 + 5 + 2
    assert out[0, 0, 0].argmax().item() == (4 + 2) * 15 + 5
    torch.manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        x = torch.rand(2, 3, 14, 19, dtype=dtype)
        for psfs in (torch.rand(2, 7, 7, dtype=dtype), torch.rand(2, 3, 7, 7, dtype=dtype)):
            got = convolve_full(x, psfs, backend=backend)
            w = psfs if psfs.ndim == 4 else psfs[:, None].expand(2, 3, 7, 7)
            for v in range(2):
                ref = F.conv2d(F.pad(x, (6, 6, 6, 6)), w[v].flip(-1, -2)[:, None], groups=3)
                torch.testing.assert_close(got[:, v], ref, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("h", "w"), [(100, 30), (23, 250), (97, 97)])
def test_fft_tiles_fit_the_image_and_give_the_full_convolution(h: int, w: int) -> None:
    """FFT tiles cover an extent evenly (as many as the kernel's tile side needs, no larger than the image) and
    the tiled FFT convolution of an image with holes (unoccupied tiles skipped) is the full convolution."""
    from neural_dp.kernels import add_full_convolution, tile_shape_px, tile_side_px

    k = 21
    side = tile_side_px(k)
    sy, sx = tile_shape_px(h, w, k)
    assert sy <= min(h, side) and sx <= min(w, side)
    assert -(-h // sy) == -(-h // side) and -(-w // sx) == -(-w // side)  # no more tiles than the square side gives
    torch.manual_seed(1)
    x = torch.rand(2, 4, h, w, dtype=torch.float64)
    x[..., : h // 2, : w // 2] = 0.0
    occupied = x.abs().sum((0, 1)) > 0
    psfs = torch.rand(2, k, k, dtype=torch.float64)
    dest = torch.zeros(2, 2, 4, h + k - 1, w + k - 1, dtype=torch.float64)
    add_full_convolution(dest, 0, 0, x, psfs, occupied)
    ref = convolve_full(x, psfs, backend="torch")
    torch.testing.assert_close(dest, ref, atol=1e-9, rtol=1e-9)
