r"""Name the cause: test every effect of the vocabulary against the fitted base model.

For each effect E the base model is extended with E's component (:mod:`dp5k_diagnose.components`), whose
parameters (plus the gain, and the rim softness for PSF-shape effects) are fitted on the *fit* set
(training crops). The extension is then judged on a *detection* set of pairs it was not fitted on
(validation split, else the remaining training pairs), tile by tile:

* per pair i: :math:`\Delta_i = \ln(\mathrm{MSE}_i(\text{base}) / \mathrm{MSE}_i(\text{base} + E))` (pairs are the
  independent units; with fewer than 4 detection pairs, 32 px tiles are used instead);
* statistic: the one-sided one-sample t statistic of :math:`\Delta_i` (H0: mean 0), its p-value;
* effect size: the relative reduction of the pooled MSE, :math:`\sum_t \Delta_t / \sum_t \mathrm{MSE}_t(\text{base})`.

``noise`` cannot be predicted, so it is tested on the base residual itself: the white-noise variance
:math:`\hat\sigma^2_t` of each tile (robust, from the residual minus its 3x3 mean) against the tile's
residual MSE; the effect size is the white fraction of the residual beyond what the noiseless fit leaves
(``NOISE_NULL_FRACTION``), tested with a one-sided t test.

An effect is *detected* when ``p < alpha`` and its effect size exceeds ``min_effect``; the cause is the
detected effect of largest effect size, else ``none``.
"""

from __future__ import annotations

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
from neural_dp.simulators.base import BaseModel, fit_parameters

from .components import COMPONENTS, Noise
from .data import Sample

log = logging.getLogger(__name__)

NOISE_NULL_FRACTION = 0.35
"""White fraction of a residual that a noiseless model mismatch can show (high-pass leakage at edges)."""

EXPLAIN = {
    "lr_gain_imbalance": "the left and right views differ in brightness: L/R ratio {lr_ratio_center:.3f} at the centre, {lr_ratio_min:.3f}..{lr_ratio_max:.3f} across the field",
    "field_varying_psf": "the blur changes across the field: CoC grows by {coc_growth_at_corner:+.1%} at the corner and the split leaks {edge_leak:.3f} x |x| toward the edges",
    "chromatic_defocus": "the colour channels focus differently: focal length shift red {focal_shift_r_mm:+.4f} mm, blue {focal_shift_b_mm:+.4f} mm versus green",
    "disparity_scale": "the L/R disparity is {disparity_scale:.3f} x the ideal half-aperture disparity (crosstalk {crosstalk:.3f})",
    "focus_offset": "the lens focuses {focus_offset_mm:+.1f} mm from the recorded focus distance",
    "psf_profile": "the blur disc is not uniform: radial weight 1 {rim_gain:+.2f} (rho/R)^4",
    "front_back_asymmetry": "blur in front of focus differs from blur behind it: back rim gain {back_rim_gain:+.2f}, front centre gain {front_center_gain:+.2f}, front size x{front_size_factor:.3f}",
    "misregistration": "the views are shifted against the sharp image: left ({left_dx_px:+.2f}, {left_dy_px:+.2f}) px, right ({right_dx_px:+.2f}, {right_dy_px:+.2f}) px",
    "noise": "the views carry more white noise than a nominal sensor: shot variance {shot_var:.2e} per unit intensity, read sigma {read_sigma:.2e} ({excess_fraction:.0%} of the residual is excess noise)",
}


@dataclass
class DetectConfig:
    """Statistical settings of the detectors.

    Attributes:
        tile_px: tile side for the per-tile statistics.
        alpha: significance level of the one-sided tests.
        min_effect: smallest relative MSE reduction (or excess white fraction) that counts as an effect.
        lm_iters: Levenberg-Marquardt iterations per effect.
        refine_top: effects fitted beyond the one-iteration screening.
        noise_min_effect: smallest excess white-noise fraction of the residual that counts as ``noise``.
        nominal_shot_var, nominal_read_sigma: the noise a healthy sensor is expected to show (linear
            units: a ~50 000 e- full well scaled to [0, 1] and a read noise of 1e-3); only noise beyond
            it counts as the ``noise`` effect.
    """

    tile_px: int = 32
    alpha: float = 0.05
    min_effect: float = 0.15
    lm_iters: int = 3
    refine_top: int = 2
    noise_min_effect: float = 0.25
    nominal_shot_var: float = 2.0e-5
    nominal_read_sigma: float = 1.0e-3


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

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "statistic": _finite(self.statistic),
            "p_value": _finite(self.p_value, 1.0),
            "effect_size": _finite(self.effect_size),
            "detected": bool(self.detected),
            "params": {k: ([_finite(x) for x in v] if isinstance(v, (list, tuple)) else _finite(v)) for k, v in self.params.items()},
            "explanation": self.explanation,
        }


