"""Per-pixel kernel application (kernel-prediction networks) and dense PSF convolution.

Two ways of blurring live here:

* :func:`apply_kernels` applies a *different* K x K kernel at every pixel (the Neural DP Simulator's
  neural PSF maps) by shift-and-accumulate: K^2 fused multiply-adds over shifted views of a replicate-
  padded input. It keeps only the padded input and the weights alive for backward, about 3x less memory
  than ``F.unfold`` (``_apply_kernels_unfold`` is kept as the reference the tests compare against).
* :func:`convolve_same` convolves a whole image with one PSF (true convolution, zero padding), switching
  to FFT for large kernels.
* :func:`convolve_full` convolves every channel with each of a few small PSFs (the left and right views
  of a layer), full output; on the CPU with OpenCV's ``filter2D`` (10-25 x faster than a grouped
  ``conv2d`` for 3-9 px kernels on this project's CPU).
* :func:`add_full_convolution` adds such a full convolution of a sparse layer into an accumulator: small
  kernels directly, large ones by batched FFTs of only the tiles that hold the layer's pixels. The layered
  renderers (peers and base model) use it.

Kernel layout convention: a flattened kernel index ``t = i * K + j`` is row ``i`` (y offset ``i - K//2``)
and column ``j`` (x offset ``j - K//2``). The weights are a *gather* kernel:

.. math::
    out(y, x) = \\sum_{i,j} w_{ij}(y, x) \\; in(y + i - K/2, x + j - K/2)

so a weight mass at ``j < K//2`` reads pixels to the left, i.e. it moves content to the **right**.
:func:`flip_lr` mirrors every kernel about its vertical axis (``j -> K-1-j``), which is the DP
relation ``H_r = hflip(H_l)`` of Eq. (2).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from scipy.fft import next_fast_len

from dp5k_common.errors import BadInputError

DIRECT_MAX_PX = 11
"""Kernels at most this many px wide are applied by direct convolution (:func:`convolve_full`), larger
ones by FFT of tiles (:func:`add_full_convolution`)."""

TILE_MIN_PX = 96
"""Smallest side of the tiles a layer is cut into for FFT convolution (px)."""

TILE_SIDE_PER_KERNEL_PX = 2
"""A layer convolved with a k-px kernel is cut into tiles of at most ``max(TILE_MIN_PX, TILE_SIDE_PER_KERNEL_PX
* k)`` px a side (:func:`tile_shape_px`), so a tile's FFT grid (side + k - 1) stays within about 1.5 x its side."""

TILES_PER_CHUNK = 16
"""Tiles transformed at once with two PSFs (bounds the memory of the batched FFTs); with V PSFs (the views of
every field node of a field-varying PSF, convolved together) ``max(1, 2 TILES_PER_CHUNK / V)``."""


def _kernel_size(weights: Tensor, dim: int) -> int:
    k2 = weights.shape[dim]
    k = int(round(math.sqrt(k2)))
    if k * k != k2 or k % 2 == 0:
        raise BadInputError(f"kernel axis has {k2} taps; need K*K with K odd", where="apply_kernels")
    return k


def apply_kernels(x: Tensor, weights: Tensor, *, padding: str = "replicate", dilation: int = 1) -> Tensor:
    """Apply a per-pixel K x K gather kernel to an image (shift-and-accumulate).

    Args:
        x: (B, C, H, W) image.
        weights: (B, K*K, H, W) one kernel per pixel shared by all channels, or
            (B, C, K*K, H, W) one kernel per pixel and channel. Not normalised here (the model's
            softmax does that), so handcrafted kernels can be applied too.
        padding: ``"replicate"`` (default; keeps sum-to-one kernels from darkening the border),
            ``"reflect"`` or ``"zeros"``.
        dilation: spacing of the taps in px (``d``): tap ``(i, j)`` reads offset ``((i - r) d, (j - r) d)``,
            so the kernel spans ``(K - 1) d + 1`` px (the multi-scale Neural DP kernels use d = 2, 4, ...).

    Returns:
        (B, C, H, W) :math:`out(y,x) = \\sum_{ij} w_{ij}(y,x)\\, x(y+(i-r)d, x+(j-r)d)`, ``r = K // 2``.

    Example:
        >>> x = torch.arange(5.0).view(1, 1, 1, 5).expand(1, 1, 3, 5).contiguous()
        >>> w = torch.zeros(1, 9, 3, 5); w[:, 3] = 1.0  # tap (i=1, j=0): read x - 1
        >>> apply_kernels(x, w)[0, 0, 1].tolist()
        [0.0, 0.0, 1.0, 2.0, 3.0]
    """
    if x.ndim != 4:
        raise BadInputError(f"x must be (B, C, H, W), got shape {tuple(x.shape)}", where="apply_kernels")
    per_channel = weights.ndim == 5
    k = _kernel_size(weights, 2 if per_channel else 1)
    B, C, H, W = x.shape
    if weights.shape[0] != B or weights.shape[-2:] != (H, W) or (per_channel and weights.shape[1] != C):
        raise BadInputError(
            f"weights {tuple(weights.shape)} do not match image {tuple(x.shape)}", where="apply_kernels"
        )
    if dilation < 1:
        raise BadInputError(f"dilation must be >= 1, got {dilation}", where="apply_kernels")
    d = int(dilation)
    r = k // 2
    mode = "constant" if padding == "zeros" else padding
    xp = F.pad(x, (r * d, r * d, r * d, r * d), mode=mode)
    out = torch.zeros_like(x)
    for i in range(k):
        for j in range(k):
            w = weights[:, :, i * k + j] if per_channel else weights[:, i * k + j : i * k + j + 1]
            out = out + w * xp[:, :, i * d : i * d + H, j * d : j * d + W]
    return out


