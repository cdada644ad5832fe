"""``dp5k diagnose``: fit, show what the model gets wrong, name the cause, extend the model, measure the gain."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dp5k_common.dataset import SHARP_F_NUMBER, DatasetReader
from dp5k_common.effects import EFFECT_NAMES, NO_EFFECT
from dp5k_common.errors import BadInputError
from dp5k_common.software import software_versions
from neural_dp.registry import BaseModel, SimulatorSpec, model_to_spec

from .data import Sample, crop_samples, full_samples, load_pairs, read_sharp_at, unstated_sharp_pairs
from .config import DetectConfig, SelectConfig
from .findings import Finding
from .fitting import fit_base
from .selection import Selection, drop_cause, model_intervals, select_causes
from .tiles import masked_mse
from .gain import TileErrors, bootstrap_ci, gain_report, pair_metrics_by_mask, tile_bootstrap_ci, tile_errors, tile_psnr
from .neural_reach import NeuralReachConfig

log = logging.getLogger(__name__)


@dataclass
class DiagnoseConfig:
    """Settings of one diagnosis.

    Attributes:
        fit_pairs: at most this many training pairs are used to fit (the rest of train helps detection);
            None = every train pair (the CLI's default where train is small, :func:`auto_fit_pairs`).
        crop_px: fit and detection use square crops of this side (whole images when smaller).
        crops_per_pair: crops per pair when the images are larger than ``crop_px``.
        det_pairs: at most this many pairs in the detection set.
        n_boot: bootstrap resamples for the gain's CI.
        seed: seeds crop positions and the bootstrap.
        detect: the detectors' statistical settings.
        effects: the effects to test (default: the whole vocabulary).
        neural: the Neural DP extension study's settings (``--simulator neural:CKPT``); its fine-tuning seed is
            ``seed``.
        sharp_f_number: how to read ``sharp`` in pairs whose params.json does not state ``sharp_f_number``:
            None = choose (:data:`SHARP_READINGS`, :class:`SharpReading`), else that f-number (0 = all-in-focus).
        select: how every cause is chosen (:mod:`dp5k_diagnose.selection`).
        threads: PyTorch intra-op threads while diagnosing (restored after; 0 = leave as set). The base model
            renders crops of about 100 px node by node, which more threads barely speed up, and where the
            cores are shared with other work, OpenMP threads that wait for each other slow it down many times:
            the base fit of the demo's 12 pairs of 96 x 64 took 3.8 s of CPU at one thread and 82 s at two
            (2-core machine at load 9, 2026-11-27).
    """

    fit_pairs: int | None = 4
    crop_px: int = 96
    crops_per_pair: int = 2
    det_pairs: int = 16
    n_boot: int = 2000
    seed: int = 0
    detect: DetectConfig = field(default_factory=DetectConfig)
    effects: tuple[str, ...] = EFFECT_NAMES
    neural: NeuralReachConfig = field(default_factory=NeuralReachConfig)
    sharp_f_number: float | None = None
    select: SelectConfig = field(default_factory=SelectConfig)
    threads: int = 1


SHARP_READINGS = (SHARP_F_NUMBER, 0.0)
"""The readings tried for a ``sharp`` whose f-number params.json does not state: format v1's f/22 capture,
and an all-in-focus image (what a generator that blurs ``sharp`` itself, Eq. 2 read literally, writes)."""


@dataclass
class SharpReading:
    """How ``sharp`` was read in the pairs whose params.json does not state ``sharp_f_number``.

    Attributes:
        f_number: the f-number given to those pairs (0 = all-in-focus); None when every pair states its own.
        source: "params.json" (every pair states it), "--sharp-f-number" (the user's) or "selected".
        unstated: ids of the pairs without the key.
        detect_mse: per reading tried, the detection-set MSE of the model that reading's diagnosis chose
            (base, or base + its named effect); the lower one is selected.
        causes: per reading tried, the cause it named.
    """

    f_number: float | None
    source: str
    unstated: frozenset[str] = frozenset()
    detect_mse: dict[str, float] = field(default_factory=dict)
    causes: dict[str, str] = field(default_factory=dict)

    def apply(self, samples: list[Sample]) -> list[Sample]:
        """The samples read this way."""
        return samples if self.f_number is None else read_sharp_at(samples, self.f_number, self.unstated)

    def to_json(self) -> dict[str, Any]:
        return {"f_number": self.f_number, "source": self.source, "pairs_without_key": len(self.unstated),
                "detect_mse": self.detect_mse, "causes": self.causes}


@dataclass
class _Pass:
    """One diagnosis of the fit and detection sets under one reading of ``sharp``."""

    base: BaseModel
    selection: Selection
    extended: BaseModel
    detect_mse: float
    seconds: tuple[float, float]
    """(fitting the base model, selecting the causes)."""

    @property
    def cause(self) -> str:
        return self.selection.names[0] if self.selection.names else NO_EFFECT


def _detect_pass(fit: list[Sample], det: list[Sample], cfg: DiagnoseConfig) -> _Pass:
    t0 = time.perf_counter()
    base = fit_base(fit, cfg.detect.base_lm_iters)
    log.info("base model fitted: %s", base.params)
    t1 = time.perf_counter()
    selection = select_causes(base, fit, det, cfg.detect, cfg.select, cfg.effects)
    extended = selection.extended()
    mse = masked_mse(extended, det)
    return _Pass(base, selection, extended, mse, (t1 - t0, time.perf_counter() - t1))


@dataclass
class Diagnosis:
    model: str
    dataset: str
    base: BaseModel
    findings: list[Finding]
    cause: str
    extended: BaseModel
    gain: dict[str, Any]
    timings_s: dict[str, float]
    splits_used: dict[str, list[str]]
    sharp_reading: SharpReading = field(default_factory=lambda: SharpReading(None, "params.json"))
    causes: list[dict[str, Any]] = field(default_factory=list)
    noise_model: dict[str, Any] = field(default_factory=dict)
    fit_coverage: dict[str, Any] = field(default_factory=dict)
    extended_intervals: dict[str, dict[str, tuple[float, float]]] = field(default_factory=dict)
    suspects: list[dict[str, Any]] = field(default_factory=list)
    """Effects the detection pairs chose whose held-out gain given the other causes did not earn them a name
    (95 % CI reaching 0): name, gain and why."""
    lookalikes: list[dict[str, Any]] = field(default_factory=list)
    """Groups of effects the data cannot tell apart (:func:`dp5k_diagnose.selection.find_lookalikes`)."""
    selection: dict[str, Any] = field(default_factory=dict)
    """How the causes were chosen: the screen, the elimination and confirmation rounds."""
    held: list[Sample] | None = field(default=None, repr=False, compare=False)
    """The held-out pairs the gain was measured on, as read (not in the report): the analysis of the same models on
    the same pairs then reuses their layered renders (:data:`neural_dp.simulators.base.model._LAYERS_CACHE`)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "dataset": self.dataset,
            "cause": self.cause,
            "causes": self.causes,
            "findings": [f.to_json() for f in self.findings],
            "gain": self.gain,
            "base_params": dict(self.base.params),
            "extended_model": self.extended.describe(),
            "extended_model_spec": model_to_spec(self.extended),
            "extended_model_intervals": {k: {n: list(v) for n, v in d.items()} for k, d in self.extended_intervals.items()},
            "suspects": self.suspects,
            "lookalikes": self.lookalikes,
            "selection": self.selection,
            "noise_model": self.noise_model,
            "fit_coverage": self.fit_coverage,
            "splits_used": self.splits_used,
            "timings_s": self.timings_s,
            "sharp_reading": self.sharp_reading.to_json(),
            "software": software_versions(),
        }


def choose_splits(reader: DatasetReader, cfg: DiagnoseConfig) -> dict[str, list[str]]:
    """Fit on train, detect on val (else the remaining train pairs, else the fit pairs), gain on test."""
    train = reader.ids("train")
    val = reader.ids("val") if "val" in reader.splits else []
    test = reader.ids("test") if "test" in reader.splits else []
    if not train:
        raise BadInputError("the dataset's train split is empty; diagnose fits on train", where=reader.root)
    rng = np.random.default_rng(cfg.seed)
    order = [train[i] for i in rng.permutation(len(train))]
    n_fit = len(order) if cfg.fit_pairs is None else cfg.fit_pairs
    fit_ids = sorted(order[:n_fit])
    rest = sorted(order[n_fit:])
    det_ids = (val + rest)[: cfg.det_pairs] if (val or rest) else fit_ids
    gain_split = "test" if test else ("val" if val else "train")
    gain_ids = test or val or train
    return {"fit": fit_ids, "detect": det_ids, gain_split: gain_ids}


SMALL_TRAIN_PAIRS = 8
"""A train split of at most this many pairs is fitted whole by the CLI's ``--fit-pairs auto`` (when another
split holds pairs to detect on); a larger one fits :data:`DEFAULT_FIT_PAIRS`."""
DEFAULT_FIT_PAIRS = 6
"""Fit pairs of ``--fit-pairs auto`` on a larger train split."""


def auto_fit_pairs(dataset: str | Path) -> int | None:
    """``--fit-pairs auto``: None (every train pair) where train is small and val is not empty, else
    :data:`DEFAULT_FIT_PAIRS`."""
    reader = DatasetReader(dataset)
    small = len(reader.ids("train")) <= SMALL_TRAIN_PAIRS
    has_val = "val" in reader.splits and bool(reader.ids("val"))
    return None if small and has_val else DEFAULT_FIT_PAIRS


@contextmanager
def intra_op_threads(n: int) -> Iterator[None]:
    """PyTorch's intra-op threads set to ``n`` (0: unchanged) inside the block, restored after."""
    before = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def diagnose_base(dataset: str | Path, cfg: DiagnoseConfig | None = None) -> Diagnosis:
    """Diagnose the physical base model on a format-v1 dataset (with :attr:`DiagnoseConfig.threads`)."""
    cfg = cfg or DiagnoseConfig()
    with intra_op_threads(cfg.threads):
        return _diagnose_base(dataset, cfg)


def _diagnose_base(dataset: str | Path, cfg: DiagnoseConfig) -> Diagnosis:
    t0 = time.perf_counter()
    reader = DatasetReader(dataset)
    splits = choose_splits(reader, cfg)
    rng = np.random.default_rng(cfg.seed)
    fit = crop_samples(load_pairs(reader, splits["fit"]), cfg.crop_px, cfg.crops_per_pair, rng)
    det = crop_samples(load_pairs(reader, splits["detect"]), cfg.crop_px, 1, rng)
    unstated = unstated_sharp_pairs(reader, sorted({pid for ids in splits.values() for pid in ids}))
    t_load = time.perf_counter()
    if not unstated:
        tries: tuple[float | None, ...] = (None,)
        source = "params.json"
    elif cfg.sharp_f_number is not None:
        tries, source = (float(cfg.sharp_f_number),), "--sharp-f-number"
    else:
        tries, source = SHARP_READINGS, "selected"
        log.info("%d pairs do not state sharp_f_number: diagnosing with sharp read at f/%g and as all-in-focus",
                 len(unstated), SHARP_F_NUMBER)
    passes: dict[float | None, _Pass] = {}
    for ns in tries:
        reading = SharpReading(ns, source, unstated)
        passes[ns] = _detect_pass(reading.apply(fit), reading.apply(det), cfg)
    chosen = min(passes, key=lambda k: passes[k].detect_mse)
    label = lambda k: "stated" if k is None else f"{k:g}"  # noqa: E731
    reading = SharpReading(chosen, source, unstated, {label(k): p.detect_mse for k, p in passes.items()},
                           {label(k): p.cause for k, p in passes.items()})
    if len(passes) > 1:
        log.info("sharp read as %s (detection MSE %s)", "all-in-focus" if chosen == 0 else f"f/{chosen:g}", reading.detect_mse)
    ps = passes[chosen]
    base, selection = ps.base, ps.selection
    t_fit = t_load + sum(p.seconds[0] for p in passes.values())
    t_det = time.perf_counter()
    gain_split = next(k for k in splits if k not in ("fit", "detect"))
    held = reading.apply(full_samples(load_pairs(reader, splits[gain_split])))
    before = pair_metrics_by_mask(lambda s: base.render(s.batch, s.field), held)
    before_tiles = tile_errors(lambda s: base.render(s.batch, s.field), held, cfg.detect.tile_px)
    selection, causes, suspects = confirm_on_held_out(selection, base, before_tiles, held, cfg)
    extended = selection.extended()
    cause = selection.names[0] if selection.names else NO_EFFECT
    after = before if extended is base else pair_metrics_by_mask(lambda s: extended.render(s.batch, s.field), held)
    gain: dict[str, Any] = gain_report(before["predictable"], after["predictable"], gain_split, cfg.n_boot, cfg.seed, "predictable")
    g_all = gain_report(before["valid"], after["valid"], gain_split, cfg.n_boot, cfg.seed, "valid")
    gain["all_valid"] = {k: v for k, v in g_all.items() if k not in ("split", "per_pair_psnr_gain")}
    intervals = model_intervals(selection, reading.apply(fit))
    causes = attach_intervals(causes, intervals)
    coverage = fit_coverage(reader, fit)
    t_end = time.perf_counter()
    timings = {"load": t_load - t0, "fit_base": t_fit - t_load, "detect": t_det - t_fit, "gain": t_end - t_det, "total": t_end - t0}
    return Diagnosis("base", str(dataset), base, selection.findings, cause, extended, gain, timings, splits, reading,
                     causes, noise_model(selection.noise, cfg.detect), coverage, intervals, suspects, selection.lookalikes,
                     selection.trace, held)


def confirm_on_held_out(selection: Selection, base: BaseModel, before: TileErrors, held: list[Sample], cfg: DiagnoseConfig,
                        ) -> tuple[Selection, list[dict[str, Any]], list[dict[str, Any]]]:
    """Name a cause only when it earns it on the held-out pairs: its PSNR gain given the other causes must have
    a 95 % bootstrap CI above 0 (tiles resampled within each held-out pair, :func:`dp5k_diagnose.gain.tile_bootstrap_ci`).
    While a cause's does not, the one with the lowest lower bound becomes a *suspect* and the others are
    refitted and confirmed without it (:func:`dp5k_diagnose.selection.drop_cause`).

    Returns (the selection, report.json ``causes``, report.json ``suspects``)."""
    suspects: list[dict[str, Any]] = []
    tile = cfg.detect.tile_px
    while True:
        def errors(m: BaseModel) -> TileErrors:
            return before if m is base else tile_errors(lambda s: m.render(s.batch, s.field), held, tile)

        step_errors = [errors(m) for m in selection.steps]
        without_errors = [errors(m) for m in selection.without]
        causes = cause_entries(selection, before, step_errors, cfg, without_errors)
        # the point gain too: a percentile interval above 0 around a negative mean is possible in principle
        weak = [c for c in causes if c["name"] != "noise" and not (c["gain_ci_db"][0] > 0.0 and c["gain_db"] > 0.0)]
        if not weak:
            return selection, causes, suspects
        worst = min(weak, key=lambda c: (c["gain_ci_db"][0], c["gain_db"]))
        log.info("%s is a suspect: its held-out gain given the other causes is %+.3f dB, 95 %% CI [%+.3f, %+.3f]", worst["name"],
                 worst["gain_db"], *worst["gain_ci_db"])
        suspects.append({"name": worst["name"], "params": worst["params"], "gain_db": worst["gain_db"], "gain_ci_db": worst["gain_ci_db"],
                         "gain_ci_pairs_db": worst["gain_ci_pairs_db"], "gain_per_pair_db": worst["gain_per_pair_db"],
                         "effect_size": worst["effect_size"], "p_value": worst["p_value"],
                         "why": "the detection pairs chose it, but its PSNR gain on the held-out pairs given the other causes has a 95 % CI "
                                f"[{worst['gain_ci_db'][0]:+.3f}, {worst['gain_ci_db'][1]:+.3f}] dB that does not lie above 0",
                         "explanation": worst["explanation"]})
        selection = drop_cause(selection, worst["name"])


def attach_intervals(causes: list[dict[str, Any]], intervals: dict[str, dict[str, tuple[float, float]]]) -> list[dict[str, Any]]:
    """Each cause entry with its parameters' 95 % intervals (``noise`` keeps its own bootstrap intervals)."""
    for c in causes:
        if c["name"] != "noise":
            c["param_intervals"] = {n: list(v) for n, v in intervals.get(c["name"], {}).items()}
    return causes


def _mean(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=np.float64)
    return float(x[np.isfinite(x)].mean()) if np.isfinite(x).any() else 0.0


def cause_entries(selection: Selection, before: TileErrors, step_errors: list[TileErrors], cfg: DiagnoseConfig,
                  without_errors: list[TileErrors] | None = None) -> list[dict[str, Any]]:
    """report.json ``causes``: per chosen effect, in order, its parameters in the final (extended) model, its
    test on the detection pairs given the other causes (effect size and p), and held-out PSNR gains (dB, the
    mean over the held-out pairs; the base model's, each step model's and each model without a cause's tile
    errors on them, :func:`dp5k_diagnose.gain.tile_errors`):

    * ``gain_db`` / ``gain_ci_db``: what the cause adds to a model holding every other cause (the final model
      against the final model without it, refitted; ``without_errors``, aligned with the steps). Effects
      that hide each other (a bright rim and a focus offset) each gain little alone and much beside the
      other; this is the gain that says the final model needs the cause. With one cause, the step's gain.
      The CI resamples tiles within each pair (:func:`dp5k_diagnose.gain.tile_bootstrap_ci`): the evidence
      of these held-out captures, the one a cause must earn its name by. ``gain_ci_pairs_db`` resamples the
      pairs instead (how much the gain varies between captures; with 4 held-out pairs it is nearly the
      range of their gains).
    * ``step_gain_db`` / ``step_gain_ci_db``: what the step adds over the model of the steps before it (CI
      over tiles within pairs).
    * ``cumulative_gain_db``: the model after the step against the base model (the step gains add up to it).

    ``noise`` comes last with every gain exactly 0 (a prediction is an expectation)."""
    final = selection.model
    final_errors = step_errors[-1] if step_errors else None
    by_name = {f.effect: f for f in selection.findings}
    before_psnr = tile_psnr(before)
    final_psnr = tile_psnr(final_errors) if final_errors is not None else None
    out: list[dict[str, Any]] = []
    prev, prev_errors = before_psnr, before
    cumulative = 0.0
    for k, (name, te) in enumerate(zip(selection.causes, step_errors)):
        comp = final.component(name)
        f = by_name[name]
        psnr = tile_psnr(te)
        d = psnr - prev
        lo, hi = tile_bootstrap_ci(prev_errors, te, cfg.n_boot, seed=cfg.seed)
        if without_errors is not None and final_errors is not None:
            g = final_psnr - tile_psnr(without_errors[k])
            glo, ghi = tile_bootstrap_ci(without_errors[k], final_errors, cfg.n_boot, seed=cfg.seed)
        else:
            g, glo, ghi = d, lo, hi
        cumulative = _mean(psnr - before_psnr)
        out.append({"name": name, "step": k + 1, "params": _json_params(comp.describe()), "param_intervals": {},
                    "effect_size": f.effect_size, "p_value": f.p_value,
                    "gain_db": _mean(g), "gain_ci_db": [glo, ghi], "gain_ci_pairs_db": list(bootstrap_ci(g, cfg.n_boot, seed=cfg.seed)),
                    "gain_per_pair_db": {pid: (float(x) if np.isfinite(x) else None) for pid, x in zip(before.pair_ids, g)},
                    "step_gain_db": _mean(d), "step_gain_ci_db": [lo, hi], "cumulative_gain_db": cumulative,
                    "explanation": f.explanation})
        prev, prev_errors = psnr, te
    nz = selection.noise
    if nz is not None and nz.detected:
        out.append({"name": "noise", "step": len(out) + 1, "params": _json_params(nz.params),
                    "param_intervals": {n: list(v) for n, v in nz.intervals.items()}, "effect_size": nz.effect_size,
                    "p_value": nz.p_value, "gain_db": 0.0, "gain_ci_db": [0.0, 0.0], "gain_ci_pairs_db": [0.0, 0.0],
                    "step_gain_db": 0.0, "step_gain_ci_db": [0.0, 0.0], "cumulative_gain_db": cumulative, "explanation": nz.explanation})
    return out


def _json_params(p: dict[str, Any]) -> dict[str, Any]:
    """Parameters as JSON numbers (a non-finite one, e.g. an offset in mm without a recorded distance, as null)."""
    num = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    return {k: ([num(x) for x in v] if isinstance(v, (list, tuple)) else num(v)) for k, v in p.items()}


def noise_model(noise: Finding | None, cfg: DetectConfig) -> dict[str, Any]:
    """report.json ``noise_model``: the views' measured white noise (variance = shot_var I + read_sigma^2,
    linear units) against the final model, with 95 % bootstrap intervals over pairs, the nominal sensor it is
    compared with, and whether its excess is significant (then ``noise`` is among the causes)."""
    if noise is None or not noise.params:
        return {"measured": False, "note": noise.explanation if noise is not None else "noise not tested"}
    keys = ("shot_var", "read_sigma", "variance_ratio")
    return {"measured": True, **{k: float(noise.params[k]) for k in keys},
            "intervals": {k: list(noise.intervals[k]) for k in keys if k in noise.intervals},
            "nominal": {"shot_var": cfg.nominal_shot_var, "read_sigma": cfg.nominal_read_sigma},
            "excess_p_value": float(noise.p_value), "excess_significant": bool(noise.detected)}


FIELD_ZONES = 3
"""The field [-1, 1]^2 is cut into FIELD_ZONES x FIELD_ZONES zones to say how much of it a fit saw."""


def fit_coverage(reader: DatasetReader, fit: list[Sample]) -> dict[str, Any]:
    """How much the fit saw: pairs, scenes, crops, field zones (of :data:`FIELD_ZONES` squared) holding scored
    pixels, and the field box they span (x0, x1, y0, y1 in [-1, 1])."""
    ids = sorted({pid for s in fit for pid in s.batch.pair_ids})
    scenes = sorted({reader.params(pid).scene for pid in ids})
    zones: set[tuple[int, int]] = set()
    box = [1.0, -1.0, 1.0, -1.0]
    for s in fit:
        m = s.score[:, 0]
        x, y = s.field[:, 0][m], s.field[:, 1][m]
        if x.numel() == 0:
            continue
        box = [min(box[0], float(x.min())), max(box[1], float(x.max())), min(box[2], float(y.min())), max(box[3], float(y.max()))]
        zx = ((x + 1) / 2 * FIELD_ZONES).long().clamp(0, FIELD_ZONES - 1)
        zy = ((y + 1) / 2 * FIELD_ZONES).long().clamp(0, FIELD_ZONES - 1)
        zones |= {(int(a), int(b)) for a, b in torch.unique(torch.stack([zx, zy], 1), dim=0).tolist()}
    return {"pairs": len(ids), "scenes": len(scenes), "crops": sum(s.batch.sharp.shape[0] for s in fit),
            "field_zones": len(zones), "field_zones_of": FIELD_ZONES**2, "field_box": box}


def analyse(predict, samples: list[Sample], with_psfs: bool = True) -> dict[str, Any]:
    """Residual tables, disparity, L/R ratio and PSFs of one model on some samples."""
    from .analysis import disparity_table, estimate_psfs, lr_ratio_table, residual_tables

    out: dict[str, Any] = {
        "residuals": residual_tables(predict, samples),
        "disparity": disparity_table(predict, samples),
        "lr_ratio": lr_ratio_table(predict, samples),
    }
    if with_psfs:
        out["psfs"] = estimate_psfs(predict, samples)
    return out


def run_diagnose(dataset: str | Path, model: SimulatorSpec = SimulatorSpec(), out: str | Path | None = None,
                 cfg: DiagnoseConfig | None = None) -> dict[str, Any]:
    """The whole ``dp5k diagnose``: returns the report.json object and writes DIR/report.{json,md} when ``out``.

    ``model`` is the base model, a peer or a Neural DP checkpoint (:class:`~neural_dp.registry.SimulatorSpec`, from
    ``--simulator``); the effect vocabulary is tested on the physical base model in every case (its components are what can be
    named and added); for a peer, its own residuals are analysed and its metrics reported beside the base's.
    """
    cfg = cfg or DiagnoseConfig()
    model.check_files()
    with intra_op_threads(cfg.threads):
        return _run_diagnose(dataset, model, out, cfg)


def _run_diagnose(dataset: str | Path, model: SimulatorSpec, out: str | Path | None, cfg: DiagnoseConfig) -> dict[str, Any]:
    diag = diagnose_base(dataset, cfg)
    result = diag.to_json()
    held = diag.held
    if held is None:
        reader = DatasetReader(dataset)
        held = diag.sharp_reading.apply(full_samples(load_pairs(reader, diag.splits_used[diag.gain["split"]])))
    analysis: dict[str, Any] = {
        "before": analyse(lambda s: diag.base.render(s.batch, s.field), held),
    }
    if diag.extended is not diag.base:
        analysis["after"] = analyse(lambda s: diag.extended.render(s.batch, s.field), held)
    if not model.is_base:
        peer = model.load()
        by_mask = {m: {k: float(np.nanmean(getattr(pm, k))) for k in ("psnr", "ssim", "mae")}
                   for m, pm in pair_metrics_by_mask(lambda s: peer(s.batch), held).items()}
        result["model"] = str(model)
        result["peer"] = {"name": str(model), "mask": "predictable", **by_mask["predictable"], "all_valid": by_mask["valid"],
                          "note": "effects are named and added on the physical base model; the peer's own errors are in analysis.peer"}
        analysis["peer"] = analyse(lambda s: peer(s.batch), held, with_psfs=False)
    if model.is_neural:
        result["neural_extension"] = extend_neural(dataset, model.checkpoint, out, cfg)
    if out is not None:
        from .report import write_report

        write_report(Path(out), result, analysis)
    return result


def extend_neural(dataset: str | Path, checkpoint: str | Path, out: str | Path | None, cfg: DiagnoseConfig) -> dict[str, Any]:
    """The learned model's structural extension (:func:`dp5k_diagnose.neural_reach.diagnose_neural`): its error
    per |CoC| bin, multi-scale kernels added (equal output at start), fine-tuned beside an equally fine-tuned
    control, gains per |CoC| bin. Files go to ``out/neural`` (a temporary folder when ``out`` is None)."""
    import tempfile
    from contextlib import nullcontext

    from .neural_reach import diagnose_neural

    keys = ("extension", "metrics", "gain", "gain_vs_control", "bins_px", "per_bin", "error_growth", "figures", "split", "n_pairs")
    study = replace(cfg.neural, finetune=replace(cfg.neural.finetune, seed=cfg.seed))
    with tempfile.TemporaryDirectory(prefix="dp5k-neural-") if out is None else nullcontext(Path(out) / "neural") as where:
        res = diagnose_neural(dataset, checkpoint, where, study)
    kept = {k: res[k] for k in keys if k in res}
    if out is not None:  # figure paths relative to the report folder
        kept["figures"] = [f"neural/{f}" for f in res.get("figures", [])]
    return kept

