r"""Signatures: one quantity per physical effect, read off two atlases measured the same way (the measured views and a
simulator's renders of the same pairs), each with a bootstrap interval over pairs.

Each effect changes its own summary of the kernels and, by construction, not the others' (docs/diagnose.md,
"Signatures"):

======================  =====================================================================================
effect                  signature (measured minus simulator)
======================  =====================================================================================
lr_gain_imbalance       ln(L/R) of the kernels' sums (their DC gains) over the field: a plane a0 + ax x + ay y
disparity_scale         the split's efficiency: the L-R centroid gap over the gap an ideal split of the same
                        L + R kernel would give (``2 E|x - x_c|``), pooled over |CoC| >= 2 px
misregistration         the L + R kernel's centroid (x, y) px near focus (|CoC| < 4 px), where no blur moves it
focus_offset            where the DP disparity vanishes: the CoC shift (px, at the mean pair) that moves the
                        simulator's L-R centroid gap onto the measured one, growing from pair to pair with the
                        pair's CoC at infinity (:func:`_focus_from_gap`)
chromatic_defocus       the same shift per colour channel, R and B against G, growing with the pair's aperture
front_back_asymmetry    the odd part's growth with |CoC| (a size ratio) and the profile's front/back difference
psf_profile             the profile index ``E[r^2] / E[r]^2`` of the L + R kernel (flat disc 9/8, a bright rim
                        lower, a bright centre higher), even over front and back
field_varying_psf       per field zone, the kernels' normalised shape (size, efficiency, anisotropy, centroid
                        per px of CoC) against the whole field's at the same CoC: each kernel's sum is
                        normalised out, so a gain ramp cannot show here
noise                   the views' white-noise variance over the nominal (:mod:`dp5k_diagnose.noise`)
======================  =====================================================================================

Every summary is a ratio of moments of a kernel, so a kernel's sum (a gain) cancels from all but the first.
Moments are taken inside a disc of the bin's blur radius plus :data:`WINDOW_MARGIN_PX`.

Units: sizes and centroids in output px, CoC as its signed diameter in output px, gains as natural logs.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from .atlas import COARSE, FINE, ZONES, Atlas, Key, zone_centre

WINDOW_MARGIN_PX = 2.5
"""Moments are taken within the bin's largest blur radius plus this (px): shifts and residual blur, not tails."""


# ---------------------------------------------------------------------------------------------- kernel moments
@dataclass
class Moments:
    """Summaries of kernels (..., 2, k, k) for (L, R), all arrays of the leading shape.

    Attributes:
        cx, cy: the L + R kernel's centroid (px; x right, y down): the mean of the two views' centroids.
        gap: the R kernel's centroid x minus the L kernel's (px; > 0 behind focus for the ideal split).
        gap_ideal: the gap an ideal split of the L + R kernel at its centroid would give, ``2 E|x - cx|`` (px).
        size: the L + R kernel's mean radius ``E[r]`` about its centroid (px; a flat disc of diameter c: c / 3).
        r2: its mean squared radius ``E[r^2]`` (px^2).
        aniso: ``(E|x - cx| - E|y - cy|) / E[r]`` (0 for a round kernel).
    """

    cx: np.ndarray
    cy: np.ndarray
    gap: np.ndarray
    gap_ideal: np.ndarray
    size: np.ndarray
    r2: np.ndarray
    aniso: np.ndarray

    @property
    def efficiency(self) -> np.ndarray:
        """|gap| / gap_ideal: 1 for a hard split, less with crosstalk."""
        return np.abs(self.gap) / np.maximum(self.gap_ideal, 1e-9)

    @property
    def profile(self) -> np.ndarray:
        """``E[r^2] / E[r]^2``: 9/8 for a flat disc, lower with a bright rim, higher with a bright centre."""
        return self.r2 / np.maximum(self.size, 1e-9) ** 2


MIN_VIEW_SHARE = 0.1
"""A view whose windowed kernel holds less than this share of the two views' mean sum has no shape to measure
(its moments are NaN): a split moved far off axis, a view nearly dark."""