def _apply_kernels_unfold(x: Tensor, weights: Tensor, *, padding: str = "replicate", dilation: int = 1) -> Tensor:
    """Reference implementation of :func:`apply_kernels` with ``F.unfold`` (memory hungry; tests only)."""
    per_channel = weights.ndim == 5
    k = _kernel_size(weights, 2 if per_channel else 1)
    B, C, H, W = x.shape
    r = k // 2 * dilation
    mode = "constant" if padding == "zeros" else padding
    cols = F.unfold(F.pad(x, (r, r, r, r), mode=mode), k, dilation=dilation).view(B, C, k * k, H, W)
    w = weights if per_channel else weights[:, None]
    return (cols * w).sum(2)


def flip_lr(weights: Tensor) -> Tensor:
    """Mirror every flattened K x K kernel left-right (``j -> K-1-j``): Eq. (2)'s ``hflip``.

    Args:
        weights: (B, K*K, H, W) or (B, C, K*K, H, W).

    Returns:
        Same shape; a kernel that moves content left moves it right after the flip.
    """
    per_channel = weights.ndim == 5
    dim = 2 if per_channel else 1
    k = _kernel_size(weights, dim)
    shape = weights.shape
    grid = weights.reshape(*shape[:dim], k, k, *shape[dim + 1 :])
    return grid.flip(dim + 1).reshape(shape)


def convolve_same(x: Tensor, psf: Tensor, *, fft_above: int = 21) -> Tensor:
    """True 2-D convolution of every channel with one PSF, zero padding, output the input's size.

    .. math::
        out(y, x) = \\sum_{u,v} psf(v, u)\\, x(y - v, x - u)

    with ``(u, v)`` offsets from the PSF centre: a PSF mass at ``u < 0`` moves content left.

    Args:
        x: (B, C, H, W).
        psf: (k, k) with k odd, on x's device and dtype.
        fft_above: kernels larger than this many taps per side use FFT instead of ``conv2d``.

    Returns:
        (B, C, H, W).
    """
    k = psf.shape[-1]
    if psf.ndim != 2 or psf.shape[0] != k or k % 2 == 0:
        raise BadInputError(f"psf must be square with odd size, got {tuple(psf.shape)}", where="convolve_same")
    B, C, H, W = x.shape
    r = k // 2
    if k <= fft_above:
        weight = psf.flip(0, 1).to(x.dtype)[None, None].expand(C, 1, k, k)
        return F.conv2d(F.pad(x, (r, r, r, r)), weight, groups=C)
    Hp, Wp = H + 2 * r, W + 2 * r
    X = torch.fft.rfft2(x, s=(Hp, Wp))
    K = torch.fft.rfft2(psf.to(x.dtype), s=(Hp, Wp))
    full = torch.fft.irfft2(X * K, s=(Hp, Wp))
    return full[..., r : r + H, r : r + W]


