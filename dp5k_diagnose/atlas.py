r"""The PSF atlas: a camera's DP kernels measured from data, per view, colour channel, signed CoC bin and field zone.

Where a kernel ``k`` is the same over a set of pixels ``M`` (one CoC bin in one field zone, away from depth edges
and the frame border), a view is the sharp image blurred by it, ``b(p) = sum_u k(u) s(p - u) + noise``: linear in
``k``. With ``s`` known, the kernel follows by regularised least squares pooled over every pair (Joshi et al. CVPR
2008; Delbracio et al. IJCV 2012):

.. math::

    \min_k \sum_i \sum_{p \in M_i} \big(b_i(p) - \beta_i - \sum_u k(u) s_i(p - u)\big)^2 + \lambda \|\nabla k\|^2,

one intercept :math:`\beta_i` per pair and cell (the patches and views are centred on their means over the cell),
:math:`\lambda` a small multiple of the normal matrix's mean diagonal. The normal matrix is the exact Gram of the
sharp patches :math:`x_p(u) = s(p - u)` of the cell's pixels (a Toeplitz or Fourier-domain form is exact only for a
cell that fills whole patches; on the band of a slanted plane it misplaced half of a kernel's mass), over at most
:data:`SAMPLES_PER_UNKNOWN` pixels per unknown drawn at random. Kernels wider than :data:`MAX_GRID` px are solved
on blocks of ``bs x bs`` px (odd ``bs``), the kernel constant on each block.

The same sharp patches serve every view-set measured on the same pairs (the measured views, a simulator's renders
of them): their estimates are the same linear map of their kernels, so what differs between two atlases is what
differs between the views, not the estimator.

A kernel's sum is read off its DC response, the ratio of the view's and the sharp image's sums over the cell's
pixels (:meth:`Atlas.dc_gain`): exact for a kernel the cell's content is smooth across, and free of the
regularisation.

Intervals: a bootstrap over pairs, linearised. Pair ``i``'s influence on a kernel is
:math:`\delta k_i = (N + \lambda L)^{-1} X_i^T (y_i - X_i \hat k)`, and a resample with pair counts ``w`` gives
:math:`\hat k + \sum_i (w_i - 1)\, \delta k_i`. The resamples are drawn once and shared by every view-set and cell,
so a signature's difference between two atlases is resampled on the same pairs.

Units: kernel offsets in output px (x right, y down; index ``h`` is offset 0), kernels map the sharp image
(linear) to a view (linear), so an ideal view's kernel sums to 1/2 times the gain (Eq. 2). CoC: the signed
diameter in output px (docs/conventions.md).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Binning:
    """Signed CoC bins from edges of |CoC| (signed diameter, output px).

    Bin 0 is ``|c| < edges[0]``; bin ``+i`` is ``edges[i-1] <= c < edges[i]`` (behind focus), bin ``-i`` its
    mirror in front of focus.
    """

    edges_px: tuple[float, ...]

    @property
    def n(self) -> int:
        """Bins on each side of focus (bins run ``-n + 1 .. n - 1``)."""
        return len(self.edges_px)

    @property
    def outside(self) -> int:
        """The index :meth:`of` gives a CoC beyond the last edge (or not finite)."""
        return self.n + 1

    def edges(self, b: int) -> tuple[float, float]:
        """(lo, hi) signed CoC (px) of bin ``b``."""
        if b == 0:
            return (-self.edges_px[0], self.edges_px[0])
        lo, hi = self.edges_px[abs(b) - 1], self.edges_px[abs(b)]
        return (lo, hi) if b > 0 else (-hi, -lo)

    def centre(self, b: int) -> float:
        """The bin's representative signed CoC (px): 0 for bin 0, else the mid-point of its edges."""
        lo, hi = self.edges(b)
        return 0.0 if b == 0 else (lo + hi) / 2

    def half_size(self, b: int) -> int:
        """Kernel half-size h (px) of bin ``b``: the largest blur radius plus :data:`MARGIN_PX`."""
        return int(math.ceil(self.edges_px[abs(b)] / 2 + MARGIN_PX))

    def of(self, coc_px: np.ndarray) -> np.ndarray:
        """Signed bin index of each CoC (px); :attr:`outside` beyond the last edge or where not finite."""
        a = np.abs(coc_px)
        idx = np.searchsorted(np.asarray(self.edges_px), a, side="right")
        out = np.where(coc_px < 0, -idx, idx).astype(np.int64)
        return np.where(np.isfinite(coc_px) & (idx < self.n), out, self.outside)


