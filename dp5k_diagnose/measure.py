r"""Measuring: the camera's atlas from the measured views, a simulator's atlas from its renders of the same pairs, and
every effect's signature between the two (:class:`Measurement`).

The simulator's renders get the views' own measured noise (shot + read, drawn from a seeded generator) before they
are measured: the kernels' moments are ratios, whose noise bias would otherwise read as a difference between two
atlases that differ only in noise.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from neural_dp.registry import BaseModel

from .atlas import Atlas, AtlasMeasurer, PairImages, Views
from .config import DiagnoseConfig
from .data import Sample
from .explain import colour_contrast, GREY_MAX_COLOUR_CONTRAST
from .noise import NoiseMeasure, measure_noise
from .signatures import (Pairing, Signature, Value, chromatic_signature, disparity_signature, field_signature, focus_signature,
                         front_back_signature, lr_gain_signature, misregistration_signature, profile_signature)

Render = Callable[[Sample], tuple[torch.Tensor, torch.Tensor]]


def pair_images(samples: Sequence[Sample]) -> list[PairImages]:
    """The atlas's view of whole-image samples (one pair each)."""
    return [PairImages(s.batch.pair_ids[0], s.batch.sharp[0].numpy(), s.batch.coc_px[0, 0].numpy(), s.score[0, 0].numpy(),
                       s.field[0].numpy()) for s in samples]


def pair_scales(samples: Sequence[Sample]) -> dict[str, np.ndarray]:
    """Per pair (P,), by the thin lens (Eq. 6, ``c = (f/N) (v/f - 1 - v/Z) / pitch`` px, ``1/v = 1/f - 1/F``): its
    CoC at infinity ``coc_at_infinity_px`` (how far a focus error that scales with the focus distance moves its CoC)
    and ``aperture_px = (f/N) v / pitch``, the CoC per dioptre (mm^-1) of depth (how far a focal-length shift or a
    focus error in dioptres moves it)."""
    f = np.array([float(s.batch.focal_length_mm[0]) for s in samples])
    N = np.array([float(s.batch.f_number[0]) for s in samples])
    F = np.array([float(s.batch.focus_distance_mm[0]) for s in samples])
    pitch = np.array([float(s.batch.pixel_pitch_mm[0]) for s in samples])
    v = 1.0 / np.maximum(1.0 / f - 1.0 / np.maximum(F, 1.05 * f), 1e-12)
    return {"coc_at_infinity_px": (f / N) * (v / f - 1.0) / pitch, "aperture_px": (f / N) * v / pitch}


def measured_views(samples: Sequence[Sample]) -> list[Views]:
    return [(s.batch.left[0].numpy(), s.batch.right[0].numpy()) for s in samples]


