r"""Naming: which physical causes explain what the measured atlas shows and the simulator's does not.

The measurement decides, the fit confirms (docs/diagnose.md, "Naming"):

1. Every effect's signature is read off the measured and the simulator's atlases (:mod:`.signatures`). An effect
   whose signature differs beyond its interval and its minimum is a *candidate*; one whose signature could not
   be measured is never named.
2. Each candidate is added to the model alone, its parameters started from its signature where the signature says
   them directly, and the model is refitted on the fit crops.
3. Of the candidates whose extended model predicts the held-out pairs better (the PSNR gain's 95 % interval, tiles
   resampled within each held-out pair, above 0, and the gain at least :data:`MIN_GAIN_DB`), the one that gains most
   is named. A candidate that never does (in :data:`MAX_TRIES` rounds) is a *suspect*: its signature differs, but
   the component that stands for it does not predict better.
4. The extended model is rendered again on every pair, its atlas re-measured (the measured side is not measured
   again) and every signature read anew: a cause's side effects (the blur of a resampled shift, the brightness
   of a moved split) leave the other signatures with it. Back to 2 until no candidate is left; a candidate that
   gained but less than the one named stays one for the next round, on top of it (:data:`MAX_TRIES`).
5. Each named cause is then checked given the others: the model without it, refitted, against the full one on
   the held-out pairs. A cause that another explains (a moved split carries a gain ramp) is dropped and reported
   as that cause's look-alike, with the capture that would tell them apart.

``noise`` is measured, not fitted (a prediction is an expectation): it is named from its own signature, the views'
white-noise variance over the nominal sensor's, and comes last.
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from neural_dp.registry import COMPONENTS, BaseModel, lm_fit
from neural_dp.registry import fittable_names

from .config import DiagnoseConfig
from .data import Sample
from .fitting import PSF_NUISANCE, covered_field_box
from .gain import TileErrors, tile_bootstrap_ci, tile_errors, tile_psnr
from .signatures import Signature

log = logging.getLogger(__name__)

SEPARATING_CAPTURE: dict[frozenset[str], str] = {
    frozenset({"lr_gain_imbalance", "field_varying_psf"}): "a flat field (a uniform, defocused target filling the frame): a gain ramp changes the L/R brightness ratio of flat content, a moved or leaking split changes the blur's shape off axis",
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
"""The capture that separates two effects whose signatures one cause can produce both of."""


def separating_capture(a: str, b: str) -> str:
    return SEPARATING_CAPTURE.get(frozenset({a, b}), "pairs with content on both sides of focus in every part of the field")


# ---------------------------------------------------------------------------------------------- models
def targets_of(model: BaseModel, fit: Sequence[Sample]) -> list[tuple[object, str]]:
    """Every parameter of ``model`` the fit crops constrain: each component's fittable ones, the gain and the PSF
    nuisance (:data:`fitting.PSF_NUISANCE`: the rim softness and the pixel sampling, which trade off against any
    effect that changes the blur and are refitted with every model)."""
    out: list[tuple[object, str]] = []
    for c in model.components:
        out += [(c, n) for n in fittable_names(c, fit)]
    return out + [(model, "gain")] + [(model, k) for k in PSF_NUISANCE]


def new_component(name: str, fit: Sequence[Sample]) -> Any:
    """A component of effect ``name`` at its neutral values, told the field its fit data covers."""
    c = COMPONENTS[name]()
    c.field_box = covered_field_box(list(fit))
    if name == "focus_offset":  # it records the mean focus distance, to report the offset in mm
        c.initial_guess(BaseModel(), fit[0].batch, fit[0].field)
    return c


def start_from_signature(comp: Any, sig: Signature, fit: Sequence[Sample]) -> None:
    """Write the parameters a signature states directly into ``comp`` (the fit starts there)."""
    v = {x.name: x.value for x in sig.values}
    b = fit[0].batch
    if comp.name == "lr_gain_imbalance":
        comp.params.update(a0=v.get("lr_log_ratio_centre", 0.0), ax=v.get("lr_log_ratio_per_x", 0.0), ay=v.get("lr_log_ratio_per_y", 0.0))
    elif comp.name == "misregistration":
        dx, dy = v.get("shift_x", 0.0), v.get("shift_y", 0.0)
        comp.params.update(left_dx_px=dx, right_dx_px=dx, left_dy_px=dy, right_dy_px=dy)
    elif comp.name == "disparity_scale":
        e = [x for x in sig.values if x.name == "split_efficiency"]
        if e and np.isfinite(e[0].model) and e[0].model > 0:
            comp.params["disparity_scale"] = float(np.clip(e[0].measured / e[0].model, -0.5, 1.0))
    elif comp.name == "focus_offset" and "coc_offset" in v:
        # beta px of CoC at the recorded focus: C'(0) = K (1 - k) to first order, K = f^2 / (N (F - f)) / pitch
        f, N, F, pitch = (float(t.mean()) for t in (b.focal_length_mm, b.f_number, b.focus_distance_mm, b.pixel_pitch_mm))
        K = f * f / (N * (F - f)) / pitch
        comp.params["focus_factor"] = float(np.clip(1.0 - v["coc_offset"] / max(K, 1e-6), 0.6, 1.6))
    for k, (lo, hi) in getattr(comp, "bounds", {}).items():
        if k in comp.params:
            comp.params[k] = float(np.clip(comp.params[k], lo, hi))


def refit(model: BaseModel, fit: Sequence[Sample], iters: int) -> BaseModel:
    """``model`` with every parameter the fit crops constrain refitted in place (Levenberg-Marquardt); returns it."""
    lm_fit(model, targets_of(model, fit), fit, iters)
    return model


def without(model: BaseModel, name: str) -> BaseModel:
    """A copy of ``model`` without the component ``name`` (the others copied with their values)."""
    return model.replaced([copy.deepcopy(c) for c in model.components if c.name != name])


def copy_model(model: BaseModel) -> BaseModel:
    return model.replaced([copy.deepcopy(c) for c in model.components])


# ---------------------------------------------------------------------------------------------- held-out gains
@dataclass
class HeldOut:
    """The held-out pairs and each model's tile errors on them (rendered once per model)."""

    samples: list[Sample]
    tile_px: int
    n_boot: int
    seed: int
    _cache: dict[int, tuple[BaseModel, TileErrors]] = field(default_factory=dict)

    def errors(self, model: BaseModel) -> TileErrors:
        key = id(model)
        if key not in self._cache or self._cache[key][0] is not model:
            self._cache[key] = (model, tile_errors(lambda s: model.render(s.batch, s.field), self.samples, self.tile_px))
        return self._cache[key][1]

    def gain(self, before: BaseModel, after: BaseModel) -> dict[str, Any]:
        """The mean PSNR gain (dB) of ``after`` over ``before`` on the held-out pairs, its 95 % interval (tiles
        resampled within each pair) and per pair."""
        eb, ea = self.errors(before), self.errors(after)
        g = tile_psnr(ea) - tile_psnr(eb)
        lo, hi = tile_bootstrap_ci(eb, ea, self.n_boot, seed=self.seed)
        mean = float(np.nanmean(g)) if np.isfinite(g).any() else 0.0
        return {"gain_db": mean, "gain_ci_db": [lo, hi],
                "gain_per_pair_db": {pid: (float(x) if np.isfinite(x) else None) for pid, x in zip(eb.pair_ids, g)}}


