r"""The sensor's noise, one model for the whole project: shot plus read noise per colour channel, in linear intensity.

A DP view's pixel value in channel ``c`` (linear units of the dataset, [0, 1]) carries independent Gaussian noise of

.. math::  \sigma_c^2(I) = \text{shot\_var}_c \, I + \text{read\_sigma}_c^2

(``shot_var``: variance per unit intensity, the Poisson part of a sensor whose full well is scaled to 1;
``read_sigma``: standard deviation in linear units). :class:`NoiseModel` holds it, draws it from a seeded numpy or
torch generator (:meth:`NoiseModel.sample`, reproducible), writes and reads it as JSON, and is built

* from a number: :meth:`NoiseModel.parse` (``shot=2e-4,read=2e-3``; per channel ``shot=a:b:c``);
* from a ``dp5k diagnose`` report: :meth:`NoiseModel.from_report` (its pooled ``noise_model``, every channel);
* from a dataset's own views, without any model of the optics: :meth:`NoiseModel.measured` (:func:`measure_views`).

**Measuring without a model.** In each pair the white part ``h`` of ``L - R`` (:data:`WHITE_NOISE_KERNEL`, blind to
anything linear or one-dimensional, so blur, shading, gains and the slowly varying DP disparity of a flat patch
vanish) holds only the two views' independent noise, :math:`E[h^2] = \sigma_L^2 + \sigma_R^2 \approx 2\sigma^2(I)`
with :math:`I = (L + R) / 2` (:data:`WHITE_NOISE_GAIN`). It is read in the flattest :data:`FLAT_QUANTILE` of each
pair's pixels by the local high-pass energy of ``I`` over :data:`FLAT_WINDOW_PX` (where texture is weakest, its DP
disparity is too), away from the border and from clipped values. Per channel, :func:`noise_model_fit` takes the
robust median of :math:`h^2 / 2` (chi^2_1 distributed: median :data:`MEDIAN_CHI2_1` sigma^2) in
:data:`NOISE_INTENSITY_BINS` intensity bins and fits the line ``var = shot_var I + read_sigma^2`` by least squares.
``dp5k diagnose`` (``dp5k_diagnose/noise.py``) measures the same way around a fitted model; the filter, its gain,
the chi^2 constant and the binned line fit are these.

:func:`noise_from_spec` turns ``dp5k synthesize --noise`` into a model: ``none | nominal | measured:DATASET |
diagnosed:REPORT.json | shot=..,read=..``; ``nominal`` is :data:`NOMINAL`, the studio's sensor.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

import numpy as np
from numpy.typing import NDArray

from .dataset import DatasetReader
from .errors import BadInputError
from .io import read_json
from .progress import progress

if TYPE_CHECKING:  # torch is imported where a tensor is handled: the studio's numpy path stays free of its import time
    import torch
    from torch import Tensor

CHANNELS = 3
"""Colour channels of a view (R, G, B)."""

NOMINAL_SHOT_VAR = 2.0e-5
"""The nominal sensor's shot-noise variance per unit linear intensity (a ~50 000 e- full well scaled to [0, 1]); the
studio's direct route and ``dp5k diagnose``'s nominal sensor."""
NOMINAL_READ_SIGMA = 1.0e-3
"""The nominal sensor's read-noise standard deviation, linear units."""

WHITE_NOISE_KERNEL = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]]) / 6.0
r"""The 3 x 3 filter that isolates white noise in ``d`` (Immerkaer 1996): the product of a second difference in x
and one in y, so it is blind to anything linear in x or in y and to what varies along one axis only; its
squared weights sum to 1. The plain high-pass ``d - mean3x3(d)`` passes curvature: on another renderer's set
whose off-axis DP split the base model's field_varying_psf only approximates, that residual read as 1.78 x
the nominal noise variance (named ``noise``, threshold 1.5); this filter reads 1.26 there and 1.01 on a clean
set (1.005 before)."""
WHITE_NOISE_GAIN = 2.0
r"""E[h^2] / sigma^2 for h = :data:`WHITE_NOISE_KERNEL` * (L - R) with independent noise of variance sigma^2
in each view (two views, unit kernel energy)."""
MEDIAN_CHI2_1 = 0.4549364
"""Median of the chi^2 distribution with one degree of freedom (median of z^2 for z ~ N(0, 1))."""
NOISE_INTENSITY_BINS = 8
"""Intensity quantile bins through whose median variances the noise model line is fitted."""

FLAT_WINDOW_PX = 13
"""Window (px, square) over which the local high-pass energy judges a pixel flat (:func:`measure_views`)."""
FLAT_QUANTILE = 0.10
"""Share of each pair's usable pixels, the flattest, in which :func:`measure_views` reads the noise."""
MIN_SAMPLES_PER_CHANNEL = 2000
"""Fewest flat noise samples (pixels) per channel for :func:`measure_views` to fit a line."""