def render_all(render: Render, samples: Sequence[Sample]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each pair rendered (noise free)."""
    with torch.no_grad():
        return [render(s) for s in samples]


def rendered_views(renders: Sequence[tuple[torch.Tensor, torch.Tensor]], noise: tuple[float, float] | None, seed: int) -> list[Views]:
    """Each pair's render with white noise of variance ``shot I + read^2`` added (``noise``; None: none) from a
    generator seeded per pair."""
    out = []
    for i, (l, r) in enumerate(renders):
        views = [l[0].numpy().astype(np.float32), r[0].numpy().astype(np.float32)]
        if noise is not None:
            rng = np.random.default_rng([seed, 7919, i])
            shot, read = noise
            views = [v + rng.standard_normal(v.shape).astype(np.float32) * np.sqrt(np.maximum(shot * np.clip(v, 0, None) + read * read, 0))
                     for v in views]
        out.append((views[0], views[1]))
    return out


def noise_signature(noise: NoiseMeasure, cfg: DiagnoseConfig) -> Signature:
    """The views' white-noise variance over the nominal sensor's, minus 1 (its minimum: ``noise_min_ratio`` - 1)."""
    if not noise.measured:
        return Signature("noise", unmeasured=noise.note)
    if noise.variance_ratio < 1.0:  # only noise beyond the nominal sensor's is an effect: less is a quieter sensor
        return Signature("noise", [Value("variance_ratio_minus_1", "1", 0.0, np.zeros(max(noise.ratio_boot.size, 10)),
                                         cfg.noise_min_ratio - 1.0, noise.variance_ratio, 1.0)])
    return Signature("noise", [Value("variance_ratio_minus_1", "1", noise.variance_ratio - 1.0, noise.ratio_boot - 1.0,
                                     cfg.noise_min_ratio - 1.0, noise.variance_ratio, 1.0)])


@dataclass
class Measurement:
    """The measured side of a diagnosis, measured once, and the simulator side, re-measured per model.

    Attributes:
        samples: one whole-image sample per pair (every split).
        measurer: the atlas's measurer (masks, pixel draws, normal equations: the sharp side, done once).
        noise: the views' measured noise (:func:`dp5k_diagnose.noise.measure_noise`).
        colour: whether the data has colour (R, G and B differ beyond noise).
    """

    samples: list[Sample]
    measurer: AtlasMeasurer
    noise: NoiseMeasure
    colour: bool
    cfg: DiagnoseConfig
    base: BaseModel | None = None
    base_renders: list[tuple[torch.Tensor, torch.Tensor]] | None = None
    """The base model and its renders of every pair: the noise is measured against them and the simulator's atlas of
    the base model is measured from them (rendered once)."""
    last_renders: dict[str, list[tuple[torch.Tensor, torch.Tensor]]] = field(default_factory=dict)
    """Per view-set, the renders its atlas was last measured from."""

    @classmethod
    def of(cls, samples: Sequence[Sample], base: BaseModel, cfg: DiagnoseConfig) -> "Measurement":
        samples = list(samples)
        measurer = AtlasMeasurer(pair_images(samples), cfg.n_boot, cfg.seed)
        renders = render_all(lambda s: base.render(s.batch, s.field), samples)
        noise = measure_noise(base, samples, cfg, renders)
        measurer.measure("measured", measured_views(samples), (noise.shot_var, noise.read_sigma) if noise.measured else None)
        return cls(samples, measurer, noise, colour_contrast(samples) > GREY_MAX_COLOUR_CONTRAST, cfg, base, renders)

    @property
    def atlas(self) -> Atlas:
        return self.measurer.atlas

    def simulator(self, render: Render, name: str = "model", renders: list[tuple[torch.Tensor, torch.Tensor]] | None = None) -> Atlas:
        """Measure ``render``'s atlas on the same pairs (with the views' noise), as view-set ``name`` (``renders``: its
        views of every pair, when rendered already)."""
        noise = (self.noise.shot_var, self.noise.read_sigma) if self.noise.measured else None
        renders = renders if renders is not None else render_all(render, self.samples)
        self.last_renders[name] = renders
        self.measurer.measure(name, rendered_views(renders, noise, self.cfg.seed), noise)
        return self.atlas

    def noise_against(self, model: BaseModel, name: str = "extended") -> NoiseMeasure:
        """The views' noise measured against ``model``, whose atlas was last measured as view-set ``name`` (its renders
        are reused): the named causes leave less structure in the flat regions' L - R than the base model does."""
        renders = self.last_renders.get(name)
        return measure_noise(model, self.samples, self.cfg, renders)

    def signatures(self, model: str = "model") -> dict[str, Signature]:
        """Every effect's signature, measured minus ``model``'s atlas."""
        p = Pairing(self.atlas, "measured", model, pair_scales=pair_scales(self.samples))
        out = [lr_gain_signature(self.atlas, p), field_signature(self.atlas, p), chromatic_signature(p, self.colour),
               disparity_signature(p), focus_signature(p), profile_signature(self.atlas, p), front_back_signature(p),
               misregistration_signature(p), noise_signature(self.noise, self.cfg)]
        return {s.effect: s for s in out}

    def of_model(self, model: BaseModel, name: str = "model") -> dict[str, Signature]:
        """Measure ``model``'s atlas as view-set ``name`` (again, when it was) and read every signature against it."""
        self.simulator(lambda s: model.render(s.batch, s.field), name, self.base_renders if model is self.base else None)
        return self.signatures(name)