MIN_GAIN_DB = 0.05
"""The smallest held-out PSNR gain (dB) that names a cause: a component fitted to a small mismatch of the model (another
renderer's discretisation, a real lens's residual blur) can gain a few hundredths of a dB with an interval above 0;
an effect at the benchmark's detection limit (a change of the views of 0.05 noise variances) gains about 0.2 dB."""


def confirmed(g: dict[str, Any]) -> bool:
    """The gain's interval lies above 0 and the gain reaches :data:`MIN_GAIN_DB`."""
    return bool(g["gain_ci_db"][0] > 0.0 and g["gain_db"] >= MIN_GAIN_DB)


# ---------------------------------------------------------------------------------------------- the loop
@dataclass
class Step:
    """One named cause: the model after it, and how it was decided."""

    name: str
    model: BaseModel
    signature: Signature
    gain: dict[str, Any]
    seconds: float


@dataclass
class Naming:
    """What :func:`name_causes` decided.

    Attributes:
        steps: the causes named, in order (each step's model holds every cause up to it).
        model: the final model (every cause that survived the check given the others).
        signatures: every effect's signature against the final model (the last re-measurement).
        first: every effect's signature against the base model (the first measurement).
        given_others: cause -> its held-out gain given the other causes (the final model against the model
            without it, refitted).
        suspects: effects whose signature differed but whose component did not predict the held-out pairs better.
        lookalikes: causes dropped because another named cause explains their signature too.
        trace: the rounds: candidates, the one tried, the decision.
    """

    steps: list[Step]
    model: BaseModel
    signatures: dict[str, Signature]
    first: dict[str, Signature]
    given_others: dict[str, dict[str, Any]] = field(default_factory=dict)
    suspects: list[dict[str, Any]] = field(default_factory=list)
    lookalikes: list[dict[str, Any]] = field(default_factory=list)
    trace: list[dict[str, Any]] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.steps]