def _functionals(k: np.ndarray, radius_px: float, cx0: np.ndarray, cy0: np.ndarray) -> Moments:
    """:class:`Moments` of kernels ``k`` (..., C, 2, K, K) inside a disc of ``radius_px`` about (cx0, cy0) (each (C,),
    also the centre the absolute moments are taken about): every moment a ratio of linear functionals of the kernels,
    so a stack of bootstrap kernels costs one contraction."""
    h = k.shape[-1] // 2
    yy, xx = np.mgrid[-h : h + 1, -h : h + 1].astype(np.float64)
    dx = xx[None] - cx0[:, None, None]
    dy = yy[None] - cy0[:, None, None]
    r = np.sqrt(dx**2 + dy**2)
    win = (r <= radius_px).astype(np.float64)
    maps = np.stack([win, win * xx, win * yy, win * r, win * r * r, win * np.abs(dx), win * np.abs(dy)], 1)  # (C, 7, K, K)
    f = np.einsum("...cvyx,cfyx->...cvf", k, maps)  # (..., C, 2, 7)
    sv = f[..., 0]
    ok = sv > MIN_VIEW_SHARE * np.abs(sv).mean(-1, keepdims=True)
    norm = f[..., 1:] / np.where(ok, sv, np.nan)[..., None]  # per view: E_v[x], E_v[y], E_v[r], E_v[r^2], ...
    F = norm.mean(-2)  # the views' normalised kernels averaged: (..., C, 6)
    cx, cy, size, r2, ax, ay = (F[..., j] for j in range(6))
    return Moments(cx, cy, norm[..., 1, 0] - norm[..., 0, 0], 2 * ax, size, r2, (ax - ay) / np.maximum(size, 1e-9))


def moments(k: np.ndarray, radius_px: float, centre: tuple[np.ndarray, np.ndarray] | None = None) -> Moments:
    """:class:`Moments` of kernels ``k`` (..., C, 2, K, K) (C kernel sets, e.g. colour channels; L, R; offset 0 at the
    centre) inside a disc of ``radius_px`` centred on the kernels' centroid: found inside the disc about 0, then once
    more about it; or, with ``centre`` ((C,) x, (C,) y), about that (the bootstrap takes its point estimate's).

    The L + R kernel is the mean of the two views' kernels each normalised to sum 1, so that no moment depends on
    the views' gains (with a plain sum, a brighter left view would pull the centroid left)."""
    if k.ndim == 3:  # one kernel set: (2, K, K)
        m = moments(k[None], radius_px, centre)
        return Moments(*(np.asarray(getattr(m, f))[0] for f in Moments.__dataclass_fields__))
    C = k.shape[-4]
    if centre is None:
        if k.ndim != 4:
            raise ValueError("moments: the centre of a stack of kernel sets is its point estimate's; pass it")
        cx0, cy0 = np.zeros(C), np.zeros(C)
        for _ in range(2):
            m = _functionals(k, radius_px, cx0, cy0)
            cx0, cy0 = np.nan_to_num(np.asarray(m.cx, dtype=np.float64)), np.nan_to_num(np.asarray(m.cy, dtype=np.float64))
    else:
        cx0, cy0 = centre
    return _functionals(k, radius_px, np.asarray(cx0, dtype=np.float64), np.asarray(cy0, dtype=np.float64))


def window_radius(key: Key) -> float:
    """The moments' window radius (px) of a cell: its bin's largest blur radius plus :data:`WINDOW_MARGIN_PX`."""
    lo, hi = (FINE if key[1] < 0 else COARSE).edges(key[0])
    return max(abs(lo), abs(hi)) / 2 + WINDOW_MARGIN_PX


def _channels(k: np.ndarray) -> np.ndarray:
    """(..., 2, 3, K, K) -> (..., 4, 2, K, K): the channels' mean, then R, G and B."""
    k = np.moveaxis(k, -3, -4)  # (..., 3, 2, K, K)
    return np.concatenate([k.mean(-4, keepdims=True), k], axis=-4)


def channel_index(channel: int | None) -> int:
    """The index :func:`cell_moments` gives a channel: 0 the channels' mean, 1-3 R, G, B."""
    return 0 if channel is None else channel + 1


def cell_moments(atlas: Atlas, key: Key, name: str) -> tuple[Moments, Moments]:
    """(point, bootstrap) :class:`Moments` of a cell's kernels, each of leading shape (4,) (point) or (B, 4)
    (bootstrap): the channels' mean, then R, G and B (:func:`channel_index`). The bootstrap's windows sit where the
    point estimate's do."""
    r = window_radius(key)
    point = moments(_channels(atlas.kernels(key, name)), r)
    centre = (np.nan_to_num(np.asarray(point.cx, dtype=np.float64)), np.nan_to_num(np.asarray(point.cy, dtype=np.float64)))
    return point, moments(_channels(atlas.kernels(key, name, boot=True)), r, centre)


