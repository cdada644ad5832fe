r"""Every cause, in order: a screen, the full model, backward elimination on held-out pairs, look-alikes.

Forward selection (add the best effect, repeat) takes a look-alike first when two effects hide each other,
and two effects that partly cancel may each make the fit worse alone, so neither enters
(``../shared/notes/model-selection.md``: masking). The selection here starts from every plausible effect at
once and removes what the held-out pairs do not need:

1. **Screen** (:func:`screen_effects`). Around the fitted base model, one Jacobian of every effect's
   parameters (and of the base model's gain, rim softness and pixel sampling) on the fit and detection crops.
   The squared error bounded Gauss-Newton steps predict each effect removes (the score test's quantity, as a
   share of the crops' systematic error): greedily, the effect that adds most to those taken while it adds at
   least :attr:`SelectConfig.screen_share` of its threshold, and every effect whose unique part of the joint
   step of all effects is that large (two effects that cancel alone). The same Jacobian gives each pair of
   effects' largest canonical correlation (how far the data separates them).
2. **Full model.** Every screened effect fitted together (Levenberg-Marquardt from the joint step).
3. **Backward elimination** on the detection pairs, which no fit saw. For each effect E of the current set
   S, the model without E (the others refitted, to first order, from the full model's Jacobian) is compared
   with S pair by pair: :math:`\Delta_i = \ln(\mathrm{SSE}_i(S \setminus E) / \mathrm{SSE}_i(S))`,
   Wilcoxon's signed-rank test, Hochberg's step-up correction over S, and E's unique share of the systematic
   error must exceed its threshold. While any effect fails, the weakest (largest p) is removed.
4. **Confirmation** with real refits: the survivors' model and the model without each one are refitted
   (nonlinear) and tested again the same way; of the effects that fail, the one whose removal costs the
   detection pairs least is removed and the rest re-confirmed.
   The models without each cause are what each cause's held-out gain given the others is measured against.
   A **re-screen** around the confirmed model proposes the effects it masked; the larger full model they make
   is eliminated and confirmed in turn, and replaces the confirmed model only when the detection pairs prefer
   it (:func:`predicts_better`). Each re-screen is first done at first order on the last screen's Jacobian
   columns with the confirmed model's exact residual (:func:`first_order_rescreen`, one render); when no
   effect comes within :attr:`SelectConfig.prescreen_margin` of the bar, the exact re-screen is not run.
5. **Look-alikes** (:func:`find_lookalikes`): each named cause C is swapped for every effect F whose
   Jacobian correlates with C's; when F, refitted in C's place, predicts the detection pairs as well as C
   (not significantly and materially worse) while explaining what C explained, the two are reported
   together as indistinguishable on this data, with the capture that would separate them
   (:data:`SEPARATING_CAPTURE`). Of two such, the one with fewer parameters is named
   (:func:`name_the_simpler`).

``noise`` is a measurement, not a structural effect (a simulator's output is an expectation): it is measured
against the final model and named after the structural causes when its excess is significant.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dp5k_common.effects import EFFECT_NAMES
from dp5k_common.progress import progress
from neural_dp.registry import COMPONENTS, BaseModel, Linearization, clustered_intervals, fittable_names, get_values, jacobian, lm_fit, residual_vector, set_values

from .config import DetectConfig, SelectConfig
from .data import Sample
from .findings import GREY_MAX_COLOUR_CONTRAST, Finding, _finite, colour_contrast, explanation, not_testable
from .fitting import PSF_NUISANCE, covered_field_box
from .noise import SharpNoise, measured_noise, noise_sse, noise_tile_sse, sharp_noise, systematic_sse, test_noise
from .tiles import clustered_delta, effect_test, hochberg_passed, kept_tiles, tile_mse, tile_sums, unit_sums

log = logging.getLogger(__name__)

Key = tuple[str, str]
"""A parameter by (owner, name): owner ``"base"`` or a component's effect name."""

SEPARATING_CAPTURE: dict[frozenset[str], str] = {
    frozenset({"lr_gain_imbalance", "field_varying_psf"}): "a flat field (a uniform, defocused target filling the frame): a gain ramp changes the L/R brightness ratio of flat content, a split leaking toward the edges does not",
    frozenset({"lr_gain_imbalance", "disparity_scale"}): "a flat field: a gain imbalance changes the L/R brightness ratio of flat content, crosstalk only mixes the views' blur",
    frozenset({"lr_gain_imbalance", "misregistration"}): "a flat field and an in-focus target: a gain changes brightness, a shift moves edges",
    frozenset({"field_varying_psf", "disparity_scale"}): "a textured plane filling the frame at one defocus: crosstalk is the same everywhere, a leaking split grows toward the edges",
    frozenset({"field_varying_psf", "psf_profile"}): "point sources (small LEDs) defocused at the centre and at the edges of the field",
    frozenset({"field_varying_psf", "front_back_asymmetry"}): "a textured plane filling the frame, in front of and behind focus",
    frozenset({"field_varying_psf", "focus_offset"}): "a textured plane filling the frame at the recorded focus distance: a focus error blurs it everywhere, a field-varying PSF only off axis",
    frozenset({"field_varying_psf", "misregistration"}): "an in-focus target filling the frame: a shift moves every edge alike",
    frozenset({"chromatic_defocus", "focus_offset"}): "a black-and-white target at the recorded focus distance: a focus error blurs every colour alike, chromatic defocus blurs red and blue but not green",
    frozenset({"chromatic_defocus", "psf_profile"}): "a black-and-white target in and out of focus: chromatic defocus changes the colour of edges",
    frozenset({"chromatic_defocus", "front_back_asymmetry"}): "a black-and-white target in front of and behind focus",
    frozenset({"disparity_scale", "psf_profile"}): "point sources (small LEDs) at several defocus distances: crosstalk puts light of one half disc into the other view, a non-uniform disc does not",
    frozenset({"disparity_scale", "front_back_asymmetry"}): "point sources in front of and behind focus",
    frozenset({"disparity_scale", "focus_offset"}): "a second focus distance (a focus bracket of the same scene): a focus error moves where disparity vanishes, crosstalk scales it everywhere",
    frozenset({"disparity_scale", "misregistration"}): "an in-focus target: misregistration shifts it, crosstalk does not",
    frozenset({"focus_offset", "psf_profile"}): "a second focus distance (a focus bracket): a focus error moves the in-focus depth, a non-uniform disc does not",
    frozenset({"focus_offset", "front_back_asymmetry"}): "a second focus distance (a focus bracket): a focus error moves the in-focus depth",
    frozenset({"focus_offset", "misregistration"}): "an in-focus target at the recorded focus distance",
    frozenset({"psf_profile", "front_back_asymmetry"}): "content on both sides of focus (a slanted plane through the focus distance): an asymmetry differs between the sides, a non-uniform disc does not",
    frozenset({"psf_profile", "misregistration"}): "an in-focus target: misregistration shifts it",
    frozenset({"front_back_asymmetry", "misregistration"}): "an in-focus target: misregistration shifts it",
    frozenset({"lr_gain_imbalance", "chromatic_defocus"}): "a flat field in white light",
    frozenset({"lr_gain_imbalance", "focus_offset"}): "a flat field and a focus bracket",
    frozenset({"lr_gain_imbalance", "psf_profile"}): "a flat field and point sources",
    frozenset({"lr_gain_imbalance", "front_back_asymmetry"}): "a flat field and point sources on both sides of focus",
    frozenset({"chromatic_defocus", "disparity_scale"}): "a black-and-white target out of focus",
    frozenset({"chromatic_defocus", "field_varying_psf"}): "a black-and-white target filling the frame",
    frozenset({"chromatic_defocus", "misregistration"}): "a black-and-white target in focus",
}
"""The capture that separates two look-alikes (what differs between their predictions)."""