def _finite(x: float, default: float = 0.0) -> float:
    x = float(x)
    return x if math.isfinite(x) else default


def copy_base(base: BaseModel) -> BaseModel:
    return BaseModel(base.params["rim_softness_px"], base.params["gain"], [], base.config)


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


def tile_mse(model: BaseModel, samples: list[Sample], tile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-tile squared-error sums, valid counts and pair ids over all samples (tiles less than half valid dropped)."""
    sums, counts, owners = [], [], []
    for s in samples:
        e = residual(model, s)
        su, co = tile_sums(e**2, s.batch.valid.float(), tile)
        sums.append(su)
        counts.append(co)
        per = su.numel() // len(s.batch.pair_ids)
        owners += [pid for pid in s.batch.pair_ids for _ in range(per)]
    su = torch.cat(sums).double().numpy()
    co = torch.cat(counts).double().numpy()
    own = np.array(owners)
    keep = co >= 0.5 * co.max()
    return su[keep], co[keep], own[keep]


def clustered_delta(base_su: np.ndarray, su: np.ndarray, co: np.ndarray, owners: np.ndarray) -> np.ndarray:
    """Per-pair log MSE ratio ``ln(MSE_base / MSE_E)`` (tiles of one pair are correlated, pairs are the
    independent units; a log ratio is comparable across pairs with little and much blur); per tile when
    fewer than 4 pairs are available."""
    ids = np.unique(owners)
    eps = 1e-20
    if ids.size < 4:
        return np.log((base_su + eps) / (su + eps))
    return np.array([np.log((base_su[owners == i].sum() + eps) / (su[owners == i].sum() + eps)) for i in ids])


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


def fit_base(fit: list[Sample], iters: int = 4) -> BaseModel:
    """The base model with its two parameters fitted on the fit samples."""
    base = BaseModel()
    # a first guess of the gain: ratio of means
    num = sum(float((s.batch.left + s.batch.right).mul(s.batch.valid).sum()) for s in fit)
    den = sum(float(s.batch.sharp.mul(s.batch.valid).sum()) for s in fit)
    base.params["gain"] = num / max(den, 1e-12)
    fit_parameters(base, [(base, "rim_softness_px"), (base, "gain")], [s.batch for s in fit], [s.field for s in fit], iters=iters)
    return base


def fit_effect(base: BaseModel, name: str, fit: list[Sample], iters: int = 4) -> tuple[BaseModel, list[tuple[object, str]], float]:
    """The base model plus ``name``'s component, its parameters fitted on the fit samples.

    Returns:
        (model, fitted targets, final fit MSE).
    """
    comp = COMPONENTS[name]()
    model = copy_base(base).with_component(comp)
    comp.initial_guess(model, fit[0].batch, fit[0].field)
    targets: list[tuple[object, str]] = [(comp, n) for n in comp.fit_names] + [(model, "gain")]
    if comp.changes_psf:
        targets.append((model, "rim_softness_px"))
    cost = fit_parameters(model, targets, [s.batch for s in fit], [s.field for s in fit], iters=iters)
    return model, targets, cost


def white_noise_tiles(base: BaseModel, samples: list[Sample], tile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per tile: robust white-noise variance of the residual, residual MSE, mean predicted intensity.

    The residual's high-pass ``e - mean3x3(e)`` has variance ``(8/9) sigma^2`` for white noise; its
    median square over a tile divided by ``0.4549 * 8/9`` (median of chi^2_1) estimates ``sigma^2``
    robustly (model-mismatch edges are outliers).
    """
    var, mse, inten = [], [], []
    for s in samples:
        l, r = base.render(s.batch, s.field)
        pred = torch.cat([l, r], 1)
        e = pred - torch.cat([s.batch.left, s.batch.right], 1)
        hp = e - F.avg_pool2d(F.pad(e, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        m = s.batch.valid.float()
        t = min(tile, e.shape[-2], e.shape[-1])
        B, C, H, W = e.shape
        nty, ntx = H // t, W // t
        hp2 = (hp[..., : nty * t, : ntx * t] ** 2)
        mm = m[..., : nty * t, : ntx * t]
        hp2 = torch.where(mm.bool().expand_as(hp2), hp2, torch.nan)
        blocks = hp2.reshape(B, C, nty, t, ntx, t).permute(0, 2, 4, 1, 3, 5).reshape(B * nty * ntx, -1)
        med = torch.nanmedian(blocks, dim=1).values / (0.4549 * 8.0 / 9.0)
        e2 = (e[..., : nty * t, : ntx * t] ** 2 * mm).reshape(B, C, nty, t, ntx, t).permute(0, 2, 4, 1, 3, 5).reshape(B * nty * ntx, -1)
        cnt = mm.expand(B, C, -1, -1).reshape(B, C, nty, t, ntx, t).permute(0, 2, 4, 1, 3, 5).reshape(B * nty * ntx, -1).sum(1)
        pi = (pred[..., : nty * t, : ntx * t] * mm).reshape(B, C, nty, t, ntx, t).permute(0, 2, 4, 1, 3, 5).reshape(B * nty * ntx, -1).sum(1)
        ok = cnt >= 0.5 * C * t * t
        var.append(med[ok])
        mse.append((e2.sum(1) / cnt.clamp(min=1))[ok])
        inten.append((pi / cnt.clamp(min=1))[ok])
    return (torch.cat(var).double().numpy(), torch.cat(mse).double().numpy(), torch.cat(inten).double().numpy())


def test_noise(base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig) -> Finding:
    r"""The noise finding: white noise in the base residual beyond a nominal sensor's.

    Per tile t: :math:`x_t = (\hat\sigma^2_t - \sigma^2_{nom}(I_t)) / \mathrm{MSE}_t`, the fraction of the
    residual that is excess white noise; one-sided t test of mean > 0; effect size = pooled fraction.
    The noise model ``var = shot_var I + read_sigma^2`` is a least-squares line through the tiles.
    """
    var, mse, inten = white_noise_tiles(base, det, cfg.tile_px)
    nominal = cfg.nominal_shot_var * np.maximum(inten, 0) + cfg.nominal_read_sigma**2
    x = np.clip((var - nominal) / np.maximum(mse, 1e-20), -1.5, 1.5)
    t, p = one_sided_t(x)
    effect = float(np.sum(var - nominal) / max(np.sum(mse), 1e-20))
    A = np.stack([inten, np.ones_like(inten)], 1)
    coef, *_ = np.linalg.lstsq(A, var, rcond=None)
    model = copy_base(base).with_component(Noise())
    comp = model.components[-1]
    comp.params = {"shot_var": float(max(coef[0], 0.0)), "read_sigma": float(math.sqrt(max(coef[1], 0.0)))}
    params = {**comp.params, "noise_sigma_mean": float(math.sqrt(max(np.mean(var), 0.0))), "excess_fraction": effect}
    detected = bool(p < cfg.alpha and effect > cfg.noise_min_effect)
    return Finding("noise", t, p, effect, detected, params, EXPLAIN["noise"].format(**params), model)


def test_effects(base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig, effects: tuple[str, ...] = EFFECT_NAMES) -> list[Finding]:
    """Every effect's finding, ranked (detected first, then by effect size).

    Fitting is two-stage to bound the cost: every effect gets one Levenberg-Marquardt iteration
    (screening), then the ``refine_top`` effects with the lowest fit error get ``lm_iters - 1`` more.
    """
    base_su, base_co, owners = tile_mse(base, det, cfg.tile_px)
    base_total = float(base_su.sum())
    fitted: dict[str, tuple[BaseModel, list[tuple[object, str]], float]] = {}
    for name in progress([e for e in effects if e != "noise"], desc="screen effects", unit="effect"):
        fitted[name] = fit_effect(base, name, fit, 1)
    order = sorted(fitted, key=lambda n: fitted[n][2])
    for name in order[: cfg.refine_top]:
        model, targets, _ = fitted[name]
        cost = fit_parameters(model, targets, [s.batch for s in fit], [s.field for s in fit], iters=max(cfg.lm_iters - 1, 1))
        fitted[name] = (model, targets, cost)
    findings = []
    for name in effects:
        if name == "noise":
            findings.append(test_noise(base, fit, det, cfg))
            continue
        model = fitted[name][0]
        su, co, _ = tile_mse(model, det, cfg.tile_px)
        delta = clustered_delta(base_su, su, base_co, owners)
        t, p = one_sided_t(delta)
        effect = float((base_su.sum() - su.sum()) / max(base_total, 1e-20))
        comp = model.components[-1]
        params = comp.describe()
        detected = bool(p < cfg.alpha and effect > cfg.min_effect)
        try:
            text = EXPLAIN[name].format(**params)
        except (KeyError, ValueError):
            text = name
        log.info("%s: effect %.4f t %.2f p %.2g params %s", name, effect, t, p, params)
        findings.append(Finding(name, t, p, effect, detected, params, text, model))
    findings.sort(key=lambda f: (not f.detected, -f.effect_size))
    return findings


def name_cause(findings: list[Finding]) -> str:
    return findings[0].effect if findings and findings[0].detected else NO_EFFECT