Remeasure = Callable[[BaseModel], dict[str, Signature]]
"""Renders a model on every pair, re-measures its atlas and returns every effect's signature against it."""


MAX_TRIES = 2
"""A candidate that did not gain is fitted in at most this many rounds before it is left a suspect: a cause can mask
another until it is in the model (a bright rim's gain is 0.05 dB beside an unmodelled 5 dB gain ramp, and a
field-varying PSF fitted before the ramp tries to carry the ramp and loses). A candidate that gained but lost to a
better one is fitted again in the next round, on top of it, even where the model with the cause just named left its
signature inside its interval: a look-alike can carry part of a cause in its fit and the rest in the signature's noise
(a front/back asymmetry's spherical term shifts the CoC as a focus error does, and beside a bright rim it gained
1.6 dB to the focus error's 0.8). The check given the others then drops whichever of the two the other explains."""


@dataclass
class _Trial:
    sig: Signature
    model: BaseModel
    gain: dict[str, Any]
    seconds: float


def name_causes(base: BaseModel, first: dict[str, Signature], remeasure: Remeasure, fit: Sequence[Sample], held: HeldOut,
                cfg: DiagnoseConfig, progress: Callable[[str], None] = lambda s: None) -> Naming:
    """Steps 2-5 of the module docstring, from the base model's signatures ``first``.

    Each round fits every candidate (an effect whose signature differs) alone on top of the model so far and names the
    one whose extended model gains most on the held-out pairs, if any is confirmed (:func:`confirmed`): the cause that
    explains most is named first, so that what it also explains (a moved split's brightness ramp) leaves the other
    signatures before they are fitted."""
    sigs = first
    model = base
    steps: list[Step] = []
    fails: dict[str, int] = {}  # rounds in which each candidate did not gain
    lost: set[str] = set()  # candidates that gained in the last round they were fitted in, but less than the one named
    last: dict[str, _Trial] = {}
    trace: list[dict[str, Any]] = []
    while len(steps) < cfg.max_causes:
        def retry(e: str) -> bool:
            """Tried again as often as it gained but lost to a better candidate, and after :data:`MAX_TRIES` failures
            no more."""
            return fails.get(e, 0) < MAX_TRIES

        cands = sorted((s for e, s in sigs.items() if e != "noise" and e in cfg.effects and e not in {x.name for x in steps}
                        and retry(e) and (s.differs(cfg.alpha) or e in lost)), key=lambda s: -s.strength())
        if not cands:
            break
        trials = []
        for sig in cands:
            progress(f"fitting {sig.effect}")
            t0 = time.perf_counter()
            comp = new_component(sig.effect, fit)
            start_from_signature(comp, sig, fit)
            ext = refit(copy_model(model).with_component(comp), fit, cfg.cause_lm_iters)
            tr = _Trial(sig, ext, held.gain(model, ext), time.perf_counter() - t0)
            trials.append(tr)
            last[sig.effect] = tr
            if not confirmed(tr.gain):
                fails[sig.effect] = fails.get(sig.effect, 0) + 1
        ok = [tr for tr in trials if confirmed(tr.gain)]
        trace.append({"candidates": [{"effect": tr.sig.effect, "strength": tr.sig.strength(), **_gain_json(tr.gain),
                                      "confirmed": confirmed(tr.gain)} for tr in trials]})
        if not ok:
            break
        best = max(ok, key=lambda tr: tr.gain["gain_db"])
        lost = {tr.sig.effect for tr in ok if tr is not best}  # fitted again on top of it, whatever their signature does
        log.info("named %s: held-out gain %+.3f dB [%+.3f, %+.3f]", best.sig.effect, best.gain["gain_db"], *best.gain["gain_ci_db"])
        trace[-1]["named"] = best.sig.effect
        steps.append(Step(best.sig.effect, best.model, best.sig, best.gain, best.seconds))
        model = best.model
        progress(f"re-measuring the atlas with {best.sig.effect}")
        sigs = remeasure(model)
    named = {s.name for s in steps}
    suspects = []
    for e, tr in last.items():
        if e in named:
            continue
        g = tr.gain
        suspects.append({"name": e, **_gain_json(g), "signature": tr.sig.to_json(cfg.alpha),
                         "why": "Its signature differs from the simulator's, but the model extended by it does not predict the "
                                f"held-out pairs better (PSNR gain {g['gain_db']:+.3f} dB, 95 % CI [{g['gain_ci_db'][0]:+.3f}, "
                                f"{g['gain_ci_db'][1]:+.3f}]; {MIN_GAIN_DB:g} dB and an interval above 0 name a cause)"})
    naming = Naming(steps, model, sigs, first, suspects=suspects, trace=trace)
    if len(steps) > 1:
        progress("checking each cause given the others")
        check_given_others(naming, fit, held, cfg)
    elif steps:
        naming.given_others[steps[0].name] = steps[0].gain
    return naming