def separating_capture(a: str, b: str) -> str:
    return SEPARATING_CAPTURE.get(frozenset({a, b}), "pairs with content on both sides of focus in every part of the field")


@dataclass
class Screen:
    """The first-order screen around the fitted base model (:func:`screen_effects`).

    Attributes:
        share: per effect, the larger of its alone and unique predicted reductions of the fit crops' squared
            error, as a share of their systematic error.
        alone, unique: the two, separately (shares).
        corr: per pair of effects (sorted names), the largest canonical correlation of their Jacobians with
            the base model's parameters projected out (1: the fit crops cannot tell them apart to first order).
        values: per effect, its parameters after the joint step of the screened effects (a starting point).
        candidates: the effects that pass, in vocabulary order.
    """

    share: dict[str, float]
    alone: dict[str, float]
    unique: dict[str, float]
    corr: dict[tuple[str, str], float]
    values: dict[Key, float]
    candidates: list[str]
    systematic: float = 0.0
    """The fit crops' systematic squared error the shares are measured on."""
    lin: Linearization | None = field(default=None, repr=False)
    """The linearization it was measured from (:func:`screen_effects`; dropped when no longer needed)."""
    keys: list[Key] = field(default_factory=list, repr=False)
    """``lin``'s parameters as (owner, name) keys."""

    def correlation(self, a: str, b: str) -> float:
        return self.corr.get(tuple(sorted((a, b))), 0.0)  # type: ignore[arg-type]

    def to_json(self) -> dict[str, Any]:
        return {"share": dict(self.share), "alone": dict(self.alone), "unique": dict(self.unique), "candidates": list(self.candidates),
                "correlation": {f"{a}|{b}": _finite(v) for (a, b), v in sorted(self.corr.items())}}


@dataclass
class Test:
    """One effect tested given the others: the model without it against the model with it, on the detection
    pairs (statistic and p of the signed-rank test; effect size: the share of the systematic error of the model
    without it that it removes, :func:`informed_test`)."""

    effect: str
    statistic: float
    p_value: float
    effect_size: float
    passed: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "statistic": _finite(self.statistic), "p_value": _finite(self.p_value, 1.0),
                "effect_size": _finite(self.effect_size), "passed": bool(self.passed)}


@dataclass
class Selection:
    """What :func:`select_causes` found.

    Attributes:
        causes: the structural causes, strongest unique contribution first.
        model: the base model with every cause, fitted (the base model when there is none).
        steps: per cause k, the model holding causes 1..k (the last is ``model``).
        without: per cause, ``model`` without it, the others refitted (the fitted base model for one cause).
        findings: one per effect of the vocabulary: named (its test given the other causes), eliminated (its
            test when it was removed), screened out (its screen share) or not testable; ``noise`` measured.
        lookalikes: groups of effects the data cannot tell apart: ``{"names", "capture", "correlation",
            "effect_size_lost", "p_value"}``; the first name is the named cause.
        trace: the screen, the elimination rounds and the confirmation rounds, for the report.
        noise: the noise finding against ``model``.
    """

    causes: list[str]
    model: BaseModel
    steps: list[BaseModel] = field(default_factory=list)
    without: list[BaseModel] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)
    lookalikes: list[dict[str, Any]] = field(default_factory=list)
    trace: dict[str, Any] = field(default_factory=dict)
    noise: Finding | None = None
    lin: Linearization | None = field(default=None, repr=False)
    """The final model's linearization on the fit crops (intervals, first-order step models)."""
    context: Any = field(default=None, repr=False)
    """The :class:`Context` it was made in (:func:`drop_cause`)."""

    @property
    def names(self) -> list[str]:
        """The causes in order: the structural ones, then ``noise`` when its excess is significant."""
        return self.causes + (["noise"] if self.noise is not None and self.noise.detected else [])

    def extended(self) -> BaseModel:
        """The final model, with the measured noise model when ``noise`` is named (it leaves the predicted views
        unchanged)."""
        if self.noise is not None and self.noise.detected and self.noise.model is not None:
            return self.model.with_component(self.noise.model.component("noise"))
        return self.model


# -- models as parameter dictionaries -------------------------------------------------------------------------


def owner_key(model: BaseModel, owner: object) -> str:
    return "base" if owner is model else owner.name  # type: ignore[attr-defined]


def targets_of(model: BaseModel, fit: Sequence[Sample]) -> list[tuple[object, str]]:
    """Every parameter of ``model`` the fit crops constrain: each component's fittable ones, the gain, and the
    PSF nuisance (:data:`fitting.PSF_NUISANCE`, the rim softness and pixel sampling).

    The nuisance is refitted with every model, including one whose effects only change the views: the base
    fit blurs to soften an error it cannot model (a planted 1 px misregistration drove its rim softness from
    0.15 to 0.80 px and its pixel sampling from box to triangle), and with that blur held the misregistration
    model left 450 x the detection error it leaves refitted."""
    out: list[tuple[object, str]] = []
    for c in model.components:
        out += [(c, n) for n in fittable_names(c, fit)]
    return out + [(model, "gain")] + [(model, k) for k in PSF_NUISANCE]


def key_values(model: BaseModel, targets: Sequence[tuple[object, str]], x: np.ndarray | None = None) -> dict[Key, float]:
    x = get_values(targets) if x is None else x
    return {(owner_key(model, o), n): float(v) for (o, n), v in zip(targets, x)}


def submodel(model: BaseModel, names: Sequence[str], values: dict[Key, float] | None = None) -> BaseModel:
    """A copy of ``model`` holding only the components ``names`` (copies), with ``values`` written in."""
    return with_values(model.replaced([copy.deepcopy(c) for c in model.components if c.name in names]), values or {})


def held_neutral(lin: Linearization, model: BaseModel, names: Sequence[str], neutral: dict[str, dict[str, float]]) -> dict[int, float]:
    """Linearization indices of the effects ``names``' parameters, mapped to their neutral values."""
    out = {}
    for i, (o, n) in enumerate(lin.targets):
        k = owner_key(model, o)
        if k in names:
            out[i] = neutral[k][n]
    return out


# -- the statistics of one comparison ---------------------------------------------------------------------------


@dataclass
class Eval:
    """A model on the detection pairs: per kept tile squared errors, and its predicted views (per sample,
    (B, 6, H, W)) to compare it with another model."""

    su: np.ndarray
    pred: list[Tensor]


INFORMATIVE_SHARE = 0.01
"""A detection pair informs a comparison of two models only where their predictions differ by at least this
share of the pair's noise energy (the summed noise variance of its scored pixels): elsewhere the log ratio is
the noise's, a coin flip of negligible size. On a set with a planted focus offset and rim, 5 of 14 detection
crops held no blur the focus offset changes (log ratios of 1e-4) and their signs alone moved the signed-rank p
from 0.019 to 0.068. The rule looks at how much the two predictions differ, not at which is better, so it
keeps the test's level."""