def convolve_full(x: Tensor, psfs: Tensor, *, backend: str = "auto") -> Tensor:
    """Full 2-D convolutions (true convolution, zero outside ``x``) of every channel with each of V PSFs.

    .. math::
        out_v(y, x) = \\sum_{i,j} psf_v(i, j)\\, x(y - i, x - j), \\qquad 0 \\le y < h + k - 1

    so the centre of a ``psf`` sits at ``(k//2, k//2)``: the input pixel ``(y, x)`` lands at
    ``(y + k//2, x + k//2)`` for a centred delta.

    Args:
        x: (B, C, h, w).
        psfs: (V, k, k), the same PSFs for every channel, or (V, C, k, k), one per channel; k odd.
        backend: ``"auto"`` (``cv2.filter2D`` per channel for float32/float64 on the CPU without autograd,
            ``conv2d`` otherwise), ``"opencv"`` or ``"torch"``.

    Returns:
        (B, V, C, h + k - 1, w + k - 1).
    """
    B, C, h, w = x.shape
    V, k = psfs.shape[0], psfs.shape[-1]
    per_channel = psfs.ndim == 4
    if psfs.shape[-2] != k or k % 2 == 0 or (per_channel and psfs.shape[1] != C):
        raise BadInputError(f"psfs {tuple(psfs.shape)} do not fit an image of {C} channels with odd square kernels",
                            where="convolve_full")
    r = k // 2
    if backend == "auto":
        on_cpu = x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)
        backend = "opencv" if on_cpu and not (x.requires_grad or psfs.requires_grad) else "torch"
    if backend == "opencv":
        src = x.detach().contiguous().numpy()
        kern = psfs.detach().to(x.dtype).flip(-1, -2).contiguous().numpy()  # filter2D correlates
        # Every plane zero-padded by r and the planes stacked into one tall image: a tap reaches at most r rows
        # into the next plane's zero border, so one filter2D call per kernel is each plane's own full convolution
        # (the same sums, in the same order, as plane by plane), at a fraction of the calls.
        hp, wp = h + 2 * r, w + 2 * r
        padded = np.zeros((C, B, hp, wp), dtype=src.dtype)
        padded[:, :, r : r + h, r : r + w] = src.transpose(1, 0, 2, 3)
        out = np.empty((V, C, B, hp, wp), dtype=src.dtype)
        if per_channel:
            for c in range(C):
                tall = padded[c].reshape(B * hp, wp)
                for v in range(V):
                    cv2.filter2D(tall, -1, kern[v, c], dst=out[v, c].reshape(B * hp, wp), borderType=cv2.BORDER_CONSTANT)
        else:
            tall = padded.reshape(C * B * hp, wp)
            for v in range(V):
                cv2.filter2D(tall, -1, kern[v], dst=out[v].reshape(C * B * hp, wp), borderType=cv2.BORDER_CONSTANT)
        return torch.from_numpy(out).permute(2, 0, 1, 3, 4)
    weight = psfs.flip(-1, -2).to(x.dtype)  # conv2d correlates
    weight = weight.transpose(0, 1) if per_channel else weight[None].expand(C, V, k, k)  # (C, V, k, k)
    out = F.conv2d(F.pad(x, (k - 1,) * 4), weight.reshape(C * V, 1, k, k), groups=C)
    return out.view(B, C, V, h + k - 1, w + k - 1).transpose(1, 2)


def tile_side_px(k: int) -> int:
    """Side (px) of the tiles used to convolve with a k-px kernel by FFT."""
    return max(TILE_MIN_PX, TILE_SIDE_PER_KERNEL_PX * k)


