"""The downstream study (the paper's Sec. 5.3, Tables 3 and 4): which simulator's synthetic DP data trains the best
DP deblurrer, scored on measured test pairs, with 95 % intervals over test scenes and seeds.

From one folder of RGBD frames (``dp5k synthesize``'s input), one measured dataset and, optionally, a second
measured dataset of real pairs (e.g. ``dp5k import sdirt``), for every seed:

1. train the Neural DP Simulator on the measured train split (as the paper trains it on real DP data) with the
   same budget as every deblurrer (steps, crops, learning rate; its own network size), unless switched off;
2. synthesize a DP dataset with every simulator, from the same frames and the same drawn optics (the random focus
   and f-number of a frame depend only on the seed and the frame's name, ``neural_dp.synthesize``); the sensor
   noise is whatever ``dp5k synthesize`` adds by default;
3. train one deblurrer per simulator with the same budget and seed (``cfg.train``); each is used as it is at the
   end of its budget (``last.pt``: a val split of a few synthetic pairs is no guide to measured pairs);
4. for every test set (``measured``, and ``real`` when given): score each deblurrer on its test split
   (**Table 3**, beside the blurred input L + R), and the transfer setting: fine-tune each pre-trained deblurrer on
   ``cfg.few_real_pairs`` of that set's train pairs, beside the same fine-tuning from scratch and a deblurrer
   trained on all of its train pairs with the full budget (**Table 4**).

Every row has a 95 % interval over the test set's scenes and the seeds, and every difference the study reports
says whether it is resolved (:mod:`dp5k_deblur.study_tables`, :mod:`dp5k_learn.intervals`).

Writes into ``out`` (atomically): ``tables.md`` (every table and the verdicts), ``study.json`` (settings, test
data, timings in wall and CPU seconds), and per test set ``<set>/table3.md/json``, ``<set>/table4.md/json``,
``<set>/differences.json``, ``<set>/figure.png``. Intermediate data and runs: ``neural/seed<k>/``,
``synth/seed<k>/<simulator>/``, ``runs/seed<k>/`` (deblurrers of synthetic data) and ``<set>/few_real/``,
``<set>/runs/seed<k>/``. A second run reuses every finished synthesis and training run (all resume).
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from dp5k_common.dataset import DatasetReader, copy_pairs
from dp5k_common.errors import BadInputError
from dp5k_common.io import write_bytes_atomic, write_json_atomic
from dp5k_learn.config import DataConfig, OptimConfig
from dp5k_learn.intervals import N_BOOT, Resampler, verdict
from neural_dp.registry import (PAPER_F_NUMBERS, PEERS, ModelConfig, SimulatorSpec, SynthConfig, TrainConfig,
                                synthesize, train)

from .config import DeblurTrainConfig
from .evaluate import DeblurScores, score
from .study_tables import INPUT_ROW, Row, differences, figure, markdown, row_json
from .train import load_deblurrer, train_deblur

logger = logging.getLogger(__name__)

PEER_SIMULATORS: tuple[str, ...] = (*PEERS, "base")
"""The simulators that need no file (``neural:CKPT`` needs a checkpoint, ``diagnosed:REPORT.json`` a report)."""
TRAINED_NEURAL = "neural"
"""The label of the Neural DP Simulator the study trains on the measured train split."""
LABEL = re.compile(r"^([A-Za-z][A-Za-z0-9_.-]*)=(.+)$")
"""``LABEL=SPEC``: a simulator under a name of its own (two checkpoints of ``neural``, two reports)."""


@dataclass(frozen=True)
class StudyConfig:
    """The study's settings; every deblurrer gets the same ``train`` budget, and every seed runs everything."""

    simulators: tuple[str, ...] = PEER_SIMULATORS
    """Simulator specs (:class:`~neural_dp.registry.SimulatorSpec`), each optionally as ``LABEL=SPEC`` (the row's
    and folder's name; the simulator's name by default), e.g. ``diagnosed:REPORT.json``,
    ``sdirt=neural:CKPT``."""
    train_neural: bool = True
    """Train the Neural DP Simulator on the measured train split (per seed, the deblurrers' budget) and study it."""
    neural_model: ModelConfig = field(default_factory=lambda: ModelConfig(base_channels=12, levels=3))
    """The network size of that Neural DP Simulator (the paper's: 64 channels, 4 levels)."""
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
    seeds: tuple[int, ...] = (0, 1, 2)
    """Every seed synthesizes (its own optics draws and noise), trains and fine-tunes everything again."""
    n_boot: int = N_BOOT
    """Bootstrap replicates of the intervals."""

    def specs(self) -> list[tuple[str, SimulatorSpec]]:
        """``(label, spec)`` of every simulator in ``simulators``, checked before any work.

        Raises:
            BadInputError: a bad spec, a missing checkpoint or report, two simulators under one label (the
                Neural DP Simulator the study trains is ``neural``), or no seed.
        """
        if not self.seeds:
            raise BadInputError("at least one seed", where="--seeds")
        out = []
        for text in self.simulators:
            m = LABEL.match(text.strip())
            spec = SimulatorSpec.parse(m.group(2) if m else text)
            spec.check_files()
            out.append((m.group(1) if m else spec.name, spec))
        labels = [label for label, _ in out] + ([TRAINED_NEURAL] if self.train_neural else [])
        if len(set(labels)) < len(labels):
            raise BadInputError(f"one label per simulator, please: {', '.join(labels)} (name one LABEL=SPEC; the Neural DP "
                                f"Simulator the study trains is '{TRAINED_NEURAL}')", where="--simulator")
        return out