@dataclass
class DetSet:
    """The detection pairs with the reference quantities every test needs.

    Attributes:
        counts, owners: per kept tile (:func:`tiles.tile_mse`), its scored entries and pair id.
        floor: the systematic error is at least this share of a model's squared error
            (:attr:`DetectConfig.systematic_floor`).
        base_systematic: the least a systematic error counts as (:func:`least_systematic` of the base
            model's).
        noise: per kept tile, the measured white noise's squared error.
    """

    samples: list[Sample]
    tile_px: int
    counts: np.ndarray
    owners: np.ndarray
    floor: float
    noise: np.ndarray
    base_systematic: float = 0.0

    def eval(self, model: BaseModel) -> Eval:
        sums, preds = [], []
        for s in self.samples:
            with torch.no_grad():
                l, r = model.render(s.batch, s.field)
            p = torch.cat([l, r], 1)
            e = p - torch.cat([s.batch.left, s.batch.right], 1)
            sums.append(tile_sums(e**2, s.score.float(), self.tile_px)[0])
            preds.append(p)
        return Eval(torch.cat(sums).double().numpy()[self._keep()], preds)

    def _keep(self) -> np.ndarray:
        if not hasattr(self, "_kept"):
            co = torch.cat([tile_sums(s.score.float().expand(-1, 6, -1, -1), s.score.float(), self.tile_px)[1] for s in self.samples])
            self._kept = kept_tiles(co.double().numpy())
        return self._kept

    def difference(self, a: Eval, b: Eval) -> np.ndarray:
        """Per kept tile, the summed squared difference of two models' predictions."""
        d = [tile_sums((pa - pb) ** 2, s.score.float(), self.tile_px)[0] for pa, pb, s in zip(a.pred, b.pred, self.samples)]
        return torch.cat(d).double().numpy()[self._keep()]

    def test(self, effect: str, without: Eval, with_: Eval) -> Test:
        """``effect``'s test: the model without it against the model with it (:func:`informed_test`)."""
        return informed_test(effect, without.su, with_.su, self.difference(without, with_), self.noise, self.counts, self.owners,
                             self.floor, self.base_systematic)


def least_systematic(base_systematic: float, samples: Sequence[Sample], cfg: DetectConfig, tile: int | None = None) -> float:
    r"""The least systematic error an effect's size is measured on, beside other effects (squared error summed
    over ``samples``' scored pixels, linear units):
    :math:`\min(\text{remaining\_floor} \cdot \mathrm{SSE}_{sys,base},\ \mathrm{SSE}_{noise,nominal})`.

    What little the other effects leave is no scale to measure a further effect on (on noise-free data
    rendered by the base model itself with an L/R gain planted, the gain model left 1e-3 of the base model's
    error, and a bright rim fitted into that numerical remainder took half of it), but a remainder as large as
    the noise a healthy sensor adds to these pixels (:attr:`DetectConfig.nominal_shot_var`,
    :attr:`DetectConfig.nominal_read_sigma`, both views) is a scale every real capture has. Until 2026-11-28
    the floor was the first term alone: beside a planted 1 px misregistration (another renderer, 26 dB of
    gain) it was 26 x what the misregistration left, and a planted focus offset that removed 97 % of that
    (p 0.01) measured 0.03 and was eliminated."""
    noise = noise_sse(list(samples), cfg.nominal_shot_var, cfg.nominal_read_sigma, tile or cfg.tile_px)
    return min(cfg.remaining_floor * base_systematic, noise)


def informed_test(effect: str, without_su: np.ndarray, with_su: np.ndarray, diff: np.ndarray, noise: np.ndarray, counts: np.ndarray,
                  owners: np.ndarray, floor: float = 0.2, least: float = 0.0) -> Test:
    r"""The signed-rank test of the per-pair log ratios :math:`\ln(\mathrm{SSE}(without) / \mathrm{SSE}(with))`
    over the informative pairs (:data:`INFORMATIVE_SHARE`: ``diff``, the two predictions' summed squared
    difference, against ``noise``, the noise energy; all per kept tile), and the effect size: the squared error
    the effect removes as a share of the systematic error of the model without it,
    :math:`\max(\mathrm{SSE}(without) - \mathrm{SSE}(noise), \text{floor} \cdot \mathrm{SSE}(without), \text{least})`.

    That denominator is what no other effect of the model explains: a weak effect beside a strong one is
    judged on what is left once the strong one is in (as a share of the base model's error, a planted
    field-varying PSF beside a strong L/R gain ramp removed 0.007, significant at p = 1e-4, but 0.083 of what
    the ramp left), while an effect that only absorbs model mismatch is judged on that mismatch alone
    whatever else the data holds. ``least`` (a share of the base model's systematic error,
    :attr:`DetectConfig.remaining_floor`) keeps crumbs crumbs: where the other effects leave almost nothing (on
    noise-free data rendered by the base model itself with an L/R gain planted, the gain model left 1e-3 of
    the base model's error, and a bright rim fitted into that numerical remainder took half of it)."""
    delta = clustered_delta(without_su, with_su, counts, owners)
    informative = unit_sums(diff, owners) >= INFORMATIVE_SHARE * unit_sums(noise, owners)
    t, p = effect_test(delta[informative])
    total = float(without_su.sum())
    systematic = max(total - float(noise.sum()), floor * total, least)
    return Test(effect, t, p, float((total - with_su.sum()) / max(systematic, 1e-20)))


def judge(tests: list[Test], cfg: DetectConfig) -> None:
    """Set each test's ``passed``: Hochberg's step-up correction at ``cfg.alpha`` over the tests
    (:func:`tiles.hochberg_passed`), and a unique share above the effect's threshold."""
    ok = hochberg_passed([t.p_value for t in tests], cfg.alpha)
    for t, h in zip(tests, ok):
        t.passed = bool(h and t.effect_size > cfg.threshold(t.effect))


# -- 1. the screen ---------------------------------------------------------------------------------------------


def neutral_components(names: Sequence[str], fit: Sequence[Sample]) -> dict[str, object]:
    """A fresh component per effect at its neutral values, told the field its fit data covers and the mean
    focus distance (for reporting)."""
    box = covered_field_box(list(fit))
    out = {}
    for n in names:
        c = COMPONENTS[n]()
        c.field_box = box
        if n == "focus_offset":  # it only records the mean focus distance, to report the offset in mm
            c.initial_guess(BaseModel(), fit[0].batch, fit[0].field)
        out[n] = c
    return out


def fit_systematic(fit: Sequence[Sample], sse: float, noise: Finding | None, cfg: DetectConfig, sharp: SharpNoise | None = None) -> float:
    """The crops' systematic squared error (their squared error less the measured noise's, the views' and the
    sharp frame's as the model carries it, aligned with ``fit``; floored)."""
    return max(sse - noise_sse(list(fit), *measured_noise(noise, cfg), 1, sharp), cfg.systematic_floor * sse)


def canonical_corr(A: np.ndarray, a: list[int], b: list[int], nuis: list[int]) -> float:
    """The largest canonical correlation between the column spaces of parameters ``a`` and ``b`` with the
    columns ``nuis`` projected out, from the Gram matrix ``A = J^T J``."""
    s = a + b
    G = A[np.ix_(s, s)]
    if nuis:
        Ann = A[np.ix_(nuis, nuis)] + 1e-12 * np.eye(len(nuis)) * max(np.trace(A[np.ix_(nuis, nuis)]), 1e-30)
        G = G - A[np.ix_(s, nuis)] @ np.linalg.solve(Ann, A[np.ix_(nuis, s)])
    na = len(a)
    Ga, Gb, Gab = G[:na, :na], G[na:, na:], G[:na, na:]

    def inv_sqrt(M: np.ndarray) -> np.ndarray:
        w, V = np.linalg.eigh(M)
        keep = w > 1e-10 * max(float(w.max()), 1e-30)
        return (V[:, keep] / np.sqrt(w[keep])) @ V[:, keep].T

    C = inv_sqrt(Ga) @ Gab @ inv_sqrt(Gb)
    return float(np.clip(np.linalg.norm(C, 2), 0.0, 1.0)) if C.size else 0.0


