r"""Name the cause: test every effect of the vocabulary against the fitted base model.

For each effect E the base model is extended with E's component (:mod:`neural_dp.simulators.base.components`), whose
parameters (plus the base model's gain and rim softness, which trade off against it) are fitted on the *fit* set
(training crops). The extension is then judged on a *detection* set of pairs it was not fitted on
(validation split, else the remaining training pairs), tile by tile:

* per pair i: :math:`\Delta_i = \ln(\mathrm{MSE}_i(\text{base}) / \mathrm{MSE}_i(\text{base} + E))` (pairs are the
  independent units; with fewer than 4 detection pairs, 32 px tiles are used instead);
* statistic: the one-sided one-sample t statistic of :math:`\Delta_i` (H0: mean 0), its p-value;
* effect size: the reduction of the pooled squared error as a share of the base model's systematic error,
  :math:`(\mathrm{SSE}(\text{base}) - \mathrm{SSE}(\text{base} + E)) / \mathrm{SSE}_{sys}` with
  :math:`\mathrm{SSE}_{sys} = \mathrm{SSE}(\text{base}) - \mathrm{SSE}(\text{noise})` (:func:`systematic_sse`).

``noise`` cannot be predicted, so it is measured directly: the white-noise variance of the views in flat
regions of the scene, from the high-pass of ``L - R`` (:func:`flat_lr_noise`), against a nominal sensor's
(``DetectConfig.nominal_*``); the effect size is the excess variance ratio (:func:`test_noise`).

An effect is *detected* when ``p < alpha`` and its effect size exceeds its threshold
(:meth:`DetectConfig.threshold`: ``min_effect``, or its entry in ``min_effect_by_effect``); the cause is the
detected effect of largest effect size, else ``none``.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy import stats
from torch import Tensor

from dp5k_common.effects import EFFECT_NAMES, NO_EFFECT
from dp5k_common.progress import progress
from neural_dp.registry import BaseModel, fit_parameters

from neural_dp.registry import COMPONENTS, Noise, fittable_names
from .data import Sample

log = logging.getLogger(__name__)

EXPLAIN = {
    "lr_gain_imbalance": "the left and right views differ in brightness: L/R ratio {lr_ratio_center:.3f} at the centre, {lr_ratio_min:.3f}..{lr_ratio_max:.3f} over the field the fit pairs cover (x {field_x0:+.2f}..{field_x1:+.2f}, y {field_y0:+.2f}..{field_y1:+.2f})",
    "field_varying_psf": "the blur changes across the field: CoC grows by {coc_growth_at_corner:+.1%} at the corner and the split leaks {edge_leak:.3f} x |x| toward the edges",
    "chromatic_defocus": "the colour channels focus differently: focal length shift red {focal_shift_r_mm:+.4f} mm, blue {focal_shift_b_mm:+.4f} mm versus green",
    "disparity_scale": "the L/R disparity is {disparity_scale:.3f} x the ideal half-aperture disparity (crosstalk {crosstalk:.3f})",
    "focus_offset": "the lens focuses at {focus_factor:.3f} x the recorded focus distance ({focus_offset_mm:+.0f} mm at the mean recorded distance)",
    "psf_profile": "the blur disc is not uniform: radial weight 1 {rim_gain:+.2f} (rho/R)^4",
    "front_back_asymmetry": "blur in front of focus differs from blur behind it: back rim gain {back_rim_gain:+.2f}, front centre gain {front_center_gain:+.2f}, front size x{front_size_factor:.3f}",
    "misregistration": "the views are shifted against the sharp image: left ({left_dx_px:+.2f}, {left_dy_px:+.2f}) px, right ({right_dx_px:+.2f}, {right_dy_px:+.2f}) px",
    "noise": "the views carry {variance_ratio:.1f} x the white-noise variance of a nominal sensor in flat regions: shot variance {shot_var:.2e} per unit intensity, read sigma {read_sigma:.2e} ({excess_fraction:.0%} of the base model's residual is excess noise)",
}


@dataclass
class DetectConfig:
    """Statistical settings of the detectors.

    Attributes:
        tile_px: tile side for the per-tile statistics.
        alpha: significance level of the one-sided tests.
        min_effect: smallest share of the base model's systematic error an effect must remove to count. It
            guards against mismatch between the model and the data (a real lens, another renderer) that an
            effect's component can absorb: on clean studio data no component explains more than 0.015, on
            the real Sdirt data components that are not the cause explain up to 0.33.
        min_effect_by_effect: per-effect thresholds that replace ``min_effect``. ``chromatic_defocus``: 0.04.
            Its component only moves the red and blue channels' focus against green, so mismatch that is the
            same in every colour channel, as a real lens' PSF shape is, cannot feed it: on the real Sdirt
            data achromatic components explain 0.14-0.33 without being the cause, chromatic_defocus -0.006;
            on 26 clean studio sets it explains at most 0.001. A strength-1 studio focal shift (0.1-0.4 px
            of CoC) explains 0.04-0.24 (docs/diagnose.md, Detectability).
        lm_iters: Levenberg-Marquardt iterations per effect.
        base_lm_iters: Levenberg-Marquardt iterations of the base model's own fit (rim softness and gain),
            which every effect is measured against; it must converge, or the effects' fits, which refit the
            rim, are credited with the rest of its convergence.
        refine_top: effects fitted beyond the one-iteration screening.
        noise_min_effect: smallest excess noise variance, as a multiple of the nominal variance, that counts
            as ``noise`` (0.5: 1.5 x the nominal variance; clean studio data measures 0.04-0.06).
        systematic_floor: the systematic error is at least this share of the base model's squared error
            (bounds effect sizes where the measured noise explains nearly all of it).
        noise_flat_window_px, noise_flat_quantile: the window over which sharp must be flat, and the
            flattest fraction of valid pixels used to measure noise.
        nominal_shot_var, nominal_read_sigma: the noise a healthy sensor is expected to show (linear
            units: a ~50 000 e- full well scaled to [0, 1] and a read noise of 1e-3); only noise beyond
            it counts as the ``noise`` effect.
    """

    tile_px: int = 32
    alpha: float = 0.05
    min_effect: float = 0.15
    min_effect_by_effect: dict[str, float] = field(default_factory=lambda: {"chromatic_defocus": 0.04})
    lm_iters: int = 3
    base_lm_iters: int = 12
    refine_top: int = 2
    noise_min_effect: float = 0.5
    noise_flat_window_px: int = 13
    noise_flat_quantile: float = 0.10
    nominal_shot_var: float = 2.0e-5
    nominal_read_sigma: float = 1.0e-3
    systematic_floor: float = 0.2

    def threshold(self, effect: str) -> float:
        """The effect size ``effect`` must exceed to be detected (share of the systematic error; ``noise``:
        excess variance ratio)."""
        if effect == "noise":
            return self.noise_min_effect
        return float(self.min_effect_by_effect.get(effect, self.min_effect))


@dataclass
class Finding:
    effect: str
    statistic: float
    p_value: float
    effect_size: float
    detected: bool
    params: dict[str, float]
    explanation: str
    model: BaseModel | None = field(default=None, repr=False)
    tile_sse: np.ndarray | None = field(default=None, repr=False)
    """Per-tile squared errors of ``model`` on the detection set (:func:`tile_mse`), kept for the nested test."""
    held: tuple[str, ...] = ()
    """Parameters of the effect's component held neutral: the fit data does not show where they act."""
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    """95 % intervals of parameters, by name (the noise model's: bootstrap over pairs)."""
    testable: bool = True
    """False when the data cannot show the effect at all (a colour effect on data with R = G = B); such a
    finding is never detected."""

    @property
    def rank_score(self) -> float:
        """The share of the base model's residual MSE this effect explains (noise: the excess noise's share;
        its ``effect_size`` is a variance ratio on another scale)."""
        if self.effect == "noise":
            return float(self.params.get("excess_fraction", 0.0))
        return float(self.effect_size)

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "statistic": _finite(self.statistic),
            "p_value": _finite(self.p_value, 1.0),
            "effect_size": _finite(self.effect_size),
            "detected": bool(self.detected),
            "params": {k: ([_finite(x) for x in v] if isinstance(v, (list, tuple)) else _finite(v)) for k, v in self.params.items()},
            "explanation": self.explanation,
            "testable": bool(self.testable),
            "param_intervals": {k: [_finite(lo), _finite(hi)] for k, (lo, hi) in self.intervals.items()},
        }