MARGIN_PX = 4
"""Kernel support beyond the bin's largest blur radius (px): pixel sampling, residual blur, shifts."""

FINE = Binning((0.3, 0.6, 1.0, 1.5, 2.2, 3.0, 4.0, 5.5, 7.5, 10.0, 13.0, 17.0, 22.0, 28.0, 36.0, 46.0, 60.0, 80.0,
                105.0, 140.0))
"""The whole field's bins (zone -1): fine near focus, where a focus or colour error moves the blur's zero."""

COARSE = Binning((1.0, 3.0, 7.5, 17.0, 36.0, 80.0, 140.0))
"""Each field zone's bins: few, so that a zone's kernels are measured from enough pixels."""

ZONES = 3
"""The field [-1, 1]^2 is cut into ZONES x ZONES zones (zone = zy * ZONES + zx)."""

MAX_GRID = 25
"""Largest kernel grid side (blocks); wider kernels are solved on blocks of several px."""

SAMPLES_PER_UNKNOWN = 12
"""Pixels drawn per kernel unknown, at least, for a cell's normal matrix (all of them where there are fewer)."""

GRAM_BUDGET = 2e9
"""... and as many more as keep a cell's normal matrix (pixels x unknowns^2 multiply-adds per channel) within this:
every pixel of a small kernel's cell counts (the kernels near focus, which a focus or colour error changes by a
fraction of a px, need all of them), a wide kernel's cell keeps 12 per unknown."""

REG = 1e-4
"""Tikhonov weight of the kernel's gradient energy, as a multiple of the normal matrix's mean diagonal."""

MIN_PIXELS_PER_UNKNOWN = 3.0
"""A cell's kernel is measured only from at least this many scored pixels per unknown (pooled over pairs)."""

MIN_PAIRS = 2
"""... and from at least this many pairs."""

DEFAULT_BOOT = 200
"""Bootstrap resamples over pairs."""

Key = tuple[int, int]
"""A cell: (signed CoC bin, field zone), zone -1 for the whole field."""


def binning(zone: int) -> Binning:
    """The bins of ``zone``: :data:`FINE` for the whole field (-1), :data:`COARSE` for a zone."""
    return FINE if zone < 0 else COARSE


def field_zones(field_xy: np.ndarray) -> np.ndarray:
    """Zone index ``zy * ZONES + zx`` of field coordinates ``(2, H, W)`` in [-1, 1]."""
    z = np.clip(((field_xy + 1) / 2 * ZONES).astype(np.int64), 0, ZONES - 1)
    return z[1] * ZONES + z[0]


def zone_centre(zone: int) -> tuple[float, float]:
    """Field (x, y) of a zone's centre."""
    zy, zx = divmod(zone, ZONES)
    return (-1 + (2 * zx + 1) / ZONES, -1 + (2 * zy + 1) / ZONES)