def local_high_pass(x: Tensor) -> Tensor:
    """``x - mean3x3(x)`` (replicated border), (B, C, H, W): local texture energy, to find flat regions."""
    import torch.nn.functional as F

    return x - F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def white_part(x: Tensor) -> Tensor:
    """``x`` (B, C, H, W) filtered by :data:`WHITE_NOISE_KERNEL` (replicated border)."""
    import torch
    import torch.nn.functional as F

    C = x.shape[1]
    k = torch.as_tensor(WHITE_NOISE_KERNEL, dtype=x.dtype, device=x.device).expand(C, 1, 3, 3)
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), k, groups=C)


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


def _per_channel(value: float | Sequence[float], name: str) -> tuple[float, float, float]:
    vals = [float(value)] * CHANNELS if np.isscalar(value) else [float(x) for x in value]  # type: ignore[union-attr, arg-type]
    if len(vals) != CHANNELS or not all(math.isfinite(x) and x >= 0 for x in vals):
        raise BadInputError(f"{name} needs one or {CHANNELS} finite values >= 0, got {value!r}", where="noise model")
    return vals[0], vals[1], vals[2]


Array = NDArray[np.floating]


def _is_tensor(x: Any) -> bool:
    """Whether ``x`` is a torch tensor (without importing torch: no tensor exists before torch is imported)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


@dataclass(frozen=True)
class NoiseModel:
    """Shot plus read noise per colour channel (R, G, B) in linear intensity (module docstring).

    Attributes:
        shot_var: per channel, noise variance per unit linear intensity.
        read_sigma: per channel, read-noise standard deviation (linear units).
        source: where the numbers come from (``nominal``, ``measured:DATASET``, ``diagnosed:REPORT``, ``shot=..``).
    """

    shot_var: tuple[float, float, float]
    read_sigma: tuple[float, float, float]
    source: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "shot_var", _per_channel(self.shot_var, "shot_var"))
        object.__setattr__(self, "read_sigma", _per_channel(self.read_sigma, "read_sigma"))

    @classmethod
    def uniform(cls, shot_var: float, read_sigma: float, source: str = "") -> "NoiseModel":
        """The same shot variance and read sigma in every channel."""
        return cls((shot_var,) * CHANNELS, (read_sigma,) * CHANNELS, source)  # type: ignore[arg-type]

    def scaled(self, gain: float) -> "NoiseModel":
        """The same sensor at ``gain`` x the variance (an ISO ``gain`` x higher for the same image brightness: fewer
        photons per unit intensity and more read noise relative to it); shot_var x gain, read_sigma x sqrt(gain)."""
        if not (gain >= 0 and math.isfinite(gain)):
            raise BadInputError(f"a noise gain must be finite and >= 0, got {gain}", where="noise model")
        return NoiseModel(tuple(s * gain for s in self.shot_var), tuple(r * math.sqrt(gain) for r in self.read_sigma),  # type: ignore[arg-type]
                          f"{self.source} x {gain:.3g}" if self.source else "")

    @overload
    def variance(self, img: Tensor, channel_axis: int | None = None) -> Tensor: ...
    @overload
    def variance(self, img: Array, channel_axis: int | None = None) -> Array: ...

    def variance(self, img: Any, channel_axis: int | None = None) -> Any:
        """Per-pixel noise variance of ``img`` (linear, negative values count as 0), same shape and dtype.

        ``channel_axis``: the colour axis; default -1 for a numpy array ((..., H, W, 3)), -3 for a tensor
        ((..., 3, H, W)), the project's layouts."""
        if _is_tensor(img):
            import torch

            ax = -3 if channel_axis is None else channel_axis
            shape = [1] * img.ndim
            shape[ax] = CHANNELS
            s = torch.tensor(self.shot_var, dtype=img.dtype, device=img.device).view(shape)
            r2 = torch.tensor([r * r for r in self.read_sigma], dtype=img.dtype, device=img.device).view(shape)
            return s * img.clamp(min=0) + r2
        a = np.asarray(img)
        ax = -1 if channel_axis is None else channel_axis
        shape = [1] * a.ndim
        shape[ax] = CHANNELS
        dt = a.dtype if np.issubdtype(a.dtype, np.floating) else np.float64
        s = np.asarray(self.shot_var, dtype=dt).reshape(shape)
        r2 = np.asarray([r * r for r in self.read_sigma], dtype=dt).reshape(shape)  # squared in float64, then cast
        return s * np.maximum(a.astype(dt, copy=False), 0.0) + r2

    @overload
    def sample(self, img: Tensor, generator: torch.Generator, channel_axis: int | None = None) -> Tensor: ...
    @overload
    def sample(self, img: Array, generator: np.random.Generator, channel_axis: int | None = None) -> Array: ...

    def sample(self, img: Any, generator: Any, channel_axis: int | None = None) -> Any:
        """``img`` plus one draw of its noise (:meth:`variance`), same dtype; no clipping.

        A numpy array takes a ``numpy.random.Generator`` (one standard normal per value, in C order), a tensor a
        ``torch.Generator`` on its device; the same generator state gives the same bytes."""
        if _is_tensor(img):
            import torch

            z = torch.randn(img.shape, generator=generator, dtype=img.dtype, device=img.device)
            return img + z * self.variance(img, channel_axis).sqrt()
        a = np.asarray(img)
        dt = a.dtype if np.issubdtype(a.dtype, np.floating) else np.float64
        z = generator.standard_normal(a.shape).astype(dt)
        return (a + z * np.sqrt(self.variance(a, channel_axis)).astype(dt)).astype(dt)

    def to_json(self) -> dict[str, Any]:
        """``{"shot_var": [r, g, b], "read_sigma": [r, g, b], "source": ...}`` (variance per unit intensity, linear sigma)."""
        return {"shot_var": list(self.shot_var), "read_sigma": list(self.read_sigma), "source": self.source}

    @classmethod
    def from_json(cls, obj: Any, where: str | os.PathLike[str] = "noise model") -> "NoiseModel":
        """From :meth:`to_json`'s object (scalars count for every channel)."""
        if not isinstance(obj, dict) or "shot_var" not in obj or "read_sigma" not in obj:
            raise BadInputError("a noise model needs 'shot_var' and 'read_sigma'", where=where)
        try:
            return cls(obj["shot_var"], obj["read_sigma"], str(obj.get("source", "")))
        except (TypeError, ValueError) as exc:
            raise BadInputError(f"bad noise model ({exc})", where=where) from exc

    @classmethod
    def parse(cls, text: str) -> "NoiseModel":
        """``shot=2e-4,read=2e-3`` (every channel) or per channel ``shot=a:b:c,read=x:y:z`` (R:G:B); both keys needed."""
        vals: dict[str, list[float]] = {}
        for part in (p.strip() for p in text.split(",") if p.strip()):
            key, sep, value = part.partition("=")
            if not sep or key.strip() not in ("shot", "read"):
                raise BadInputError(f"expected shot=..,read=.. (per channel shot=a:b:c), got {text!r}", where="--noise")
            try:
                vals[key.strip()] = [float(v) for v in value.split(":")]
            except ValueError as exc:
                raise BadInputError(f"{key.strip()} must be numbers, got {value!r}", where="--noise") from exc
        if set(vals) != {"shot", "read"}:
            raise BadInputError(f"both shot= and read= are needed, got {text!r}", where="--noise")
        shot, read = (v[0] if len(v) == 1 else v for v in (vals["shot"], vals["read"]))
        try:
            return cls(shot, read, text)  # type: ignore[arg-type]
        except BadInputError as exc:
            raise BadInputError(exc.message, where="--noise") from exc

    @classmethod
    def from_report(cls, report: str | os.PathLike[str]) -> "NoiseModel":
        """The pooled noise a ``dp5k diagnose`` report measured (``noise_model``: ``shot_var``, ``read_sigma``), in
        every channel.

        Raises:
            BadInputError: missing or unreadable file, or a report without a measured noise model.
        """
        obj = read_json(report)
        nm = obj.get("noise_model") if isinstance(obj, dict) else None
        if not isinstance(nm, dict):
            raise BadInputError("no 'noise_model' (not a dp5k diagnose report?)", where=report)
        if not nm.get("measured", False) or "shot_var" not in nm or "read_sigma" not in nm:
            raise BadInputError(f"the report measured no noise model ({nm.get('note', 'no reason given')})", where=report)
        return cls.uniform(float(nm["shot_var"]), float(nm["read_sigma"]), f"diagnosed:{report}")

    @classmethod
    def measured(cls, dataset: str | os.PathLike[str], max_pairs: int = 0) -> "NoiseModel":
        """The noise of a format-v1 dataset's views, measured from the views alone (:func:`measure_views`).

        ``max_pairs`` > 0 reads only that many pairs (every split, in order)."""
        return measure_views(dataset, max_pairs).model