def screen_point(model: BaseModel, new: dict[str, object], fit: Sequence[Sample]) -> tuple[BaseModel, list[tuple[object, str]]]:
    """The model a screen linearizes (``model`` with the effects ``new`` added at their neutral values) and its
    targets: the new effects' parameters the crops constrain, then the base model's gain and PSF nuisances."""
    point = model.replaced(sorted([copy.deepcopy(c) for c in model.components] + [copy.deepcopy(c) for c in new.values()],
                                  key=lambda c: c.stage))
    targets = [(c, n) for c in point.components if c.name in new for n in fittable_names(c, fit)]
    targets += [(point, "gain")] + [(point, k) for k in PSF_NUISANCE]
    return point, targets


def screen_effects(model: BaseModel, new: dict[str, object], fit: Sequence[Sample], noise: Finding | None,
                   cfg: DetectConfig, sel: SelectConfig, sharp: SharpNoise | None = None, least: float = 0.0) -> Screen:
    """The first-order screen of the effects ``new`` around the fitted ``model`` (the base model, or a model
    already holding some effects): the module docstring's step 1. The base model's gain, rim softness and
    pixel sampling are refitted in every step; the effects ``model`` already holds keep their fitted values
    (their columns would cost a render each, and the screen only proposes). Candidates: greedily, the effect
    that adds most to those already taken, while it adds at least :attr:`SelectConfig.screen_share` of its
    threshold; and every effect whose unique part of the joint step of all effects is that large. Shares are
    of the fit crops' systematic error around ``model``, but of at least ``least`` (a re-screen passes
    :func:`least_systematic` of the base model's: what little the confirmed causes leave is not a scale to
    measure a further one on, as in the tests). The returned screen keeps its linearization
    (:attr:`Screen.lin`) for :func:`first_order_rescreen`."""
    point, targets = screen_point(model, new, fit)
    lin = jacobian(point, targets, fit)
    out = screen_from(lin, point, targets, new, fit, noise, cfg, sel, sharp, least)
    out.lin, out.keys = lin, [(owner_key(point, o), n) for o, n in targets]
    return out


def first_order_rescreen(last: Screen, model: BaseModel, new: dict[str, object], fit: Sequence[Sample], noise: Finding | None,
                         cfg: DetectConfig, sel: SelectConfig, sharp: SharpNoise | None = None, least: float = 0.0) -> Screen | None:
    r"""The screen of ``new`` around ``model`` (:func:`screen_effects`) with the Jacobian columns of the screen
    ``last`` (measured around an earlier model, on the same crops ``fit``) and ``model``'s exact residual, its
    bar lowered to :attr:`SelectConfig.prescreen_margin` of the screen's: one render of the crops instead of one
    per parameter. Its candidates say only whether the exact screen is worth running. None when ``last``
    lacks a column (an effect the last screen did not hold, its linearization dropped).

    The residual around the confirmed model is exact; the columns are those of the model it was confirmed
    from, off by the second-order terms :math:`\partial^2 r / \partial\theta_c \partial\theta_f \, \Delta\theta_c`
    (a confirmed gain ramp scales every column by the ramp, a confirmed shift moves them): hence the margin."""
    if last.lin is None or not last.keys:
        return None
    point, targets = screen_point(model, new, fit)
    column = {k: j for j, k in enumerate(last.keys)}
    keys = [(owner_key(point, o), n) for o, n in targets]
    if any(k not in column for k in keys):
        return None
    r = residual_vector(point, fit)
    if r.numel() != last.lin.r.numel():
        return None
    lin = Linearization(targets, get_values(targets), r, last.lin.J[:, [column[k] for k in keys]])
    return screen_from(lin, point, targets, new, fit, noise, cfg, sel, sharp, least, bar_scale=sel.prescreen_margin)


def screen_from(lin: Linearization, point: BaseModel, targets: list[tuple[object, str]], new: dict[str, object], fit: Sequence[Sample],
                noise: Finding | None, cfg: DetectConfig, sel: SelectConfig, sharp: SharpNoise | None = None, least: float = 0.0,
                bar_scale: float = 1.0) -> Screen:
    """The screen's shares, candidates, correlations and joint step from a linearization ``lin`` of ``point``
    in ``targets`` (:func:`screen_effects`); ``bar_scale`` scales every effect's bar."""
    systematic = max(fit_systematic(fit, lin.sse, noise, cfg, sharp), least)
    idx = {n: lin.index(point.component(n)) for n in new}
    current = [i for i in range(len(targets)) if not any(i in v for v in idx.values())]
    neutral = {i: float(lin.theta[i]) for n in new for i in idx[n]}
    sse_ref = lin.predicted_sse(lin.solve(neutral))
    sse_all = lin.predicted_sse(lin.solve())
    alone, unique, share = {}, {}, {}
    for n in new:
        if not idx[n]:
            alone[n] = unique[n] = share[n] = 0.0
            continue
        alone[n] = (sse_ref - lin.predicted_sse(lin.solve({i: v for i, v in neutral.items() if i not in idx[n]}))) / systematic
        unique[n] = (lin.predicted_sse(lin.solve({i: neutral[i] for i in idx[n]})) - sse_all) / systematic
        share[n] = max(alone[n], unique[n])

    def bar(n: str) -> float:
        return bar_scale * sel.screen_share * cfg.threshold(n)

    # greedy at first order: the effect that adds most to those taken, while it adds enough; look-alikes of a
    # taken effect then add little (a focus offset's blur-size look-alikes, a front size factor, red and blue
    # focal shifts, a CoC growth, all passed "alone" and made a five-effect full model that predicted the
    # detection pairs worse than one effect)
    taken: list[str] = []
    free_of = lambda names: {i: v for i, v in neutral.items() if not any(i in idx[m] for m in names)}  # noqa: E731
    while True:
        now = lin.predicted_sse(lin.solve(free_of(taken)))
        gains = {n: (now - lin.predicted_sse(lin.solve(free_of(taken + [n])))) / systematic for n in new if idx[n] and n not in taken}
        best = max(gains, key=gains.get, default=None)
        if best is None or gains[best] < bar(best):
            break
        taken.append(best)
    # and every effect whose unique part of the joint step is large: two effects that cancel each other alone
    candidates = [n for n in new if n in taken or (idx[n] and unique[n] >= bar(n))]
    corr = {}
    names = [n for n in new if idx[n]]
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            corr[tuple(sorted((a, b)))] = canonical_corr(lin.A, idx[a], idx[b], current)
    x = lin.solve({i: v for i, v in neutral.items() if not any(i in idx[n] for n in candidates)})
    log.info("screen: %s -> candidates %s", {n: round(share[n], 3) for n in new}, candidates)
    return Screen(share, alone, unique, corr, key_values(point, targets, x), candidates, systematic)


START_STEPS = (1.0, 0.5, 0.25, 0.125)
"""Fractions of the screen's joint step tried, in turn, as the full model's start (:func:`start_full_model`);
when none fits as well as the nested model, the start is the nested model itself."""