@dataclass(frozen=True)
class Grid:
    """A kernel's sampling: ``2 g + 1`` blocks of ``bs`` px (odd) per side, centred; ``h = g bs + bs // 2``."""

    g: int
    bs: int

    @classmethod
    def of(cls, key: Key) -> "Grid":
        h = binning(key[1]).half_size(key[0])
        bs = 1
        while 2 * math.ceil((h - bs // 2) / bs) + 1 > MAX_GRID:
            bs += 2
        return cls(int(math.ceil((h - bs // 2) / bs)), bs)

    @property
    def side(self) -> int:
        """Blocks per side."""
        return 2 * self.g + 1

    @property
    def n(self) -> int:
        """Unknowns."""
        return self.side**2

    @property
    def h(self) -> int:
        """Half-size in px of the kernel expanded to px."""
        return self.g * self.bs + self.bs // 2

    def offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """(dy, dx) px of each block centre, (n,) each, row-major."""
        j = np.arange(-self.g, self.g + 1) * self.bs
        dy, dx = np.meshgrid(j, j, indexing="ij")
        return dy.ravel(), dx.ravel()

    def to_px(self, k: np.ndarray) -> np.ndarray:
        """(..., side, side) block values -> (..., 2h + 1, 2h + 1) px (each block's value on its px)."""
        return np.repeat(np.repeat(k, self.bs, axis=-2), self.bs, axis=-1) if self.bs > 1 else k


@dataclass
class PairImages:
    """One pair's sharp side as the atlas reads it (float32 or float64, linear).

    Attributes:
        pair_id: the pair's id.
        sharp: (3, H, W) the sharp image.
        coc_px: (H, W) signed CoC diameter (output px).
        score: (H, W) bool: pixels whose views the sharp image predicts (valid, away from depth edges and the
            frame border; :func:`dp5k_diagnose.data.predictable_mask`).
        field: (2, H, W) field coordinates in [-1, 1] of the full frame.
    """

    pair_id: str
    sharp: np.ndarray
    coc_px: np.ndarray
    score: np.ndarray
    field: np.ndarray


Views = tuple[np.ndarray, np.ndarray]
"""(left, right) of one pair, each (3, H, W) linear: measured, or a simulator's render."""


def cell_masks(img: PairImages) -> dict[Key, np.ndarray]:
    """Every cell the pair's scored pixels fall in, with its (H, W) bool mask: the whole field's fine bins and each
    zone's coarse bins (:func:`binning`)."""
    zones = field_zones(img.field)
    out: dict[Key, np.ndarray] = {}
    groups = [(-1, img.score)] + [(int(z), img.score & (zones == z)) for z in np.unique(zones[img.score])]
    for z, where in groups:
        bn = binning(z)
        bins = np.where(where, bn.of(img.coc_px), bn.outside)
        for b in np.unique(bins):
            if b < bn.outside:
                out[(int(b), z)] = bins == b
    return out


def _box(img: np.ndarray, bs: int) -> np.ndarray:
    """(3, H, W) summed over a centred ``bs x bs`` box (zero outside)."""
    if bs == 1:
        return img
    r = bs // 2
    p = np.pad(img, ((0, 0), (r + 1, r), (r + 1, r)))
    c = p.cumsum(1).cumsum(2)
    return c[:, bs:, bs:] - c[:, :-bs, bs:] - c[:, bs:, :-bs] + c[:, :-bs, :-bs]


def _patches(padded: np.ndarray, pad: int, ys: np.ndarray, xs: np.ndarray, grid: Grid, centred: bool = True) -> Tensor:
    """(3, m, n) float32: the sharp patches ``x_p(u) = s(p - u)`` of pixels (ys, xs) on the grid's blocks (each block's
    px summed: ``padded`` is sharp box-summed over ``grid.bs`` and zero-padded by ``pad`` >= ``grid.h``), centred on
    their mean over the pixels (the intercept) unless ``centred`` is False: ``X^T y`` is the same for a centred ``y``,
    and ``X k`` differs by a constant that centring the residual removes."""
    dy, dx = grid.offsets()
    Wp = padded.shape[-1]
    idx = ((ys + pad) * Wp + xs + pad)[:, None] - (dy * Wp + dx)[None, :]  # (m, n) linear indices of s(p - u)
    X = torch.from_numpy(padded.reshape(3, -1)).index_select(1, torch.from_numpy(idx.reshape(-1))).reshape(3, *idx.shape)
    return _centred(X) if centred else X


def _centred(v: Tensor) -> Tensor:
    """(3, m, k) less its mean over the m pixels."""
    return v - v.mean(1, keepdim=True)


def _gather_views(views: Views, ys: np.ndarray, xs: np.ndarray) -> Tensor:
    """(3, m, 2) float32: the left and right views at pixels (ys, xs), centred on their mean."""
    return _centred(torch.from_numpy(np.stack([views[0][:, ys, xs], views[1][:, ys, xs]], -1).astype(np.float32)))


def _xty(X: Tensor, y: Tensor) -> Tensor:
    """(3, n, k) float64: ``X^T y`` of patches ``X`` (3, m, n) and views ``y`` (3, m, k), as ``(y^T X)^T``: the same
    sums, streamed along the patches' rows (X^T's strided rows took 3.7 times as long with k = 2)."""
    return torch.bmm(y.transpose(1, 2), X).transpose(1, 2).double()


def _laplacian(side: int) -> Tensor:
    """(n, n) ``D^T D`` of the kernel grid's forward differences (n = side^2), float64."""
    d = torch.zeros(side - 1, side, dtype=torch.float64)
    d[torch.arange(side - 1), torch.arange(side - 1)] = -1.0
    d[torch.arange(side - 1), torch.arange(1, side)] = 1.0
    eye = torch.eye(side, dtype=torch.float64)
    Dx, Dy = torch.kron(eye, d), torch.kron(d, eye)
    return Dx.T @ Dx + Dy.T @ Dy


@dataclass
class Cell:
    """One cell of the atlas.

    Attributes:
        bin: signed CoC bin (of :func:`binning` of the zone).
        zone: field zone (:func:`zone_centre`), -1 for the whole field.
        grid: the kernel's sampling.
        pairs: (P_c,) indices (into :attr:`Atlas.pair_ids`) of the pairs holding scored pixels here.
        pixels: (P_c,) scored pixels per pair.
        coc_sum: (P_c,) per pair, the sum of the signed CoC (px) over the cell's pixels.
        dc_sharp: (P_c, 3) per pair, the sum of sharp over the cell's pixels.
        dc: view-set -> (P_c, 2, 3) per pair, the sums of the left and right views.
        kernels: view-set -> (2, 3, side, side) block kernels (L, R; channels R, G, B); empty when unmeasured.
        influence: view-set -> (P_c, 2, 3, side, side) each pair's first-order influence on them (0 for a pair no
            pixel of which was drawn).
        noise_sd: view-set -> (2, 3) the views' white-noise standard deviation over the cell's sampled pixels (linear
            units; 0 when the view-set was measured without a noise model).
        factor: (3, n, n) the Cholesky factor of the cell's regularised normal matrix, per channel.
        unmeasured: why the cell has no kernels ("" when it has).
    """

    bin: int
    zone: int
    grid: Grid
    pairs: np.ndarray
    pixels: np.ndarray
    coc_sum: np.ndarray
    dc_sharp: np.ndarray
    dc: dict[str, np.ndarray] = field(default_factory=dict)
    kernels: dict[str, np.ndarray] = field(default_factory=dict)
    influence: dict[str, np.ndarray] = field(default_factory=dict)
    noise_sd: dict[str, np.ndarray] = field(default_factory=dict)
    factor: Tensor | None = None
    unmeasured: str = ""

    @property
    def key(self) -> Key:
        return (self.bin, self.zone)

    @property
    def measured(self) -> bool:
        return not self.unmeasured

    @property
    def coc_px(self) -> tuple[float, float]:
        """(lo, hi) signed CoC of the cell's bin."""
        return binning(self.zone).edges(self.bin)

    @property
    def mean_coc_px(self) -> float:
        """The mean signed CoC (px) of the cell's pixels."""
        return float(self.coc_sum.sum() / max(self.pixels.sum(), 1.0))


@dataclass
class Atlas:
    """Kernels of one dataset per view-set and cell, with a bootstrap over pairs shared by all of them.

    Attributes:
        names: the view-sets (``"measured"``, ``"model"``, ...).
        cells: (bin, zone) -> :class:`Cell` (zone -1: the whole field), measured or not.
        pair_ids: every pair read, in order.
        weights: (B, P) bootstrap pair counts, shared by every view-set, cell and signature.
        seed: seeds the noise draws (:meth:`noise_draws`).
    """

    names: tuple[str, ...]
    cells: dict[Key, Cell]
    pair_ids: list[str]
    weights: np.ndarray
    seed: int = 0

    def measured_bins(self, zone: int = -1) -> list[int]:
        """The bins of ``zone`` (-1: the whole field) with measured kernels, sorted."""
        return sorted(b for (b, z), c in self.cells.items() if z == zone and c.measured)

    def kernels(self, key: Key, name: str, boot: bool = False) -> np.ndarray:
        """(2, 3, k, k) the cell's kernels in px (k = 2h + 1); with ``boot`` (B, 2, 3, k, k), one per bootstrap
        resample: the pairs resampled (first order) plus a draw of the views' white noise through the solve
        (:meth:`noise_draws`)."""
        c = self.cells[key]
        if not boot:
            return c.grid.to_px(c.kernels[name])
        w = self.weights[:, c.pairs] - 1.0  # (B, P_c)
        return c.grid.to_px(c.kernels[name][None] + np.tensordot(w, c.influence[name], axes=(1, 0)) + self.noise_draws(key, name))

    def noise_draws(self, key: Key, name: str) -> np.ndarray:
        r"""(B, 2, 3, side, side): draws of what the views' white noise does to the kernels,
        :math:`\sigma A^{-1} u` with :math:`u \sim N(0, A)`, i.e. covariance :math:`\sigma^2 A^{-1} \approx
        \sigma^2 (X^T X)^{-1}`, from a generator seeded by the cell and the view-set (the same draws on every call).

        Added to the pair bootstrap, whose residuals already hold the noise, it makes the intervals conservative
        where a cell holds many pairs; without it, two atlases that differ only in their noise draws (the measured
        views and a simulator's renders with the measured noise, on another renderer's clean data) differed in their
        signatures by 3-10 of the pair bootstrap's standard errors, where few pairs held a bin."""
        c = self.cells[key]
        sd = c.noise_sd.get(name)
        B = self.weights.shape[0]
        side = c.grid.side
        if sd is None or c.factor is None or not np.any(sd > 0):
            return np.zeros((B, 2, 3, side, side))
        seed = [self.seed, abs(key[0]), int(key[0] < 0), key[1] + 1, sum(map(ord, name))]
        z = torch.from_numpy(np.random.default_rng(seed).standard_normal((3, side * side, 2 * B)))
        d = torch.linalg.solve_triangular(c.factor.transpose(1, 2), z, upper=True)  # (3, n, 2B): A^-1 L z = L^-T z
        d = d.reshape(3, side, side, 2, B).permute(4, 3, 0, 1, 2).numpy()  # (B, 2, 3, side, side)
        return d * sd[None, :, :, None, None]

    def dc_gain(self, key: Key, name: str, boot: bool = False) -> np.ndarray:
        """(2, 3) each view's DC gain in the cell, sum(view) / sum(sharp) over its pixels (the kernel's sum, read
        off its DC response); with ``boot`` (B, 2, 3)."""
        c = self.cells[key]
        if not boot:
            return c.dc[name].sum(0) / np.maximum(c.dc_sharp.sum(0), 1e-30)[None]
        w = self.weights[:, c.pairs]  # (B, P_c)
        num = np.tensordot(w, c.dc[name], axes=(1, 0))  # (B, 2, 3)
        den = np.tensordot(w, c.dc_sharp, axes=(1, 0))[:, None]  # (B, 1, 3)
        return num / np.maximum(den, 1e-30)

    def unmeasured(self) -> dict[Key, str]:
        """Why each cell without kernels has none."""
        return {k: c.unmeasured for k, c in self.cells.items() if not c.measured}


class AtlasMeasurer:
    """Measures atlases of any number of view-sets on one set of pairs, with the same cells, sampled pixels, normal
    equations and bootstrap: the sharp side's work (masks, samples, each cell's Gram and its factor) is done once,
    and each view-set (:meth:`measure`) costs two gathers of the sampled patches and a solve.

    Args:
        pairs: the pairs' sharp sides.
        n_boot: bootstrap resamples over pairs.
        seed: seeds the pixel draws and the bootstrap.
    """

    def __init__(self, pairs: Sequence[PairImages], n_boot: int = DEFAULT_BOOT, seed: int = 0) -> None:
        self.pairs = list(pairs)
        self.masks = [cell_masks(img) for img in self.pairs]
        counts: dict[Key, float] = {}
        for ms in self.masks:
            for key, m in ms.items():
                counts[key] = counts.get(key, 0.0) + float(m.sum())
        self.grids = {key: Grid.of(key) for key in counts}
        rates = {key: min(1.0, max(SAMPLES_PER_UNKNOWN * self.grids[key].n, GRAM_BUDGET / self.grids[key].n ** 2) / counts[key])
                 for key in counts}
        # the sampled pixels of every (pair, cell), drawn once from a generator per pair
        self.samples: list[dict[Key, tuple[np.ndarray, np.ndarray]]] = []
        for i, ms in enumerate(self.masks):
            rng = np.random.default_rng([seed, i])
            drawn = {}
            for key in sorted(ms):
                ys, xs = np.nonzero(ms[key])
                if rates[key] < 1.0:
                    keep = rng.random(ys.size) < rates[key]
                    ys, xs = ys[keep], xs[keep]
                if ys.size >= 2:
                    drawn[key] = (ys, xs)
            self.samples.append(drawn)
        self.cells: dict[Key, Cell] = {}
        for key in sorted(counts):
            idx = [i for i, ms in enumerate(self.masks) if key in ms]
            pix = np.array([float(self.masks[i][key].sum()) for i in idx])
            coc = np.array([float(self.pairs[i].coc_px[self.masks[i][key]].sum()) for i in idx])
            dcs = np.stack([self.pairs[i].sharp[:, self.masks[i][key]].sum(1) for i in idx]).astype(np.float64)
            drawn = any(key in self.samples[i] for i in idx)
            self.cells[key] = Cell(key[0], key[1], self.grids[key], np.asarray(idx), pix, coc, dcs)
            self.cells[key].unmeasured = _why_unmeasured(len(idx), float(pix.sum()), self.grids[key], drawn)
        self._pad_cache: dict[tuple[int, int], tuple[np.ndarray, int]] = {}
        self.factors: dict[Key, Tensor] = {}
        lap: dict[int, Tensor] = {}
        for key, cell in self.cells.items():
            if not cell.measured:
                continue
            N = sum(torch.bmm(X.transpose(1, 2), X).double() for _, X, _ in self._designs(key))  # (3, n, n)
            side = self.grids[key].side
            if side not in lap:
                lap[side] = _laplacian(side)
            diag = torch.diagonal(N, dim1=-2, dim2=-1).mean(-1).clamp(min=1e-30)
            chol, info = torch.linalg.cholesky_ex(N + (REG * diag)[:, None, None] * lap[side][None])
            if bool((info != 0).any()):
                cell.unmeasured = "no texture to measure a kernel from (the normal matrix is singular)"
                continue
            self.factors[key] = chol
        rng = np.random.default_rng(seed)
        P = len(self.pairs)
        self.weights = rng.multinomial(P, np.full(P, 1.0 / P), size=n_boot).astype(np.float64) if P else np.zeros((n_boot, 0))
        self.atlas = Atlas((), self.cells, [p.pair_id for p in self.pairs], self.weights, seed)

    def _padded(self, i: int, bs: int) -> tuple[np.ndarray, int]:
        """Pair ``i``'s sharp image box-summed over ``bs`` px and zero-padded by the largest half-size of the grids of
        that block size, less its mean per channel (float32, cached). Patches shifted by a constant are the same
        once centred, and give the same ``X^T y`` for a centred ``y``; uncentred (:meth:`measure`), the shift keeps
        those float32 sums from adding up the image's mean level only for it to cancel."""
        if (i, bs) not in self._pad_cache:
            pad = max(g.h for g in self.grids.values() if g.bs == bs)
            img = _box(self.pairs[i].sharp.astype(np.float32), bs)
            padded = np.pad(img, ((0, 0), (pad, pad), (pad, pad)))
            self._pad_cache[(i, bs)] = (padded - img.mean((1, 2), keepdims=True), pad)
        return self._pad_cache[(i, bs)]

    def _designs(self, key: Key, centred: bool = True) -> Iterator[tuple[int, Tensor, tuple[np.ndarray, np.ndarray]]]:
        """(pair index, its patches (3, m, n), centred or not, its sampled pixels) of every pair with pixels drawn in
        ``key``."""
        grid = self.grids[key]
        for i in self.cells[key].pairs:
            if key in self.samples[i]:
                ys, xs = self.samples[i][key]
                padded, pad = self._padded(int(i), grid.bs)
                yield int(i), _patches(padded, pad, ys, xs, grid, centred), (ys, xs)

    def measure(self, name: str, views: Sequence[Views], noise: tuple[float, float] | None = None) -> Atlas:
        """Add view-set ``name`` (one :data:`Views` per pair, in order) to the atlas: DC sums, kernels, each pair's
        influence and, with ``noise`` (the views' ``shot_var``, ``read_sigma``: variance ``shot_var I +
        read_sigma^2``), the noise level its bootstrap draws through the solve. Returns the atlas (the same object,
        now holding ``name`` too)."""
        if len(views) != len(self.pairs):
            raise ValueError(f"{len(views)} views for {len(self.pairs)} pairs")
        for key, cell in self.cells.items():
            cell.dc[name] = np.stack([[v[:, self.masks[i][key]].sum(1) for v in views[i]] for i in cell.pairs]).astype(np.float64)
            if key not in self.factors:
                continue
            side = self.grids[key].side
            # y: (3, m, 2), centred; the patches need not be (:func:`_patches`)
            parts = [(i, X, _gather_views(views[i], *yx)) for i, X, yx in self._designs(key, centred=False)]
            cell.factor = self.factors[key]
            if noise is not None:
                inten = np.concatenate([np.stack([views[i][0][:, ys, xs], views[i][1][:, ys, xs]]) for i, _, (ys, xs) in
                                        ((i, None, self.samples[i][key]) for i, _, _ in parts)], -1)  # (2, 3, m)
                cell.noise_sd[name] = np.sqrt(np.maximum(noise[0] * np.clip(inten, 0, None) + noise[1] ** 2, 0).mean(-1))
            k = torch.cholesky_solve(sum(_xty(X, y) for _, X, y in parts), self.factors[key])  # (3, n, 2)
            cell.kernels[name] = k.permute(2, 0, 1).reshape(2, 3, side, side).numpy()
            cell.influence[name] = np.zeros((len(cell.pairs), 2, 3, side, side))
            kf = k.float()
            row = {int(i): j for j, i in enumerate(cell.pairs)}
            for i, X, y in parts:
                infl = torch.cholesky_solve(_xty(X, _centred(y - torch.bmm(X, kf))), self.factors[key])  # (3, n, 2)
                cell.influence[name][row[i]] = infl.permute(2, 0, 1).reshape(2, 3, side, side).numpy()
        if name not in self.atlas.names:
            self.atlas.names = self.atlas.names + (name,)
        return self.atlas


def measure_atlas(pairs: Sequence[PairImages], views: Mapping[str, Sequence[Views]], n_boot: int = DEFAULT_BOOT,
                  seed: int = 0) -> Atlas:
    """The atlas of every view-set in ``views`` (name -> one :data:`Views` per pair) on ``pairs``."""
    m = AtlasMeasurer(pairs, n_boot, seed)
    for name, v in views.items():
        m.measure(name, v)
    return m.atlas


def _why_unmeasured(n_pairs: int, pixels: float, grid: Grid, drawn: bool) -> str:
    if n_pairs < MIN_PAIRS:
        return f"{n_pairs} pair(s) hold scored pixels here; {MIN_PAIRS} needed"
    if pixels < MIN_PIXELS_PER_UNKNOWN * grid.n or not drawn:
        return f"{pixels:.0f} scored pixels for {grid.n} unknowns; {MIN_PIXELS_PER_UNKNOWN * grid.n:.0f} needed"
    return ""


ATLAS_FORMAT = "dp5k-atlas"
ATLAS_VERSION = 1


def save_atlas(path: str | Path, atlas: Atlas) -> None:
    """Write ``atlas`` as ``atlas.npz`` (atomically), in the layout docs/data-format.md gives ("The PSF atlas"):

    * ``format`` ``"dp5k-atlas"``, ``version`` 1; ``view_sets`` (V,) names; ``pair_ids`` (P,);
    * ``coc_edges_px`` (the whole field's |CoC| edges), ``zone_coc_edges_px`` (each zone's), ``zones`` (per side);
    * ``cells`` (K, 5) int: signed bin, zone (-1: the whole field), half-size h (px), block size (px), measured (0/1);
    * ``cell_coc_px`` (K, 3): the bin's lower and upper signed CoC and its pixels' mean CoC (px);
    * ``cell_pixels`` (K,): scored pixels; ``cell_pairs`` (K,): pairs holding them;
    * ``dc_gain`` (K, V, 2, 3): each view's DC gain, sum(view) / sum(sharp) over the cell (the kernel's sum);
    * ``kernel_<k>`` and ``kernel_sd_<k>`` (V, 2, 3, 2h + 1, 2h + 1) float32 for each measured cell ``k`` (its row in
      ``cells``): the kernels and their bootstrap standard deviations. Axis 1 is the view (L, R), axis 2 the colour
      channel (R, G, B); entry ``[y, x]`` is the share of a sharp pixel's light that lands ``(x - h, y - h)`` px from
      it (x right, y down), on the scale of the views (an ideal view's kernel sums to 1/2, Eq. 2).
    """
    from dp5k_common.io import atomic_path

    names = list(atlas.names)
    keys = sorted(atlas.cells, key=lambda k: (k[1], k[0]))
    arrays: dict[str, np.ndarray] = {
        "format": np.array(ATLAS_FORMAT), "version": np.array(ATLAS_VERSION), "view_sets": np.array(names),
        "pair_ids": np.array(atlas.pair_ids), "coc_edges_px": np.array(FINE.edges_px), "zone_coc_edges_px": np.array(COARSE.edges_px),
        "zones": np.array(ZONES),
        "cells": np.array([[k[0], k[1], atlas.cells[k].grid.h, atlas.cells[k].grid.bs, int(atlas.cells[k].measured)] for k in keys],
                          dtype=np.int64).reshape(-1, 5),
        "cell_coc_px": np.array([[*atlas.cells[k].coc_px, atlas.cells[k].mean_coc_px] for k in keys]).reshape(-1, 3),
        "cell_pixels": np.array([atlas.cells[k].pixels.sum() for k in keys]),
        "cell_pairs": np.array([len(atlas.cells[k].pairs) for k in keys]),
        "dc_gain": np.array([[atlas.dc_gain(k, n) if n in atlas.cells[k].dc else np.full((2, 3), np.nan) for n in names] for k in keys]).reshape(-1, len(names), 2, 3),
    }
    for i, k in enumerate(keys):
        c = atlas.cells[k]
        if not c.measured or not all(n in c.kernels for n in names):
            continue
        arrays[f"kernel_{i}"] = np.stack([atlas.kernels(k, n) for n in names]).astype(np.float32)
        arrays[f"kernel_sd_{i}"] = np.stack([atlas.kernels(k, n, boot=True).std(0) for n in names]).astype(np.float32)
    with atomic_path(Path(path)) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