def _finite(x: float, default: float = 0.0) -> float:
    x = float(x)
    return x if math.isfinite(x) else default


def copy_base(base: BaseModel) -> BaseModel:
    """A copy of ``base`` with copies of its components (an extended model's effects stay, and fitting the
    copy's parameters leaves ``base`` as it was)."""
    return base.replaced([copy.deepcopy(c) for c in base.components])


VIEW_CHANNELS = 6
"""Terms per scored pixel in a squared error of both views: 2 views x 3 colour channels."""


def tile_sums(x: Tensor, mask: Tensor, tile: int) -> tuple[Tensor, Tensor]:
    """Per-tile sums of ``x`` (B, C, H, W) over channels and pixels, and per-tile valid pixel counts.

    Returns:
        sums, counts: (B * nty * ntx,) flattened.
    """
    t = min(tile, x.shape[-2], x.shape[-1])
    s = F.avg_pool2d(x.sum(1, keepdim=True) * mask, t, stride=t) * t * t
    c = F.avg_pool2d(mask, t, stride=t) * t * t * x.shape[1]
    return s.reshape(-1), c.reshape(-1)


def residual(model: BaseModel, s: Sample) -> Tensor:
    """(B, 6, H, W) prediction minus measurement for both views."""
    l, r = model.render(s.batch, s.field)
    return torch.cat([l - s.batch.left, r - s.batch.right], 1)


def masked_mse(model: BaseModel, samples: list[Sample]) -> float:
    """Mean squared error of both views over the samples' scored pixels (linear units squared)."""
    se = sum(float(residual(model, s).pow(2).mul(s.score).sum()) for s in samples)
    n = sum(VIEW_CHANNELS * float(s.score.sum()) for s in samples)
    return se / max(n, 1.0)


