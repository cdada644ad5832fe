r"""The views' noise, measured: white noise in flat regions against a nominal sensor (:func:`test_noise`), the
noise model ``var = shot_var I + read_sigma^2`` with bootstrap intervals, and the share of a model's squared
error that noise alone explains (:func:`systematic_sse`, the denominator of every effect size).

``noise`` cannot be predicted (a simulator's output is an expectation), so it is measured rather than fitted:
the high-pass of ``L - R`` in flat regions (:func:`flat_lr_noise`) against the nominal variance; the effect
size is the excess variance ratio.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dp5k_common.sensor_noise import MEDIAN_CHI2_1, WHITE_NOISE_GAIN, noise_model_fit, white_part
from dp5k_common.sensor_noise import local_high_pass as _high_pass
from neural_dp.registry import BaseModel
from neural_dp.registry import Noise

from .config import DetectConfig
from .data import Sample
from .fitting import copy_base
from .findings import EXPLAIN, Finding
from .tiles import kept_tiles, one_sided_t, tile_mse, tile_sums


def flat_pixels(images: tuple[Tensor, ...], use: Tensor, cfg: DetectConfig) -> Tensor:
    """(B, H, W) bool: the flattest ``noise_flat_quantile`` of the ``use`` pixels (B, H, W) of each image by the
    local high-pass energy (``noise_flat_window_px``) of ``images`` (each (B, C, H, W): the predicted views, or
    ``sharp``), away from the image border (the 3 x 3 filters need neighbours); none in an image with too few
    usable pixels."""
    k = cfg.noise_flat_window_px | 1
    energy = sum((_high_pass(im) ** 2).sum(1, keepdim=True) for im in images)
    energy = F.avg_pool2d(F.pad(energy, (k // 2,) * 4, mode="replicate"), k, stride=1)[:, 0]
    use = use.clone()
    use[:, :1] = use[:, -1:] = False
    use[:, :, :1] = use[:, :, -1:] = False
    out = torch.zeros_like(use)
    for i in range(use.shape[0]):
        if int(use[i].sum()) >= MIN_NOISE_PX_PER_IMAGE:
            out[i] = use[i] & (energy[i] <= torch.quantile(energy[i][use[i]], cfg.noise_flat_quantile))
    return out


def flat_lr_noise(samples: list[Sample], cfg: DetectConfig, base: BaseModel | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    r"""Per pair: the white-noise variance samples of the views in flat regions, and their intensities.

    Where the views are flat over a ``noise_flat_window_px`` window, their difference :math:`d = L - R` is
    smooth as well (blur, shading, gains and shifts of a flat patch cancel or vary slowly), and its white part
    :math:`h` (:data:`WHITE_NOISE_KERNEL`, blind to what is linear or one-dimensional) holds only the two
    views' independent noise:
    :math:`E[h^2] = \sigma_L^2 + \sigma_R^2 \approx 2 \sigma^2(I)` with :math:`I = (L + R) / 2`
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
        (v, I): per pair, 1-D arrays of :math:`h^2 / 2` (an unbiased per-pixel estimate of
        :math:`\sigma^2`, chi^2_1 distributed) and :math:`I`, over flat valid pixels and channels.
    """
    var_by_pair: dict[str, list[Tensor]] = {}
    int_by_pair: dict[str, list[Tensor]] = {}
    for s in samples:
        b = s.batch
        d = b.left - b.right
        if base is None:
            flat = flat_pixels((b.sharp,), b.valid[:, 0], cfg)
        else:
            with torch.no_grad():
                pl, pr = base.render(b, s.field)
            flat = flat_pixels((pl, pr), s.score[:, 0] & b.valid[:, 0], cfg)
            d = d - (pl - pr)
        v = white_part(d) ** 2 / WHITE_NOISE_GAIN
        inten = (b.left + b.right) / 2
        for i, pid in enumerate(b.pair_ids):
            m = flat[i]
            if not bool(m.any()):
                continue
            var_by_pair.setdefault(pid, []).append(v[i][:, m].reshape(-1))
            int_by_pair.setdefault(pid, []).append(inten[i][:, m].reshape(-1))
    ids = sorted(var_by_pair)
    return ([torch.cat(var_by_pair[p]).double().numpy() for p in ids], [torch.cat(int_by_pair[p]).double().numpy() for p in ids])


MIN_NOISE_PX_PER_IMAGE = 16
"""An image (or crop) adds noise samples only with at least this many usable pixels (px)."""


MIN_NOISE_SAMPLES = 256
"""Fewest flat noise samples (pixel x channel values) over all pairs to measure noise at all."""


MIN_PAIR_NOISE_SAMPLES = 32
"""Fewest flat noise samples (pixel x channel values) for a pair's own variance ratio (a unit of the test)."""


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
        return Finding("noise", 0.0, 1.0, 0.0, False, {}, "too few flat valid pixels to measure noise", None, stage="measured")
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
    return Finding("noise", t, p, effect, detected, params, EXPLAIN["noise"].format(**params), model, intervals=intervals, stage="measured")


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


