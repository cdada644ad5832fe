"""Every cause, in order: greedy forward selection of effects on top of the fitted base model.

Step k tests the effects not yet chosen against the model of steps 1..k-1 (:func:`detect.test_effects` with
that model as the reference), extends it with the strongest detected structural effect (after the nested
test of the two leading ones), refits every chosen component together, and repeats until no structural
effect is detected or :attr:`ChainConfig.max_causes` are chosen.

Greedy forward selection can take a look-alike first when two effects hide each other (a bright rim and a
focus offset each make the base model's fit worse alone), so with two or more causes an exchange step
follows (:func:`exchange_causes`, "floating" selection): every chosen cause's slot is re-selected given the
others (the model without it, refitted, is tested against every effect); a cause nothing detected replaces is
dropped, a cause the data prefers another effect for is replaced. When the set changed, the causes are
ordered by what each explains alone against the base model and the models of the steps are refitted.
When no single effect is detected against the base model but one is promising (large, not significant), a
look-ahead of two screens it with each other effect as a pair (:func:`pair_step`); later steps leave such
cases to the exchange step.

``noise`` is a measurement, not a
structural effect: a simulator's output is an expectation, so noise cannot raise PSNR; it is measured
against the final model and, when its excess over the nominal sensor is significant, named after every
structural effect.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from dp5k_common.effects import EFFECT_NAMES
from neural_dp.registry import BaseModel, fit_parameters, fittable_names, parameter_intervals

from .data import Sample
from .detect import (PSF_NUISANCE, DetectConfig, Discrimination, Finding, _finite, clustered_delta, discriminate, effect_test, explanation,
                     fit_effect, keep_rim_if_better, masked_mse, systematic_sse, test_effects, tile_mse)

log = logging.getLogger(__name__)


@dataclass
class ChainConfig:
    """Settings of the forward selection.

    Attributes:
        max_causes: the most structural effects chained (each step costs about one single-effect diagnosis).
        retest_min_effect: an effect is re-tested at the next step only if its effect size at this step
            exceeded this (share of the systematic error): one that made the model worse on the detection
            pairs is not a candidate once the model is better. Its ``-inf`` re-tests every effect.
        joint_lm_iters: Levenberg-Marquardt iterations of the joint refit of all chosen components.
        exchange_passes: passes of the exchange step over the chosen causes (0: none); a pass that changes
            nothing ends it.
    """

    max_causes: int = 4
    retest_min_effect: float = 0.0
    joint_lm_iters: int = 2
    exchange_passes: int = 2


@dataclass
class ChainStep:
    """One chosen effect: its finding at the step it was chosen (tested against the previous model) and the
    model after the step (all chosen components refitted together)."""

    finding: Finding
    model: BaseModel
    discrimination: Discrimination | None = None


@dataclass
class Exchange:
    """One chosen cause's slot re-selected given the other causes (:func:`exchange_causes`).

    Attributes:
        slot: the cause re-tested.
        action: "kept" (it is still the strongest detected effect given the others), "dropped" (nothing is
            detected without it) or "replaced" (the data prefers ``by``).
        by: the effect chosen for the slot ("" when dropped).
        effect_size, p_value: the chosen effect's finding against the model without the slot (the slot's
            own when dropped: what it adds to the others).
        findings: every effect tested for the slot.
    """

    slot: str
    action: str
    by: str
    effect_size: float
    p_value: float
    findings: list[Finding] = field(default_factory=list, repr=False)

    def to_json(self) -> dict[str, object]:
        return {"slot": self.slot, "action": self.action, "by": self.by or None, "effect_size": _finite(self.effect_size),
                "p_value": _finite(self.p_value, 1.0),
                "tests": [{k: f.to_json()[k] for k in ("effect", "effect_size", "p_value", "detected", "testable")} for f in self.findings]}


@dataclass
class Chain:
    """The result of the forward selection.

    Attributes:
        steps: the structural effects in the order chosen.
        first_findings: every effect's finding against the base model (step 1).
        first_discrimination: the nested test of step 1.
        noise: the noise finding measured against the final structural model (None when not tested).
        step_findings: every step's findings (step 1 first), for the report.
        exchanges: the exchange step's slot tests, in the order run (empty when it did not run).
        forward_order: the causes as the forward selection chose them, before the exchange step.
        without: per step, the final model without that step's cause, the others refitted together (the
            fitted base model for a single cause): what the cause adds given every other one is measured
            against it.
    """

    steps: list[ChainStep]
    first_findings: list[Finding]
    first_discrimination: Discrimination | None
    noise: Finding | None
    step_findings: list[list[Finding]] = field(default_factory=list)
    exchanges: list[Exchange] = field(default_factory=list)
    forward_order: list[str] = field(default_factory=list)
    without: list[BaseModel] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        """The causes in order: the structural ones, then ``noise`` when its excess is significant."""
        out = [s.finding.effect for s in self.steps]
        if self.noise is not None and self.noise.detected:
            out.append("noise")
        return out

    def extended(self, base: BaseModel) -> BaseModel:
        """The model after the whole chain (with the fitted noise model when ``noise`` is named; it leaves the
        predicted views unchanged)."""
        model = self.steps[-1].model if self.steps else base
        if self.noise is not None and self.noise.detected and self.noise.model is not None:
            model = model.with_component(self.noise.model.component("noise"))
        return model


def joint_targets(model: BaseModel, fit: list[Sample]) -> list[tuple[object, str]]:
    """Every parameter of ``model`` the fit samples constrain: each component's fittable ones, the gain, and
    the PSF nuisance parameters (:data:`detect.PSF_NUISANCE`) when a component changes blur."""
    targets: list[tuple[object, str]] = []
    for c in model.components:
        targets += [(c, n) for n in fittable_names(c, fit)]
    targets.append((model, "gain"))
    if any(c.changes_psf or not c.post_only for c in model.components):
        targets += [(model, k) for k in PSF_NUISANCE]
    return targets


def joint_refit(model: BaseModel, previous: BaseModel, fit: list[Sample], det: list[Sample], cfg: ChainConfig) -> BaseModel:
    """``model`` (previous model + the new effect, fitted alone) with all its components refitted together,
    when that predicts the detection pairs better; else ``model`` as it is. Effects that trade off (a
    focus offset and a PSF profile both change the blur's size) settle together."""
    joint = model.replaced([copy.deepcopy(c) for c in model.components])
    fit_parameters(joint, joint_targets(joint, fit), [s.batch for s in fit], [s.field for s in fit], masks=[s.score for s in fit],
                   iters=cfg.joint_lm_iters)
    joint = keep_rim_if_better(joint, previous, det)
    if masked_mse(joint, det) < masked_mse(model, det):
        return joint
    return model


def select_causes(base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig, chain: ChainConfig,
                  effects: tuple[str, ...] = EFFECT_NAMES) -> Chain:
    """Greedy forward selection of the effects in ``effects`` on top of ``base`` (module docstring)."""
    current = base
    steps: list[ChainStep] = []
    candidates = tuple(e for e in effects if e != "noise")
    with_noise = "noise" in effects
    first: list[Finding] | None = None
    first_disc: Discrimination | None = None
    noise: Finding | None = None
    all_findings: list[list[Finding]] = []
    while True:
        findings = test_effects(current, fit, det, cfg, candidates + (("noise",) if with_noise else ()))
        disc = discriminate(findings, current, fit, det, cfg)
        all_findings.append(findings)
        if first is None:
            first, first_disc = findings, disc
        noise = next((f for f in findings if f.effect == "noise"), None)
        chosen = next((f for f in findings if f.detected and f.effect != "noise" and f.model is not None), None)
        if chosen is None:
            pair = pair_step(current, findings, candidates, fit, det, cfg, chain, noise) if not steps else None
            if pair is None:
                break
            new = [ChainStep(f, model, None) for f, model in pair]
            taken = {st.finding.effect for st in new}
            candidates = tuple(e for e in candidates if e not in taken)
        else:
            model = chosen.model if not steps else joint_refit(chosen.model, current, fit, det, chain)
            new = [ChainStep(chosen, model, disc)]
            candidates = tuple(f.effect for f in findings if f.effect not in ("noise", chosen.effect) and f.testable
                               and f.effect_size > chain.retest_min_effect)
        for st in new:
            steps.append(st)
            log.info("cause %d: %s (effect size %.3f, p %.2g)%s", len(steps), st.finding.effect, st.finding.effect_size,
                     st.finding.p_value, " (pair look-ahead)" if chosen is None else "")
        current = steps[-1].model
        if len(steps) >= chain.max_causes or not candidates:
            if with_noise:  # noise measured against the final model
                noise = measure_noise(current, fit, det, cfg)
            break
    result = Chain(steps, first or [], first_disc, noise, all_findings, forward_order=[s.finding.effect for s in steps])
    if len(steps) >= 2 and chain.exchange_passes > 0:
        result = exchange_causes(result, base, fit, det, cfg, chain, tuple(e for e in effects if e != "noise"))
        if with_noise and result.forward_order != [s.finding.effect for s in result.steps]:  # noise against the new final model
            result.noise = measure_noise(result.steps[-1].model, fit, det, cfg)
    if len(result.steps) == 1:
        result.without = [base]
    elif result.steps and not result.without:
        final = result.steps[-1].model
        result.without = [without_cause(final, st.finding.effect, base, fit, det, chain) for st in result.steps]
    return result


def measure_noise(model: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig) -> Finding:
    """The ``noise`` finding measured against ``model`` (its residual and systematic error)."""
    return next(f for f in test_effects(model, fit, det, cfg, ("noise",)) if f.effect == "noise")


def step_statistics(prev: BaseModel, model: BaseModel, det: list[Sample], cfg: DetectConfig,
                    noise: Finding | None) -> tuple[float, float, float, np.ndarray]:
    """How much ``model`` improves on ``prev`` on the detection pairs, as :func:`detect.test_effects` judges an
    effect: (signed-rank statistic, p-value, effect size as a share of ``prev``'s systematic error, ``model``'s
    per-tile squared errors)."""
    prev_su, prev_co, owners = tile_mse(prev, det, cfg.tile_px)
    su = tile_mse(model, det, cfg.tile_px)[0]
    t, p = effect_test(clustered_delta(prev_su, su, prev_co, owners))
    effect = float((prev_su.sum() - su.sum()) / max(systematic_sse(float(prev_su.sum()), det, noise, cfg), 1e-20))
    return t, p, effect, su


def pair_step(current: BaseModel, findings: list[Finding], candidates: tuple[str, ...], fit: list[Sample], det: list[Sample],
              cfg: DetectConfig, chain: ChainConfig, noise: Finding | None) -> list[tuple[Finding, BaseModel]] | None:
    """A look-ahead of two when no single effect is detected against the base model: two effects that each
    need the other (a focus offset and a bright rim; alone, each makes some detection pairs worse) are
    screened as a pair.

    Runs only when an effect is *promising*: its effect size exceeds its threshold but its p-value does not
    pass (on clean data no effect comes near the threshold, so nothing is tried there). The most promising
    effect P's fitted model is the reference for every other candidate (:func:`detect.test_effects`); the
    strongest detected one E, refitted together with P, is then tested as a pair against ``current``: the
    pair is taken (P first, then E) when its per-pair log MSE ratios pass the signed-rank test and it removes
    more than the larger of the two thresholds of ``current``'s systematic error. The exchange step
    (:func:`exchange_causes`) re-examines both.

    Returns:
        [(P's finding, its model), (the pair's finding for E, the pair's model)], or None.
    """
    promising = [f for f in findings if not f.detected and f.testable and f.effect != "noise" and f.model is not None
                 and f.effect in candidates and f.effect_size > cfg.threshold(f.effect)]
    if not promising:
        return None
    lead = max(promising, key=lambda f: f.effect_size)
    others = tuple(e for e in candidates if e != lead.effect)
    if not others:
        return None
    inner = test_effects(lead.model, fit, det, cfg, others)
    second = next((f for f in inner if f.detected and f.effect != "noise" and f.model is not None), None)
    if second is None:
        log.info("pair look-ahead from %s (effect %.3f, p %.2g): nothing detected beside it", lead.effect, lead.effect_size, lead.p_value)
        return None
    pair_model = joint_refit(second.model, lead.model, fit, det, chain)
    t, p, effect, su = step_statistics(current, pair_model, det, cfg, noise)
    ok = p < cfg.alpha and effect > max(cfg.threshold(lead.effect), cfg.threshold(second.effect))
    log.info("pair look-ahead %s + %s against the model before: effect %.3f p %.2g -> %s", lead.effect, second.effect, effect, p,
             "taken" if ok else "not taken")
    if not ok:
        return None
    pair_finding = Finding(second.effect, t, p, effect, True, second.params, second.explanation, pair_model, su, second.held)
    return [(lead, lead.model), (pair_finding, pair_model)]


def without_cause(model: BaseModel, name: str, base: BaseModel, fit: list[Sample], det: list[Sample], cfg: ChainConfig) -> BaseModel:
    """``model`` without the component ``name``, the others refitted together (the fitted ``base`` when none
    is left)."""
    kept = [copy.deepcopy(c) for c in model.components if c.name != name]
    if not kept:
        return base
    reduced = model.replaced(kept)
    fit_parameters(reduced, joint_targets(reduced, fit), [s.batch for s in fit], [s.field for s in fit], masks=[s.score for s in fit],
                   iters=cfg.joint_lm_iters)
    return keep_rim_if_better(reduced, model, det)


def exchange_causes(chain: Chain, base: BaseModel, fit: list[Sample], det: list[Sample], cfg: DetectConfig, chain_cfg: ChainConfig,
                    candidates: tuple[str, ...]) -> Chain:
    """Re-select every chosen cause's slot given the others, then rebuild the steps when the set changed.

    For each cause c (in the order chosen): the final model without c, refitted (:func:`without_cause`), is
    the reference for :func:`detect.test_effects` over every structural effect not among the others (c
    included), with the nested test of the two leading ones. If nothing is detected, c is dropped; if the
    winner is another effect and its model predicts the detection pairs better than the current final model,
    it replaces c; otherwise c stays. Up to :attr:`ChainConfig.exchange_passes` passes, until one changes
    nothing. Detection pairs decide; the fit pairs only fit.
    """
    names = [s.finding.effect for s in chain.steps]
    model = chain.steps[-1].model
    mse = masked_mse(model, det)
    exchanges: list[Exchange] = []
    chosen_finding: dict[str, Finding] = {s.finding.effect: s.finding for s in chain.steps}
    reduced_of: dict[str, BaseModel] = {}
    """The current final model without each cause, as this pass computed it (a change empties it)."""
    for _ in range(chain_cfg.exchange_passes):
        changed = False
        reduced_of = {}
        for name in list(names):
            if name not in names or len(names) < 2:
                continue
            others = [n for n in names if n != name]
            reduced = without_cause(model, name, base, fit, det, chain_cfg)
            reduced_of[name] = reduced
            pool = tuple(e for e in candidates if e not in others)
            findings = test_effects(reduced, fit, det, cfg, pool)
            discriminate(findings, reduced, fit, det, cfg)
            win = next((f for f in findings if f.detected and f.model is not None), None)
            own = next((f for f in findings if f.effect == name), None)
            if win is None:
                names.remove(name)
                model, mse, changed = reduced, masked_mse(reduced, det), True
                reduced_of = {}
                exchanges.append(Exchange(name, "dropped", "", own.effect_size if own else 0.0, own.p_value if own else 1.0, findings))
                log.info("exchange: %s dropped (nothing detected without it)", name)
                continue
            if win.effect != name:
                cand = joint_refit(win.model, reduced, fit, det, chain_cfg)
                cand_mse = masked_mse(cand, det)
                if cand_mse < mse:
                    names[names.index(name)] = win.effect
                    chosen_finding[win.effect] = win
                    model, mse, changed = cand, cand_mse, True
                    reduced_of = {}
                    exchanges.append(Exchange(name, "replaced", win.effect, win.effect_size, win.p_value, findings))
                    log.info("exchange: %s replaced by %s (detection MSE %.4g)", name, win.effect, cand_mse)
                    continue
            exchanges.append(Exchange(name, "kept", name, own.effect_size if own else win.effect_size,
                                      own.p_value if own else win.p_value, findings))
        if not changed:
            break
    # a last pass that changed nothing left the final model without each cause: what Chain.without holds
    without = [reduced_of[n] for n in names] if len(names) >= 2 and set(reduced_of) == set(names) else []
    if [s.finding.effect for s in chain.steps] == names:
        chain.exchanges = exchanges
        chain.without = [reduced_of[s.finding.effect] for s in chain.steps] if without else []
        return chain
    steps = ordered_steps(names, model, base, chain.first_findings, chosen_finding, fit, det, cfg, chain_cfg)
    order = [st.finding.effect for st in steps]
    return Chain(steps, chain.first_findings, chain.first_discrimination, chain.noise, chain.step_findings, exchanges,
                 chain.forward_order, [reduced_of[n] for n in order] if without else [])


def ordered_steps(names: list[str], final: BaseModel, base: BaseModel, first: list[Finding], chosen: dict[str, Finding],
                  fit: list[Sample], det: list[Sample], cfg: DetectConfig, chain_cfg: ChainConfig) -> list[ChainStep]:
    """The steps of an exchanged set: causes ordered by what each explains alone against the base model
    (step 1's effect sizes), step k's model the base model with the first k causes fitted together (the last
    is ``final``), and each step's finding measured against the model of the steps before it on the
    detection pairs (its statistic, p-value and effect size; parameters and text from the final model)."""
    solo = {f.effect: f.effect_size for f in first}
    order = sorted(names, key=lambda n: -solo.get(n, -math.inf))
    models: list[BaseModel] = []
    prev = base
    for k, name in enumerate(order):
        if k == len(order) - 1:
            model = final
        else:
            model = fit_effect(prev, name, fit, cfg.lm_iters, refit_rim=True, refit_previous="all")[0]
            model = keep_rim_if_better(model if prev is base else joint_refit(model, prev, fit, det, chain_cfg), prev, det)
        models.append(model)
        prev = model
    noise = next((f for f in first if f.effect == "noise"), None)
    steps: list[ChainStep] = []
    prev = base
    for name, model in zip(order, models):
        t, p, effect, su = step_statistics(prev, model, det, cfg, noise)
        comp = final.component(name)
        params = comp.describe()
        src = chosen.get(name)
        f = Finding(name, t, p, effect, bool(p < cfg.alpha and effect > cfg.threshold(name)), params,
                    explanation(name, params, src.held if src else ()), model, su, src.held if src else (), testable=True)
        log.info("step %d after the exchange: %s effect %.4f p %.2g", len(steps) + 1, name, effect, p)
        steps.append(ChainStep(f, model, None))
        prev = model
    return steps


def model_intervals(model: BaseModel, fit: list[Sample]) -> dict[str, dict[str, tuple[float, float]]]:
    """95 % intervals (clustered over pairs, :func:`parameter_intervals`) of every fitted parameter of
    ``model``: ``{"base": {...}, <component name>: {...}}``, in each parameter's own units."""
    targets = joint_targets(model, fit)
    iv = parameter_intervals(model, targets, [s.batch for s in fit], [s.field for s in fit], [s.score for s in fit])
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for o, n in targets:
        key = "base" if o is model else o.name  # type: ignore[attr-defined]
        if (id(o), n) in iv:
            out.setdefault(key, {})[n] = iv[(id(o), n)]
    return out
