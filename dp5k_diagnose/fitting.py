"""Fitting the physical base model on the fit crops (:func:`fit_base`) and the helpers every extension's fit
shares."""

from __future__ import annotations

import copy

import torch

from neural_dp.registry import BaseModel, fit_parameters

from .data import Sample


def copy_base(base: BaseModel) -> BaseModel:
    """A copy of ``base`` with copies of its components (an extended model's effects stay, and fitting the
    copy's parameters leaves ``base`` as it was)."""
    return base.replaced([copy.deepcopy(c) for c in base.components])


PSF_NUISANCE = ("rim_softness_px", "pixel_box")
"""The base model's parameters that shape every PSF without being a lens effect (the residual blur and the
pixel sampling): refitted with every effect that changes blur, since each trades off against it."""


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


def covered_field_box(samples: list[Sample]) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the field (coordinates in [-1, 1]) the samples' scored pixels span."""
    xs = [s.field[:, 0][s.score[:, 0]] for s in samples]
    ys = [s.field[:, 1][s.score[:, 0]] for s in samples]
    x, y = torch.cat(xs), torch.cat(ys)
    if x.numel() == 0:
        return (-1.0, 1.0, -1.0, 1.0)
    return (float(x.min()), float(x.max()), float(y.min()), float(y.max()))