def noise_tile_sse(samples: list[Sample], shot_var: float, read_sigma: float, tile: int,
                   sharp: "SharpNoise | None" = None) -> np.ndarray:
    r"""Per tile that :func:`tile_mse` keeps, the squared error white noise alone gives: the sum over scored
    pixels and both views' channels of :math:`\sigma^2(I) = \text{shot\_var}\, I + \text{read\_sigma}^2`, with
    :math:`I` the measured view (linear units), plus the sharp frame's noise as the model carries it into its
    prediction (``sharp``, :func:`sharp_noise`, aligned with ``samples``)."""
    sums, counts = [], []
    for i, s in enumerate(samples):
        var = shot_var * torch.cat([s.batch.left, s.batch.right], 1).clamp(min=0) + read_sigma**2
        if sharp is not None and sharp.ratio > 0:
            var = var + sharp.ratio * sharp.propagated[i]
        su, co = tile_sums(var, s.score.float(), tile)
        sums.append(su)
        counts.append(co)
    if not sums:
        return np.zeros(0)
    su, co = torch.cat(sums).double().numpy(), torch.cat(counts).double().numpy()
    return su[kept_tiles(co)]


def noise_sse(samples: list[Sample], shot_var: float, read_sigma: float, tile: int, sharp: "SharpNoise | None" = None) -> float:
    """The sum of :func:`noise_tile_sse`."""
    return float(noise_tile_sse(samples, shot_var, read_sigma, tile, sharp).sum())


@dataclass
class SharpNoise:
    """The sharp frame's noise as a model's prediction carries it (:func:`sharp_noise`).

    Attributes:
        ratio: the sharp frame's noise variance over the nominal sensor's at its intensity (0: noise free).
        propagated: per sample, (B, 6, H, W) one draw of nominal sharp noise carried through the model, squared
            (its sum over a tile estimates the tile's propagated noise energy at the nominal level).
    """

    ratio: float
    propagated: list[Tensor]


def sharp_noise(model: BaseModel, samples: list[Sample], cfg: DetectConfig, seed: int = 0) -> SharpNoise:
    r"""How much of the prediction's error is the sharp frame's own noise, carried into both views.

    A real ``sharp`` is an f/22 capture with sensor noise; the model blurs it (and undoes its f/22 blur, which
    amplifies fine detail), so that noise reaches both predicted views alike. It is no error a better model of
    the lens could remove, and counted as systematic it made every effect look small (on another renderer's
    clean set with a noisy ``sharp`` it was 7.3 of the base model's 32.3 units of squared error, the views'
    noise 26.2, and nothing else was left). Measured without knowing the sharp frame's noise level: one draw
    :math:`n` of nominal noise at the sharp frame's intensity is carried through the model,
    :math:`p = M(s + n) - M(s)`; in the flat regions of the predicted views (:func:`flat_pixels`), the
    covariance of the white parts (:data:`WHITE_NOISE_KERNEL`) of the left and right residuals holds only what
    both views share: the propagated sharp noise (the views' own noise is independent, smooth model error has
    no white part). Its ratio to the same covariance of :math:`p` is the sharp frame's noise over the nominal
    (texture in ``sharp`` is predicted in both views and cancels in the residuals, where a single-image
    estimate on ``sharp`` read another renderer's noise-free texture as 1.7 x nominal noise)."""
    g = torch.Generator().manual_seed(seed)
    num = den = 0.0
    maps = []
    for s in samples:
        b = s.batch
        sd = torch.sqrt(cfg.nominal_shot_var * b.sharp.clamp(min=0) + cfg.nominal_read_sigma**2)
        noisy = dataclasses.replace(b, sharp=b.sharp + sd * torch.randn(b.sharp.shape, generator=g))
        with torch.no_grad():
            pl, pr = model.render(b, s.field)
            nl, nr = model.render(noisy, s.field)
        prop_l, prop_r = nl - pl, nr - pr
        maps.append(torch.cat([prop_l, prop_r], 1) ** 2)
        m = flat_pixels((pl, pr), s.score[:, 0] & b.valid[:, 0], cfg)[:, None].float()
        num += float((white_part(pl - b.left) * white_part(pr - b.right) * m).sum())
        den += float((white_part(prop_l) * white_part(prop_r) * m).sum())
    ratio = max(num / den, 0.0) if den > 0 else 0.0
    return SharpNoise(ratio, maps)


def measured_noise(noise: Finding | None, cfg: DetectConfig) -> tuple[float, float]:
    """(shot_var, read_sigma) of the views' white noise as :func:`test_noise` measured it: its robust variance
    ratio times the nominal sensor's (the nominal sensor when it could not be measured)."""
    rho = float(noise.params.get("variance_ratio", 1.0)) if noise is not None else 1.0
    return rho * cfg.nominal_shot_var, math.sqrt(rho) * cfg.nominal_read_sigma


def systematic_sse(base_total: float, det: list[Sample], noise: Finding | None, cfg: DetectConfig, sharp: SharpNoise | None = None) -> float:
    r"""The part of the base model's squared error on the detection set that a better model could remove:
    :math:`\max(\mathrm{SSE}_{base} - \mathrm{SSE}_{noise},\ \text{systematic\_floor} \cdot \mathrm{SSE}_{base})`,
    with the views' white noise as measured by :func:`test_noise`: its robust variance ratio times the
    nominal sensor's variance (the nominal variance when it could not be measured). Effect sizes are shares
    of it, so they do not shrink with the noise level; the floor bounds them where noise explains nearly all
    of the error. ``sharp`` adds the sharp frame's noise as the model carries it (:func:`sharp_noise`)."""
    shot, read = measured_noise(noise, cfg)
    floor = cfg.systematic_floor * base_total
    return max(base_total - noise_sse(det, shot, read, cfg.tile_px, sharp), floor)