def tile_shape_px(h: int, w: int, k: int) -> tuple[int, int]:
    """(rows, cols) px of the tiles an (h, w) image is cut into to convolve it with a k-px kernel by FFT: as many
    tiles per axis as :func:`tile_side_px` needs, each as small as covers the image evenly (a 100-px extent is
    two 50-px tiles, a 30-px one a single 30-px tile, not 96 px padded with zeros: the FFT grid, tile + k - 1,
    shrinks with it and the linear convolution is the same)."""
    side = tile_side_px(k)
    return -(-h // -(-h // side)), -(-w // -(-w // side))


def tile_occupancy(occupied: Tensor, tile: tuple[int, int]) -> Tensor:
    """(ny, nx) bool: which ``tile`` (rows, cols) tiles of an (h, w) bool map hold a True (tiles from the top
    left; the last row and column may be partial)."""
    h, w = occupied.shape
    sy, sx = tile
    ny, nx = -(-h // sy), -(-w // sx)
    return F.pad(occupied, (0, nx * sx - w, 0, ny * sy - h)).view(ny, sy, nx, sx).any(3).any(1)


def occupied_tiles(x: Tensor, occupied: Tensor, tile: tuple[int, int]) -> tuple[Tensor, list[tuple[int, int]]]:
    """Cut ``x`` (B, C, h, w) into ``tile`` (rows, cols) tiles (zero-padded at the bottom and right) and keep
    those where ``occupied`` (h, w) bool holds a True.

    Returns:
        (n, B, C, rows, cols) tiles and their n (y, x) origins in ``x``, px.
    """
    B, C, h, w = x.shape
    sy, sx = tile
    ny, nx = -(-h // sy), -(-w // sx)
    padded = F.pad(x, (0, nx * sx - w, 0, ny * sy - h))
    tiles = padded.view(B, C, ny, sy, nx, sx).permute(2, 4, 0, 1, 3, 5)  # (ny, nx, B, C, sy, sx)
    iy, ix = torch.nonzero(tile_occupancy(occupied, tile), as_tuple=True)
    return tiles[iy, ix], [(int(a) * sy, int(b) * sx) for a, b in zip(iy.tolist(), ix.tolist())]


def fft_grid(tile: tuple[int, int], k: int) -> tuple[int, int]:
    """The FFT grid (rows, cols) for full convolutions of ``tile``-sized images with k-px kernels: each side at
    least tile + k - 1, rounded up to a size the real FFT is fast at."""
    return next_fast_len(tile[0] + k - 1, real=True), next_fast_len(tile[1] + k - 1, real=True)


def fft_convolve_full(x: Tensor, psfs: Tensor, grid: tuple[int, int]) -> Tensor:
    """Full linear convolutions of (..., C, h, w) images with V PSFs (V, k, k) or (V, C, k, k) by FFT on a
    ``grid`` (rows, cols) grid (at least h + k - 1 rows and w + k - 1 columns).

    Returns:
        (..., V, C, rows, cols); the full convolution is its top-left (h + k - 1, w + k - 1) corner.
    """
    k = psfs.shape[-1]
    gy, gx = grid
    X = torch.fft.rfft2(x, s=(gy, gx)).unsqueeze(-4)  # (..., 1, C, gy, gx // 2 + 1)
    big = psfs.new_zeros(*psfs.shape[:-2], gy, gx).to(x.dtype)
    big[..., :k, :k] = psfs
    K = torch.fft.rfft2(big)
    if psfs.ndim == 3:
        K = K.unsqueeze(-3)  # (V, 1, gy, gx // 2 + 1): the same PSF for every channel
    return torch.fft.irfft2(X * K, s=(gy, gx))


def add_full_convolution(dest: Tensor, y0: int, x0: int, x: Tensor, psfs: Tensor, occupied: Tensor | None = None) -> None:
    """``dest[:, :, :, y0 + i, x0 + j] += full(x * psf_v)[i, j]`` for every PSF v (in place).

    Kernels up to :data:`DIRECT_MAX_PX` wide by :func:`convolve_full`; larger ones by :func:`fft_convolve_full`
    of only the tiles of ``x`` that hold a True of ``occupied`` (h, w) (``x`` is zero elsewhere; default:
    every tile), :data:`TILES_PER_CHUNK` at a time (fewer with more than two PSFs).

    Args:
        dest: (B, V, C, Hd, Wd); it must hold the full convolution's (h + k - 1, w + k - 1) extent at
            (y0, x0).
        x: (B, C, h, w).
        psfs: (V, k, k) or (V, C, k, k), k odd (true convolution: mass at u < 0 moves content left).
    """
    h, w = x.shape[-2:]
    k = psfs.shape[-1]
    if k <= DIRECT_MAX_PX:
        dest[..., y0 : y0 + h + k - 1, x0 : x0 + w + k - 1] += convolve_full(x, psfs).to(dest.device)
        return
    tile = sy, sx = tile_shape_px(h, w, k)
    occ = occupied if occupied is not None else torch.ones(h, w, dtype=torch.bool, device=x.device)
    tiles, origins = occupied_tiles(x, occ, tile)
    grid = fft_grid(tile, k)
    step = max(1, 2 * TILES_PER_CHUNK // max(psfs.shape[0], 2))
    for i in range(0, len(origins), step):
        full = fft_convolve_full(tiles[i : i + step], psfs, grid)
        for f, (ty, tx) in zip(full, origins[i : i + step]):
            ny, nx = min(sy + k - 1, h + k - 1 - ty), min(sx + k - 1, w + k - 1 - tx)
            dest[..., y0 + ty : y0 + ty + ny, x0 + tx : x0 + tx + nx] += f[..., :ny, :nx]