NOMINAL = NoiseModel.uniform(NOMINAL_SHOT_VAR, NOMINAL_READ_SIGMA, "nominal")
"""The nominal sensor (the studio's direct route, ``dp5k diagnose``'s nominal): variance ``2e-5 I + (1e-3)^2``."""


@dataclass(frozen=True)
class NoiseMeasurement:
    """What :func:`measure_views` found.

    Attributes:
        model: the fitted :class:`NoiseModel` (negative fits clipped to 0).
        samples: flat noise samples (pixels) in each channel.
        pairs: pairs read.
    """

    model: NoiseModel
    samples: int
    pairs: int


def flat_noise_samples(left: Tensor, right: Tensor) -> tuple[Tensor, Tensor]:
    r"""Noise samples of one pair, (B, 3, H, W) views each: per channel, :math:`h^2 / 2` (:data:`WHITE_NOISE_GAIN`;
    an unbiased estimate of one view's :math:`\sigma^2`) and :math:`I = (L + R) / 2` at the flattest
    :data:`FLAT_QUANTILE` of each image's pixels (module docstring), away from the border and clipped values.

    Returns:
        (v, I): each (3, n), channels by samples (n = 0 when no image has enough usable pixels)."""
    import torch
    import torch.nn.functional as F

    d = left - right
    v = white_part(d) ** 2 / WHITE_NOISE_GAIN
    inten = (left + right) / 2
    k = FLAT_WINDOW_PX | 1
    energy = (local_high_pass(inten) ** 2).sum(1, keepdim=True)
    energy = F.avg_pool2d(F.pad(energy, (k // 2,) * 4, mode="replicate"), k, stride=1)[:, 0]
    clipped = ((left <= 0) | (left >= 1) | (right <= 0) | (right >= 1)).any(1, keepdim=True).float()
    use = F.max_pool2d(clipped, 3, stride=1, padding=1)[:, 0] == 0  # the 3 x 3 filter sees no clipped value
    use[:, :1] = use[:, -1:] = False
    use[:, :, :1] = use[:, :, -1:] = False
    vs, Is = [], []
    for i in range(left.shape[0]):
        if int(use[i].sum()) < 16:
            continue
        flat = use[i] & (energy[i] <= torch.quantile(energy[i][use[i]], FLAT_QUANTILE))
        vs.append(v[i][:, flat])
        Is.append(inten[i][:, flat])
    if not vs:
        return torch.zeros(CHANNELS, 0, dtype=left.dtype), torch.zeros(CHANNELS, 0, dtype=left.dtype)
    return torch.cat(vs, 1), torch.cat(Is, 1)


def measure_views(dataset: str | os.PathLike[str], max_pairs: int = 0) -> NoiseMeasurement:
    """Measure the views' noise model of a format-v1 dataset without any model of its optics (module docstring).

    Raises:
        BadInputError: not a dataset, or fewer than :data:`MIN_SAMPLES_PER_CHANNEL` flat samples per channel.
    """
    import torch

    reader = DatasetReader(dataset)
    ids = reader.ids()
    if max_pairs > 0:
        ids = ids[:max_pairs]
    vs: list[Tensor] = []
    Is: list[Tensor] = []
    for pid in progress(ids, desc="measure noise", unit="pair"):
        pair = reader.load(pid)
        to_t = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None].double()  # noqa: E731
        v, inten = flat_noise_samples(to_t(pair.left), to_t(pair.right))
        vs.append(v)
        Is.append(inten)
    v_all = torch.cat(vs, 1).numpy() if vs else np.zeros((CHANNELS, 0))
    i_all = torch.cat(Is, 1).numpy() if Is else np.zeros((CHANNELS, 0))
    n = v_all.shape[1]
    if n < MIN_SAMPLES_PER_CHANNEL:
        raise BadInputError(f"too few flat pixels to measure the noise ({n} of {MIN_SAMPLES_PER_CHANNEL} needed)", where=dataset)
    shot, read = [], []
    for c in range(CHANNELS):
        _, coef = noise_model_fit(v_all[c], i_all[c], np.ones_like(v_all[c]))
        shot.append(max(float(coef[0]), 0.0))
        read.append(math.sqrt(max(float(coef[1]), 0.0)))
    return NoiseMeasurement(NoiseModel(tuple(shot), tuple(read), f"measured:{dataset}"), n, len(ids))  # type: ignore[arg-type]


NOISE_SPEC_SYNTAX = "none | nominal | measured:DATASET | diagnosed:REPORT.json | shot=S,read=R (per channel S:S:S)"
"""The ``--noise`` forms :func:`noise_from_spec` reads."""


def noise_from_spec(spec: str) -> NoiseModel | None:
    """The noise model a ``--noise`` spec names (:data:`NOISE_SPEC_SYNTAX`); None for ``none``.

    Raises:
        BadInputError: an unknown form, a bad number, an unreadable dataset or report (each names its file)."""
    text = spec.strip()
    if text == "none":
        return None
    if text == "nominal":
        return NOMINAL
    if text.startswith("measured:"):
        return NoiseModel.measured(Path(text[len("measured:"):]))
    if text.startswith("diagnosed:"):
        return NoiseModel.from_report(Path(text[len("diagnosed:"):]))
    if "=" in text:
        return NoiseModel.parse(text)
    raise BadInputError(f"unknown noise {spec!r}; expected {NOISE_SPEC_SYNTAX}", where="--noise")