def start_full_model(full: BaseModel, nested: dict[Key, float], step: dict[Key, float], fit: Sequence[Sample]) -> float:
    r"""Write into ``full`` the start of its Levenberg-Marquardt fit, and return the fraction of the step taken.

    ``nested`` holds the values of the model ``full`` extends (the fitted base model, or the confirmed causes
    as fitted: every parameter not in it, the new effects', stays neutral); ``step``, the screen's bounded
    Gauss-Newton step from there. The start is :math:`\theta_n + t (\theta_s - \theta_n)` for the first
    :math:`t` of :data:`START_STEPS` whose squared error on the fit crops is no larger than the nested
    model's, else :math:`t = 0`, the nested model itself. Parameters ``step`` lacks (the confirmed causes')
    keep their nested values. Levenberg-Marquardt accepts only steps that lower the
    error, so the full model then fits the fit crops at least as well as the model it extends. The first-order
    step can overshoot far: around a confirmed 1 px misregistration on another renderer it put a chromatic
    focal shift and the pixel sampling where the fit crops' error was 10 x the confirmed model's, and five
    iterations ended there; the detection pairs then rejected the chromatic defocus that was planted."""
    with_values(full, nested)
    targets = targets_of(full, fit)
    theta_n = get_values(targets)
    with_values(full, step)
    theta_s = get_values(targets)
    set_values(targets, theta_n)
    r = residual_vector(full, fit)
    sse_nested = float(r @ r)
    for t in START_STEPS:
        set_values(targets, theta_n + t * (theta_s - theta_n))
        r = residual_vector(full, fit)
        if float(r @ r) <= sse_nested:
            return t
    set_values(targets, theta_n)
    return 0.0


def with_values(model: BaseModel, values: dict[Key, float]) -> BaseModel:
    """``model`` with ``values`` written in (in place; clipped to the bounds); returns it."""
    for (k, n), v in values.items():
        owner = model if k == "base" else next((c for c in model.components if c.name == k), None)
        if owner is not None and n in owner.params:
            owner.params[n] = float(np.clip(v, *owner.bounds.get(n, (-np.inf, np.inf))))
    return model


# -- 3. backward elimination (first order) ----------------------------------------------------------------------


def eliminate(full: BaseModel, lin: Linearization, fit: Sequence[Sample], det: DetSet, neutral: dict[str, dict[str, float]],
              cfg: DetectConfig, sel: SelectConfig) -> tuple[BaseModel, list[dict[str, Any]], dict[str, Test]]:
    """Backward elimination from the fitted full model (module docstring, step 3).

    Each round tests every effect of the current model against the current model without it, the others
    refitted to first order from the current model's Jacobian (one render of the detection pairs per
    effect). The failing effects are then tried weakest first (largest p): the model without it is
    refitted for real (Levenberg-Marquardt from the first-order start) and tested again; the first that
    still fails is removed, and the refitted model becomes the current one. A first-order refit can land
    better or worse on the detection pairs than a real one (on a chromatic + focus offset set it put the
    focus offset's unique share at 0.05 where refitting gave 0.18), so nothing is removed on it alone.

    Returns (the surviving model, the rounds, each removed effect's test when it was removed)."""
    model, su_cur = full, det.eval(full)
    rounds: list[dict[str, Any]] = []
    removed: dict[str, Test] = {}
    while model.components:
        names = [c.name for c in model.components]
        tests, start = [], {}
        for n in names:
            x = lin.solve(held_neutral(lin, model, [n], neutral))
            start[n] = key_values(model, lin.targets, x)
            w = submodel(model, [m for m in names if m != n], start[n])
            tests.append(det.test(n, det.eval(w), su_cur))
        judge(tests, cfg)
        record: dict[str, Any] = {"set": names, "tests": [t.to_json() for t in tests], "refitted": []}
        rounds.append(record)
        dropped = None
        for t in sorted((t for t in tests if not t.passed), key=lambda t: (-t.p_value, t.effect_size)):
            w = submodel(model, [m for m in names if m != t.effect], start[t.effect])
            w_lin = refit(w, fit, sel.refit_lm_iters) if w.components else None
            w_su = det.eval(w)
            real = det.test(t.effect, w_su, su_cur)
            judge_one = [real if u.effect == t.effect else u for u in tests]
            judge(judge_one, cfg)
            record["refitted"].append(real.to_json())
            if not real.passed:
                dropped = (t.effect, real, w, w_lin, w_su)
                break
        if dropped is None:
            break
        name, test, model, w_lin, su_cur = dropped
        log.info("eliminated %s (effect %.3f, p %.2g)", name, test.effect_size, test.p_value)
        removed[name] = test
        if w_lin is None:
            break
        lin = w_lin
    return model, rounds, removed


# -- 4. confirmation with real refits ---------------------------------------------------------------------------


@dataclass
class Confirmed:
    names: list[str]
    model: BaseModel
    lin: Linearization | None
    su: Eval
    without: dict[str, BaseModel]
    without_su: dict[str, Eval]
    tests: dict[str, Test]


def refit(model: BaseModel, fit: Sequence[Sample], iters: int) -> Linearization:
    return lm_fit(model, targets_of(model, fit), fit, iters)


def confirm(base: BaseModel, base_ev: Eval, full: BaseModel, names: list[str], values: dict[Key, float], fit: Sequence[Sample],
            det: DetSet, neutral: dict[str, dict[str, float]], cfg: DetectConfig, sel: SelectConfig,
            removed: dict[str, Test], rounds: list[dict[str, Any]]) -> Confirmed:
    """Refit the survivors' model and the model without each survivor, test each given the others; drop the
    failure whose removal costs the detection pairs least and repeat (module docstring, step 4)."""
    names = list(names)
    while True:
        if not names:
            return Confirmed([], base, None, base_ev, {}, {}, {})
        model = submodel(full, names, values)
        lin = refit(model, fit, sel.refit_lm_iters)
        su = det.eval(model)
        without: dict[str, BaseModel] = {}
        without_su: dict[str, np.ndarray] = {}
        tests: list[Test] = []
        for n in names:
            if len(names) == 1:
                w, wsu = base, base_ev
            else:
                x = lin.solve(held_neutral(lin, model, [n], neutral))
                start = key_values(model, lin.targets, x)
                w = submodel(model, [m for m in names if m != n], start)
                refit(w, fit, sel.refit_lm_iters)
                wsu = det.eval(w)
            without[n], without_su[n] = w, wsu
            tests.append(det.test(n, wsu, su))
        judge(tests, cfg)
        rounds.append({"set": list(names), "confirmation": True, "tests": [t.to_json() for t in tests]})
        failing = [t for t in tests if not t.passed]
        if not failing:
            return Confirmed(names, model, lin, su, without, without_su, {t.effect: t for t in tests})
        # backward elimination's rule: drop the failure whose removal costs the detection pairs least (the
        # largest p instead dropped a chromatic defocus that removed 11.4 units, p 0.042, beside a focus offset
        # that removed 1.5, p 0.027, and the focus offset alone then lost to the base model)
        worst = min(failing, key=lambda t: (float(without_su[t.effect].su.sum() - su.su.sum()), -t.p_value))
        log.info("confirmation dropped %s (effect %.3f, p %.2g)", worst.effect, worst.effect_size, worst.p_value)
        removed[worst.effect] = worst
        values = key_values(without[worst.effect], targets_of(without[worst.effect], fit))
        names.remove(worst.effect)


# -- 5. look-alikes ---------------------------------------------------------------------------------------------