def few_pairs_dataset(real: Path, out: Path, count: int) -> Path:
    """A dataset of ``real``'s first ``count`` train pairs and its val pairs (copied), no test pairs.

    Raises:
        BadInputError: ``real`` has fewer than ``count`` train pairs, or ``out`` holds other pairs (a resumed study
            with another ``count``).
    """
    reader = DatasetReader(real)
    train_ids, val = reader.ids("train")[:count], reader.ids("val")
    if len(train_ids) < count:
        raise BadInputError(f"the transfer setting needs {count} train pairs, the dataset has {len(train_ids)}", where=real)
    if (out / "dataset.json").is_file():
        if DatasetReader(out).ids("train") != train_ids:
            raise BadInputError(f"holds another set of few measured pairs than the first {count}; use another --out", where=out)
        return out
    return copy_pairs(real, out, {"train": train_ids, "val": val, "test": []}, source=f"{count} train pairs of {real}")


def neural_train_config(cfg: StudyConfig, seed: int) -> TrainConfig:
    """The Neural DP Simulator's run under the deblurrers' budget: their crops, batch, items per epoch, epochs and
    learning rate; its own network size and loss (Eq. 8, with its gradient terms); crops mostly of valid depth."""
    data, optim = cfg.train.data, cfg.train.optim
    return TrainConfig(seed=seed, device=cfg.device, model=cfg.neural_model,
                       data=replace(DataConfig(), crop_px=data.crop_px, batch_size=data.batch_size,
                                    samples_per_epoch=data.samples_per_epoch),
                       optim=replace(OptimConfig(), epochs=optim.epochs, lr=optim.lr, lr_min=optim.lr_min))