# ---------------------------------------------------------------------------------------------- signatures
@dataclass
class Value:
    """One signature value: measured minus simulator, with its bootstrap (or a test of its own).

    Attributes:
        name: what it is (``a0``, ``efficiency``, ...).
        unit: its unit.
        value: the point difference.
        boot: (B,) the difference under each resample (its spread gives the interval and the test).
        min_effect: the smallest |value| that counts.
        measured, model: the point values of each atlas (NaN where a value is a difference by nature).
        p: the two-sided p-value of "no difference"; by default from the bootstrap's standard error (normal).
    """

    name: str
    unit: str
    value: float
    boot: np.ndarray
    min_effect: float
    measured: float = float("nan")
    model: float = float("nan")
    p: float | None = None

    @property
    def se(self) -> float:
        """The bootstrap's standard error, robustly (1.4826 x its median absolute deviation): a first-order
        resample that draws one pair of a thin cell several times can throw a few values far out."""
        return robust_se(self.boot)

    @property
    def p_value(self) -> float:
        if self.p is not None:
            return self.p
        if not np.isfinite(self.value) or not np.isfinite(self.se):
            return 1.0
        if self.se <= 0:  # no spread over the resamples: the difference is what it is
            return 0.0 if self.value != 0 else 1.0
        return float(math.erfc(abs(self.value) / self.se / math.sqrt(2)))

    def interval(self, level: float = 0.95) -> tuple[float, float]:
        """The ``level`` interval: value +- z se (normal, from the bootstrap's spread)."""
        z = _z(level)
        return (self.value - z * self.se, self.value + z * self.se)

    def differs(self, alpha: float) -> bool:
        """Significant at ``alpha`` and at least :attr:`min_effect`."""
        return bool(self.p_value < alpha and abs(self.value) >= self.min_effect)

    def to_json(self) -> dict:
        lo, hi = self.interval()
        return {"name": self.name, "unit": self.unit, "value": _f(self.value), "interval95": [_f(lo), _f(hi)],
                "p_value": _f(self.p_value), "min_effect": self.min_effect, "measured": _f(self.measured),
                "simulator": _f(self.model)}


def robust_se(boot: np.ndarray, axis: int = 0) -> np.ndarray | float:
    """1.4826 x the median absolute deviation of the finite values along ``axis`` (inf with fewer than 10)."""
    b = np.where(np.isfinite(boot), boot, np.nan)
    n = np.isfinite(b).sum(axis)
    with warnings.catch_warnings():  # a cell no resample measured is all NaN: its s is inf below, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(b, axis=axis, keepdims=True)
        s = 1.4826 * np.nanmedian(np.abs(b - med), axis=axis)
    s = np.where(n >= 10, s, np.inf)
    return float(s) if np.ndim(s) == 0 else s


