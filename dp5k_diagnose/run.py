"""``dp5k diagnose``, its steps in order: read the dataset once, measure (the camera's PSF atlas and the simulator's),
read every effect's signature, name the causes (:mod:`.naming`), measure the gain on the held-out pairs, report."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dp5k_common.dataset import SHARP_F_NUMBER
from dp5k_common.effects import NO_EFFECT
from dp5k_common.progress import progress as progress_bar
from dp5k_common.software import PROVENANCE_KEY, provenance, software_versions
from neural_dp.registry import BaseModel, Noise, SimulatorSpec, clustered_intervals, lm_fit, model_to_spec

from .atlas import Atlas
from .config import DiagnoseConfig
from .data import DiagnoseInput, Sample, auto_fit_pairs, read_input
from .explain import explanation
from .fitting import fit_base
from .gain import gain_report, pair_metrics_by_mask
from .measure import Measurement, noise_signature
from .naming import HeldOut, Naming, name_causes, targets_of
from .signatures import Signature

log = logging.getLogger(__name__)

__all__ = ["DiagnoseConfig", "Diagnosis", "auto_fit_pairs", "diagnose_base", "run_diagnose"]

SHARP_READINGS = (SHARP_F_NUMBER, 0.0)
"""The readings tried for a ``sharp`` whose f-number params.json does not state: format v1's f/22 capture, and an
all-in-focus image (what a generator that blurs ``sharp`` itself, Eq. 2 read literally, writes)."""


@dataclass
class SharpReading:
    """How ``sharp`` was read in the pairs whose params.json does not state ``sharp_f_number``.

    Attributes:
        f_number: the f-number given to those pairs (0 = all-in-focus); None when every pair states its own.
        source: "params.json" (every pair states it), "--sharp-f-number" (the user's) or "selected" (the reading
            whose base fit leaves the smaller error on the fit crops).
        unstated: how many pairs do not state it.
        fit_mse: per reading tried, the base model's fit error.
    """

    f_number: float | None
    source: str
    unstated: int = 0
    fit_mse: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"f_number": self.f_number, "source": self.source, "pairs_without_key": self.unstated, "fit_mse": self.fit_mse}


def choose_reading(inp: DiagnoseInput, cfg: DiagnoseConfig) -> tuple[DiagnoseInput, BaseModel, SharpReading]:
    """The input read as its pairs state ``sharp``, or, for pairs that do not, as the user says or as the reading whose
    base fit leaves the smaller error; with the base model fitted under it."""
    if not inp.unstated:
        return inp, fit_base(inp.fit, cfg.base_lm_iters), SharpReading(None, "params.json")
    if cfg.sharp_f_number is not None:
        read = inp.read_sharp_at(cfg.sharp_f_number)
        return read, fit_base(read.fit, cfg.base_lm_iters), SharpReading(cfg.sharp_f_number, "--sharp-f-number", len(inp.unstated))
    tries = {}
    for f in SHARP_READINGS:
        read = inp.read_sharp_at(f)
        base = fit_base(read.fit, cfg.base_lm_iters)
        lin = lm_fit(base, [], read.fit, 0)
        tries[f] = (read, base, lin.sse / max(lin.r.numel(), 1))
    best = min(tries, key=lambda f: tries[f][2])
    log.info("%d pairs do not state sharp_f_number: read as %s (base fit MSE %s)", len(inp.unstated),
             "all-in-focus" if best == 0 else f"f/{best:g}", {f"{k:g}": v[2] for k, v in tries.items()})
    return tries[best][0], tries[best][1], SharpReading(best, "selected", len(inp.unstated), {f"{k:g}": v[2] for k, v in tries.items()})


@dataclass
class Diagnosis:
    """One diagnosis of the physical base model: what was measured, named and gained."""

    dataset: str
    base: BaseModel
    extended: BaseModel
    naming: Naming
    measurement: Measurement
    causes: list[dict[str, Any]]
    gain: dict[str, Any]
    splits_used: dict[str, list[str]]
    sharp_reading: SharpReading
    noise_model: dict[str, Any]
    fit_coverage: dict[str, Any]
    extended_intervals: dict[str, dict[str, tuple[float, float]]]
    timings_s: dict[str, float]
    held: list[Sample] = field(repr=False, default_factory=list)
    """The held-out pairs the gain was measured on, as read: the report's analysis of the same models on the same pairs
    reuses their renders."""

    @property
    def cause(self) -> str:
        return self.causes[0]["name"] if self.causes else NO_EFFECT

    @property
    def atlas(self) -> Atlas:
        return self.measurement.atlas

    def to_json(self) -> dict[str, Any]:
        alpha = self.measurement.cfg.alpha
        return {
            "model": "base",
            "dataset": self.dataset,
            "cause": self.cause,
            "causes": self.causes,
            "signatures": {e: s.to_json(alpha) for e, s in self.naming.first.items()},
            "signatures_after": {e: s.to_json(alpha) for e, s in self.naming.signatures.items()},
            "atlas": atlas_summary(self.atlas),
            "gain": self.gain,
            "base_params": dict(self.base.params),
            "extended_model": self.extended.describe(),
            "extended_model_spec": model_to_spec(self.extended),
            "extended_model_intervals": {k: {n: list(v) for n, v in d.items()} for k, d in self.extended_intervals.items()},
            "suspects": self.naming.suspects,
            "lookalikes": self.naming.lookalikes,
            "naming": self.naming.trace,
            "noise_model": self.noise_model,
            "fit_coverage": self.fit_coverage,
            "splits_used": self.splits_used,
            "timings_s": self.timings_s,
            "sharp_reading": self.sharp_reading.to_json(),
            "software": software_versions(),
            PROVENANCE_KEY: provenance(),
        }


def atlas_summary(atlas: Atlas) -> dict[str, Any]:
    """report.json ``atlas``: what was measured, where it is, and which cells could not be measured (and why)."""
    cells = atlas.cells.values()
    return {"file": "atlas.npz", "view_sets": list(atlas.names), "pairs": len(atlas.pair_ids),
            "cells": sum(1 for _ in cells), "measured": sum(1 for c in cells if c.measured),
            "unmeasured": [{"bin": c.bin, "zone": c.zone, "coc_px": list(c.coc_px), "why": c.unmeasured}
                           for c in cells if not c.measured]}


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


class _Steps:
    """A progress bar over a diagnosis's steps (each named as it starts), silenced like every other bar."""

    def __init__(self, total: int) -> None:
        self.bar = progress_bar(total=total, desc="diagnose", unit="step")

    def __call__(self, what: str) -> None:
        self.bar.set_postfix_str(what, refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def diagnose_base(dataset: str | Path, cfg: DiagnoseConfig | None = None) -> Diagnosis:
    """Diagnose the physical base model on a format-v1 dataset (with :attr:`DiagnoseConfig.threads`)."""
    cfg = cfg or DiagnoseConfig()
    with intra_op_threads(cfg.threads):
        steps = _Steps(6 + 3 * cfg.max_causes)
        try:
            return _diagnose_base(dataset, cfg, steps)
        finally:
            steps.close()


def _diagnose_base(dataset: str | Path, cfg: DiagnoseConfig, step: Callable[[str], None]) -> Diagnosis:
    t = {"start": time.perf_counter()}
    step("reading the dataset")
    inp = read_input(dataset, cfg.fit_pairs, cfg.crop_px, cfg.crops_per_pair, cfg.seed)
    t["read"] = time.perf_counter()
    step("fitting the base model")
    inp, base, reading = choose_reading(inp, cfg)
    t["fit_base"] = time.perf_counter()
    step("measuring the PSF atlas")
    meas = Measurement.of(inp.samples(inp.splits["all"]), base, cfg)
    t["atlas"] = time.perf_counter()
    first = meas.of_model(base, "simulator")
    t["signatures"] = time.perf_counter()
    held = HeldOut(inp.samples(inp.splits["held"]), cfg.tile_px, cfg.n_boot, cfg.seed)
    naming = name_causes(base, first, lambda m: meas.of_model(m, "extended"), inp.fit, held, cfg, step)
    if naming.steps and naming.model is not naming.steps[-1].model:  # the check given the others dropped a cause
        naming.signatures = meas.of_model(naming.model, "extended")
    t["name"] = time.perf_counter()
    step("measuring the gain on the held-out pairs")
    extended = naming.model
    causes = cause_entries(naming, held, cfg)
    if naming.steps:  # against the final model: the named causes leave less structure in the flat regions' L - R
        meas.noise = meas.noise_against(naming.model)
        naming.signatures["noise"] = noise_signature(meas.noise, cfg)
    if naming.signatures["noise"].differs(cfg.alpha) and "noise" in cfg.effects:
        extended = with_noise(extended, meas)
        causes.append(noise_entry(meas, naming.signatures["noise"], len(causes) + 1, causes[-1]["cumulative_gain_db"] if causes else 0.0))
    before = pair_metrics_by_mask(lambda s: base.render(s.batch, s.field), held.samples)
    after = before if extended is base else pair_metrics_by_mask(lambda s: extended.render(s.batch, s.field), held.samples)
    gain = gain_report(before["predictable"], after["predictable"], inp.held_split, cfg.n_boot, cfg.seed, "predictable")
    g_all = gain_report(before["valid"], after["valid"], inp.held_split, cfg.n_boot, cfg.seed, "valid")
    gain["all_valid"] = {k: v for k, v in g_all.items() if k not in ("split", "per_pair_psnr_gain")}
    intervals = parameter_intervals(naming.model, inp.fit) if naming.steps else {}
    for c in causes:
        if c["name"] in intervals:
            c["param_intervals"] = {n: list(v) for n, v in intervals[c["name"]].items()}
    t["gain"] = time.perf_counter()
    # atlas: the measured views' atlas (the sharp side's normal equations, the views' kernels and noise); signatures:
    # the simulator's atlas of its renders of the same pairs, and every signature read off the two
    timings = {"read": t["read"] - t["start"], "fit_base": t["fit_base"] - t["read"], "atlas": t["atlas"] - t["fit_base"],
               "signatures": t["signatures"] - t["atlas"], "name": t["name"] - t["signatures"], "gain": t["gain"] - t["name"],
               "total": t["gain"] - t["start"]}
    splits = {"fit": inp.splits["fit"], "atlas": inp.splits["all"], inp.held_split: inp.splits["held"]}
    return Diagnosis(str(dataset), base, extended, naming, meas, causes, gain, splits, reading, noise_model(meas, cfg),
                     fit_coverage(inp), intervals, timings, held.samples)


def cause_entries(naming: Naming, held: HeldOut, cfg: DiagnoseConfig) -> list[dict[str, Any]]:
    """report.json ``causes``: per named cause, in the order named, its parameters in the final model, its signature
    (against the base model), and its held-out PSNR gains (dB, mean over the held-out pairs, 95 % intervals over
    tiles resampled within each pair): ``gain_db`` given every other cause (the final model against the final model
    without it, refitted), ``step_gain_db`` over the model of the causes before it, ``cumulative_gain_db`` of the
    model up to it over the base model."""
    out: list[dict[str, Any]] = []
    for k, s in enumerate(naming.steps):
        params = _json_params(naming.model.component(s.name).describe())
        g = naming.given_others.get(s.name, s.gain)
        cumulative = (out[-1]["cumulative_gain_db"] if out else 0.0) + s.gain["gain_db"]
        out.append({"name": s.name, "step": k + 1, "params": params, "param_intervals": {},
                    "signature": naming.first[s.name].to_json(cfg.alpha),
                    "gain_db": g["gain_db"], "gain_ci_db": list(g["gain_ci_db"]), "gain_per_pair_db": g.get("gain_per_pair_db", {}),
                    "step_gain_db": s.gain["gain_db"], "step_gain_ci_db": list(s.gain["gain_ci_db"]),
                    "cumulative_gain_db": cumulative, "explanation": explanation(s.name, params)})
    return out


def with_noise(model: BaseModel, meas: Measurement) -> BaseModel:
    """``model`` with the measured noise as its ``noise`` component (a simulator then draws calibrated noise)."""
    comp = Noise()
    comp.params = {"shot_var": meas.noise.shot_var, "read_sigma": meas.noise.read_sigma}
    return model.with_component(comp)


def noise_entry(meas: Measurement, sig: Signature, step: int, cumulative: float) -> dict[str, Any]:
    """The ``noise`` cause: measured, not fitted, so every gain is exactly 0 (a prediction is an expectation)."""
    n = meas.noise
    params = {"shot_var": n.shot_var, "read_sigma": n.read_sigma, "variance_ratio": n.variance_ratio}
    return {"name": "noise", "step": step, "params": params, "param_intervals": {k: list(v) for k, v in n.intervals.items()},
            "signature": sig.to_json(meas.cfg.alpha), "gain_db": 0.0, "gain_ci_db": [0.0, 0.0], "gain_per_pair_db": {},
            "step_gain_db": 0.0, "step_gain_ci_db": [0.0, 0.0], "cumulative_gain_db": cumulative,
            "explanation": explanation("noise", params)}


def _json_params(p: dict[str, Any]) -> dict[str, Any]:
    """Parameters as JSON numbers (a non-finite one, e.g. an offset in mm without a recorded distance, as null)."""
    num = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    return {k: ([num(x) for x in v] if isinstance(v, (list, tuple)) else num(v)) for k, v in p.items()}


def parameter_intervals(model: BaseModel, fit: list[Sample]) -> dict[str, dict[str, tuple[float, float]]]:
    """95 % intervals (clustered over pairs) of every fitted parameter of ``model`` on the fit crops:
    ``{"base": {...}, <effect>: {...}}``, each in its parameter's units."""
    targets = targets_of(model, fit)
    lin = lm_fit(model, targets, fit, 0)
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for (o, n), (lo, hi) in zip(lin.targets, clustered_intervals(lin, fit)):
        if np.isfinite(lo) and np.isfinite(hi):
            out.setdefault("base" if o is model else o.name, {})[n] = (float(lo), float(hi))
    return out


def noise_model(meas: Measurement, cfg: DiagnoseConfig) -> dict[str, Any]:
    """report.json ``noise_model``: the views' measured white noise (variance = shot_var I + read_sigma^2, linear
    units) with 95 % bootstrap intervals over pairs, the nominal sensor it is compared with, and whether its excess
    is named."""
    n = meas.noise
    if not n.measured:
        return {"measured": False, "note": n.note}
    return {"measured": True, "shot_var": n.shot_var, "read_sigma": n.read_sigma, "variance_ratio": n.variance_ratio,
            "intervals": {k: list(v) for k, v in n.intervals.items()},
            "nominal": {"shot_var": cfg.nominal_shot_var, "read_sigma": cfg.nominal_read_sigma}}


FIELD_ZONES = 3
"""The field [-1, 1]^2 is cut into FIELD_ZONES x FIELD_ZONES zones to say how much of it a fit saw."""


def fit_coverage(inp: DiagnoseInput) -> dict[str, Any]:
    """How much the fit saw: pairs, scenes, crops, field zones (of :data:`FIELD_ZONES` squared) holding scored pixels,
    and the field box they span (x0, x1, y0, y1 in [-1, 1])."""
    ids = inp.splits["fit"]
    scenes = sorted({inp.pairs[pid].params.scene for pid in ids})
    zones: set[tuple[int, int]] = set()
    box = [1.0, -1.0, 1.0, -1.0]
    for s in inp.fit:
        m = s.score[:, 0]
        x, y = s.field[:, 0][m], s.field[:, 1][m]
        if x.numel() == 0:
            continue
        box = [min(box[0], float(x.min())), max(box[1], float(x.max())), min(box[2], float(y.min())), max(box[3], float(y.max()))]
        zx = ((x + 1) / 2 * FIELD_ZONES).long().clamp(0, FIELD_ZONES - 1)
        zy = ((y + 1) / 2 * FIELD_ZONES).long().clamp(0, FIELD_ZONES - 1)
        zones |= {(int(a), int(b)) for a, b in torch.unique(torch.stack([zx, zy], 1), dim=0).tolist()}
    return {"pairs": len(ids), "scenes": len(scenes), "crops": sum(s.batch.sharp.shape[0] for s in inp.fit),
            "atlas_pairs": len(inp.splits["all"]), "field_zones": len(zones), "field_zones_of": FIELD_ZONES**2, "field_box": box}


def analyse(predict: Callable[[Sample], tuple[torch.Tensor, torch.Tensor]], samples: list[Sample]) -> dict[str, Any]:
    """Residual tables, disparity and the L/R ratio of one model on some samples (the report's figures)."""
    from .analysis import disparity_table, lr_ratio_table, residual_tables

    return {"residuals": residual_tables(predict, samples), "disparity": disparity_table(predict, samples),
            "lr_ratio": lr_ratio_table(predict, samples)}


def run_diagnose(dataset: str | Path, model: SimulatorSpec = SimulatorSpec(), out: str | Path | None = None,
                 cfg: DiagnoseConfig | None = None) -> dict[str, Any]:
    """The whole ``dp5k diagnose``: returns the report.json object and writes DIR/report.{json,md}, DIR/atlas.npz and
    the figures when ``out``.

    ``model`` is the base model, a peer or a Neural DP checkpoint (:class:`~neural_dp.registry.SimulatorSpec`, from
    ``--simulator``); causes are named and added on the physical base model in every case (its components are what
    can be named); a peer's own atlas, signatures and metrics are reported beside the base model's.
    """
    cfg = cfg or DiagnoseConfig()
    model.check_files()
    with intra_op_threads(cfg.threads):
        return _run_diagnose(dataset, model, out, cfg)


def _run_diagnose(dataset: str | Path, model: SimulatorSpec, out: str | Path | None, cfg: DiagnoseConfig) -> dict[str, Any]:
    diag = diagnose_base(dataset, cfg)
    result = diag.to_json()
    held = diag.held
    analysis: dict[str, Any] = {"before": analyse(lambda s: diag.base.render(s.batch, s.field), held)}
    if diag.extended is not diag.base:
        analysis["after"] = analyse(lambda s: diag.extended.render(s.batch, s.field), held)
    if not model.is_base:
        peer = model.load()
        by_mask = {m: {k: float(np.nanmean(getattr(pm, k))) for k in ("psnr", "ssim", "mae")}
                   for m, pm in pair_metrics_by_mask(lambda s: peer(s.batch), held).items()}
        result["model"] = str(model)
        diag.measurement.simulator(lambda s: peer(s.batch), "peer")
        result["peer"] = {"name": str(model), "mask": "predictable", **by_mask["predictable"], "all_valid": by_mask["valid"],
                          "signatures": {e: s.to_json(cfg.alpha) for e, s in diag.measurement.signatures("peer").items()},
                          "note": "causes are named and added on the physical base model; the peer's own atlas is view-set 'peer' "
                                  "of atlas.npz and its signatures against the measured atlas are these"}
        result["atlas"] = atlas_summary(diag.atlas)
        analysis["peer"] = analyse(lambda s: peer(s.batch), held)
    if model.is_neural:
        result["neural_extension"] = extend_neural(dataset, model.checkpoint, out, cfg)
    if out is not None:
        from .report import write_report

        write_report(Path(out), result, analysis, diag.atlas)
    return result


def extend_neural(dataset: str | Path, checkpoint: str | Path, out: str | Path | None, cfg: DiagnoseConfig) -> dict[str, Any]:
    """The learned model's structural extension (:func:`dp5k_diagnose.neural_reach.diagnose_neural`): its error per
    |CoC| bin, multi-scale kernels added (equal output at start), fine-tuned beside an equally fine-tuned control,
    gains per |CoC| bin. Files go to ``out/neural`` (a temporary folder when ``out`` is None)."""
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