def swapped_model(conf: Confirmed, cause: str, effect: object, screen: Screen, fit: Sequence[Sample], sel: SelectConfig) -> BaseModel:
    """The confirmed model with ``effect`` (a neutral component) in place of ``cause``: the model without the
    cause, plus the effect started at the screen's joint step and refitted with every parameter as long as a
    full model (as converged as the model it stands in for)."""
    swap = submodel(conf.without[cause], [m for m in conf.names if m != cause]).with_component(copy.deepcopy(effect))
    for (k, n), v in screen.values.items():
        if k == effect.name:  # type: ignore[attr-defined]
            swap.component(k).params[n] = v
    refit(swap, fit, sel.full_lm_iters)
    return swap


def find_lookalikes(conf: Confirmed, comps: dict[str, object], screen: Screen, fit: Sequence[Sample], det: DetSet,
                    cfg: DetectConfig, sel: SelectConfig, swaps: dict[tuple[str, str], BaseModel] | None = None) -> list[dict[str, Any]]:
    """For each named cause C and each other testable effect F correlated with it (:attr:`Screen.corr`), F
    refitted in C's place: a look-alike when it explains what C explained (against the model without C it
    passes C's test: significant, and above C's threshold) and the detection pairs do not prefer C
    materially: the signed-rank test of C's model against F's is not significant, or what F loses is below
    :attr:`SelectConfig.lookalike_loss` of C's threshold (two fits of exactly equivalent models differ by
    their convergence alone, consistently over every pair: a significant but negligible preference).
    Such an F is reported with kind ``instead`` (one or the other).

    A correlated F that is not is still reported, with kind ``also``, where C's effect contains it: alone F
    would explain at least its threshold of the base model's systematic error, but beside every other effect
    its unique part is below the screen's bar (:attr:`Screen.alone`, :attr:`Screen.unique`). The data then
    cannot tell whether F is present beside C: a field-varying PSF's split leaking toward the edges planted
    with an L/R gain ramp (another renderer, 2026-11-27) was all explained by the ramp's gain map, its unique
    part 0.002 of the systematic error against 0.685 alone, at a correlation of 0.998.

    ``swaps``, when given, receives every refitted model tried, by (cause, effect)."""
    groups = []
    for c in conf.names:
        group = {"names": [c], "captures": [], "correlation": [], "effect_size_lost": [], "p_value": [], "kinds": []}
        others = [f for f in comps if f not in conf.names and screen.correlation(c, f) >= sel.lookalike_corr]
        for f in sorted(others, key=lambda f: -screen.correlation(c, f))[: sel.lookalike_tries]:
            swap = swapped_model(conf, c, comps[f], screen, fit, sel)
            if swaps is not None:
                swaps[(c, f)] = swap
            su = det.eval(swap)
            explains = det.test(f, conf.without_su[c], su)
            worse = det.test(c, su, conf.su)
            lost = worse.effect_size
            same = explains.p_value < cfg.alpha and explains.effect_size > cfg.threshold(c) and (
                worse.p_value >= cfg.alpha or lost < sel.lookalike_loss * cfg.threshold(c))
            log.info("look-alike %s for %s: explains %.3f (p %.2g), loses %.3f (p %.2g) -> %s", f, c, explains.effect_size,
                     explains.p_value, lost, worse.p_value, same)
            if same:
                group["names"].append(f)
                group["captures"].append(separating_capture(c, f))
                group["correlation"].append(_finite(screen.correlation(c, f)))
                group["effect_size_lost"].append(_finite(lost))
                group["p_value"].append(_finite(worse.p_value, 1.0))
                group["kinds"].append("instead")
        for f in others:
            contained = screen.alone.get(f, 0.0) >= cfg.threshold(f) and screen.unique.get(f, 0.0) < sel.screen_share * cfg.threshold(f)
            if f in group["names"] or not contained:
                continue
            log.info("look-alike %s inside %s: alone %.3f, unique %.4f", f, c, screen.alone[f], screen.unique[f])
            group["names"].append(f)
            group["captures"].append(separating_capture(c, f))
            group["correlation"].append(_finite(screen.correlation(c, f)))
            group["effect_size_lost"].append(None)
            group["p_value"].append(None)
            group["kinds"].append("also")
        if len(group["names"]) > 1:
            groups.append(group)
    return groups


# -- the whole selection ----------------------------------------------------------------------------------------


@dataclass
class Context:
    """What a selection was made from, kept to redo its last steps without a cause (:func:`drop_cause`)."""

    base: BaseModel
    base_ev: Eval
    base_mse: float
    fit: list[Sample]
    det: DetSet
    cfg: DetectConfig
    sel: SelectConfig
    comps: dict[str, object]
    neutral: dict[str, dict[str, float]]
    screen: Screen
    full: BaseModel
    removed: dict[str, Test]
    untestable: dict[str, Finding]
    structural: list[str]
    with_noise: bool
    suspects: set[str] = field(default_factory=set)
    """Causes dropped because their held-out gain did not earn them (:func:`drop_cause`)."""
    simpler_lookalike: dict[str, tuple[str, dict[str, float], int, int]] = field(default_factory=dict)
    """Causes confirmed first and then not named: per cause, the look-alike of fewer parameters named in its
    place, the cause's fitted parameters, and both parameter counts (:func:`name_the_simpler`)."""