CHECK_LM_ITERS = 3
"""Iterations of each refit of the check given the others (started at the full model's values)."""


def check_given_others(naming: Naming, fit: Sequence[Sample], held: HeldOut, cfg: DiagnoseConfig) -> None:
    """Step 5: each cause's held-out gain given the others; while one's interval does not lie above 0, the weakest
    is dropped (a look-alike of the cause whose model explains it) and the rest are refitted and checked again."""
    while True:
        model = naming.model
        gains: dict[str, dict[str, Any]] = {}
        models: dict[str, BaseModel] = {}
        for s in naming.steps:  # started at the full model's values: a few iterations reach the refit
            models[s.name] = refit(without(model, s.name), fit, CHECK_LM_ITERS)
            gains[s.name] = held.gain(models[s.name], model)
        weak = [n for n, g in gains.items() if not confirmed(g)]
        if not weak:
            naming.given_others = gains
            return
        worst = min(weak, key=lambda n: (gains[n]["gain_ci_db"][0], gains[n]["gain_db"]))
        rest = [s.name for s in naming.steps if s.name != worst]
        # the cause that explains it: the one whose removal from the model without ``worst`` costs most
        explainer = rest[0] if len(rest) == 1 else _explainer(models[worst], rest, fit, held, cfg)
        log.info("%s is explained by %s given the other causes (gain %+.3f dB [%+.3f, %+.3f])", worst, explainer,
                 gains[worst]["gain_db"], *gains[worst]["gain_ci_db"])
        naming.lookalikes.append({"names": [explainer, worst], "captures": [separating_capture(explainer, worst)], "kinds": ["explains"],
                                  "gain_given_others_db": gains[worst]["gain_db"], "gain_given_others_ci_db": gains[worst]["gain_ci_db"],
                                  "why": f"{worst}'s signature differed from the simulator's, but beside {explainer} its component adds "
                                         f"{gains[worst]['gain_db']:+.3f} dB (95 % CI [{gains[worst]['gain_ci_db'][0]:+.3f}, "
                                         f"{gains[worst]['gain_ci_db'][1]:+.3f}]) on the held-out pairs: {explainer} explains it"})
        naming.steps = [s for s in naming.steps if s.name != worst]
        naming.model = models[worst]
        if len(naming.steps) == 1:
            naming.given_others = {naming.steps[0].name: held.gain(refit(without(naming.model, naming.steps[0].name), fit, CHECK_LM_ITERS),
                                                                   naming.model)}
            return


def _explainer(model: BaseModel, names: list[str], fit: Sequence[Sample], held: HeldOut, cfg: DiagnoseConfig) -> str:
    """Of ``names`` (causes of ``model``), the one whose removal costs ``model`` most on the held-out pairs."""
    costs = {n: held.gain(refit(without(model, n), fit, CHECK_LM_ITERS), model)["gain_db"] for n in names}
    return max(costs, key=costs.get)


def _gain_json(g: dict[str, Any]) -> dict[str, Any]:
    return {"gain_db": g["gain_db"], "gain_ci_db": list(g["gain_ci_db"])}
