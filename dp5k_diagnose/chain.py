"""Every cause, in order: greedy forward selection of effects on top of the fitted base model.

Step k tests the effects not yet chosen against the model of steps 1..k-1 (:func:`detect.test_effects` with
that model as the reference), extends it with the strongest detected structural effect (after the nested
test of the two leading ones), refits every chosen component together, and repeats until no structural
effect is detected or :attr:`ChainConfig.max_causes` are chosen. ``noise`` is a measurement, not a
structural effect: a simulator's output is an expectation, so noise cannot raise PSNR; it is measured
against the final model and, when its excess over the nominal sensor is significant, named after every
structural effect.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field

from dp5k_common.effects import EFFECT_NAMES
from neural_dp.simulators.base import BaseModel, fit_parameters
from neural_dp.simulators.base.components import fittable_names
from neural_dp.simulators.base.fit import parameter_intervals

from .data import Sample
from .detect import PSF_NUISANCE, DetectConfig, Discrimination, Finding, discriminate, keep_rim_if_better, masked_mse, test_effects

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
    """

    max_causes: int = 4
    retest_min_effect: float = 0.0
    joint_lm_iters: int = 2


@dataclass
class ChainStep:
    """One chosen effect: its finding at the step it was chosen (tested against the previous model) and the
    model after the step (all chosen components refitted together)."""

    finding: Finding
    model: BaseModel
    discrimination: Discrimination | None = None


@dataclass
class Chain:
    """The result of the forward selection.

    Attributes:
        steps: the structural effects in the order chosen.
        first_findings: every effect's finding against the base model (step 1).
        first_discrimination: the nested test of step 1.
        noise: the noise finding measured against the final structural model (None when not tested).
        step_findings: every step's findings (step 1 first), for the report.
    """

    steps: list[ChainStep]
    first_findings: list[Finding]
    first_discrimination: Discrimination | None
    noise: Finding | None
    step_findings: list[list[Finding]] = field(default_factory=list)

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
            break
        model = chosen.model if not steps else joint_refit(chosen.model, current, fit, det, chain)
        steps.append(ChainStep(chosen, model, disc))
        log.info("cause %d: %s (effect size %.3f, p %.2g)", len(steps), chosen.effect, chosen.effect_size, chosen.p_value)
        current = model
        candidates = tuple(f.effect for f in findings if f.effect not in ("noise", chosen.effect) and f.testable
                           and f.effect_size > chain.retest_min_effect)
        if len(steps) >= chain.max_causes or not candidates:
            if with_noise:  # noise measured against the final model
                noise = next(f for f in test_effects(current, fit, det, cfg, ("noise",)) if f.effect == "noise")
            break
    return Chain(steps, first or [], first_disc, noise, all_findings)


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