class _Clock:
    """Wall and CPU seconds (this process, every thread) of each named stage, summed over seeds."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        w, c = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - w
            self.cpu[name] = self.cpu.get(name, 0.0) + time.process_time() - c


def run_downstream(rgbd_dir: str | Path, real: str | Path, out: str | Path, cfg: StudyConfig | None = None,
                   real_pairs: str | Path | None = None) -> dict[str, Any]:
    """Run the study (module docstring). ``real``: the measured dataset (its train split trains the Neural DP
    Simulator, feeds its transfer setting and the all-measured reference; its test split is test set ``measured``).
    ``real_pairs``: another measured dataset (test set ``real``, with its own transfer setting and reference), e.g.
    Sdirt's targets split by photo. Returns the study.json object.

    Raises:
        BadInputError / EmptySplitError: unusable frames, datasets or settings (checked before any training).
    """
    cfg = cfg or StudyConfig()
    specs = cfg.specs()
    rgbd_dir, out = Path(rgbd_dir), Path(out)
    sets = {"measured": Path(real), **({"real": Path(real_pairs)} if real_pairs is not None else {})}
    test_ids = {name: DatasetReader(path).ids("test") for name, path in sets.items()}
    for name, ids in test_ids.items():
        if not ids:
            raise BadInputError(f"the {name} test set is empty: nothing to score", where=sets[name] / "dataset.json")
    few = {name: few_pairs_dataset(path, out / name / "few_real", cfg.few_real_pairs) for name, path in sets.items()}
    clock = _Clock()
    per_seed: dict[tuple[str, str], list[DeblurScores]] = {}
    """(test set, row) -> one DeblurScores per seed."""
    labels: list[str] = []
    synthetic_noise: dict[str, dict[str, Any] | None] = {}
    """label -> the sensor noise model its first seed's synthetic pairs carry (``noise_model`` of their dataset.json)."""

    def scored(test: str, key: str, run: Path) -> None:
        per_seed.setdefault((test, key), []).append(score(load_deblurrer(run / "last.pt", cfg.device), sets[test], "test", cfg.device))

    for seed in cfg.seeds:
        train_cfg = replace(cfg.train, seed=seed, device=cfg.device)
        tune_cfg = replace(train_cfg, optim=replace(train_cfg.optim, epochs=cfg.finetune_epochs, lr=cfg.finetune_lr))
        for test, path in sets.items():
            runs = out / test / "runs" / f"seed{seed}"
            with clock(f"{test}: measured-only deblurrers"):
                train_deblur(path, runs / "measured_all", train_cfg)
                scored(test, "measured_all", runs / "measured_all")
                train_deblur(few[test], runs / "measured_few", tune_cfg)
                scored(test, "measured_few", runs / "measured_few")
        sims = list(specs)
        if cfg.train_neural:
            with clock("neural: training on the measured train split"):
                train(sets["measured"], out / "neural" / f"seed{seed}", neural_train_config(cfg, seed))
            sims.append((TRAINED_NEURAL, SimulatorSpec("neural", out / "neural" / f"seed{seed}" / "best.pt")))
        labels = [label for label, _ in sims]
        for label, spec in sims:
            with clock(f"{label}: synthesis + deblurrers"):
                synth = out / "synth" / f"seed{seed}" / label
                synthesize(rgbd_dir, synth, SynthConfig(simulator=str(spec), f_numbers=cfg.f_numbers, max_coc_px=cfg.max_coc_px,
                                                         encoding=cfg.encoding, seed=seed, device=cfg.device))
                synthetic_noise.setdefault(label, DatasetReader(synth).extra.get("noise_model"))
                pre = out / "runs" / f"seed{seed}" / f"synth_{label}"
                train_deblur(synth, pre, train_cfg)
                for test in sets:
                    scored(test, f"synth_{label}", pre)
                    tuned = out / test / "runs" / f"seed{seed}" / f"synth_{label}+few"
                    train_deblur(few[test], tuned, tune_cfg, init_from=pre / "last.pt")
                    scored(test, f"synth_{label}+few", tuned)
        logger.info("seed %d done (%.0f s CPU so far)", seed, sum(clock.cpu.values()))

    report: dict[str, Any] = {}
    summary = []
    for test, path in sets.items():
        report[test] = _write_tables(test, path, out / test, test_ids[test], labels, per_seed, cfg)
        summary.append(report[test]["markdown"])
    write_bytes_atomic(out / "tables.md", "\n".join(summary).encode())
    study = {"rgbd_frames": str(rgbd_dir), "test_sets": {k: str(v) for k, v in sets.items()}, "test_pairs": test_ids,
             "seeds": list(cfg.seeds), "simulators": {label: str(spec) for label, spec in specs}, "config": _jsonable(asdict(cfg)),
             "synthetic_noise": synthetic_noise, "timings_s": clock.wall, "cpu_s": clock.cpu,
             **{test: {k: v for k, v in r.items() if k != "markdown"} for test, r in report.items()}}
    write_json_atomic(out / "study.json", study)
    return study


