"""The downstream study (the paper's Sec. 5.3, Tables 3 and 4): which simulator's synthetic DP data trains the best
DP deblurrer, scored on real (measured) test pairs.

From one folder of RGBD frames (``dp5k synthesize``'s input) and one measured dataset:

1. synthesize a DP dataset with every simulator, from the same frames and the same drawn optics (the random focus
   and f-number of a frame depend only on the seed and the frame's name, ``neural_dp.synthesize``);
2. train one deblurrer per simulator with the same budget and seed (``cfg.train``); each is used as it is at the
   end of its budget (``last.pt``: a val split of a few synthetic pairs is no guide to measured pairs);
3. score each on the measured test split: **Table 3** (with the blurred input L + R as the floor);
4. the transfer setting: fine-tune each pre-trained deblurrer on a few measured train pairs (``cfg.few_real_pairs``,
   ``cfg.finetune_epochs``), beside the same fine-tuning budget from scratch and a deblurrer trained on every
   measured train pair with the full budget: **Table 4**.

Writes into ``out`` (atomically): ``table3.md/json``, ``table4.md/json``, ``figure.png``, ``study.json`` (settings,
test data, timings); intermediate data and runs under ``synth/``, ``runs/``, ``few_real/``. A second run reuses
finished syntheses and runs (both resume).
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from dp5k_common.dataset import DatasetReader, write_index
from dp5k_common.errors import BadInputError
from dp5k_common.io import atomic_path, write_bytes_atomic, write_json_atomic
from neural_dp.registry import PAPER_F_NUMBERS, PEERS, SimulatorSpec, SynthConfig, synthesize

from .config import DeblurTrainConfig
from .evaluate import METRICS, DeblurScores, score
from .train import load_deblurrer, train_deblur

logger = logging.getLogger(__name__)
FIGURE_MARGIN_DB = 0.3
"""Space above and below the figure's PSNR range, dB."""

PEER_SIMULATORS: tuple[str, ...] = (*PEERS, "base")
"""The simulators that need no file (``neural:CKPT`` needs a checkpoint, ``diagnosed:REPORT.json`` a report)."""


@dataclass(frozen=True)
class StudyConfig:
    """The study's settings; every deblurrer gets the same ``train`` budget and seed."""

    simulators: tuple[str, ...] = PEER_SIMULATORS
    """Simulator specs (:class:`~neural_dp.registry.SimulatorSpec`), e.g. ``neural:CKPT`` for the Neural DP
    Simulator and ``diagnosed:REPORT.json`` for the base model with the effects ``dp5k diagnose`` fitted."""
    f_numbers: tuple[float, ...] = PAPER_F_NUMBERS
    """Drawn per frame (the paper: 1.8-5.6)."""
    max_coc_px: float | None = None
    """Sensor-size adjustment target of ``synthesize`` (px); None keeps the frames' own pixel pitch."""
    encoding: str = "linear"
    """How the frames' image.png is encoded."""
    train: DeblurTrainConfig = field(default_factory=DeblurTrainConfig)
    few_real_pairs: int = 4
    """Measured train pairs of the transfer setting (the paper: 570)."""
    finetune_epochs: int = 10
    finetune_lr: float = 1e-3
    device: str = "cpu"
    seed: int = 0

    def specs(self) -> list[SimulatorSpec]:
        """The parsed ``simulators``; each names a folder and a row, so two of one name are refused.

        Raises:
            BadInputError: a bad spec, a missing checkpoint or report, or two specs of one simulator.
        """
        specs = [SimulatorSpec.parse(s) for s in self.simulators]
        names = [s.name for s in specs]
        if len(set(names)) < len(names):
            raise BadInputError(f"each simulator once, please: {', '.join(self.simulators)}", where="--simulator")
        for spec in specs:
            spec.check_files()
        return specs


def few_pairs_dataset(real: Path, out: Path, count: int) -> Path:
    """A dataset of ``real``'s first ``count`` train pairs and its val pairs (copied), no test pairs.

    Raises:
        BadInputError: ``real`` has fewer than ``count`` train pairs, or ``out`` holds other pairs (a resumed study
            with another ``count``).
    """
    reader = DatasetReader(real)
    train, val = reader.ids("train")[:count], reader.ids("val")
    if len(train) < count:
        raise BadInputError(f"the transfer setting needs {count} train pairs, the dataset has {len(train)}", where=real)
    if (out / "dataset.json").is_file():
        if DatasetReader(out).ids("train") != train:
            raise BadInputError(f"holds another set of few measured pairs than the first {count}; use another --out", where=out)
    else:
        for pid in train + val:
            dst = out / "pairs" / pid
            if not dst.is_dir():
                tmp = out / "pairs" / f".{pid}.partial"
                shutil.rmtree(tmp, ignore_errors=True)
                shutil.copytree(reader.root / "pairs" / pid, tmp)
                tmp.rename(dst)
        write_index(out, {"train": train, "val": val, "test": []}, source=f"{count} train pairs of {real}")
    return out


def _row(name: str, s: DeblurScores, key: str = "prediction", **extra: Any) -> dict[str, Any]:
    return {"setting": name, **extra, **{k: s.mean[key][k] for k in METRICS}}


def _md(title: str, rows: list[dict[str, Any]], note: str) -> str:
    lines = [f"### {title}", "", note, "", "| setting | PSNR (dB) | SSIM | MAE |", "|---|---|---|---|"]
    lines += [f"| {r['setting']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['mae']:.4f} |" for r in rows]
    return "\n".join(lines) + "\n"


def _figure(path: Path, t3: list[dict[str, Any]], t4: list[dict[str, Any]]) -> None:
    """Bars: test PSNR per simulator, synthetic only and fine-tuned; lines: L + R and all measured pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sims = [r for r in t3 if r.get("simulator")]
    tuned = {r["simulator"]: r["psnr"] for r in t4 if r.get("simulator")}
    fig, ax = plt.subplots(figsize=(1.2 * len(sims) + 3, 3.2))
    xs = range(len(sims))
    ax.bar([x - 0.2 for x in xs], [r["psnr"] for r in sims], 0.4, label="synthetic only (Table 3)")
    ax.bar([x + 0.2 for x in xs], [tuned.get(r["simulator"], float("nan")) for r in sims], 0.4, label="+ fine-tune (Table 4)")
    for r, style in ((t3[0], "k--"), (t4[1], "g:")):
        ax.axhline(r["psnr"], color=style[0], linestyle=style[1:], label=r["setting"])
    ax.set_xticks(list(xs), [r["simulator"] for r in sims])
    ax.set_ylabel("test PSNR vs sharp (dB)")
    values = [r["psnr"] for r in t3 + t4]
    ax.set_ylim(min(values) - FIGURE_MARGIN_DB, max(values) + FIGURE_MARGIN_DB)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def run_downstream(rgbd_dir: str | Path, real: str | Path, out: str | Path, cfg: StudyConfig | None = None) -> dict[str, Any]:
    """Run the study (module docstring). ``real``: the measured dataset (its test split is scored; its train split
    feeds the transfer setting and the all-measured reference). Returns the study.json object.

    Raises:
        BadInputError / EmptySplitError: unusable frames, dataset or settings.
    """
    cfg = cfg or StudyConfig()
    specs = cfg.specs()
    rgbd_dir, real, out = Path(rgbd_dir), Path(real), Path(out)
    train_cfg = replace(cfg.train, seed=cfg.seed, device=cfg.device)
    tune_cfg = replace(train_cfg, optim=replace(train_cfg.optim, epochs=cfg.finetune_epochs, lr=cfg.finetune_lr))
    timings: dict[str, float] = {}
    floor: DeblurScores | None = None
    t3: list[dict[str, Any]] = []
    t4: list[dict[str, Any]] = []

    def scored(run: Path) -> DeblurScores:
        return score(load_deblurrer(run / "last.pt", cfg.device), real, "test", cfg.device)

    few = few_pairs_dataset(real, out / "few_real", cfg.few_real_pairs)
    t0 = time.perf_counter()
    train_deblur(real, out / "runs" / "real_all", train_cfg)
    all_real = scored(out / "runs" / "real_all")
    train_deblur(few, out / "runs" / "real_few", tune_cfg)
    few_only = scored(out / "runs" / "real_few")
    timings["real"] = time.perf_counter() - t0
    floor = all_real
    t4 += [_row(f"measured: {cfg.few_real_pairs} pairs only (fine-tune budget)", few_only),
           _row("measured: all train pairs (full budget)", all_real)]
    t3.append(_row("blurred input L + R (no deblurring)", floor, "input"))
    for spec in specs:
        name = spec.name
        t0 = time.perf_counter()
        synth = out / "synth" / name
        synthesize(rgbd_dir, synth, SynthConfig(simulator=str(spec), f_numbers=cfg.f_numbers, max_coc_px=cfg.max_coc_px,
                                                 encoding=cfg.encoding, seed=cfg.seed, device=cfg.device))
        pre = out / "runs" / f"synth_{name}"
        train_deblur(synth, pre, train_cfg)
        t3.append(_row(f"synthetic: {name}", scored(pre), simulator=name))
        tuned = out / "runs" / f"synth_{name}+few_real"
        train_deblur(few, tuned, tune_cfg, init_from=pre / "last.pt")
        t4.append(_row(f"synthetic: {name} + fine-tune on {cfg.few_real_pairs} measured pairs", scored(tuned), simulator=name))
        timings[name] = time.perf_counter() - t0
        logger.info("%s: %.2f dB synthetic only, %.2f dB fine-tuned", name, t3[-1]["psnr"], t4[-1]["psnr"])

    test_ids = DatasetReader(real).ids("test")
    test_note = (f"Test data: the test split of `{real}` ({len(test_ids)} pairs), masked PSNR / SSIM / MAE of the "
                 "deblurred image against its `sharp`.")
    tables = {
        "table3": (f"Table 3: deblurrers trained on each simulator's synthetic data from the same {_frames(rgbd_dir)} "
                   "RGBD frames", t3, test_note),
        "table4": (f"Table 4: transfer, pre-trained on synthetic data then fine-tuned on {cfg.few_real_pairs} measured "
                   f"train pairs of `{real}` ({cfg.finetune_epochs} epochs)", t4, test_note),
    }
    for key, (title, rows, note) in tables.items():
        write_json_atomic(out / f"{key}.json", {"title": title, "test_data": str(real), "test_pairs": test_ids, "rows": rows})
        write_bytes_atomic(out / f"{key}.md", _md(title, rows, note).encode())
    _figure(out / "figure.png", t3, t4)
    study = {"rgbd_frames": str(rgbd_dir), "measured": str(real), "test_pairs": test_ids, "config": _jsonable(asdict(cfg)),
             "timings_s": timings, "table3": t3, "table4": t4}
    write_json_atomic(out / "study.json", study)
    return study


def _frames(rgbd_dir: Path) -> int:
    return sum(1 for p in rgbd_dir.iterdir() if p.is_dir() and not p.name.startswith("."))


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj
