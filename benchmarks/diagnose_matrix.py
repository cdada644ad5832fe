"""The confusion matrix of ``dp5k diagnose``: every effect alone, every pair, a few triples and clean sets, each at
two strengths and three seeds, rendered by three renderers that share no code with dp5k.

Renderers: ``foreign`` (``dp5k_testing/foreign_dp.py``: a per-pixel scatter of half discs without occlusion, its
nominal noise 2e-5, 1e-3), ``aperture`` (``dp5k_testing/aperture_dp.py``: a sub-aperture gather with z-buffer
occlusion, nominal noise 2e-4, 2e-3) and ``pupil`` (``dp5k_testing/pupil_dp.py``: PSFs from a pupil function with
layered occlusion, nominal noise 5e-5, 1.5e-3). ``pupil`` is held out: diagnose is developed on the other two and
its results on ``pupil`` are reported as they come. Each case writes a dataset (sensor noise on), runs diagnose in-process as
``dp5k diagnose --nominal-noise SHOT,READ`` does with every other option at its default, reads report.json and
appends one line to ``OUT/results.jsonl``: planted set, named ``causes`` in order, ``suspects``, ``lookalikes``,
seconds and machine load. Re-runs skip finished cases; datasets are deleted after each case unless ``--keep``
(report.json is kept under ``OUT/reports/``).

Strengths (docs/diagnose.md, "Benchmarks"): ``moderate`` is each renderer's own defaults (strength 1);
``near`` puts every effect near the detection limit: the strength at which its noise-free change of the views
is :data:`NEAR_SIGNAL` of the nominal noise variance (its "oracle signal", measured on noise-free renders of
the benchmark's size and stored in ``OUT/strengths.json``), and for ``noise`` the strength at which the views'
variance is :data:`NEAR_NOISE_RATIO` x nominal (diagnose names noise above 1.5 x).

    python benchmarks/diagnose_matrix.py [--out DIR] [--quick] [--renderers foreign,aperture,pupil] [--cases LIST]
        [--strengths near,moderate] [--seeds 0,1,2] [--size 256x170] [--pairs 24] [--jobs N] [--keep]
        [--report-only] [--details] [--calibrate] [--time-render]

``--cases``: comma-separated names (``none``, ``psf_profile``, ``lr_gain_imbalance+disparity_scale``, in any
order) and groups ``clean``, ``singles``, ``pairs``, ``triples``, ``all`` (default). ``--quick``: the moderate
strength, seed 0, one renderer (``aperture``, or the one ``--renderers`` names).
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import math
import multiprocessing
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
import traceback
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from dp5k_common.effects import EFFECT_NAMES
from dp5k_common.software import software_line
from dp5k_testing import aperture_dp, foreign_dp, pupil_dp

TRIPLES: tuple[tuple[str, ...], ...] = (
    ("lr_gain_imbalance", "field_varying_psf", "disparity_scale"),  # issue 30: the gain ramp was absorbed
    ("chromatic_defocus", "focus_offset", "psf_profile"),
    ("disparity_scale", "focus_offset", "psf_profile"),
    ("field_varying_psf", "chromatic_defocus", "misregistration"),
    ("lr_gain_imbalance", "focus_offset", "front_back_asymmetry"),
    ("front_back_asymmetry", "misregistration", "noise"),
)
LEVELS = ("near", "moderate")
NEAR_SIGNAL = 0.05
"""Oracle signal at the ``near`` strength: mean squared noise-free change of the views / nominal noise variance
(an rms change of 0.22 sigma per pixel)."""
NEAR_NOISE_RATIO = 1.75
"""The views' noise variance over the nominal at ``noise``'s ``near`` strength (diagnose's threshold is 1.5)."""
CALIBRATION_PAIRS = 24
SHORT = {"lr_gain_imbalance": "lr", "field_varying_psf": "fvp", "chromatic_defocus": "chrom", "disparity_scale": "disp",
         "focus_offset": "focus", "psf_profile": "prof", "front_back_asymmetry": "fba", "misregistration": "misreg",
         "noise": "noise"}


# ----------------------------------------------------------------------------------------------- renderers
@dataclass(frozen=True)
class Renderer:
    """How the benchmark drives one renderer.

    Attributes:
        name: ``foreign`` or ``aperture``.
        nominal_noise: (shot variance per unit intensity, read sigma), passed to diagnose as ``--nominal-noise``.
        write: ``write(out, {effect: strength}, seed, (W, H), pairs, noise)`` writes a format-v1 dataset.
        noise_ratio: the views' noise variance over the nominal at a view intensity of 0.25 with ``noise`` at a
            strength.
    """

    name: str
    nominal_noise: tuple[float, float]
    write: Callable[[Path, dict[str, float], int, tuple[int, int], int, bool], None]
    noise_ratio: Callable[[float], float]


def _write_foreign(out: Path, strengths: dict[str, float], seed: int, size: tuple[int, int], pairs: int, noise: bool) -> None:
    # its splits are by scene: 2 test, 2 val, the rest train, so at least 5 scenes
    foreign_dp.write_dataset(out, strengths or "none", 1.0, scenes=max(5, pairs // 2), size=size, seed=seed, noise=noise)


def _write_aperture(out: Path, strengths: dict[str, float], seed: int, size: tuple[int, int], pairs: int, noise: bool) -> None:
    aperture_dp.write_dataset(out, strengths or "none", 1.0, scenes=max(3, pairs // 2), size=size, seed=seed, noise=noise)


def _write_pupil(out: Path, strengths: dict[str, float], seed: int, size: tuple[int, int], pairs: int, noise: bool) -> None:
    pupil_dp.write_dataset(out, strengths or "none", 1.0, scenes=max(3, pairs // 2), size=size, seed=seed, noise=noise)


def _empirical_ratio(add_noise: Callable[[np.ndarray], np.ndarray], shot: float, read: float) -> float:
    img = np.full((256, 256, 3), 0.25)
    return float(np.var(add_noise(img) - img) / (shot * 0.25 + read * read))


def _foreign_noise_ratio(strength: float) -> float:
    planted = foreign_dp.Planted.of({"noise": strength} if strength else "none")
    return _empirical_ratio(lambda img: foreign_dp.add_noise(np.random.default_rng(0), img, planted),
                            foreign_dp.NOMINAL_SHOT_VAR, foreign_dp.NOMINAL_READ_SIGMA)


def _aperture_noise_ratio(strength: float) -> float:
    nominal = (aperture_dp.NOMINAL_SHOT_VAR, aperture_dp.NOMINAL_READ_SIGMA)
    shot, read = aperture_dp.views_noise(aperture_dp.Effects.of({"noise": strength} if strength else "none"), *nominal)
    return _empirical_ratio(lambda img: aperture_dp.add_sensor_noise(np.random.default_rng(0), img, shot, read), *nominal)


RENDERERS: dict[str, Renderer] = {
    "foreign": Renderer("foreign", (foreign_dp.NOMINAL_SHOT_VAR, foreign_dp.NOMINAL_READ_SIGMA), _write_foreign, _foreign_noise_ratio),
    "aperture": Renderer("aperture", (aperture_dp.NOMINAL_SHOT_VAR, aperture_dp.NOMINAL_READ_SIGMA), _write_aperture, _aperture_noise_ratio),
    "pupil": Renderer("pupil", (pupil_dp.NOMINAL_SHOT_VAR, pupil_dp.NOMINAL_READ_SIGMA), _write_pupil, lambda s: pupil_dp.noise_ratio(s, 0.25)),
}


# ----------------------------------------------------------------------------------------------- cases
@dataclass(frozen=True)
class Case:
    """One cell of the matrix: a renderer, the planted effects (in EFFECT_NAMES order), a strength level
    (``clean`` for no effect) and a seed."""

    renderer: str
    effects: tuple[str, ...]
    level: str
    seed: int

    @property
    def name(self) -> str:
        return "+".join(self.effects) or "none"

    @property
    def key(self) -> str:
        return f"{self.renderer}|{self.name}|{self.level}|{self.seed}"

    @property
    def slug(self) -> str:
        return f"{self.renderer}_{'+'.join(SHORT[e] for e in self.effects) or 'none'}_{self.level}_s{self.seed}"


def canonical(name: str) -> tuple[str, ...]:
    """``a+b`` in any order -> the names in EFFECT_NAMES order; ``none`` -> ()."""
    parts = [p for p in name.strip().split("+") if p and p != "none"]
    unknown = [p for p in parts if p not in EFFECT_NAMES]
    if unknown:
        raise SystemExit(f"diagnose_matrix: unknown effect(s) {unknown} in --cases; known: {', '.join(EFFECT_NAMES)}")
    return tuple(e for e in EFFECT_NAMES if e in parts)


def case_sets(spec: str) -> list[tuple[str, ...]]:
    """The planted sets that ``--cases`` names, in the order: clean, singles, pairs, triples, then the rest."""
    groups = {"clean": [()], "singles": [(e,) for e in EFFECT_NAMES],
              "pairs": list(itertools.combinations(EFFECT_NAMES, 2)), "triples": [canonical("+".join(t)) for t in TRIPLES]}
    groups["all"] = groups["clean"] + groups["singles"] + groups["pairs"] + groups["triples"]
    out: list[tuple[str, ...]] = []
    for item in (s.strip() for s in spec.split(",") if s.strip()):
        for effects in groups[item] if item in groups else [canonical(item)]:
            if effects not in out:
                out.append(effects)
    return out


def build_cases(renderers: list[str], sets: list[tuple[str, ...]], levels: list[str], seeds: list[int]) -> list[Case]:
    """Every (renderer, set, level, seed); a clean set has no strength, so it runs at ``2 x len(seeds)`` seeds
    when both levels are asked (as many clean sets as a single effect has cells), else at ``seeds``."""
    clean_seeds = seeds + [s + 1000 for s in seeds] if len(levels) > 1 else seeds
    cases = []
    for r in renderers:
        for effects in sets:
            if not effects:
                cases += [Case(r, (), "clean", s) for s in clean_seeds]
            else:
                cases += [Case(r, effects, lv, s) for lv in levels for s in seeds]
    return cases


# ----------------------------------------------------------------------------------------------- strengths
def oracle_signal(clean: Path, planted: Path, shot: float, read: float) -> float:
    """Mean over both views of (planted - clean)^2 / the nominal noise variance ``shot I + read^2`` at the clean
    intensities, for two noise-free datasets written with the same seed (so the same scenes)."""
    from dp5k_common.dataset import DatasetReader

    num = den = 0.0
    a, b = DatasetReader(clean), DatasetReader(planted)
    for pid in a.ids():
        pa, pb = a.load(pid), b.load(pid)
        for va, vb in ((pa.left, pb.left), (pa.right, pb.right)):
            num += float(((vb.astype(np.float64) - va) ** 2).sum())
            den += float((shot * np.clip(va, 0, None) + read * read).sum())
    return num / den


def calibrate(renderer: Renderer, size: tuple[int, int], work: Path) -> dict[str, Any]:
    """Oracle signal of every effect at strength 1 and the ``near`` strengths (see the module docstring)."""
    base = work / f"calib-{renderer.name}-{size[0]}x{size[1]}"
    shutil.rmtree(base, ignore_errors=True)
    base.mkdir(parents=True)
    try:
        clean = base / "none"
        renderer.write(clean, {}, 0, size, CALIBRATION_PAIRS, False)
        signal, near = {}, {}
        for e in EFFECT_NAMES:
            if e == "noise":
                signal[e] = renderer.noise_ratio(1.0) - 1.0
                lo, hi = 0.0, 1.0
                while renderer.noise_ratio(hi) < NEAR_NOISE_RATIO and hi < 64:
                    hi *= 2
                for _ in range(30):
                    mid = (lo + hi) / 2
                    lo, hi = (mid, hi) if renderer.noise_ratio(mid) < NEAR_NOISE_RATIO else (lo, mid)
                near[e] = round(hi, 4)
                continue
            renderer.write(base / e, {e: 1.0}, 0, size, CALIBRATION_PAIRS, False)
            signal[e] = oracle_signal(clean, base / e, *renderer.nominal_noise)
            near[e] = round(float(np.clip(math.sqrt(NEAR_SIGNAL / max(signal[e], 1e-12)), 0.005, 1.0)), 4)
        return {"size": list(size), "pairs": CALIBRATION_PAIRS, "signal_at_1": signal, "near": near,
                "near_signal": NEAR_SIGNAL, "near_noise_ratio": NEAR_NOISE_RATIO}
    finally:
        shutil.rmtree(base, ignore_errors=True)


def strengths_table(out: Path, renderers: Iterable[str], size: tuple[int, int], need: bool) -> dict[str, Any]:
    """``OUT/strengths.json`` (calibrated once per renderer and size, then reused), calibrating what is missing
    when ``need``."""
    path = out / "strengths.json"
    table = json.loads(path.read_text()) if path.exists() else {}
    key = f"{size[0]}x{size[1]}"
    for r in renderers:
        if need and key not in table.get(r, {}):
            print(f"calibrating the near strengths of {r} at {key} (noise-free renders, {CALIBRATION_PAIRS} pairs per effect) ...", flush=True)
            t0 = time.perf_counter()
            table.setdefault(r, {})[key] = calibrate(RENDERERS[r], size, out)
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(table, indent=1))
            tmp.replace(path)
            print(f"  done in {time.perf_counter() - t0:.0f} s", flush=True)
    return table


def case_strengths(case: Case, table: dict[str, Any], size: tuple[int, int]) -> dict[str, float]:
    if case.level == "moderate":
        return {e: 1.0 for e in case.effects}
    if case.level == "near":
        near = table[case.renderer][f"{size[0]}x{size[1]}"]["near"]
        return {e: float(near[e]) for e in case.effects}
    return {}


# ----------------------------------------------------------------------------------------------- one case
def stamp() -> dict[str, Any]:
    """Date, 1/5/15-min load, commit (``+changes`` when tracked files differ from it; the benchmarks' own result
    files under ``benchmarks/results/``, which a running matrix appends to, do not count) and CPU count now."""
    here = Path(__file__).parent
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True, cwd=here).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ":(exclude)benchmarks/results"],
                               capture_output=True, text=True, check=True, cwd=here.parent).stdout.strip()
        commit += "+changes" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {"date": f"{datetime.datetime.now():%Y-%m-%d %H:%M}", "load": [round(v, 2) for v in os.getloadavg()],
            "commit": commit, "nproc": os.cpu_count()}


def stamp_line(s: dict[str, Any]) -> str:
    return f"_{s['date']} · load {'/'.join(f'{v:.1f}' for v in s['load'])} (1/5/15 min) · commit {s['commit']} · {s['nproc']} CPUs_"


def init_worker(ignore_sigint: bool = True) -> None:
    """One thread per case: ``--jobs`` processes share the cores. Workers leave Ctrl-C to the main process,
    which stops them."""
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    os.environ.setdefault("DP5K_PROGRESS", "0")
    if ignore_sigint:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


COSTLY_EFFECTS: dict[str, float] = {"field_varying_psf": 3.0, "chromatic_defocus": 1.5}
"""How many times a set's usual diagnosis time an effect's presence costs, roughly: a field-varying PSF renders on
3 x 3 field nodes, a chromatic defocus three colour planes."""


def expected_cost(case: Case) -> float:
    """A rough relative diagnosis time of ``case``, for ordering parallel runs longest first (it changes no result)."""
    cost = 1.0 + len(case.effects)
    for e in case.effects:
        cost *= COSTLY_EFFECTS.get(e, 1.0)
    return cost


def run_job(job: tuple[Case, dict[str, float], Path, tuple[int, int], int, bool]) -> dict[str, Any]:
    return run_case(*job)


def run_case(case: Case, strengths: dict[str, float], out: Path, size: tuple[int, int], pairs: int, keep: bool) -> dict[str, Any]:
    """Write the case's dataset, diagnose it as the CLI does, and return its result row."""
    from dp5k_diagnose.config import DiagnoseConfig
    from dp5k_diagnose.data import auto_fit_pairs
    from dp5k_diagnose.run import run_diagnose
    from neural_dp.registry import SimulatorSpec

    renderer = RENDERERS[case.renderer]
    ds = out / "sets" / case.slug
    ds.parent.mkdir(parents=True, exist_ok=True)
    for stale in [ds, *ds.parent.glob(f".{ds.name}.tmp-*")]:  # what an interrupted run left behind
        shutil.rmtree(stale, ignore_errors=True)
    row: dict[str, Any] = {"key": case.key, "renderer": case.renderer, "case": case.name, "planted": list(case.effects),
                           "level": case.level, "strengths": strengths, "seed": case.seed, "size": list(size), "pairs": pairs,
                           "causes": [], "suspects": [], "lookalikes": [], "error": None, **stamp()}
    try:
        t0 = time.perf_counter()
        renderer.write(ds, strengths, case.seed, size, pairs, True)
        row["render_seconds"] = round(time.perf_counter() - t0, 1)
        row["load_before"] = round(os.getloadavg()[0], 2)
        shot, read = renderer.nominal_noise
        cfg = DiagnoseConfig(seed=0, fit_pairs=auto_fit_pairs(ds), nominal_shot_var=shot, nominal_read_sigma=read)
        t1 = time.perf_counter()
        run_diagnose(ds, SimulatorSpec(), ds / "diagnose", cfg)
        row["seconds"] = round(time.perf_counter() - t1, 1)
        row["load_after"] = round(os.getloadavg()[0], 2)
        rep = json.loads((ds / "diagnose" / "report.json").read_text())
        (out / "reports").mkdir(exist_ok=True)
        shutil.copyfile(ds / "diagnose" / "report.json", out / "reports" / f"{case.slug}.json")
        row["causes"] = [c["name"] for c in rep.get("causes", [])]
        row["suspects"] = [s["name"] for s in rep.get("suspects", []) or []]
        row["lookalikes"] = [{"names": list(g.get("names", [])), "capture": "; ".join(g.get("captures", []) or [g.get("capture", "")])} for g in rep.get("lookalikes", []) or []]
        row["gain_db"] = rep.get("gain", {}).get("psnr_after", 0.0) - rep.get("gain", {}).get("psnr_before", 0.0)
        row["timings_s"] = rep.get("timings_s", {})
        row["software"] = rep.get("software", {})
    except Exception as exc:  # noqa: BLE001 - one failed case must not stop the matrix
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc()[-2000:]
    finally:
        if not keep:
            shutil.rmtree(ds, ignore_errors=True)
    return row


# ----------------------------------------------------------------------------------------------- scoring
def covered(effect: str, named: set[str], groups: list[set[str]]) -> bool:
    """Named, or in a reported look-alike group together with a named cause."""
    return effect in named or any(effect in g and g & named for g in groups)


def frac(rows: list[dict[str, Any]], pred: Callable[[dict[str, Any]], bool], of: Callable[[dict[str, Any]], bool] = lambda r: True) -> str:
    """``k/n (p %)``: of the rows that satisfy ``of``, how many satisfy ``pred`` (``-`` when none)."""
    sel = [r for r in rows if of(r)]
    if not sel:
        return "-"
    k = sum(1 for r in sel if pred(r))
    return f"{k}/{len(sel)} ({100 * k / len(sel):.0f} %)"


def md_table(header: list[str], body: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(header) + " |", "|---" * len(header) + "|"] + ["| " + " | ".join(row) + " |" for row in body])


def named(r: dict[str, Any]) -> set[str]:
    return set(r["causes"])


def groups(r: dict[str, Any]) -> list[set[str]]:
    return [set(g["names"]) for g in r["lookalikes"]]


def exact(r: dict[str, Any]) -> bool:
    return named(r) == set(r["planted"])


def exact_la(r: dict[str, Any]) -> bool:
    """Exact up to reported look-alikes: every planted effect covered, every named cause planted or a look-alike
    of a planted one."""
    p, n, g = set(r["planted"]), named(r), groups(r)
    return all(covered(e, n, g) for e in p) and all(covered(c, p, g) for c in n)


def all_named(r: dict[str, Any], la: bool = False) -> bool:
    return all(covered(e, named(r), groups(r) if la else []) for e in r["planted"])


def n_planted(k: int) -> Callable[[dict[str, Any]], bool]:
    return lambda r: len(r["planted"]) == k


def counts(c: Counter) -> str:
    return ", ".join(f"{k} x{v}" for k, v in c.most_common()) or "-"


def summary_table(rows: list[dict[str, Any]]) -> str:
    header = ["renderer", "strength", "singles named exactly", "+ look-alikes", "pairs: both named", "+ look-alikes",
              "pairs exactly", "+ look-alikes", "triples: all named", "triples exactly", "planted sets exactly", "+ look-alikes",
              "a missed effect among suspects"]
    missed_suspect = lambda r: any(e in r["suspects"] and e not in r["causes"] for e in r["planted"])  # noqa: E731
    body = [[rend, lv, frac(rs, exact, n_planted(1)), frac(rs, exact_la, n_planted(1)), frac(rs, all_named, n_planted(2)),
             frac(rs, lambda r: all_named(r, True), n_planted(2)), frac(rs, exact, n_planted(2)), frac(rs, exact_la, n_planted(2)),
             frac(rs, all_named, n_planted(3)), frac(rs, exact, n_planted(3)), frac(rs, exact), frac(rs, exact_la),
             frac(rs, missed_suspect)]
            for (rend, lv), rs in grouped(rows, lambda r: (r["renderer"], r["level"])) if lv != "clean"]
    return md_table(header, body)


def clean_table(rows: list[dict[str, Any]]) -> str:
    body = [[rend, frac(rs, lambda r: bool(r["causes"])), counts(Counter(c for r in rs for c in r["causes"])),
             frac(rs, lambda r: bool(r["suspects"])), counts(Counter(c for r in rs for c in r["suspects"]))]
            for (rend,), rs in grouped([r for r in rows if r["level"] == "clean"], lambda r: (r["renderer"],))]
    return md_table(["renderer", "clean sets with a cause named (false alarms)", "causes named", "clean sets with suspects", "suspects"], body)


def seconds_table(rows: list[dict[str, Any]]) -> str:
    body = []
    for (rend, k), rs in grouped(rows, lambda r: (r["renderer"], len(r["planted"]))):
        secs = [r["seconds"] for r in rs if "seconds" in r]
        if secs:
            loads = [r["load_before"] for r in rs if "load_before" in r]
            rend_s = [r["render_seconds"] for r in rs if "render_seconds" in r]

            # both atlases and the signatures (diagnose's "atlas" stage until it timed the measured atlas apart), and the
            # measured atlas alone where timed apart
            both = [t["atlas"] + t.get("signatures", 0.0) for t in (r.get("timings_s", {}) for r in rs) if "atlas" in t]
            alone = [r["timings_s"]["atlas"] for r in rs if "signatures" in r.get("timings_s", {})]
            body.append([rend, str(k), str(len(secs)), f"{statistics.median(secs):.0f}", f"{max(secs):.0f}",
                         f"{statistics.median(both):.1f}" if both else "-", f"{statistics.median(alone):.1f}" if alone else "-",
                         f"{statistics.median(rend_s):.0f}", f"{statistics.median(loads):.1f} ({min(loads):.1f}-{max(loads):.1f})"])
    return md_table(["renderer", "planted effects", "sets", "diagnose s median", "max", "atlases + signatures s median",
                     "of which the measured atlas", "render s median", "load at start, median (range)"], body)


def confusion_table(rows: list[dict[str, Any]]) -> str:
    """Rows: planted effect (``none`` for clean sets); columns: named effects and ``missed`` (planted, not named;
    for ``none``: nothing named, the right answer). A named cause that was not planted is counted once for each
    effect planted in its set."""
    cols = list(EFFECT_NAMES) + ["missed"]
    m = {p: Counter() for p in list(EFFECT_NAMES) + ["none"]}
    for r in rows:
        n = named(r)
        for p in r["planted"] or ["none"]:
            if p != "none":
                m[p][p if p in n else "missed"] += 1
            elif not n:
                m[p]["missed"] += 1
            for c in n - set(r["planted"]):
                m[p][c] += 1
    body = [[p] + [((f"**{cnt[c]}**" if c == p else str(cnt[c])) if cnt[c] else ".") for c in cols] for p, cnt in m.items() if sum(cnt.values())]
    return md_table(["planted \\ named"] + [SHORT.get(c, c) for c in cols], body)


def details_table(rows: list[dict[str, Any]]) -> str:
    body = []
    for r in rows:
        la = "; ".join(f"{'/'.join(g['names'])} ({g['capture']})" for g in r["lookalikes"]) or "-"
        st = ", ".join(f"{SHORT[e]} {s:g}" for e, s in r["strengths"].items()) or "-"
        what = (", ".join(r["causes"]) or "none") if not r.get("error") else f"**error**: {r['error'][:80]}"
        body.append([r["renderer"], r["case"], f"{r['level']}: {st}", str(r["seed"]), what, ", ".join(r["suspects"]) or "-", la,
                     f"{r.get('gain_db', 0.0):+.2f}", f"{r.get('seconds', float('nan')):.0f}", f"{r.get('load_before', float('nan')):.1f}"])
    return md_table(["renderer", "planted", "strength", "seed", "named, in order", "suspects", "look-alikes", "gain dB", "s", "load"], body)


def strengths_markdown(table: dict[str, Any]) -> str:
    body = []
    for r, by_size in table.items():
        for size, t in by_size.items():
            body.append([f"{r} {size}: oracle signal at 1"] + [f"{t['signal_at_1'][e]:.3g}" for e in EFFECT_NAMES])
            body.append([f"{r} {size}: near strength"] + [f"{t['near'][e]:.3g}" for e in EFFECT_NAMES])
    return md_table(["renderer, size"] + [SHORT[e] for e in EFFECT_NAMES], body)


def grouped(rows: list[dict[str, Any]], key: Callable[[dict[str, Any]], tuple]) -> list[tuple[tuple, list[dict[str, Any]]]]:
    out: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(key(r), []).append(r)
    order = {"clean": 0, "near": 1, "moderate": 2}
    return sorted(out.items(), key=lambda kv: tuple(order.get(k, k) if isinstance(k, str) else k for k in kv[0]))


def report(rows: list[dict[str, Any]], strengths: dict[str, Any], details: bool) -> str:
    now = stamp_line(stamp())
    ok = [r for r in rows if not r.get("error")]
    errors = [r for r in rows if r.get("error")]
    runs = sorted({r["date"] for r in ok}) or ["-"]
    loads = [r["load_before"] for r in ok if "load_before" in r]
    commits = sorted({r["commit"] for r in ok})
    machines = sorted({str(r["nproc"]) for r in ok})
    softwares = sorted({software_line(r["software"]) for r in ok if r.get("software")})
    parts = [f"{len(ok)} sets diagnosed ({len(errors)} failed), run {runs[0]} .. {runs[-1]}, load at start "
             f"{min(loads, default=float('nan')):.1f}-{max(loads, default=float('nan')):.1f}, commits {', '.join(commits) or '-'}, "
             f"{'/'.join(machines) or '-'} CPUs, software {' | '.join(softwares) or 'not recorded'}."]
    for title, body in (("Named causes (strength: near the detection limit / moderate)", summary_table(ok)),
                        ("Clean sets", clean_table(ok)), ("Seconds per set (diagnose only; render separately)", seconds_table(ok))):
        parts += [f"\n### {title}\n", now + "\n", body]
    for (rend,), rs in grouped(ok, lambda r: (r["renderer"],)):
        parts += [f"\n### Confusion matrix, {rend} (all strengths and seeds)\n", now + "\n", confusion_table(rs)]
    parts += ["\nColumns: " + ", ".join(f"{v} = {k}" for k, v in SHORT.items()) + "; missed = planted and not named (row "
              "none: nothing named, the right answer). A cause named but not planted counts once per effect planted in its set."]
    if strengths:
        parts += ["\n### Strengths\n", now + "\n", strengths_markdown(strengths)]
    if details or len(rows) <= 60:
        parts += ["\n### Every set\n", now + "\n", details_table(rows)]
    for r in errors:
        parts += [f"\nerror in {r['key']}: {r['error']}"]
    return "\n".join(parts)


# ----------------------------------------------------------------------------------------------- main
def load_rows(path: Path) -> list[dict[str, Any]]:
    """The JSONL's rows, the last one per key (a re-run of a failed case replaces it)."""
    rows: dict[str, dict[str, Any]] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                try:
                    r = json.loads(line)
                except json.JSONDecodeError:
                    continue  # a line cut by a crash
                rows[r["key"]] = r
    return list(rows.values())


def append_row(path: Path, row: dict[str, Any]) -> None:
    with path.open("a") as f:
        f.write(json.dumps(row) + "\n")
        f.flush()
        os.fsync(f.fileno())


def parse_size(text: str) -> tuple[int, int]:
    try:
        W, H = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"diagnose_matrix: --size must be WxH, got {text!r}") from None
    if W < 32 or H < 32:
        raise SystemExit(f"diagnose_matrix: --size {text} is too small (at least 32x32)")
    return W, H


TIMED_CASES = ("none", "chromatic_defocus", "field_varying_psf+psf_profile", "lr_gain_imbalance+field_varying_psf+disparity_scale")


def time_rendering(renderers: list[str], size: tuple[int, int], pairs: int, work: Path) -> str:
    """Seconds to write one set with each renderer on one thread (OpenCV and numpy), for a few cases."""
    import cv2

    cv2.setNumThreads(1)
    body = []
    for name in TIMED_CASES:
        cells = []
        for r in renderers:
            ds = work / f"timing-{r}"
            shutil.rmtree(ds, ignore_errors=True)
            t0 = time.perf_counter()
            RENDERERS[r].write(ds, {e: 1.0 for e in canonical(name)}, 0, size, pairs, True)
            cells.append(f"{time.perf_counter() - t0:.1f}")
            shutil.rmtree(ds, ignore_errors=True)
        body.append([name] + cells)
    return stamp_line(stamp()) + "\n\n" + md_table([f"case ({size[0]} x {size[1]}, {pairs} pairs, one thread)"] + [f"{r} s" for r in renderers], body)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("diagnose-matrix"), help="results.jsonl, strengths.json, reports/ (default ./diagnose-matrix)")
    ap.add_argument("--quick", action="store_true", help="moderate strength, seed 0, one renderer (aperture, or the one --renderers names)")
    ap.add_argument("--renderers", help="comma-separated, from foreign, aperture, pupil (default all three)")
    ap.add_argument("--cases", help="names (a, a+b, none) and groups clean, singles, pairs, triples, all (default all)")
    ap.add_argument("--strengths", help="comma-separated, from near, moderate (default both)")
    ap.add_argument("--seeds", help="comma-separated integers (default 0,1,2)")
    ap.add_argument("--size", default="256x170", help="WxH of the rendered pairs")
    ap.add_argument("--pairs", type=int, default=24, help="pairs per set (scenes x 2 f-numbers)")
    ap.add_argument("--jobs", type=int, default=1, help="cases run in this many processes at once, one thread each")
    ap.add_argument("--keep", action="store_true", help="keep each case's dataset and report under OUT/sets/")
    ap.add_argument("--report-only", action="store_true",
                    help="print the tables from OUT/results.jsonl and exit: every row, or the cases that --quick, "
                         "--renderers, --cases, --strengths and --seeds select when any is given")
    ap.add_argument("--details", action="store_true", help="also print every set's row (always when 60 rows or fewer)")
    ap.add_argument("--calibrate", action="store_true", help="(re)compute the near strengths, print them and exit")
    ap.add_argument("--time-render", action="store_true", help="time writing one set per renderer (one thread), print and exit")
    a = ap.parse_args(argv)
    selected_by_flags = a.quick or any(v is not None for v in (a.renderers, a.cases, a.strengths, a.seeds))
    if a.quick:  # one strength, one seed, one renderer (aperture unless --renderers names one)
        a.strengths, a.seeds = "moderate", "0"
        a.renderers = a.renderers or "aperture"
        if "," in a.renderers:
            raise SystemExit("diagnose_matrix: --quick runs one renderer; give --renderers foreign, aperture or pupil")
    a.renderers = a.renderers or "foreign,aperture,pupil"
    a.cases = a.cases or "all"
    a.strengths = a.strengths or "near,moderate"
    a.seeds = a.seeds or "0,1,2"
    renderers = [r.strip() for r in a.renderers.split(",") if r.strip()]
    bad = [r for r in renderers if r not in RENDERERS]
    levels = [s.strip() for s in a.strengths.split(",") if s.strip()]
    if bad or not renderers or any(lv not in LEVELS for lv in levels) or not levels:
        raise SystemExit(f"diagnose_matrix: --renderers from {', '.join(RENDERERS)}, --strengths from {', '.join(LEVELS)}")
    try:
        seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    except ValueError:
        raise SystemExit(f"diagnose_matrix: --seeds must be integers, got {a.seeds!r}") from None
    size = parse_size(a.size)
    if a.pairs < 6:
        raise SystemExit("diagnose_matrix: --pairs must be at least 6 (train, val and test need a scene each)")
    a.out.mkdir(parents=True, exist_ok=True)
    results = a.out / "results.jsonl"
    if a.time_render:
        print(time_rendering(renderers, size, a.pairs, a.out))
        return 0
    if a.calibrate:
        path = a.out / "strengths.json"
        table = json.loads(path.read_text()) if path.exists() else {}
        for r in renderers:
            table.get(r, {}).pop(f"{size[0]}x{size[1]}", None)
        path.write_text(json.dumps(table, indent=1))
        print(strengths_markdown({r: {k: v} for r, t in strengths_table(a.out, renderers, size, True).items()
                                  for k, v in t.items() if r in renderers}))
        return 0
    cases = build_cases(renderers, case_sets(a.cases), levels, seeds)
    if a.report_only:
        path = a.out / "strengths.json"
        rows = load_rows(results)
        if selected_by_flags:
            keys = {c.key for c in cases}
            rows = [r for r in rows if r["key"] in keys]
        print(report(rows, json.loads(path.read_text()) if path.exists() else {}, a.details))
        return 0
    done = {r["key"] for r in load_rows(results) if not r.get("error")}
    todo = [c for c in cases if c.key not in done]
    table = strengths_table(a.out, renderers, size, any(c.level == "near" for c in todo))
    print(f"{len(cases)} cases, {len(cases) - len(todo)} already in {results}, {len(todo)} to run with {a.jobs} job(s); "
          f"{size[0]}x{size[1]}, {a.pairs} pairs per set", flush=True)
    t0 = time.perf_counter()
    if a.jobs > 1:  # longest first, so that no long set runs alone at the end while the other processes wait
        todo = sorted(todo, key=expected_cost, reverse=True)
    jobs = [(c, case_strengths(c, table, size), a.out, size, a.pairs, a.keep) for c in todo]

    def done_line(i: int, row: dict[str, Any]) -> None:
        append_row(results, row)
        what = f"error: {row['error']}" if row["error"] else f"named [{', '.join(row['causes'])}]" + (
            f", suspects [{', '.join(row['suspects'])}]" if row["suspects"] else "")
        print(f"[{i}/{len(jobs)}] {row['key']}: {what}, {row.get('seconds', float('nan')):.0f} s, load {row.get('load_before', float('nan')):.1f}",
              flush=True)

    try:
        if a.jobs <= 1:
            init_worker(ignore_sigint=False)
            for i, job in enumerate(jobs, 1):
                done_line(i, run_job(job))
        else:
            pool = multiprocessing.get_context("spawn").Pool(a.jobs, initializer=init_worker)
            try:
                for i, row in enumerate(pool.imap_unordered(run_job, jobs), 1):
                    done_line(i, row)
                pool.close()
            except BaseException:
                pool.terminate()  # the running cases are lost; their rows were never written, so a re-run redoes them
                raise
            finally:
                pool.join()
    except KeyboardInterrupt:
        print(f"interrupted; finished cases are in {results} and a re-run continues from there", file=sys.stderr)
        return 130
    print(f"\nwall time {time.perf_counter() - t0:.0f} s\n", flush=True)
    selected = {c.key for c in cases}
    print(report([r for r in load_rows(results) if r["key"] in selected], table, a.details))
    return 0


if __name__ == "__main__":
    sys.exit(main())