def _write_tables(test: str, path: Path, out: Path, pair_ids: list[str], labels: list[str],
                  per_seed: dict[tuple[str, str], list[DeblurScores]], cfg: StudyConfig) -> dict[str, Any]:
    """One test set's Tables 3 and 4, differences, figure; returns their JSON and Markdown."""
    reader = DatasetReader(path)
    scenes = [reader.params(pid).scene for pid in pair_ids]
    rs = Resampler(scenes, len(cfg.seeds), cfg.n_boot)

    def row(setting: str, key: str, simulator: str | None = None, kind: str = "prediction") -> Row:
        return Row.of(setting, per_seed[(test, key)][:1] if kind == "input" else per_seed[(test, key)], pair_ids, kind, simulator)

    n = cfg.few_real_pairs
    floor = row(INPUT_ROW, "measured_all", kind="input")
    t3 = [floor] + [row(f"synthetic: {lb}", f"synth_{lb}", lb) for lb in labels]
    # the few and all train pairs are those of this test set's own dataset (MEASURED's, or --real's)
    t4 = [row(f"{test}: {n} train pairs only (fine-tune budget)", "measured_few"),
          row(f"{test}: all train pairs (full budget)", "measured_all")]
    t4 += [row(f"synthetic: {lb} + fine-tune on {n} {test} train pairs", f"synth_{lb}+few", lb) for lb in labels]
    diffs = differences(t3, t4, rs)
    rows3 = [row_json(r, floor, rs) for r in t3]
    rows4 = [row_json(r, floor, rs) for r in t4]
    n_scenes = len(set(scenes))
    note = (f"Test set `{test}`: the test split of `{path}` ({len(pair_ids)} pairs from {n_scenes} scenes), masked PSNR / "
            f"SSIM / MAE of the deblurred image against its `sharp`; means over pairs and seeds {list(cfg.seeds)}, 95 % "
            f"intervals from a two-way bootstrap over the {n_scenes} scenes and the {len(cfg.seeds)} seeds "
            f"({cfg.n_boot} replicates; dp5k_learn/intervals.py).")
    tables = {
        "table3": (f"Table 3 ({test}): deblurrers trained on each simulator's synthetic data", rows3),
        "table4": (f"Table 4 ({test}): transfer, pre-trained on synthetic data then fine-tuned on {n} train pairs of "
                   f"`{path}` ({cfg.finetune_epochs} epochs)", rows4),
    }
    md = [f"## Test set `{test}`", ""]
    for key, (title, rows) in tables.items():
        write_json_atomic(out / f"{key}.json", {"title": title, "test_data": str(path), "test_pairs": pair_ids,
                                                "scenes": scenes, "seeds": list(cfg.seeds), "rows": rows})
        text = markdown(title, rows, note)
        write_bytes_atomic(out / f"{key}.md", text.encode())
        md.append(text)
    words = verdict(diffs)
    write_json_atomic(out / "differences.json", {"test_data": str(path), "metric": "PSNR (dB), a - b",
                                                 "differences": [d.to_json() for d in diffs], "verdict": words})
    figure(out / "figure.png", rows3, rows4, f"test set {test}: {len(pair_ids)} pairs, {n_scenes} scenes, {len(cfg.seeds)} seeds")
    md += [f"Differences on `{test}` (PSNR):", "", words]
    return {"table3": rows3, "table4": rows4, "differences": [d.to_json() for d in diffs], "verdict": words,
            "markdown": "\n".join(md)}


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj
