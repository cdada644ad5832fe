r"""The views' noise, measured: white noise in flat regions against a nominal sensor (:func:`measure_noise`) and the
noise model ``var = shot_var I + read_sigma^2`` with bootstrap intervals.

``noise`` cannot be predicted (a simulator's output is an expectation), so it is measured rather than fitted: the
white part of ``L - R`` in flat regions (:func:`flat_lr_noise`) against the nominal variance. Its signature is the
variance ratio (:func:`dp5k_diagnose.measure.noise_signature`); the measured model also gives a simulator's renders
the views' noise before their atlas is measured.
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

from .config import DiagnoseConfig
from .data import Sample


@dataclass(frozen=True)
class Flatness:
    """Where the views count as flat: the flattest ``quantile`` of the usable pixels by their local high-pass energy
    over ``window_px``."""

    window_px: int = 13
    quantile: float = 0.10


FLAT = Flatness()


def flat_pixels(images: tuple[Tensor, ...], use: Tensor, cfg: Flatness) -> Tensor:
    """(B, H, W) bool: the flattest ``cfg.quantile`` of the ``use`` pixels (B, H, W) of each image by the local
    high-pass energy (over ``cfg.window_px``) of ``images`` (each (B, C, H, W): the predicted views, or ``sharp``),
    away from the image border (the 3 x 3 filters need neighbours); none in an image with too few usable pixels."""
    k = cfg.window_px | 1
    energy = sum((_high_pass(im) ** 2).sum(1, keepdim=True) for im in images)
    energy = F.avg_pool2d(F.pad(energy, (k // 2,) * 4, mode="replicate"), k, stride=1)[:, 0]
    use = use.clone()
    use[:, :1] = use[:, -1:] = False
    use[:, :, :1] = use[:, :, -1:] = False
    out = torch.zeros_like(use)
    for i in range(use.shape[0]):
        if int(use[i].sum()) >= MIN_NOISE_PX_PER_IMAGE:
            out[i] = use[i] & (energy[i] <= torch.quantile(energy[i][use[i]], cfg.quantile))
    return out


def flat_lr_noise(samples: list[Sample], cfg: Flatness, base: BaseModel | None = None,
                  predictions: list[tuple[Tensor, Tensor]] | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
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
    for k, s in enumerate(samples):
        b = s.batch
        d = b.left - b.right
        if base is None:
            flat = flat_pixels((b.sharp,), b.valid[:, 0], cfg)
        else:
            if predictions is not None:
                pl, pr = predictions[k]
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


@dataclass
class NoiseMeasure:
    """The views' white noise, measured in flat regions against a model's prediction (:func:`measure_noise`).

    Attributes:
        measured: False when too few flat pixels were found (``note`` says why).
        variance_ratio: the views' noise variance over the nominal sensor's (robust, pooled over pairs).
        ratio_boot: (B,) the ratio under a bootstrap over pairs.
        shot_var, read_sigma: the noise model ``var = shot_var I + read_sigma^2`` (linear units) fitted to it.
        intervals: 95 % bootstrap intervals of shot_var, read_sigma and variance_ratio.
    """

    measured: bool
    variance_ratio: float = 1.0
    ratio_boot: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    shot_var: float = 0.0
    read_sigma: float = 0.0
    intervals: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    note: str = ""


def measure_noise(base: BaseModel, samples: list[Sample], cfg: DiagnoseConfig,
                  predictions: list[tuple[Tensor, Tensor]] | None = None) -> NoiseMeasure:
    r"""The views' white noise from :func:`flat_lr_noise` (flatness and the L - R signal predicted by ``base``):
    per pixel :math:`z = \hat\sigma^2 / \sigma^2_{nom}(I)`, the pooled robust variance ratio and the noise model
    ``var = shot_var I + read_sigma^2`` (:func:`dp5k_common.sensor_noise.noise_model_fit`), with a bootstrap over
    pairs of each pair's own fit weighted by its samples (:func:`noise_model_draws`). ``predictions``: ``base``'s views of
    ``samples``, when they are rendered already."""
    var, inten = flat_lr_noise(samples, FLAT, base, predictions)
    if sum(v.size for v in var) < MIN_NOISE_SAMPLES:
        return NoiseMeasure(False, note="too few flat valid pixels to measure noise")
    nominal = [cfg.nominal_shot_var * np.maximum(i, 0) + cfg.nominal_read_sigma**2 for i in inten]
    rho, coef = noise_model_fit(np.concatenate(var), np.concatenate(inten), np.concatenate(nominal))
    draws = noise_model_draws(var, inten, nominal, cfg.seed)
    a = (1 - INTERVAL_LEVEL) / 2
    intervals = {} if draws.size == 0 else {k: (float(np.quantile(draws[:, j], a)), float(np.quantile(draws[:, j], 1 - a)))
                                            for j, k in enumerate(("shot_var", "read_sigma", "variance_ratio"))}
    return NoiseMeasure(True, float(rho), draws[:, 2] if draws.size else np.zeros(0), float(max(coef[0], 0.0)),
                        float(math.sqrt(max(coef[1], 0.0))), intervals)


NOISE_BOOT = 200
"""Bootstrap resamples (over pairs) of the noise model's intervals."""


INTERVAL_LEVEL = 0.95
"""Level of every parameter interval diagnose reports."""


RATIO_BINS = np.linspace(-12.0, 8.0, 801)
"""Bins of ln(v / nominal) for the variance ratio's bootstrap (0.025 wide: the median within 2.5 %)."""


def noise_model_draws(var: list[np.ndarray], inten: list[np.ndarray], nominal: list[np.ndarray], seed: int = 0) -> np.ndarray:
    """(NOISE_BOOT, 3) bootstrap draws over pairs of (shot_var, read_sigma, variance_ratio); empty with fewer than 2
    pairs that hold noise samples.

    The ratio is the pooled robust ratio (the median of every sample's ``v / nominal`` over that of chi^2_1) of each
    resample, read off the pairs' histograms of ln(v / nominal) summed with the resample's counts. shot_var and
    read_sigma are the resample's weighted means of each pair's own line (pairs of at least
    :data:`MIN_PAIR_NOISE_SAMPLES` samples), as the report's intervals."""
    used = [k for k, v in enumerate(var) if v.size >= MIN_PAIR_NOISE_SAMPLES]
    if len(used) < 2:
        return np.zeros((0, 3))
    hists = np.stack([np.histogram(np.log(np.maximum(var[k] / nominal[k], 1e-30)), RATIO_BINS)[0] for k in used]).astype(np.float64)
    lines = np.array([noise_model_fit(var[k], inten[k], nominal[k])[1] for k in used])  # (P, 2): shot_var, read_sigma^2
    sizes = np.array([var[k].size for k in used], dtype=np.float64)
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(len(used), np.full(len(used), 1.0 / len(used)), size=NOISE_BOOT).astype(np.float64)  # (B, P)
    cum = np.cumsum(counts @ hists, axis=1)  # (B, bins)
    half = cum[:, -1:] / 2
    j = (cum < half).sum(1)
    centres = (RATIO_BINS[:-1] + RATIO_BINS[1:]) / 2
    ratio = np.exp(centres[np.clip(j, 0, len(centres) - 1)]) / MEDIAN_CHI2_1
    w = counts * sizes[None]
    m = w @ np.maximum(lines, 0.0) / w.sum(1, keepdims=True)
    return np.stack([m[:, 0], np.sqrt(m[:, 1]), ratio], 1)


