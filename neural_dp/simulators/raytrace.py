r"""Ray tracing through a thin lens discretised into points (after Pan et al., CVPR 2021).

Pan et al.'s simulator is closed (encrypted P-code), so this follows the paper's description: the
aperture of a thin lens is discretised into a regular grid of points; every scene pixel sends one ray
through each aperture point and the ray lands on the sensor displaced from the pixel's in-focus image by

.. math::
    \Delta(u, v) = \frac{C}{2} (u, v), \qquad u^2 + v^2 \le 1

(:math:`C` the signed CoC diameter in px, :math:`(u, v)` the normalised aperture position). Each DP
photodiode sees half of the aperture: the left view collects the rays with :math:`u < 0`, the right view
those with :math:`u > 0`. For C > 0 the left view's light therefore lands on the left half of the disc and
for C < 0 on the right half (docs/conventions.md), and the right PSF is the hflip of the left one.

Every ray carries :math:`1/N_{ap}` of its pixel's energy and is splatted bilinearly (taps outside the
image are lost); the views are divided by the accumulated coverage of all rays (1 in the interior of a
region of constant CoC), which fills the gaps that forward splatting leaves at depth edges and at the image
border. The grid has ``n x n`` points with ``n >= |C|`` chosen per pixel (even, so no point sits on the
split; capped at ``max_points_side``), i.e. a pixel's rays land at most 1 px apart while small blurs stay
cheap.

How it is computed (that sum exactly, in another order): pixel centres are integers, so the splat of a
pixel's rays relative to the pixel is a kernel ``K_C(dX, dY)`` (px) that depends only on its CoC. The
bilinear weight is separable and the aperture points form a product lattice, so each lattice row ``j`` (one
``v_j``) puts its x-profile (the summed x-weights of its kept rays) on two sensor rows with weights
``1 - fy, fy``; the kept ``u`` of a row are a contiguous range that always ends at the centre, so the
row's profile is the profile of the full half row cut at the range's outer ray (only the two taps at the
cut differ from it). A compiled kernel (numba) builds per pixel the full half-row profile (O(n)), and per
sensor row of the footprint the weights of its taps, times ``(colour, 1) / N_ap``, once; it then adds them
to contiguous ``(H, W, C + 1)`` accumulators, about ``π/8 · (|C| + 2)²`` taps of ``C + 1`` channels a view
instead of ``π/4 · n²`` scattered rays. The lattice's symmetries give the rest: sensor rows ``y + Y`` and
``y - Y`` get the same weights, the right view gets them mirrored in x, and ``C < 0`` swaps the views.
Image row bands of the footprint's radius are rendered in parallel in three passes (bands three apart never
share an accumulator row), so no two threads write the same memory and the result is the same for any
thread count.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_learn.batch import DPBatch

from .interface import DPSimulator


def aperture_points(n: int, *, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
    """Centres of an ``n x n`` grid over [-1, 1]^2 that fall inside the unit disk. Returns (P, 2) as (u, v)."""
    t = (torch.arange(n, dtype=dtype, device=device) + 0.5) / n * 2 - 1
    v, u = torch.meshgrid(t, t, indexing="ij")
    keep = u**2 + v**2 <= 1.0
    return torch.stack([u[keep], v[keep]], dim=1)


def _splat_image_py(coc: Any, n_pix: Any, sharp: Any, t_tab: Any, lo_tab: Any, tab_off: Any, n_ap: Any,
                    band_h: int, passes: int, reach: int, acc_l: Any, acc_r: Any) -> None:  # pragma: no cover - compiled
    """Add every pixel's rays into ``acc_l`` / ``acc_r`` (compiled by numba; see :func:`_compiled_splat`).

    Args:
        coc: (H, W) signed CoC diameter in px (0 where invalid), float32 or float64.
        n_pix: (H, W) int64 aperture grid side per pixel (even).
        sharp: (C, H, W) linear image, float32 or float64.
        t_tab: float64 grid coordinates ``(k + 0.5) / n * 2 - 1`` of every used ``n``, concatenated.
        lo_tab: int64 per grid row ``j`` of every used ``n``: first kept index ``i`` of the left half
            (kept: ``lo <= i < n/2``; ``n/2`` when the row keeps none), concatenated like ``t_tab``.
        tab_off: int64 (max n + 1,) offset of ``n``'s entries in ``t_tab`` / ``lo_tab``.
        n_ap: int64 (max n + 1,) kept points of an ``n x n`` grid (both halves).
        band_h, passes: image rows per band, and the number of passes: pass ``p`` renders the bands
            ``p, p + passes, ...`` in parallel, which never touch the same accumulator row
            (``(passes - 1) * band_h >= 2 * reach``).
        reach: ``ceil(max |C| / 2) + 2`` px, bound on a footprint's radius (sizes the scratch buffers).
        acc_l, acc_r: (H * W * (C + 1),) float32 or float64 accumulators of the left and right view,
            (H, W, C + 1) flattened (colour, then the coverage), added to in place.
    """
    H, W = coc.shape
    C1 = sharp.shape[0] + 1
    n_bands = (H + band_h - 1) // band_h
    n_max = tab_off.shape[0] - 1
    m = 2 * reach + 4
    for first in range(passes):
        for bi in _prange((n_bands - first + passes - 1) // passes):
            band = first + passes * bi
            rx0 = np.empty(n_max // 2 + 1, np.int64)  # left half's rays in a grid row: x tap, fraction
            rfx = np.empty(n_max // 2 + 1)
            bk = np.empty(n_max // 2 + 1, np.int64)  # grid row cut at ray k: first tap, its two weights
            g0 = np.empty(n_max // 2 + 1)
            g1 = np.empty(n_max // 2 + 1)
            ry0 = np.empty(n_max // 2 + 1, np.int64)  # grid rows n/2 + r: y tap, fraction, cut tap and its weights
            rfy = np.empty(n_max // 2 + 1)
            rb = np.empty(n_max // 2 + 1, np.int64)
            rg0 = np.empty(n_max // 2 + 1)
            rg1 = np.empty(n_max // 2 + 1)
            gfull = np.empty(m)  # x-profile of a full half row, from tap dmin
            pre = np.empty(m)
            kb = np.empty(m)  # one sensor row's weights at the taps next to the grid rows' cuts
            # gfull and one sensor row's weights, times (colour, 1) / N_ap, interleaved (tap, channel), in
            # x order (left view) and mirrored (right view)
            gv = np.empty(m * C1, acc_l.dtype)
            gr = np.empty(m * C1, acc_l.dtype)
            rv = np.empty(m * C1, acc_l.dtype)
            rr = np.empty(m * C1, acc_l.dtype)
            val = np.empty(C1)
            wbuf = np.empty(1, acc_l.dtype)
            for y in range(band * band_h, min(H, (band + 1) * band_h)):
                for x in range(W):
                    c = coc[y, x]
                    n = n_pix[y, x]
                    half = n // 2
                    h = abs(c) * 0.5
                    off = tab_off[n]
                    inv = 1.0 / n_ap[n]
                    for ch in range(C1 - 1):
                        val[ch] = sharp[ch, y, x] * inv
                    val[C1 - 1] = inv
                    # for C < 0 each half lands where the other half lands for |C|
                    dst_l, dst_r = (acc_r, acc_l) if c < 0 else (acc_l, acc_r)
                    # rays of the left half (u < 0) of a grid row land at x + h u_i, i < n/2, sorted by x
                    for i in range(half):
                        o = h * t_tab[off + i]
                        f = math.floor(o)
                        rx0[i] = np.int64(f)
                        rfx[i] = o - f
                    dmin = rx0[0]
                    wp = rx0[half - 1] + 2 - dmin  # taps dmin .. rx0[half-1] + 1, indexed d = 0 .. wp - 1
                    for d in range(wp):
                        gfull[d] = 0.0
                        pre[d] = 0.0
                    for i in range(half):
                        b = rx0[i] - dmin
                        gfull[b] += 1.0 - rfx[i]
                        gfull[b + 1] += rfx[i]
                    for d in range(wp):
                        for ch in range(C1):
                            gv[d * C1 + ch] = gfull[d] * val[ch]
                            gr[(wp - 1 - d) * C1 + ch] = gfull[d] * val[ch]
                    # a grid row keeping rays k .. n/2-1 weighs 0 before tap bk[k], g0[k] and g1[k] at
                    # bk[k] and bk[k] + 1, and gfull from bk[k] + 2 on
                    for k in range(half):
                        b = rx0[k] - dmin
                        bk[k] = b
                        g0[k] = gfull[b] - pre[b]
                        g1[k] = gfull[b + 1] - pre[b + 1]
                        pre[b] += 1.0 - rfx[k]
                        pre[b + 1] += rfx[k]
                    # Grid rows j >= n/2 (v > 0) land on sensor rows Y >= 0, the rows j < n/2 mirror them onto
                    # Y <= 0, so sensor rows y + Y and y - Y get the same weights; on Y = 0 the mirrored rows
                    # add as much as the rows themselves. Going out from the centre row, a grid row lands
                    # lower (ry0 + fy) and keeps fewer rays (its cut tap rb is further right).
                    nr = 0
                    for r in range(half):
                        k = lo_tab[off + half + r]
                        if k >= half:  # no ray kept here, nor in the rows further out
                            break
                        q = h * t_tab[off + half + r]
                        f = math.floor(q)
                        ry0[r] = np.int64(f)
                        rfy[r] = q - f
                        rb[r] = bk[k]
                        rg0[r] = g0[k]
                        rg1[r] = g1[k]
                        nr += 1
                    ra = 0
                    re = 0
                    for Y in range(0, ry0[nr - 1] + 2 if nr > 0 else 0):
                        while ra < nr and ry0[ra] < Y - 1:
                            ra += 1
                        while re < nr and ry0[re] <= Y:
                            re += 1
                        if (y - Y < 0 and y + Y >= H) or ra == re:
                            continue
                        # grid rows ra .. re - 1 land on sensor row Y: those with ry0 == Y - 1 with weight fy,
                        # those with ry0 == Y with weight 1 - fy
                        bmin = rb[ra]
                        e_hi = rb[re - 1] + 1  # taps bmin .. e_hi depend on each grid row's cut, later ones are wsum * gfull
                        for d in range(bmin, e_hi + 1):
                            kb[d] = 0.0
                        wsum = 0.0
                        for r in range(ra, re):
                            w = (1.0 - rfy[r]) if ry0[r] == Y else rfy[r]
                            if Y == 0:
                                w *= 2.0
                            wsum += w
                            b = rb[r]
                            kb[b] += w * rg0[r]
                            kb[b + 1] += w * rg1[r]
                            for d in range(b + 2, e_hi + 1):
                                kb[d] += w * gfull[d]
                        # rv[(d - bmin) * C1 + ch] and rr[(wp - 1 - d) * C1 + ch] for taps d = bmin .. wp - 1
                        if C1 == 4:  # spelled out, so that it compiles to one vector operation per tap
                            for d in range(bmin, e_hi + 1):
                                kv = kb[d]
                                pl = (d - bmin) * 4
                                pr = (wp - 1 - d) * 4
                                rv[pl] = kv * val[0]
                                rv[pl + 1] = kv * val[1]
                                rv[pl + 2] = kv * val[2]
                                rv[pl + 3] = kv * val[3]
                                rr[pr] = kv * val[0]
                                rr[pr + 1] = kv * val[1]
                                rr[pr + 2] = kv * val[2]
                                rr[pr + 3] = kv * val[3]
                        else:
                            for d in range(bmin, e_hi + 1):
                                pl = (d - bmin) * C1
                                pr = (wp - 1 - d) * C1
                                for ch in range(C1):
                                    rv[pl + ch] = kb[d] * val[ch]
                                    rr[pr + ch] = kb[d] * val[ch]
                        wbuf[0] = wsum
                        ws = wbuf[0]  # in the accumulators' dtype
                        seg = rv[(e_hi + 1 - bmin) * C1 : (wp - bmin) * C1]
                        gs = gv[(e_hi + 1) * C1 : wp * C1]
                        for i in range(seg.shape[0]):
                            seg[i] = ws * gs[i]
                        seg = rr[: (wp - 1 - e_hi) * C1]
                        gs = gr[: (wp - 1 - e_hi) * C1]
                        for i in range(seg.shape[0]):
                            seg[i] = ws * gs[i]
                        for side in range(2 if Y > 0 else 1):
                            yy = y + Y if side == 0 else y - Y
                            if yy < 0 or yy >= H:
                                continue
                            # left view at X = x + dmin + d, right view at X = x - dmin - d, inside the image
                            lo = max(bmin, -x - dmin)
                            hi = min(wp - 1, W - 1 - x - dmin)
                            if hi >= lo:
                                p = (yy * W + x + dmin) * C1
                                seg = dst_l[p + lo * C1 : p + (hi + 1) * C1]
                                gs = rv[(lo - bmin) * C1 : (hi + 1 - bmin) * C1]
                                for i in range(seg.shape[0]):
                                    seg[i] += gs[i]
                            lo = max(bmin, x - dmin - (W - 1))
                            hi = min(wp - 1, x - dmin)
                            if hi >= lo:  # X = x - dmin - hi .. x - dmin - lo, rr from wp - 1 - hi on
                                p = (yy * W + x - dmin - hi) * C1
                                seg = dst_r[p : p + (hi + 1 - lo) * C1]
                                gs = rr[(wp - 1 - hi) * C1 : (wp - lo) * C1]
                                for i in range(seg.shape[0]):
                                    seg[i] += gs[i]


_prange = range  # numba replaces this global with its prange when it compiles _splat_image_py
_SPLAT: Callable[..., None] | None = None


def _compiled_splat() -> Callable[..., None]:
    """:func:`_splat_image_py` compiled by numba (imported on first use, so ``import neural_dp`` stays fast;
    compiled once per machine and then loaded from numba's on-disk cache)."""
    global _SPLAT, _prange
    if _SPLAT is None:
        import os

        import numba

        if "NUMBA_THREADING_LAYER" not in os.environ:
            # numba tries TBB first; Open3D's older TBB makes it warn on every first render ("requires TBB 2021
            # update 6") before it falls back to OpenMP, so go to OpenMP (libgomp, scripts/setup.sh) directly
            numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
        _prange = numba.prange
        _SPLAT = numba.njit(cache=True, parallel=True, fastmath=False, nogil=True)(_splat_image_py)
    return _SPLAT


def _aperture_tables(ns: list[int], dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per grid side ``n`` in ``ns``: coordinates, each row's kept left-half range and the kept count.

    The kept set is decided exactly as :func:`aperture_points` decides it in ``dtype`` (float32 for other
    dtypes); it must be symmetric under u -> -u and v -> -v (checked), which the mirrored right view and
    the swap for C < 0 rely on.

    Returns:
        t_tab (float64), lo_tab (int64), tab_off (int64, (max n + 1,)), n_ap (int64, (max n + 1,)), as
        :func:`_splat_image_py` takes them.
    """
    mask_dt = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    tab_off = np.full(max(ns) + 1, -1, np.int64)
    n_ap = np.ones(max(ns) + 1, np.int64)
    t_parts, lo_parts, pos = [], [], 0
    for n in ns:
        t = (torch.arange(n, dtype=mask_dt) + 0.5) / n * 2 - 1
        v, u = torch.meshgrid(t, t, indexing="ij")
        keep = u**2 + v**2 <= 1.0
        if not (torch.equal(keep, keep.flip(0)) and torch.equal(keep, keep.flip(1))):
            raise BadInputError(f"the {n} x {n} aperture grid is not symmetric in {mask_dt}; lower max_points_side",
                                where="render_raytrace")
        t_parts.append(((np.arange(n, dtype=np.float64) + 0.5) / n * 2 - 1))
        lo_parts.append((n // 2 - keep[:, : n // 2].sum(1)).numpy().astype(np.int64))
        tab_off[n], n_ap[n] = pos, int(keep.sum())
        pos += n
    return np.concatenate(t_parts), np.concatenate(lo_parts), tab_off, n_ap


def render_raytrace(sharp: Tensor, coc_px: Tensor, valid: Tensor, max_points_side: int = 64,
                    threads: int | None = None) -> tuple[Tensor, Tensor]:
    """Render both DP views by thin-lens ray splatting (module docstring).

    Runs on the CPU (inputs on another device are copied there and the views copied back): ray weights in
    float64, the accumulated views in float64 for float64 input and float32 otherwise (half the memory
    traffic; 3e-6 from float64 sums on a 1680 x 1120 studio pair with |CoC| up to 73 px). Returns the
    input's dtype. Each image of the batch is rendered on its own. The first call on a machine compiles the
    kernel (numba, about 6 s per dtype), later calls and processes load it from numba's cache.

    Args:
        sharp: (B, C, H, W) linear image.
        coc_px: (B, 1, H, W) signed CoC diameter in px (invalid pixels are treated as in focus).
        valid: (B, 1, H, W) bool.
        max_points_side: cap on the aperture grid's side (time bound for huge CoCs; above it the rays of a
            pixel land more than 1 px apart).
        threads: CPU threads of the compiled kernel (default: torch's intra-op thread count; at most
            numba's thread pool size). The result does not depend on it.

    Returns:
        (left, right), each (B, C, H, W).
    """
    B, C, H, W = sharp.shape
    dev, dt = sharp.device, sharp.dtype
    work_dt = torch.float64 if dt == torch.float64 else torch.float32
    c_all = torch.where(valid, coc_px, torch.zeros_like(coc_px))
    # Each pixel gets an n x n aperture grid with n >= |C| (even), so its rays land <= 1 px apart.
    n_all = torch.clamp(torch.ceil(c_all.abs()), 2, max_points_side).to(torch.int64)
    n_all = n_all + n_all % 2
    splat = _compiled_splat()
    import numba

    lefts, rights = [], []
    prev_threads = numba.get_num_threads()
    numba.set_num_threads(max(1, min(threads or torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
    try:
        for b in range(B):
            coc = c_all[b, 0].detach().to("cpu", work_dt).contiguous().numpy()
            n_pix = n_all[b, 0].cpu().contiguous().numpy()
            img = sharp[b].detach().to("cpu", work_dt).contiguous().numpy()
            t_tab, lo_tab, tab_off, n_ap = _aperture_tables(np.flatnonzero(np.bincount(n_pix.reshape(-1))).tolist(), dt)
            reach = int(math.ceil(float(np.abs(coc).max()) / 2)) + 2
            acc = np.zeros((2, H * W * (C + 1)), np.float64 if work_dt == torch.float64 else np.float32)
            # bands of `reach` rows in 3 passes: balanced over a few threads, and independent of their number
            splat(coc, n_pix, img, t_tab, lo_tab, tab_off, n_ap, reach, 3, reach, acc[0], acc[1])
            views = torch.from_numpy(acc).view(2, H, W, C + 1)
            cover = (views[0, ..., C:] + views[1, ..., C:]).clamp_min(1e-8)
            lefts.append((views[0, ..., :C] / cover).permute(2, 0, 1))
            rights.append((views[1, ..., :C] / cover).permute(2, 0, 1))
    finally:
        numba.set_num_threads(prev_threads)
    return torch.stack(lefts).to(dev, dt), torch.stack(rights).to(dev, dt)


class RayTracingSimulator(DPSimulator):
    """Thin-lens ray tracing with the aperture discretised into points (Pan et al.'s model, re-implemented)."""

    name = "raytrace"

    def __init__(self, max_points_side: int = 64) -> None:
        super().__init__()
        self.max_points_side = max_points_side

    def forward(self, batch: DPBatch):  # type: ignore[override]
        return render_raytrace(batch.sharp, batch.coc_px, batch.valid, self.max_points_side)