def tile_mse(model: BaseModel, samples: list[Sample], tile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-tile squared-error sums, counts of scored pixels (``Sample.score``) and pair ids over all samples
    (nearly unscored tiles dropped: :func:`kept_tiles`)."""
    sums, counts, owners = [], [], []
    for s in samples:
        e = residual(model, s)
        su, co = tile_sums(e**2, s.score.float(), tile)
        sums.append(su)
        counts.append(co)
        per = su.numel() // len(s.batch.pair_ids)
        owners += [pid for pid in s.batch.pair_ids for _ in range(per)]
    su = torch.cat(sums).double().numpy()
    co = torch.cat(counts).double().numpy()
    own = np.array(owners)
    keep = kept_tiles(co)
    return su[keep], co[keep], own[keep]


KEEP_TILE_SHARE = 0.1
"""A tile counts when at least this share of the best-scored tile's pixels are scored. Statistics are sums
over a pair's tiles, so partly scored tiles add their pixels' weight and no more; only nearly empty ones,
whose per-tile log ratios (the < 4 pairs fallback) would be noisy, are dropped. It was 0.5: that dropped
most tiles of blurred regions, where the depth-edge mask leaves tiles partly scored, and with them most of
the signal of effects that act on blur (front_back_asymmetry's oracle explained 3 % of the systematic error
on the kept tiles, 17 % on all)."""


def kept_tiles(counts: np.ndarray) -> np.ndarray:
    """(n,) bool: the tiles the statistics use (:data:`KEEP_TILE_SHARE`)."""
    return counts >= max(KEEP_TILE_SHARE * float(counts.max()), 1.0)


MIN_PAIRS_AS_UNITS = 4
"""With fewer detection pairs than this, the statistics' units are tiles instead of pairs."""
SSE_EPS = 1e-20
"""Added to squared-error sums (linear units^2) inside log ratios, so an empty tile gives 0, not NaN."""


def clustered_delta(base_su: np.ndarray, su: np.ndarray, co: np.ndarray, owners: np.ndarray) -> np.ndarray:
    """Per-pair log MSE ratio ``ln(MSE_base / MSE_E)`` (tiles of one pair are correlated, pairs are the
    independent units; a log ratio is comparable across pairs with little and much blur); per tile when
    fewer than :data:`MIN_PAIRS_AS_UNITS` pairs are available."""
    ids = np.unique(owners)
    eps = SSE_EPS
    if ids.size < MIN_PAIRS_AS_UNITS:
        return np.log((base_su + eps) / (su + eps))
    return np.array([np.log((base_su[owners == i].sum() + eps) / (su[owners == i].sum() + eps)) for i in ids])


PSF_NUISANCE = ("rim_softness_px", "pixel_box")
"""The base model's parameters that shape every PSF without being a lens effect (the residual blur and the
pixel sampling): refitted with every effect that changes blur, since each trades off against it."""


def keep_rim_if_better(model: BaseModel, base: BaseModel, det: list[Sample]) -> BaseModel:
    """``model``, or ``model`` with the base model's rim softness and pixel sampling where that predicts the
    detection set better.

    An effect's refinement refits them (they trade off against the PSF's size and shape), but the fit crops
    may barely constrain them: on a 320 x 192 studio set with a planted chromatic focal shift the refit
    moved the rim from 0.143 to 0.166 px for a 0.01 % lower fit error, which cost 0.65 dB on the held-out
    pairs' in-focus texture (the extension lost 0.27 dB instead of gaining 0.38). The detection pairs,
    which the fit did not see, decide between the two settings.
    """
    kept = {k: base.params[k] for k in PSF_NUISANCE}
    if all(model.params[k] == v for k, v in kept.items()):
        return model
    alt = model.replaced(**kept)
    if masked_mse(alt, det) < masked_mse(model, det):
        log.info("%s: refit rim softness %.4f px / pixel_box %.3f predict the detection set worse than the base's %.4f / %.3f; kept the base's",
                 "+".join(c.name for c in model.components) or "base", model.params["rim_softness_px"], model.params["pixel_box"],
                 kept["rim_softness_px"], kept["pixel_box"])
        return alt
    return model


def one_sided_t(x: np.ndarray) -> tuple[float, float]:
    """(t, p) of the one-sided one-sample t test H1: mean(x) > 0."""
    x = np.asarray(x, dtype=np.float64)
    if x.size < 2 or not np.isfinite(x).all():
        return 0.0, 1.0
    sd = x.std(ddof=1)
    if sd <= 0:
        return (math.inf, 0.0) if x.mean() > 0 else (0.0, 1.0)
    t = float(x.mean() / (sd / math.sqrt(x.size)))
    return t, float(stats.t.sf(t, df=x.size - 1))


MIN_SIGNED_RANK_N = 6
"""From this many units on, effects are tested with the signed-rank test (its smallest one-sided p-value is
``2^-n``: 0.016 at 6); below, with the t test."""


def effect_test(delta: np.ndarray) -> tuple[float, float]:
    r"""(statistic, p) of the one-sided test that an effect lowers the error: H1 the per-unit log MSE ratios
    :math:`\Delta_i` are centred above 0.

    Wilcoxon's signed-rank test, statistic = its standardised rank sum
    :math:`z = (W^+ - n(n+1)/4) / \sqrt{n(n+1)(2n+1)/24}`, when there are at least
    :data:`MIN_SIGNED_RANK_N` units; the t test of :func:`one_sided_t` otherwise. How much an effect changes
    a pair varies with the pair's blur: on another renderer's set with a planted focus offset (fitted 1.058
    for 1.06) two of 14 detection pairs had :math:`\Delta` of 2.0 and 2.7 and the rest 0.0-0.18 (one
    -0.02), and the t test, whose standard deviation those two pairs inflate, gave p = 0.065 (not named);
    the signed-rank test gives 0.001.
    """
    x = np.asarray(delta, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < MIN_SIGNED_RANK_N:
        return one_sided_t(x)
    nz = x[x != 0]
    if nz.size == 0:
        return 0.0, 1.0
    res = stats.wilcoxon(nz, alternative="greater")
    n = nz.size
    ranks = stats.rankdata(np.abs(nz))
    w_plus = float(ranks[nz > 0].sum())
    z = (w_plus - n * (n + 1) / 4) / math.sqrt(n * (n + 1) * (2 * n + 1) / 24)
    return float(z), float(res.pvalue)


def fit_base(fit: list[Sample], iters: int = 4) -> BaseModel:
    """The base model with its parameters (rim softness, gain, pixel sampling) fitted on the fit samples.

    ``pixel_box`` is the renderer's discretisation, not a lens effect: whether the data's PSFs reach pixels
    as if each sharp pixel were a linearly interpolated sample (0, dp5k's studio) or a uniform square of
    light (1, a renderer that draws anti-aliased discs on the pixel grid). Below ~2 px of CoC the two
    differ by more than most effects: on such data (``dp5k_testing/foreign_dp.py``, ``sampling="box"``)
    the base model with the triangle alone erred 10 x the noise at 0.5-2 px of CoC on fine texture, and
    five of the nine effects were not found (``benchmarks/foreign_sweep.py``).
    """
    base = BaseModel()
    # a first guess of the gain: ratio of means
    num = sum(float((s.batch.left + s.batch.right).mul(s.score).sum()) for s in fit)
    den = sum(float(s.batch.sharp.mul(s.score).sum()) for s in fit)
    base.params["gain"] = num / max(den, 1e-12)
    batches, fields, masks = [s.batch for s in fit], [s.field for s in fit], [s.score for s in fit]
    fit_parameters(base, [(base, "rim_softness_px"), (base, "gain")], batches, fields, masks=masks, iters=iters)
    # then the sampling, from the triangle's optimum: a joint fit from the default rim (0.5 px) stopped in a
    # local minimum (box + 0.24 px of rim for triangle-sampled data, 5 x the fit error of triangle + 0)
    fit_parameters(base, [(base, "rim_softness_px"), (base, "gain"), (base, "pixel_box")], batches, fields, masks=masks,
                   iters=max(iters // 2, 1))
    return base


def fit_effect(base: BaseModel, name: str, fit: list[Sample], iters: int = 4, refit_rim: bool = True,
               refit_previous: str = "none") -> tuple[BaseModel, list[tuple[object, str]], float]:
    """The base model plus ``name``'s component, its parameters fitted on the fit samples (with the base
    model's gain, and its rim softness and pixel sampling, :data:`PSF_NUISANCE`, when ``refit_rim`` or the
    component changes blur).

    ``base`` may already hold components (effects chosen earlier, :mod:`dp5k_diagnose.chain`);
    ``refit_previous`` says which of their parameters are refitted with the new one: "none", "post" (those
    of components that only change the rendered views, when the new one does too: one layered render serves
    the fit) or "all". A new view mix changes what earlier view gains mean: on a studio set with an L/R gain
    ratio of 1.2 and crosstalk halving the disparity, crosstalk fitted with the gain components held at
    their values fitted alone reached 0.92 instead of 0.5, since it also scaled their L - R.

    Returns:
        (model, fitted targets, final fit MSE).
    """
    comp = COMPONENTS[name]()
    comp.field_box = covered_field_box(fit)
    model = copy_base(base).with_component(comp)
    comp.initial_guess(model, fit[0].batch, fit[0].field)
    # the base model's own parameters are refitted with every effect: the rim softness fitted without the
    # effect absorbs part of it (on real Canon data the base fit blurs by 1.3 px to soften a 5x too large
    # disparity; refitted with disparity_scale it falls to 0.25 px and the held-out gain rises by 1.3 dB)
    targets: list[tuple[object, str]] = [(comp, n) for n in fittable_names(comp, fit)] + [(model, "gain")]
    targets += previous_targets(model, comp, fit, refit_previous)
    if refit_rim or comp.changes_psf or not comp.post_only:
        targets += [(model, k) for k in PSF_NUISANCE]
    cost = fit_parameters(model, targets, [s.batch for s in fit], [s.field for s in fit], masks=[s.score for s in fit], iters=iters)
    return model, targets, cost


def previous_targets(model: BaseModel, comp: object, fit: list[Sample], which: str) -> list[tuple[object, str]]:
    """The fittable parameters of ``model``'s components other than ``comp`` that :func:`fit_effect` refits
    (``which``: "none", "post" or "all")."""
    if which == "none":
        return []
    out: list[tuple[object, str]] = []
    for c in model.components:
        if c is comp or not (which == "all" or (c.post_only and getattr(comp, "post_only", False))):
            continue
        out += [(c, n) for n in fittable_names(c, fit)]
    return out


def covered_field_box(samples: list[Sample]) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the field (coordinates in [-1, 1]) the samples' scored pixels span."""
    xs = [s.field[:, 0][s.score[:, 0]] for s in samples]
    ys = [s.field[:, 1][s.score[:, 0]] for s in samples]
    x, y = torch.cat(xs), torch.cat(ys)
    if x.numel() == 0:
        return (-1.0, 1.0, -1.0, 1.0)
    return (float(x.min()), float(x.max()), float(y.min()), float(y.max()))


def flat_lr_noise(samples: list[Sample], cfg: DetectConfig, base: BaseModel | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    r"""Per pair: the white-noise variance samples of the views in flat regions, and their intensities.

    Where the views are flat over a ``noise_flat_window_px`` window, their difference :math:`d = L - R` is
    smooth as well (blur, shading, gains and shifts of a flat patch cancel or vary slowly), and its high-pass
    :math:`h = d - \mathrm{mean}_{3 \times 3}(d)` holds only the two views' independent noise:
    :math:`E[h^2] = (8/9) (\sigma_L^2 + \sigma_R^2) \approx (16/9) \sigma^2(I)` with :math:`I = (L + R) / 2`
    (linear units of the views). Content common to both views (ringing of a misregistered view, texture
    leaking into the window) cancels in :math:`d`.

    With ``base`` (the fitted base model) "flat" is judged on the views it predicts, noise free: the
    flattest ``noise_flat_quantile`` of scored pixels by the local high-pass energy of :math:`\hat L` and
    :math:`\hat R`, and the predicted difference is taken out, :math:`d = (L - R) - (\hat L - \hat R)`. So
    strongly blurred texture counts as flat (it is, in the views) and the DP disparity of what texture is
    left does not count as noise. On data textured everywhere (no flat patch in ``sharp``,
    ``dp5k_testing/foreign_dp.py``) the sharp image's own flatness picked textured defocused pixels, whose
    DP disparity read as 1.7-1.9 x the nominal variance on clean sets with nominal noise (1.01 this way)
    and a planted 4 x as 5.3 x (4.03); on studio sets 1.09 (1.00) and 4.09 (4.01). Without ``base`` the
    flattest pixels of ``sharp`` are used and ``d = L - R`` (model-free).

    Returns:
        (v, I): per pair, 1-D arrays of :math:`h^2 / (16/9)` (an unbiased per-pixel estimate of
        :math:`\sigma^2`, chi^2_1 distributed) and :math:`I`, over flat valid pixels and channels.
    """
    k = cfg.noise_flat_window_px | 1
    var_by_pair: dict[str, list[Tensor]] = {}
    int_by_pair: dict[str, list[Tensor]] = {}
    for s in samples:
        b = s.batch
        d = b.left - b.right
        if base is None:
            energy = (_high_pass(b.sharp) ** 2).sum(1, keepdim=True)
            use = b.valid[:, 0].clone()
        else:
            with torch.no_grad():
                pl, pr = base.render(b, s.field)
            energy = (_high_pass(pl) ** 2 + _high_pass(pr) ** 2).sum(1, keepdim=True)
            d = d - (pl - pr)
            use = s.score[:, 0] & b.valid[:, 0]
        energy = F.avg_pool2d(F.pad(energy, (k // 2,) * 4, mode="replicate"), k, stride=1)
        v = _high_pass(d) ** 2 / HIGH_PASS_NOISE_GAIN
        inten = (b.left + b.right) / 2
        use[:, :1] = use[:, -1:] = False  # the 3x3 mean needs neighbours
        use[:, :, :1] = use[:, :, -1:] = False
        for i, pid in enumerate(b.pair_ids):
            vi = use[i]
            if int(vi.sum()) < MIN_NOISE_PX_PER_IMAGE:
                continue
            m = vi & (energy[i, 0] <= torch.quantile(energy[i, 0][vi], cfg.noise_flat_quantile))
            var_by_pair.setdefault(pid, []).append(v[i][:, m].reshape(-1))
            int_by_pair.setdefault(pid, []).append(inten[i][:, m].reshape(-1))
    ids = sorted(var_by_pair)
    return ([torch.cat(var_by_pair[p]).double().numpy() for p in ids], [torch.cat(int_by_pair[p]).double().numpy() for p in ids])


MIN_NOISE_PX_PER_IMAGE = 16
"""An image (or crop) adds noise samples only with at least this many usable pixels (px)."""
HIGH_PASS_NOISE_GAIN = 16.0 / 9.0
r"""E[h^2] / sigma^2 for the 3 x 3 high-pass h of L - R with independent noise of variance sigma^2 in each
view: (8/9) per view, two views."""
MIN_NOISE_SAMPLES = 256
"""Fewest flat noise samples (pixel x channel values) over all pairs to measure noise at all."""
MIN_PAIR_NOISE_SAMPLES = 32
"""Fewest flat noise samples (pixel x channel values) for a pair's own variance ratio (a unit of the test)."""
NOISE_INTENSITY_BINS = 8
"""Intensity quantile bins through whose median variances the noise model line is fitted."""


def _high_pass(x: Tensor) -> Tensor:
    """``x - mean3x3(x)`` (replicated border), (B, C, H, W)."""
    return x - F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


MEDIAN_CHI2_1 = 0.4549364
"""Median of the chi^2 distribution with one degree of freedom (median of z^2 for z ~ N(0, 1))."""


def test_noise(base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig, base_mse: float | None = None) -> Finding:
    r"""The noise finding: white noise in the views beyond a nominal sensor's.

    From :func:`flat_lr_noise` (fit and detection samples, flatness and the L - R signal predicted by
    ``base``; nothing is fitted to them), the per-pixel ratio
    :math:`z = \hat\sigma^2 / \sigma^2_{nom}(I)` with :math:`\sigma^2_{nom}(I) = s_{nom} I + r_{nom}^2`;
    per pair the robust variance ratio :math:`\rho_i = \mathrm{median}(z) / 0.4549` (median of chi^2_1).
    Statistic: one-sided t of :math:`\ln \rho_i` (H1: more noise than nominal); effect size: the pooled
    excess variance :math:`\rho - 1` (0 for a nominal sensor; the ``noise`` effect at studio strength 1 is
    about 3). The noise model ``var = shot_var I + read_sigma^2`` is a least-squares line through the
    medians of :data:`NOISE_INTENSITY_BINS` intensity bins. Also reported: ``excess_fraction``, the share of the base model's residual
    MSE that the excess noise accounts for (used to rank noise against effects measured in MSE;
    ``base_mse``, the base model's MSE on the detection set, is measured here when not given).
    """
    var, inten = flat_lr_noise(fit + det, cfg, base)
    if sum(v.size for v in var) < MIN_NOISE_SAMPLES:
        return Finding("noise", 0.0, 1.0, 0.0, False, {}, "too few flat valid pixels to measure noise", None)
    nominal = [cfg.nominal_shot_var * np.maximum(i, 0) + cfg.nominal_read_sigma**2 for i in inten]
    ratios = np.array([np.median(v / n) / MEDIAN_CHI2_1 for v, n in zip(var, nominal) if v.size >= MIN_PAIR_NOISE_SAMPLES])
    t, p = one_sided_t(np.log(np.maximum(ratios, 1e-12)))
    v_all, i_all, n_all = np.concatenate(var), np.concatenate(inten), np.concatenate(nominal)
    rho, coef = noise_model_fit(v_all, i_all, n_all)
    effect = rho - 1.0
    intervals = noise_model_intervals(var, inten, nominal)
    model = copy_base(base).with_component(Noise())
    comp = model.components[-1]
    comp.params = {"shot_var": float(max(coef[0], 0.0)), "read_sigma": float(math.sqrt(max(coef[1], 0.0)))}
    if base_mse is None:
        base_su, base_co, _ = tile_mse(base, det or fit, cfg.tile_px)
        base_mse = float(base_su.sum() / max(base_co.sum(), 1.0))
    excess_var = max(rho - 1.0, 0.0) * float(np.mean(n_all))
    params = {**comp.params, "variance_ratio": rho, "noise_sigma_mean": float(math.sqrt(max(np.mean(v_all), 0.0))),
              "excess_fraction": float(min(excess_var / max(base_mse, 1e-20), 1.0))}
    detected = bool(p < cfg.alpha and effect > cfg.threshold("noise"))
    return Finding("noise", t, p, effect, detected, params, EXPLAIN["noise"].format(**params), model, intervals=intervals)


def noise_model_fit(v: np.ndarray, inten: np.ndarray, nominal: np.ndarray) -> tuple[float, np.ndarray]:
    """(variance ratio to the nominal sensor, [shot_var, read_sigma^2]) from flat-region noise samples ``v``
    (linear units^2), their intensities and nominal variances: the robust ratio and a least-squares line
    through the medians of :data:`NOISE_INTENSITY_BINS` intensity bins."""
    rho = float(np.median(v / nominal) / MEDIAN_CHI2_1)
    nb = NOISE_INTENSITY_BINS
    edges = np.quantile(inten, np.linspace(0, 1, nb + 1))
    which = np.clip(np.searchsorted(edges, inten, side="right") - 1, 0, nb - 1)
    rows = [(float(inten[which == j].mean()), float(np.median(v[which == j]) / MEDIAN_CHI2_1)) for j in range(nb) if np.any(which == j)]
    A = np.array([[i, 1.0] for i, _ in rows])
    coef, *_ = np.linalg.lstsq(A, np.array([val for _, val in rows]), rcond=None)
    return rho, coef


NOISE_BOOT = 200
"""Bootstrap resamples (over pairs) of the noise model's intervals."""
INTERVAL_LEVEL = 0.95
"""Level of every parameter interval diagnose reports."""


def noise_model_intervals(var: list[np.ndarray], inten: list[np.ndarray], nominal: list[np.ndarray], seed: int = 0) -> dict[str, tuple[float, float]]:
    """95 % percentile bootstrap intervals over pairs of ``shot_var`` (per unit intensity), ``read_sigma``
    (linear units) and ``variance_ratio`` (to the nominal sensor); empty with fewer than 2 pairs."""
    if len(var) < 2:
        return {}
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(NOISE_BOOT):
        idx = rng.integers(0, len(var), len(var))
        rho, coef = noise_model_fit(*(np.concatenate([a[i] for i in idx]) for a in (var, inten, nominal)))
        draws.append((max(coef[0], 0.0), math.sqrt(max(coef[1], 0.0)), rho))
    d = np.array(draws)
    a = (1 - INTERVAL_LEVEL) / 2
    lo, hi = np.quantile(d, a, axis=0), np.quantile(d, 1 - a, axis=0)
    return {k: (float(lo[j]), float(hi[j])) for j, k in enumerate(("shot_var", "read_sigma", "variance_ratio"))}


ACHROMATIC_TWIN = {"chromatic_defocus": "focus_offset"}
"""A colour effect and the achromatic effect it becomes when its channels move together. A colour effect must
explain a colour *difference*: it is judged against the better of its usual reference and its twin's fitted
model (:func:`test_effects`). With red and blue focal shifts alike (+0.106 / +0.116 mm) chromatic_defocus
explained 0.155 of a studio set with a planted focus offset and bright rim and was named first, ahead of
the focus offset (0.160, p = 0.13); issue 21 saw the same on grey real data (0.078 over 0.04)."""

GREY_MAX_COLOUR_CONTRAST = 1e-3
"""Largest colour contrast (:func:`colour_contrast`, a variance ratio) at which the data counts as grey (R = G
= B within noise): colour effects are then not testable. Colour scenes measure far more (pooled over all
pairs: 0.15 on a 13-scene studio set, 0.94 on a 12-scene dp5k_testing/foreign_dp.py set); nominal sensor
noise alone (read sigma 1e-3, shot 2e-5 I at I = 0.5, independent per channel, averaged over 3 x 3) adds a
colour-difference variance of about 2e-6, 2e-4 of a texture variance of 1e-2."""
COLOUR_SMOOTH_PX = 3
"""Box window (px) that averages noise out of the images before their colour contrast is measured."""


def colour_contrast(samples: list[Sample]) -> float:
    r"""How much colour the data holds: over the scored pixels of ``sharp`` and of the views (each smoothed
    over :data:`COLOUR_SMOOTH_PX`), :math:`\sum_c (I_c - \bar I)^2 / \sum (\bar I - \langle \bar I \rangle)^2`
    with :math:`\bar I` the mean over R, G, B: the colour-difference variance per unit of luminance
    texture variance (dimensionless; 0 for grey data, the larger of the images')."""
    k = COLOUR_SMOOTH_PX
    worst = 0.0
    for key in ("sharp", "left", "right"):
        chroma = lum = 0.0
        for s in samples:
            img = getattr(s.batch, key)
            if img is None:
                continue
            img = F.avg_pool2d(F.pad(img.float(), (k // 2,) * 4, mode="replicate"), k, stride=1)
            m = s.score.float()
            y = img.mean(1, keepdim=True)
            n = m.sum().clamp(min=1.0)
            y_mean = (y * m).sum() / n
            chroma += float(((img - y) ** 2 * m).sum())
            lum += float(((y - y_mean) ** 2 * m).sum())
        if lum > 0:
            worst = max(worst, chroma / lum)
    return worst


def not_testable(name: str, contrast: float) -> Finding:
    """The finding of a colour effect on grey data: not testable, never detected."""
    text = (f"not testable: the data has no colour (R = G = B within noise; colour contrast {contrast:.1e} <= "
            f"{GREY_MAX_COLOUR_CONTRAST:g}), and {name} acts between colour channels")
    return Finding(name, 0.0, 1.0, 0.0, False, {}, text, None, testable=False)


def test_effects(base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig, effects: tuple[str, ...] = EFFECT_NAMES) -> list[Finding]:
    """Every effect's finding, ranked (detected first, then by effect size).

    Fitting is two-stage to bound the cost: every effect gets one Levenberg-Marquardt iteration
    (screening; effects that only change the rendered views keep the base model's rim softness there, so one
    layered render serves the whole fit), then the ``refine_top`` effects with the lowest fit error get
    ``lm_iters - 1`` more, with the rim softness refitted.
    """
    base_su, base_co, owners = tile_mse(base, det, cfg.tile_px)
    base_total = float(base_su.sum())
    noise = test_noise(base, fit, det, cfg, float(base_su.sum() / max(base_co.sum(), 1.0))) if "noise" in effects else None
    systematic = systematic_sse(base_total, det, noise, cfg)
    untestable: dict[str, Finding] = {}
    if any(COMPONENTS[e].needs_colour for e in effects):
        contrast = colour_contrast(fit + det)
        if contrast <= GREY_MAX_COLOUR_CONTRAST:
            untestable = {e: not_testable(e, contrast) for e in effects if COMPONENTS[e].needs_colour}
            log.info("grey data (colour contrast %.2e): %s not testable", contrast, ", ".join(untestable))
    fitted: dict[str, tuple[BaseModel, list[tuple[object, str]], float]] = {}
    for name in progress([e for e in effects if e != "noise" and e not in untestable], desc="screen effects", unit="effect"):
        fitted[name] = fit_effect(base, name, fit, 1, refit_rim=False, refit_previous="post")
    order = sorted(fitted, key=lambda n: fitted[n][2])
    for name in order[: cfg.refine_top]:
        model, targets, _ = fitted[name]
        targets = targets + [(model, k) for k in PSF_NUISANCE if (model, k) not in targets]
        targets += [t for t in previous_targets(model, model.component(name), fit, "all") if t not in targets]
        cost = fit_parameters(model, targets, [s.batch for s in fit], [s.field for s in fit], masks=[s.score for s in fit], iters=max(cfg.lm_iters - 1, 1))
        fitted[name] = (keep_rim_if_better(model, base, det), targets, cost)
    for name, twin in ACHROMATIC_TWIN.items():  # a colour effect is judged against its achromatic twin too
        if name in fitted and twin not in fitted and twin not in {c.name for c in base.components}:
            fitted[twin] = fit_effect(base, twin, fit, 1, refit_rim=False, refit_previous="post")
    findings = []
    for name in effects:
        if name == "noise":
            findings.append(noise)
            continue
        if name in untestable:
            findings.append(untestable[name])
            continue
        model = fitted[name][0]
        su, co, _ = tile_mse(model, det, cfg.tile_px)
        ref_su = reference_sse(base, model, det, base_su, cfg)
        twin = ACHROMATIC_TWIN.get(name)
        if twin in fitted:
            twin_su = tile_mse(fitted[twin][0], det, cfg.tile_px)[0]
            if float(twin_su.sum()) < float(ref_su.sum()):
                ref_su = twin_su
                log.info("%s judged against %s's model, which predicts the detection set better than the base model", name, twin)
        delta = clustered_delta(ref_su, su, base_co, owners)
        t, p = effect_test(delta)
        effect = float((ref_su.sum() - su.sum()) / max(systematic, 1e-20))
        comp = model.component(name)
        params = comp.describe()
        detected = bool(p < cfg.alpha and effect > cfg.threshold(name))
        held = [n for n in comp.fit_names if (comp, n) not in fitted[name][1]]
        text = explanation(name, params, held)
        log.info("%s: effect %.4f t %.2f p %.2g params %s", name, effect, t, p, params)
        findings.append(Finding(name, t, p, effect, detected, params, text, model, su, tuple(held)))
    one_sided_asymmetry_is_a_profile(findings)
    findings = [remeasure_noise(f, findings, fit, det, cfg, base_total / max(float(base_co.sum()), 1.0)) for f in findings]
    findings.sort(key=lambda f: (not f.detected, -f.rank_score))
    return findings


def explanation(name: str, params: dict[str, Any], held: tuple[str, ...] | list[str] = ()) -> str:
    """One sentence saying what ``name``'s fitted ``params`` mean (:data:`EXPLAIN`), and which parameters the
    fit data could not constrain."""
    try:
        text = EXPLAIN[name].format(**params)
    except (KeyError, ValueError):
        text = name
    if held:
        text += f" ({', '.join(held)} not fitted: too little of the fit data is where they act; held neutral)"
    return text


def reference_sse(base: BaseModel, model: BaseModel, det: list[Sample], base_su: np.ndarray, cfg: DetectConfig) -> np.ndarray:
    """Per-tile squared errors of the base model an effect's ``model`` is judged against: the fitted base
    model, or the base model with ``model``'s gain, rim softness and pixel sampling where that predicts the
    detection set better.

    An effect's fit refits those (they trade off against it), and :func:`keep_rim_if_better` lets the
    detection pairs choose them; without the same choice for the base model an effect was credited with
    what the choice alone gained. On a clean set of another renderer (box-sampled) the base fit had
    converged at pixel_box 0.970 on the fit crops; chromatic_defocus's fit moved it to 0.990 with focal
    shifts of -0.001 mm, lowered the detection MSE by 3 % and was named at 0.14 of the systematic error.
    Where the effect needs its own setting (real Canon data: the rim falls from 1.4 to 0.48 px with
    disparity_scale) the base model with that setting is worse and the fitted base stays the reference.
    """
    keys = ("gain", *PSF_NUISANCE)
    if all(model.params[k] == base.params[k] for k in keys):
        return base_su
    alt_su = tile_mse(base.replaced(**{k: model.params[k] for k in keys}), det, cfg.tile_px)[0]
    return alt_su if float(alt_su.sum()) < float(base_su.sum()) else base_su


def one_sided_asymmetry_is_a_profile(findings: list[Finding]) -> None:
    """Do not name front_back_asymmetry where the fit data shows blur on one side of focus only and
    psf_profile is detected too (in place: its ``detected`` is cleared and its explanation says why).

    An asymmetry between front and back needs both sides; seen from one side, a rim-heavy (or centre-heavy)
    disc is psf_profile's claim, and which of the two fits better then depends only on their radial
    forms (front_back_asymmetry's back rim is quadratic in rho/R, psf_profile's quartic).
    """
    by = {f.effect: f for f in findings}
    fba, psf = by.get("front_back_asymmetry"), by.get("psf_profile")
    if fba is None or psf is None or not (fba.detected and psf.detected and fba.held):
        return
    fba.detected = False
    fba.explanation += "; not named: the fit data shows blur on one side of focus only, where it is psf_profile's non-uniform disc"
    log.info("front_back_asymmetry not named: one side of focus only (%s held), psf_profile detected", ", ".join(fba.held))


def remeasure_noise(noise: Finding, findings: list[Finding], fit: list[Sample], det: list[Sample], cfg: DetectConfig,
                    base_mse: float) -> Finding:
    """``noise`` measured again against the best detected predictable effect's model, when both were detected.

    :func:`flat_lr_noise` takes the L - R the base model predicts out of the views; where the base model
    mispredicts it (a planted disparity scale, misregistration or field-varying split on texture that is
    nowhere flat), that error reads as excess noise: 0.6-1.2 x the nominal variance on such data, over the
    0.5 threshold. Measured against the model with the effect, only noise the effect does not explain is
    left. The systematic error (effect sizes' denominator) keeps the first measurement. Other findings are
    returned as they are.
    """
    if noise.effect != "noise" or not noise.detected:
        return noise
    best = max((f for f in findings if f.effect != "noise" and f.detected and f.model is not None), key=lambda f: f.effect_size, default=None)
    if best is None:
        return noise
    again = test_noise(best.model, fit, det, cfg, base_mse)
    again.params["variance_ratio_vs_base"] = noise.params.get("variance_ratio", float("nan"))
    again.explanation += f" (measured against the base model with {best.effect}; against the base model alone {noise.params.get('variance_ratio', float('nan')):.2f} x)"
    log.info("noise re-measured against base + %s: variance ratio %.3f (base alone %.3f)", best.effect,
             again.params.get("variance_ratio", float("nan")), noise.params.get("variance_ratio", float("nan")))
    return again


def noise_sse(samples: list[Sample], shot_var: float, read_sigma: float, tile: int) -> float:
    r"""The squared error white noise alone gives on the tiles :func:`tile_mse` keeps: the sum over scored
    pixels and both views' channels of :math:`\sigma^2(I) = \text{shot\_var}\, I + \text{read\_sigma}^2`, with
    :math:`I` the measured view (linear units)."""
    sums, counts = [], []
    for s in samples:
        var = shot_var * torch.cat([s.batch.left, s.batch.right], 1).clamp(min=0) + read_sigma**2
        su, co = tile_sums(var, s.score.float(), tile)
        sums.append(su)
        counts.append(co)
    su, co = torch.cat(sums).double().numpy(), torch.cat(counts).double().numpy()
    return float(su[kept_tiles(co)].sum()) if co.size else 0.0


def systematic_sse(base_total: float, det: list[Sample], noise: Finding | None, cfg: DetectConfig) -> float:
    r"""The part of the base model's squared error on the detection set that a better model could remove:
    :math:`\max(\mathrm{SSE}_{base} - \mathrm{SSE}_{noise},\ \text{systematic\_floor} \cdot \mathrm{SSE}_{base})`,
    with the views' white noise as measured by :func:`test_noise`: its robust variance ratio times the
    nominal sensor's variance (the nominal variance when it could not be measured). Effect sizes are shares
    of it, so they do not shrink with the noise level; the floor bounds them where noise explains nearly all
    of the error."""
    rho = float(noise.params.get("variance_ratio", 1.0)) if noise is not None else 1.0
    shot, read = rho * cfg.nominal_shot_var, math.sqrt(rho) * cfg.nominal_read_sigma
    floor = cfg.systematic_floor * base_total
    return max(base_total - noise_sse(det, shot, read, cfg.tile_px), floor)


@dataclass
class Discrimination:
    """Which of two detected effects the data needs, from their unique contributions.

    ``unique[e]`` is the relative reduction of the detection set's MSE (as a share of the base model's) that
    ``e`` adds on top of the other effect: ``(MSE(other) - MSE(both)) / MSE(base)``, with the one-sided t
    test of its per-pair log ratio. The effect that adds more is the cause.
    """

    effects: tuple[str, str]
    unique: dict[str, float]
    p_value: dict[str, float]
    joint_effect_size: float
    winner: str

    def to_json(self) -> dict[str, Any]:
        return {"effects": list(self.effects), "unique_effect_size": {k: _finite(v) for k, v in self.unique.items()},
                "unique_p_value": {k: _finite(v, 1.0) for k, v in self.p_value.items()},
                "joint_effect_size": _finite(self.joint_effect_size), "winner": self.winner}


def discriminate(findings: list[Finding], base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig) -> Discrimination | None:
    """Nested comparison of the two leading detected effects (both predictable, i.e. not ``noise``).

    Two effects can mimic each other where the data is weak (an off-axis photodiode leak is a field-linear L/R
    brightness ratio in focus, like a gain imbalance); what separates them is what each explains that the
    other cannot. Both components are fitted together (starting from their separate fits) and each one's
    unique contribution is measured on the detection set. ``findings`` is reordered so the winner leads.

    Returns:
        None when fewer than two predictable effects are detected.
    """
    lead = [f for f in findings if f.detected and f.effect != "noise" and f.model is not None]
    if len(lead) < 2:
        return None
    a, b = lead[0], lead[1]
    model = copy_base(base)
    model.params.update(a.model.params)  # start from the leader's fitted gain and rim
    targets: list[tuple[object, str]] = []
    for f in (a, b):
        comp = COMPONENTS[f.effect]()
        comp.params = dict(f.model.component(f.effect).params)
        model = model.with_component(comp)
        targets += [(comp, n) for n in fittable_names(comp, fit)]
    targets += [(model, "gain")] + [(model, k) for k in PSF_NUISANCE]
    fit_parameters(model, targets, [s.batch for s in fit], [s.field for s in fit], masks=[s.score for s in fit], iters=max(cfg.lm_iters - 1, 1))
    base_su, _, owners = tile_mse(base, det, cfg.tile_px)
    su = {f.effect: f.tile_sse if f.tile_sse is not None else tile_mse(f.model, det, cfg.tile_px)[0] for f in (a, b)}
    su_ab = tile_mse(model, det, cfg.tile_px)[0]
    total = max(float(base_su.sum()), 1e-20)
    unique, pv = {}, {}
    for f, other in ((a, b), (b, a)):
        unique[f.effect] = float((su[other.effect].sum() - su_ab.sum()) / total)
        pv[f.effect] = one_sided_t(clustered_delta(su[other.effect], su_ab, su_ab, owners))[1]
    winner = max(unique, key=lambda e: unique[e])
    log.info("discriminate %s vs %s: unique %s p %s", a.effect, b.effect, unique, pv)
    if winner != findings[0].effect:
        findings.sort(key=lambda f: (f.effect != winner, not f.detected, -f.rank_score))
    return Discrimination((a.effect, b.effect), unique, pv, float((base_su.sum() - su_ab.sum()) / total), winner)