def select_causes(base: BaseModel, fit: list[Sample], det_samples: list[Sample], cfg: DetectConfig, sel: SelectConfig,
                  effects: tuple[str, ...] = EFFECT_NAMES) -> Selection:
    """Name every structural cause in ``effects`` on top of the fitted ``base`` (module docstring) and measure
    ``noise`` against the result."""
    base_su, base_co, owners = tile_mse(base, det_samples, cfg.tile_px)
    base_total = float(base_su.sum())
    base_mse = base_total / max(float(base_co.sum()), 1.0)
    noise0 = test_noise(base, fit, det_samples, cfg, base_mse) if "noise" in effects else None
    pool = fit + det_samples  # the screen only proposes; the tests are on the detection pairs alone
    sharp = sharp_noise(base, pool, cfg)
    det_sharp = SharpNoise(sharp.ratio, sharp.propagated[len(fit):])
    det = DetSet(det_samples, cfg.tile_px, base_co, owners, cfg.systematic_floor,
                 noise_tile_sse(det_samples, *measured_noise(noise0, cfg), cfg.tile_px, det_sharp))
    base_ev = det.eval(base)
    det.base_systematic = least_systematic(systematic_sse(base_total, det_samples, noise0, cfg, det_sharp), det_samples, cfg)
    structural = [e for e in effects if e != "noise"]
    untestable: dict[str, Finding] = {}
    if any(COMPONENTS[e].needs_colour for e in structural):
        contrast = colour_contrast(fit + det_samples)
        if contrast <= GREY_MAX_COLOUR_CONTRAST:
            untestable = {e: not_testable(e, contrast) for e in structural if COMPONENTS[e].needs_colour}
    comps = neutral_components([e for e in structural if e not in untestable], fit)
    neutral = {n: dict(c.params) for n, c in comps.items()}
    screen = screen_effects(base, comps, pool, noise0, cfg, sel, sharp)
    last = screen  # the screen whose Jacobian the next re-screen's first-order check reuses
    rounds: list[dict[str, Any]] = []
    trace: dict[str, Any] = {"method": "screen, full model, backward elimination on the detection pairs, refitted confirmation, "
                                       "re-screen around the confirmed model", "screen": screen.to_json(), "rescreens": [], "rounds": rounds,
                             "full_models": [], "sharp_noise_ratio": {"base": sharp.ratio}}
    ctx = Context(base, base_ev, base_mse, fit, det, cfg, sel, comps, neutral, screen, base, {}, untestable, structural, "noise" in effects)
    conf = Confirmed([], base, None, base_ev, {}, {}, {})
    names, values = list(screen.candidates), screen.values
    for k in range(sel.rescreens + 1):
        if not names:
            break
        full = base.replaced(sorted([copy.deepcopy(comps[n]) for n in names], key=lambda c: c.stage))
        nested = conf.model  # the model the full model extends (its new effects neutral)
        t = start_full_model(full, key_values(nested, targets_of(nested, fit)), values, fit)
        lin = refit(full, fit, sel.full_lm_iters)
        trace["full_models"].append({**full.describe(), "start_step": t})
        if k == 0:  # the sharp frame's noise again, against a model that explains the planted effects
            remeasure_sharp_noise(det, full, fit, noise0, base_total, cfg, trace)
        survivor, elim_rounds, removed = eliminate(full, lin, fit, det, neutral, cfg, sel)
        rounds += elim_rounds
        ctx.removed.update(removed)
        survivors = [c.name for c in survivor.components]
        new = confirm(base, base_ev, full, survivors, key_values(survivor, targets_of(survivor, fit)), fit, det, neutral, cfg, sel,
                      ctx.removed, rounds)
        if k > 0 and not predicts_better(new, conf):
            trace["rescreens"][-1]["kept"] = {"model": list(conf.names), "detect_sse": float(conf.su.su.sum()),
                                              "rejected": list(new.names), "rejected_detect_sse": float(new.su.su.sum())}
            log.info("re-screen's model %s predicts the detection pairs no better than %s: kept", new.names, conf.names)
            break
        conf, ctx.full = new, full  # the full model the kept causes came from
        rest = {n: comps[n] for n in comps if n not in conf.names}
        if k == sel.rescreens or not rest:
            break
        least = least_systematic(screen.systematic, pool, cfg, 1)
        cheap = first_order_rescreen(last, conf.model, rest, pool, noise0, cfg, sel, sharp, least) if sel.prescreen_margin > 0 else None
        if cheap is not None and not cheap.candidates:  # nothing near the bar even at first order: the exact screen is not run
            trace["rescreens"].append({"model": list(conf.names), "first_order": True, **cheap.to_json()})
            log.info("re-screen at first order on the last screen's Jacobian: nothing within %.2f of the bar", sel.prescreen_margin)
            for n in rest:
                screen.share[n] = max(screen.share.get(n, 0.0), cheap.share[n])
            break
        again = screen_effects(conf.model, rest, pool, noise0, cfg, sel, sharp, least)
        last.lin, last = None, again
        trace["rescreens"].append({"model": list(conf.names), **again.to_json(),
                                   **({"first_order_share": dict(cheap.share), "first_order_candidates": list(cheap.candidates)} if cheap else {})})
        for n in rest:
            screen.share[n] = max(screen.share.get(n, 0.0), again.share[n])
        if not [n for n in again.candidates if n not in names]:
            break  # nothing the last full model did not already hold
        names = conf.names + again.candidates
        values = again.values  # start_full_model keeps the confirmed causes as fitted
    screen.lin = last.lin = None  # the Jacobians are the largest arrays a selection holds
    for n in conf.names:
        ctx.removed.pop(n, None)
    trace["full_model"] = trace["full_models"][-1] if trace["full_models"] else {"components": {}}
    return finish(ctx, conf, trace)


def predicts_better(new: Confirmed, old: Confirmed) -> bool:
    """Whether a re-screen's confirmed model ``new`` predicts the detection pairs (which no fit saw) better than
    the confirmed model ``old`` it was built to extend: a lower summed squared error over their kept tiles.

    A re-screen adds the effects that pass around ``old`` and eliminates backward from the larger full model;
    that elimination can lose confirmed causes to a look-alike that stands in for them (on ``foreign_dp``,
    L/R gain + focus offset + front/back asymmetry confirmed exactly, then a five-effect full model ended as
    the gain and a chromatic defocus whose R and B focal shifts mimicked the focus offset). Such a model is
    kept only when the held-out pairs prefer it."""
    return float(new.su.su.sum()) < float(old.su.su.sum())


def remeasure_sharp_noise(det: DetSet, model: BaseModel, fit: list[Sample], noise0: Finding | None, base_total: float, cfg: DetectConfig,
                          trace: dict[str, Any]) -> None:
    """The sharp frame's noise (:func:`noise.sharp_noise`) measured against the fitted full model, and the
    detection set's noise energy and least systematic error set from it (in place). Against the base model,
    error both views share (a planted rim and focus offset on another renderer's noise-free ``sharp``) read as
    0.52 x nominal sharp noise; against a model that explains it, only the noise is left."""
    again = sharp_noise(model, fit + det.samples, cfg)
    d = SharpNoise(again.ratio, again.propagated[len(fit):])
    trace["sharp_noise_ratio"] = {"base": trace.get("sharp_noise_ratio", {}).get("base"), "full_model": again.ratio}
    det.noise = noise_tile_sse(det.samples, *measured_noise(noise0, cfg), cfg.tile_px, d)
    det.base_systematic = least_systematic(systematic_sse(base_total, det.samples, noise0, cfg, d), det.samples, cfg)


def finish(ctx: Context, conf: Confirmed, trace: dict[str, Any]) -> Selection:
    """Order the confirmed causes, find their look-alikes, build the step models, measure noise against the
    final model and write every effect's finding."""
    swaps: dict[tuple[str, str], BaseModel] = {}
    lookalikes = find_lookalikes(conf, ctx.comps, ctx.screen, ctx.fit, ctx.det, ctx.cfg, ctx.sel, swaps) if conf.names else []
    for _ in range(len(conf.names)):  # each swap names fewer parameters, so this ends
        swapped = name_the_simpler(ctx, conf, lookalikes, swaps, trace)
        if swapped is None:
            break
        conf, swaps = swapped, {}
        lookalikes = find_lookalikes(conf, ctx.comps, ctx.screen, ctx.fit, ctx.det, ctx.cfg, ctx.sel, swaps)
    for g in lookalikes:  # why the named one of each group was named: parsimony, where it chose
        g["fewer_parameters_than"] = [c for c in g["names"][1:] if ctx.simpler_lookalike.get(c, ("",))[0] == g["names"][0]]
    order = sorted(conf.names, key=lambda n: -conf.tests[n].effect_size)
    steps = step_models(conf, order, ctx.neutral) if order else []
    noise = test_noise(conf.model, ctx.fit, ctx.det.samples, ctx.cfg, ctx.base_mse) if ctx.with_noise else None
    findings = effect_findings(conf, order, ctx.full, ctx.screen, ctx.removed, ctx.untestable, noise, ctx.fit, ctx.cfg, ctx.sel, ctx.structural,
                               ctx.suspects, ctx.simpler_lookalike)
    out = Selection(order, conf.model, steps, [conf.without[n] for n in order], findings, lookalikes, trace, noise, conf.lin)
    out.context = ctx
    return out


def parameter_count(comp: object, fit: Sequence[Sample]) -> int:
    """How many parameters of ``comp`` the fit crops constrain (:func:`fittable_names`): what a model holding it
    fits."""
    return len(fittable_names(comp, fit))