def _z(level: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(1 - (1 - level) / 2)


def _f(x: float) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


@dataclass
class Signature:
    """An effect's signature: its values, and why it could not be measured (then nothing is named from it)."""

    effect: str
    values: list[Value] = field(default_factory=list)
    unmeasured: str = ""

    def differs(self, alpha: float) -> bool:
        """Any value differs at ``alpha`` / (its number of values) (Bonferroni) and beyond its minimum."""
        if self.unmeasured or not self.values:
            return False
        return any(v.differs(alpha / len(self.values)) for v in self.values)

    def strength(self) -> float:
        """The largest |value| / min_effect of its values (how far beyond its bar it is)."""
        return max((abs(v.value) / v.min_effect for v in self.values if np.isfinite(v.value)), default=0.0)

    def to_json(self, alpha: float) -> dict:
        return {"effect": self.effect, "differs": self.differs(alpha), "unmeasured": self.unmeasured or None,
                "values": [v.to_json() for v in self.values]}


def _wmean(x: np.ndarray, w: np.ndarray, axis: int = -1) -> np.ndarray:
    """Weighted mean over ``axis`` of the finite entries."""
    w = np.broadcast_to(w, x.shape)
    ok = np.isfinite(x) & (w > 0)
    return np.where(ok, x * w, 0.0).sum(axis) / np.maximum(np.where(ok, w, 0.0).sum(axis), 1e-30)


MOMENTS = ("cx", "cy", "gap", "gap_ideal", "size", "r2", "aniso", "efficiency", "profile")


def _table(atlas: Atlas, keys: list[Key], name: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """attr -> (point (4, n), boot (B, 4, n)) of every :class:`Moments` field and property over ``keys``, per
    :func:`channel_index`."""
    pts: dict[str, list] = {a: [] for a in MOMENTS}
    bts: dict[str, list] = {a: [] for a in MOMENTS}
    for key in keys:
        p, b = cell_moments(atlas, key, name)
        for attr in MOMENTS:
            pts[attr].append(np.asarray(getattr(p, attr), dtype=np.float64))
            bts[attr].append(np.asarray(getattr(b, attr), dtype=np.float64))
    if not keys:
        return {a: (np.zeros((4, 0)), np.zeros((atlas.weights.shape[0], 4, 0))) for a in MOMENTS}
    return {a: (np.stack(pts[a], -1), np.stack(bts[a], -1)) for a in MOMENTS}


PLAUSIBLE: dict[str, tuple[float, float]] = {
    "efficiency": (0.0, 1.6), "profile": (0.8, 2.5), "size": (0.0, float("inf")), "aniso": (-1.0, 1.0),
}
"""The range a moment of any physical PSF lies in; a kernel whose moment falls outside was not measured reliably (a
sliver of a view, a cell of few pairs under resampling) and that value counts as missing."""


def _plausible(attr: str, x: np.ndarray) -> np.ndarray:
    lo, hi = PLAUSIBLE.get(attr, (-np.inf, np.inf))
    return np.where((x >= lo) & (x <= hi), x, np.nan)


@dataclass
class Pairing:
    """The two view-sets a signature compares, and the moments of a set of cells (by default the whole field's
    measured bins), read once.

    Attributes:
        atlas: the atlas holding both view-sets.
        measured, model: the view-sets' names.
        keys: the cells (default: every measured whole-field bin).
    """

    atlas: Atlas
    measured: str = "measured"
    model: str = "model"
    keys: list[Key] | None = None
    pair_scales: Mapping[str, np.ndarray] | None = None
    """Per-pair scales (name -> (P,) in the atlas's pair order) that a cell's value is expected to grow with, such as a
    pair's CoC at infinity (:func:`dp5k_diagnose.measure.pair_scales`); :meth:`cell_scale` averages them per cell."""

    def __post_init__(self) -> None:
        if self.keys is None:
            self.keys = [(b, -1) for b in self.atlas.measured_bins(-1)]
        self.keys = [k for k in self.keys if self.measured in self.atlas.cells[k].kernels and self.model in self.atlas.cells[k].kernels]
        self.c = np.array([self.atlas.cells[k].mean_coc_px for k in self.keys])
        self.cbar = self.c
        self.pix = np.array([float(self.atlas.cells[k].pixels.sum()) for k in self.keys])
        self._t: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}

    def cell_scale(self, name: str) -> np.ndarray | None:
        """(n,) per cell, the pixel-weighted mean of the pairs' scale ``name`` over its pixels, over that mean over
        every cell (so about 1); None without that scale."""
        if not self.pair_scales or name not in self.pair_scales:
            return None
        s = np.asarray(self.pair_scales[name], dtype=np.float64)
        cells = [self.atlas.cells[k] for k in self.keys]
        num = np.array([float((c.pixels * s[c.pairs]).sum()) for c in cells])
        den = np.array([float(c.pixels.sum()) for c in cells])
        if not den.sum() or not np.isfinite(num).all() or abs(num.sum()) < 1e-12:
            return None
        return (num / np.maximum(den, 1e-12)) / (num.sum() / den.sum())

    def t(self, name: str, channel: int | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """attr -> (point (n,), boot (B, n)) of view-set ``name``'s moments over the cells (one ``channel`` or their
        mean), computed once for every channel."""
        if name not in self._t:
            self._t[name] = _table(self.atlas, self.keys, name)
        j = channel_index(channel)
        return {a: (p[j], b[:, j]) for a, (p, b) in self._t[name].items()}

    def diff(self, attr: str, channel: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(point (n,), boot (B, n)): measured minus simulator of a moment over the cells, missing (NaN) where either
        side is implausible (:data:`PLAUSIBLE`)."""
        (pm, bm), (ps, bs) = self.t(self.measured, channel)[attr], self.t(self.model, channel)[attr]
        return _plausible(attr, pm) - _plausible(attr, ps), _plausible(attr, bm) - _plausible(attr, bs)

    def weights(self, attr: str, channel: int | None = None) -> np.ndarray:
        """(n,) inverse-variance weights of the cells' differences (their bootstrap's robust standard error), 0 where
        missing."""
        d, db = self.diff(attr, channel)
        se = np.asarray(robust_se(db, axis=0), dtype=np.float64)
        return np.where(np.isfinite(d) & np.isfinite(se) & (se > 0), 1.0 / np.maximum(se, 1e-12) ** 2, 0.0)

    def value(self, name: str, unit: str, attr: str, sel: np.ndarray, min_effect: float, channel: int | None = None) -> Value:
        """The inverse-variance weighted mean of ``attr``'s difference over the cells ``sel``."""
        d, db = self.diff(attr, channel)
        (pm, _), (ps, _) = self.t(self.measured, channel)[attr], self.t(self.model, channel)[attr]
        ww = np.where(sel, self.weights(attr, channel), 0.0)
        return Value(name, unit, float(_wmean(d, ww)), _wmean(db, ww[None]), min_effect,
                     float(_wmean(_plausible(attr, pm), ww)), float(_wmean(_plausible(attr, ps), ww)))

    def sided_fit(self, attr: str, lo: float, hi: float, channel: int | None = None,
                  terms: tuple[str, ...] = ("d0", "alpha", "g_even", "g_odd"),
                  per: np.ndarray | None = None, d0_scale: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Fit the difference of ``attr`` against each cell's mean CoC c over the cells with ``lo <= |c| <= hi``:
        ``d(c) = d0 + alpha sign(c) + g_even |c| + g_odd c`` (the ``terms`` asked; inverse-variance weighted). A
        focus error is ``alpha`` (the same CoC added on both sides), a size that grows differently in front and
        behind is ``g_odd``; a residual blur or a profile change moves ``d0`` and ``g_even``. Fitted against the
        cells' own mean CoC, so that a bin whose pixels sit at another CoC in front than behind does not read as a
        difference. With ``per`` ((n,), per cell) the difference is fitted in units of it, ``d / per`` (weights
        ``per^2 / se^2``; a cell where ``per`` is 0 or missing carries none). Returns (coefficients in ``terms`` order,
        boot (B, len(terms))), or None with fewer than two cells on either side. With ``d0_scale`` ((n,), about 1) the
        constant term is ``d0 d0_scale``: a difference that grows with a per-pair scale (:meth:`cell_scale`), whose
        pairs a cell pools in its own proportions; ``d0`` is then its value at the mean pair."""
        d, db = self.diff(attr, channel)
        c = self.cbar
        w = self.weights(attr, channel)
        if per is not None:
            ok = np.isfinite(per) & (np.abs(per) > 0)
            safe = np.where(ok, per, 1.0)
            d, db, w = d / safe, db / safe[None], np.where(ok, w * safe ** 2, 0.0)
        sel = (np.abs(c) >= lo) & (np.abs(c) <= hi) & (w > 0)
        if (sel & (c > 0)).sum() < 2 or (sel & (c < 0)).sum() < 2:
            return None
        cs = c[sel]
        ones = np.ones_like(cs) if d0_scale is None else np.asarray(d0_scale, dtype=np.float64)[sel]
        cols = {"d0": ones, "alpha": np.sign(cs), "g_even": np.abs(cs), "g_odd": cs}
        sw = np.sqrt(w[sel])
        X = np.stack([cols[k] for k in terms], 1) * sw[:, None]
        pinv = np.linalg.pinv(X)
        bt = np.where(np.isfinite(db[:, sel]), db[:, sel], d[sel][None])
        return pinv @ (d[sel] * sw), (bt * sw[None]) @ pinv.T


SIZE_PER_COC = 1.0 / 3.0
"""The mean radius of a flat disc per px of its diameter: a CoC change dc moves the size by dc / 3."""


def lr_gain_signature(atlas: Atlas, p: Pairing) -> Signature:
    """ln(L/R) of the kernels' DC gains per field zone (each zone's bins pooled), measured minus simulator, fitted by
    a plane over the zones' centres: a0 (at the centre), ax, ay (per unit field)."""
    zones = sorted({z for (_, z) in atlas.cells if z >= 0})
    if not zones:
        return Signature("lr_gain_imbalance", unmeasured="no field zone holds scored pixels")
    d_pt, d_bt, w = [], [], []
    for z in zones:
        keys = [k for k in atlas.cells if k[1] == z]
        lr = {}
        for name in (p.measured, p.model):
            num = sum(atlas.cells[k].dc[name].sum(0).sum(-1) for k in keys)  # (2,)
            nb = sum(np.tensordot(atlas.weights[:, atlas.cells[k].pairs], atlas.cells[k].dc[name].sum(-1), axes=(1, 0)) for k in keys)
            lr[name] = (np.log(num[0] / num[1]), np.log(nb[:, 0] / nb[:, 1]))
        d_pt.append(lr[p.measured][0] - lr[p.model][0])
        d_bt.append(lr[p.measured][1] - lr[p.model][1])
        w.append(sum(float(atlas.cells[k].pixels.sum()) for k in keys))
    xy = np.array([zone_centre(z) for z in zones])
    w = np.asarray(w)
    cols = [np.ones(len(zones))] + ([xy[:, 0], xy[:, 1]] if len(zones) >= 3 else [])
    X = np.stack(cols, 1) * np.sqrt(w)[:, None]
    pinv = np.linalg.pinv(X)
    coef = pinv @ (np.asarray(d_pt) * np.sqrt(w))
    coef_b = (np.stack(d_bt, 1) * np.sqrt(w)[None]) @ pinv.T
    names = ("lr_log_ratio_centre", "lr_log_ratio_per_x", "lr_log_ratio_per_y")
    mins = (0.012, 0.02, 0.02)
    return Signature("lr_gain_imbalance", [Value(names[j], "ln(L/R)" + ("" if j == 0 else " per unit field"), float(coef[j]),
                                                 coef_b[:, j], mins[j]) for j in range(len(cols))])


def disparity_signature(p: Pairing) -> Signature:
    """The split's efficiency (:attr:`Moments.efficiency`) at |CoC| >= 2.2 px, weighted by pixels x CoC^2."""
    sel = np.abs(p.c) >= 2.2
    if not sel.any():
        return Signature("disparity_scale", unmeasured="no bin of |CoC| >= 2.2 px is measured")
    return Signature("disparity_scale", [p.value("split_efficiency", "1", "efficiency", sel, 0.03)])


def misregistration_signature(p: Pairing) -> Signature:
    """The L + R kernel's centroid (px) near focus (|CoC| < 4 px), weighted by pixels."""
    sel = np.abs(p.c) < 4.0
    if not sel.any():
        return Signature("misregistration", unmeasured="no bin of |CoC| < 4 px is measured")
    return Signature("misregistration", [p.value("shift_x", "px", "cx", sel, 0.08), p.value("shift_y", "px", "cy", sel, 0.08)])


FOCUS_RANGE_PX = (0.5, 22.0)
"""|CoC| range (px) of the bins whose front/back odd part measures a focus or colour error."""


MIN_GAP_SLOPE = 0.05
"""The smallest local slope of the simulator's gap (px of gap per px of CoC) a cell must have to say where the
disparity vanishes: below about a pixel of CoC both views' kernels fit in one pixel and the gap stays 0 whatever the
focus (a focus error moves nothing there)."""


def gap_slope(c: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """(n,) d gap / dc (px of gap per px of CoC) of a gap curve sampled at the cells' mean CoC ``c`` (any order; the
    neighbours' central difference), NaN where the curve is missing or flat on either side (a difference to a
    neighbour below :data:`MIN_GAP_SLOPE`: the onset of blur, where sub-pixel kernels leave the gap at 0)."""
    out = np.full(len(c), np.nan)
    ok = np.isfinite(gap) & np.isfinite(c)
    if ok.sum() < 2:
        return out
    idx = np.flatnonzero(ok)[np.argsort(c[ok])]
    cs, gs = c[idx], gap[idx]
    keep = np.concatenate([[True], np.diff(cs) > 1e-9])
    idx, cs, gs = idx[keep], cs[keep], gs[keep]
    if len(cs) < 2:
        return out
    step = np.diff(gs) / np.diff(cs)  # (m - 1,) between neighbours
    flattest = np.minimum(np.concatenate([step[:1], step]), np.concatenate([step, step[-1:]]))
    out[idx] = np.where(flattest >= MIN_GAP_SLOPE, np.gradient(gs, cs), np.nan)
    return out


def _focus_from_gap(p: Pairing, channel: int | None = None, scale: str | None = None) -> tuple[float, np.ndarray] | None:
    """beta, the CoC (px) a focus error adds on both sides of focus, and its bootstrap: each cell's gap difference
    over the simulator's local gap slope (:func:`gap_slope`) is the CoC shift that moves one gap onto the other, and
    beta is the constant ``d0`` of its fit ``d0 + alpha sign(c) + g_odd c`` (:meth:`Pairing.sided_fit`): a change of
    the split's efficiency moves ``g_odd``, a profile that differs between the sides ``alpha``. A ``g_even |c|`` term
    is left out: beside a ``d0`` that grows with the pairs' scale it is nearly collinear (on another renderer's clean
    set it swung beta to +0.31 px, 95 % interval [+0.10, +0.48]; without it +0.06 [-0.01, +0.10]). The gap is a first
    moment, measured more precisely than a size. Dividing by the local slope, not the ideal split's ``4 / (3 pi)``, keeps the
    cells near focus, where the gap is flat (sub-pixel kernels) and very precisely 0 on both sides, from pulling beta
    to 0 (a focus error of -0.25 px read as -0.04).

    With ``scale`` (a per-pair scale of :attr:`Pairing.pair_scales`) beta is taken to grow with it from pair to pair,
    and is reported at the mean pair: a focus error's CoC is the pair's CoC at infinity times ``1/k - 1`` (a relative
    error k), a chromatic focal shift's the pair's aperture times the shift. A bin pools the pairs in its own
    proportions (far background only from pairs focused near), so a constant beta would read the spread as a growth
    with |CoC|."""
    slope = gap_slope(p.c, p.t(p.model, channel)["gap"][0])
    fit = p.sided_fit("gap", *FOCUS_RANGE_PX, channel=channel, terms=("d0", "alpha", "g_odd"), per=slope,
                      d0_scale=p.cell_scale(scale) if scale else None)
    if fit is None:
        return None
    (d0, _, _), boot = fit
    return float(d0), boot[:, 0]


def focus_signature(p: Pairing) -> Signature:
    """A focus error adds the same CoC beta (px) on both sides of focus: it moves where the DP disparity vanishes
    (:func:`_focus_from_gap`)."""
    f = _focus_from_gap(p, scale="coc_at_infinity_px")
    if f is None:
        return Signature("focus_offset", unmeasured=f"too few bins measured on both sides of focus (|CoC| {FOCUS_RANGE_PX[0]:g}-{FOCUS_RANGE_PX[1]:g} px)")
    return Signature("focus_offset", [Value("coc_offset", "px of CoC", f[0], f[1], 0.15)])


def chromatic_signature(p: Pairing, colour: bool) -> Signature:
    """The focus signature per colour channel, red and blue against green (px of CoC)."""
    if not colour:
        return Signature("chromatic_defocus", unmeasured="the data has no colour (R = G = B within noise)")
    fits = [_focus_from_gap(p, channel=ch, scale="aperture_px") for ch in range(3)]
    if any(f is None for f in fits):
        return Signature("chromatic_defocus", unmeasured=f"too few bins measured on both sides of focus (|CoC| {FOCUS_RANGE_PX[0]:g}-{FOCUS_RANGE_PX[1]:g} px)")
    return Signature("chromatic_defocus", [Value(f"coc_offset_{label}_vs_green", "px of CoC", fits[ch][0] - fits[1][0], fits[ch][1] - fits[1][1], 0.15)
                                           for ch, label in ((0, "red"), (2, "blue"))])


def front_back_signature(p: Pairing) -> Signature:
    """Blur in front of focus against blur behind it at equal |CoC|: how much faster the size grows with |CoC| in
    front (``-2 g_odd`` of the size fit, :meth:`Pairing.sided_fit`) and the profile index's front-minus-back
    difference (``-2 alpha`` of a fit ``d0 + alpha sign(c)`` over |CoC| >= 3 px: the index is scale-free, so a
    shape that differs between the sides differs by a constant)."""
    size = p.sided_fit("size", 3.0, FOCUS_RANGE_PX[1])
    prof = p.sided_fit("profile", 3.0, 60.0, terms=("d0", "alpha"))
    if size is None or prof is None:
        return Signature("front_back_asymmetry", unmeasured="too few bins measured on both sides of focus (|CoC| >= 3 px)")
    (_, _, _, g), gb = size
    (_, pa), pb = prof
    return Signature("front_back_asymmetry", [Value("size_growth_front_minus_back", "px of size per px of |CoC|", -2 * float(g), -2 * gb[:, 3], 0.012),
                                              Value("profile_front_minus_back", "1", -2 * float(pa), -2 * pb[:, 1], 0.02)])


def profile_signature(atlas: Atlas, p: Pairing) -> Signature:
    """The profile index (:attr:`Moments.profile`) of each field zone's kernels at |CoC| >= 3 px, front and back
    pooled (inverse-variance weighted). Zone by zone, so that blur that grows over the field (a mixture of disc sizes
    in a whole-field bin, which is centre-heavy) does not read as a profile."""
    keys = [k for k in atlas.cells if k[1] >= 0 and atlas.cells[k].measured and abs(atlas.cells[k].mean_coc_px) >= 3.0]
    zp = Pairing(atlas, p.measured, p.model, keys)
    if not zp.keys:
        return Signature("psf_profile", unmeasured="no field zone holds a measured kernel of |CoC| >= 3 px")
    return Signature("psf_profile", [zp.value("profile_index", "1", "profile", np.ones(len(zp.keys), bool), 0.012)])


FVP_MIN_COC_PX = 3.0
"""Zone kernels from this |CoC| (px) on show the shape over the field (smaller ones are pixel sampling)."""

FVP_DESCRIPTORS: dict[str, tuple[str, float]] = {
    "size": ("size over the zones' mean at the same CoC, minus 1", 0.03),
    "efficiency": ("split efficiency minus the zones' mean", 0.04),
    "aniso": ("anisotropy minus the zones' mean", 0.03),
    "shift_x": ("centroid x, front/back odd part, per px of CoC, minus the zones' mean", 0.015),
    "shift_y": ("centroid y, front/back odd part, per px of CoC, minus the zones' mean", 0.015),
}
"""Each field-zone descriptor of :func:`field_signature`: its meaning and its smallest rms over the zones that counts."""


def _zone_descriptors(atlas: Atlas, name: str) -> dict[str, dict[tuple[int, int], tuple[float, np.ndarray, float]]]:
    """descriptor -> (zone, coarse bin) -> (point, boot (B,), weight), relative to the zones' weighted mean per bin."""
    zkeys = [k for k in atlas.cells if k[1] >= 0 and atlas.cells[k].measured and abs(COARSE.centre(k[0])) >= FVP_MIN_COC_PX]
    mom = {}
    for k in zkeys:  # the channels' mean
        pt, bt = cell_moments(atlas, k, name)
        mom[k] = (Moments(*(np.asarray(getattr(pt, f))[0] for f in Moments.__dataclass_fields__)),
                  Moments(*(np.asarray(getattr(bt, f))[:, 0] for f in Moments.__dataclass_fields__)))
    pix = {k: float(atlas.cells[k].pixels.sum()) for k in zkeys}
    out: dict[str, dict[tuple[int, int], tuple[float, np.ndarray, float]]] = {d: {} for d in FVP_DESCRIPTORS}
    for b in sorted({k[0] for k in zkeys}):
        ks = [k for k in zkeys if k[0] == b]
        if len(ks) < 2:
            continue
        c = COARSE.centre(b)
        w = np.array([pix[k] for k in ks])

        def rel(attr: str, ratio: bool = False) -> list[tuple[float, np.ndarray]]:
            pt = np.array([float(getattr(mom[k][0], attr)) for k in ks])
            bt = np.stack([getattr(mom[k][1], attr) for k in ks], -1)
            ref, refb = _wmean(pt, w), _wmean(bt, w[None])
            if ratio:
                return [(pt[i] / ref - 1, bt[:, i] / refb - 1) for i in range(len(ks))]
            return [(pt[i] - ref, bt[:, i] - refb) for i in range(len(ks))]

        for d, attr, ratio in (("size", "size", True), ("efficiency", "efficiency", False), ("aniso", "aniso", False)):
            for k, (v, vb) in zip(ks, rel(attr, ratio)):
                out[d][(k[1], b)] = (v, vb, pix[k] * c * c)
        if b > 0 and all((-b, k[1]) in mom for k in ks):  # centroid: odd part per px of CoC
            for d, attr in (("shift_x", "cx"), ("shift_y", "cy")):
                pt = np.array([(float(getattr(mom[k][0], attr)) - float(getattr(mom[(-b, k[1])][0], attr))) / (2 * c) for k in ks])
                bt = np.stack([(getattr(mom[k][1], attr) - getattr(mom[(-b, k[1])][1], attr)) / (2 * c) for k in ks], -1)
                ref, refb = _wmean(pt, w), _wmean(bt, w[None])
                for i, k in enumerate(ks):
                    out[d][(k[1], b)] = (pt[i] - ref, bt[:, i] - refb, pix[k] * c * c)
    return out


def field_signature(atlas: Atlas, p: Pairing) -> Signature:
    """The kernels' normalised shape per field zone against the zones' mean at the same CoC (:data:`FVP_DESCRIPTORS`),
    measured minus simulator, averaged over the bins in each zone; per descriptor the rms over zones and a chi-square
    test of its zones (Z - 1 degrees of freedom, each zone's variance from the bootstrap)."""
    from scipy.stats import chi2

    dm, ds = _zone_descriptors(atlas, p.measured), _zone_descriptors(atlas, p.model)
    values = []
    for d, (what, min_rms) in FVP_DESCRIPTORS.items():
        cells = sorted(set(dm[d]) & set(ds[d]))
        zones = sorted({z for z, _ in cells})
        if len(zones) < 3:
            continue
        pts, bts, ws = [], [], []
        for z in zones:
            cz = [c for c in cells if c[0] == z]
            w = np.array([dm[d][c][2] for c in cz])
            pts.append(_wmean(np.array([dm[d][c][0] - ds[d][c][0] for c in cz]), w))
            bts.append(_wmean(np.stack([dm[d][c][1] - ds[d][c][1] for c in cz], -1), w[None]))
            ws.append(w.sum())
        pt, bt, wz = np.array(pts), np.stack(bts, -1), np.array(ws)
        se = bt.std(0, ddof=1)
        stat = float(np.sum((pt / np.maximum(se, 1e-12)) ** 2))
        rms = float(np.sqrt(_wmean(pt**2, wz)))
        rms_b = np.sqrt(_wmean(bt**2, wz[None]))
        values.append(Value(f"{d}_rms_over_zones", what, rms, rms_b, min_rms, p=float(chi2.sf(stat, len(zones) - 1))))
    if not values:
        return Signature("field_varying_psf", unmeasured=f"fewer than 3 field zones hold kernels of |CoC| >= {FVP_MIN_COC_PX:g} px")
    return Signature("field_varying_psf", values)