def name_the_simpler(ctx: Context, conf: Confirmed, lookalikes: list[dict[str, Any]], swaps: dict[tuple[str, str], BaseModel],
                     trace: dict[str, Any]) -> Confirmed | None:
    """Parsimony between look-alikes: where a named cause C has an ``instead`` look-alike F (the detection pairs
    do not prefer C materially, and F explains what C explained, :func:`find_lookalikes`) that fits fewer
    parameters on this data (:func:`parameter_count`), F is named in C's place, and C is reported as its
    look-alike. The model with F (``swaps``: the refitted models :func:`find_lookalikes` tried) is confirmed
    like any other (:func:`confirm`); the swap stands only when every cause of it passes its test given the
    others. Returns the new confirmed model, or None when no swap stands.

    Two models that predict held-out data equally well are told apart by their complexity alone: on another
    renderer's bright-rim disc beside a focus offset, a misregistration or chromatic defocus, the first model
    confirmed was front_back_asymmetry (4 parameters: a back rim, a front centre, a front size, spherical
    aberration), whose back rim matched the planted rim as well as psf_profile (2 parameters) did."""
    for group in lookalikes:
        c = group["names"][0]
        n_c = parameter_count(conf.model.component(c), ctx.fit)
        simpler = [(parameter_count(ctx.comps[f], ctx.fit), lost if lost is not None else 0.0, f)
                   for f, kind, lost in zip(group["names"][1:], group["kinds"], group["effect_size_lost"]) if kind == "instead"]
        simpler = sorted(t for t in simpler if t[0] < n_c)
        if not simpler:
            continue
        n_f, _, f = simpler[0]
        swap = swaps[(c, f)]
        names = [m for m in conf.names if m != c] + [f]
        removed = dict(ctx.removed)
        new = confirm(ctx.base, ctx.base_ev, swap, names, key_values(swap, targets_of(swap, ctx.fit)), ctx.fit, ctx.det, ctx.neutral,
                      ctx.cfg, ctx.sel, removed, trace.setdefault("rounds", []))
        record = {"named": c, "parameters": n_c, "simpler": f, "simpler_parameters": n_f, "confirmed": list(new.names)}
        trace.setdefault("parsimony", []).append(record)
        if sorted(new.names) != sorted(names):
            log.info("parsimony: %s (%d parameters) for %s (%d) did not confirm: %s", f, n_f, c, n_c, new.names)
            continue
        log.info("parsimony: %s (%d parameters) named in place of its look-alike %s (%d)", f, n_f, c, n_c)
        ctx.removed.update(removed)
        ctx.removed[c] = conf.tests[c]
        ctx.simpler_lookalike[c] = (f, conf.model.component(c).describe(), n_c, n_f)
        return new
    return None


def drop_cause(selection: Selection, name: str) -> Selection:
    """``selection`` without the cause ``name`` (its held-out gain did not earn it): the other causes, from the
    model without it, refitted and confirmed again on the detection pairs."""
    ctx = selection.context
    k = selection.causes.index(name)
    f = next(f for f in selection.findings if f.effect == name)
    ctx.removed[name] = Test(name, f.statistic, f.p_value, f.effect_size)
    ctx.suspects.add(name)
    start = selection.without[k]
    rest = [n for n in selection.causes if n != name]
    rounds = selection.trace.setdefault("rounds", [])
    conf = confirm(ctx.base, ctx.base_ev, start, rest, key_values(start, targets_of(start, ctx.fit)), ctx.fit, ctx.det, ctx.neutral,
                   ctx.cfg, ctx.sel, ctx.removed, rounds)
    return finish(ctx, conf, selection.trace)


def step_models(conf: Confirmed, order: list[str], neutral: dict[str, dict[str, float]]) -> list[BaseModel]:
    """The model after causes 1..k for each k: the final model with the later causes removed and the rest
    refitted to first order (the last is the final model itself)."""
    out = []
    for k in range(1, len(order)):
        later = order[k:]
        x = conf.lin.solve(held_neutral(conf.lin, conf.model, later, neutral))
        out.append(submodel(conf.model, order[:k], key_values(conf.model, conf.lin.targets, x)))
    return out + [conf.model]


def effect_findings(conf: Confirmed, order: list[str], full: BaseModel, screen: Screen, removed: dict[str, Test],
                    untestable: dict[str, Finding], noise: Finding | None, fit: Sequence[Sample], cfg: DetectConfig, sel: SelectConfig,
                    structural: list[str], suspects: set[str] = frozenset(),
                    simpler: dict[str, tuple[str, dict[str, float], int, int]] | None = None) -> list[Finding]:
    """One finding per effect (named first, in order; then the others by effect size). ``simpler``: the causes
    a look-alike of fewer parameters was named in place of (:attr:`Context.simpler_lookalike`)."""
    simpler = simpler or {}
    out: list[Finding] = []
    for n in order:
        t, comp = conf.tests[n], conf.model.component(n)
        params = comp.describe()
        held = tuple(m for m in comp.fit_names if m not in fittable_names(comp, fit))
        out.append(Finding(n, t.statistic, t.p_value, t.effect_size, True, params, explanation(n, params, held), conf.model, held=held,
                           stage="named"))
    rest: list[Finding] = []
    for n in structural:
        if n in order:
            continue
        if n in untestable:
            rest.append(untestable[n])
            continue
        if n in simpler and n in removed:
            t, (f, params, n_n, n_f) = removed[n], simpler[n]
            why = (f"; not named: a look-alike of {f}, which the detection pairs do not tell from it and which fits fewer parameters "
                   f"({n_f} against {n_n}); {f} is named in its place")
            rest.append(Finding(n, t.statistic, t.p_value, t.effect_size, False, params, explanation(n, params) + why, None, stage="look-alike"))
            continue
        if n in removed:
            t = removed[n]
            comp = next((c for c in full.components if c.name == n), None)
            params = comp.describe() if comp is not None else {}
            if n in suspects:
                why = "; a suspect, not named: it passed the detection pairs but its held-out gain given the other causes has a 95 % CI reaching 0"
                rest.append(Finding(n, t.statistic, t.p_value, t.effect_size, False, params, explanation(n, params) + why, None, stage="suspect"))
                continue
            rest.append(Finding(n, t.statistic, t.p_value, t.effect_size, False, params,
                                explanation(n, params) + f"; not named: given the other effects it removes {t.effect_size:.3f} of the "
                                f"systematic error (threshold {cfg.threshold(n):g}), p = {t.p_value:.2g}", None, stage="eliminated"))
            continue
        share = screen.share.get(n, 0.0)
        rest.append(Finding(n, 0.0, 1.0, share, False, {}, f"screened out: one Gauss-Newton step predicts it removes at most {share:.3f} of "
                            f"the systematic error the models it was screened against leave (screen {sel.screen_share * cfg.threshold(n):.3f})",
                            None, stage="screened out"))
    if noise is not None:
        rest.append(noise)
    rest.sort(key=lambda f: (not f.detected, -f.rank_score))
    return out + rest


def model_intervals(selection: Selection, fit: Sequence[Sample]) -> dict[str, dict[str, tuple[float, float]]]:
    """95 % intervals (clustered over pairs, :func:`neural_dp.simulators.base.fit.clustered_intervals`) of every fitted parameter of
    the final model: ``{"base": {...}, <effect>: {...}}``, in each parameter's own units; empty without a cause."""
    lin = selection.lin
    if lin is None:
        return {}
    iv = clustered_intervals(lin, fit)
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for (o, n), (lo, hi) in zip(lin.targets, iv):
        if np.isfinite(lo) and np.isfinite(hi):
            out.setdefault(owner_key(selection.model, o), {})[n] = (float(lo), float(hi))
    return out
