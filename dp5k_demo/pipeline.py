"""The demo's stages, each run through the same click command a user would type (networks on the CPU, so that
its numbers are the same on every machine).

Stages (in order): simulated capture of a few scenes and a wall, ``process``, ``validate-depth``, a studio
training set with realistic effects, a short ``train``, ``evaluate`` of every simulator, ``diagnose`` of the
base model and of the Neural DP Simulator on a dataset with a hidden effect, and ``synthesize`` on RGBD
frames. :mod:`dp5k_demo.figures` and :mod:`dp5k_demo.build_report` turn the outputs into the report.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from dp5k_common.effects import EFFECT_NAMES
from dp5k_common.errors import PartialFailureError, StageError

from .stages import Stage


@dataclass(frozen=True)
class DemoScale:
    """Sizes of one demo scale.

    Attributes:
        name: small / medium / paper.
        sim_scale: studio scale for the simulated capture (sensor downscale factor or a named scale).
        scenes: captured scenes (presets) besides the wall.
        train_scenes: random studio scenes in the training set (each gives one pair per f-number).
        train_size: (W, H) of the studio training and diagnosis datasets.
        f_numbers: f-numbers of the studio datasets.
        epochs: training epochs.
        crop: training crop in px.
        base_channels: channels of the U-Net's first level (the paper's 64 only at the paper scale: the demo
            trains on the CPU for a few epochs, where a narrower network learns as much (at the small scale 16
            channels match the 64-channel network's Table 2 to the third digit) and every stage that runs it,
            train, evaluate, diagnose's fine-tuning and synthesize, costs a fraction).
        eval_fit_pairs: training pairs the base model is fitted on before ``evaluate`` compares it.
        diag_scenes: scenes of the hidden-effect dataset (each gives one pair per camera and f-number).
        diag_fit_pairs: training pairs ``diagnose`` fits on (``--fit-pairs``; the other train pairs join the
            detection set); None = diagnose's own default (``auto``).
        rgbd_frames: RGBD frames given to ``synthesize``.
        eval_pairs: pairs per dataset that ``evaluate`` compares the simulators on.
        neural_steps: fine-tuning steps of the Neural DP extension in ``diagnose --simulator neural:CKPT``
            (each arm; the demo's network is the paper's U-Net, so a step costs about a second on the CPU).
    """

    name: str
    sim_scale: str
    scenes: tuple[str, ...]
    train_scenes: int
    train_size: tuple[int, int]
    f_numbers: str
    epochs: int
    crop: int
    base_channels: int
    eval_fit_pairs: int
    diag_scenes: int
    diag_fit_pairs: int | None
    rgbd_frames: int
    eval_pairs: int
    neural_steps: int


SCALES: dict[str, DemoScale] = {
    "small": DemoScale("small", "20", ("demo01",), 6, (96, 64), "1.8,4", 2, 48, 16, 2, 4, 4, 2, 4, 2),
    "medium": DemoScale("medium", "10", ("demo01", "boxes"), 12, (192, 128), "1.8,2.8,5.6", 6, 96, 32, 4, 6, 6, 4, 8, 20),
    "paper": DemoScale("paper", "paper", ("demo01", "boxes", "near"), 40, (576, 384), "1.8,2,2.8,4,5.6", 20, 256, 64, 8, 30, None, 8, 0, 150),
}

# Realistic effects for the training data (the world is not the ideal model): Canon-like weak disparity,
# Pixel-like L/R imbalance, a soft non-flat disc and sensor noise.
TRAIN_EFFECTS = ("disparity_scale=1", "lr_gain_imbalance=1", "psf_profile=1")


def run_cli(args: list[str]) -> None:
    """Run one ``dp5k`` sub-command in-process exactly as the CLI would, letting dp5k errors propagate."""
    from dp5k_cli import main

    name = args[0]
    command = main.get_command(click.Context(main), name)
    if command is None:
        raise StageError(f"this dp5k has no '{name}' command", where="demo")
    command.main(args[1:], prog_name=f"dp5k {name}", standalone_mode=False, obj={"verbose": 0})


def hidden_effect(seed: int) -> str:
    """The effect hidden in the diagnosis dataset, drawn from ``seed`` (the report reveals it at the end)."""
    rng = np.random.default_rng(seed)
    return str(EFFECT_NAMES[int(rng.integers(len(EFFECT_NAMES)))])


def build_stages(out: Path, scale: DemoScale, seed: int) -> list[Stage]:
    """The demo's stages for ``scale``, writing under ``out``."""
    raw = out / "raw"
    processed = out / "processed"
    train_ds = out / "studio-train"
    diag_ds = out / "studio-hidden"
    run_dir = out / "neural_dp"
    rgbd = out / "rgbd-frames"
    effect = hidden_effect(seed)
    diag_fit = [] if scale.diag_fit_pairs is None else ["--fit-pairs", str(scale.diag_fit_pairs)]

    def capture(ctx: dict[str, Any]) -> dict[str, Any]:
        for scene in (*scale.scenes, "wall"):
            manifest = raw / scene / "manifest.json"
            if not (manifest.is_file() and json.loads(manifest.read_text()).get("complete")):
                run_cli(["capture", "--scene", scene, "--sim", "--out", str(raw), "--sim-scale", scale.sim_scale, "--seed", str(seed)])
            run_cli(["verify", str(raw / scene)])  # a finished scene from an earlier run is checked, not recaptured
        return {"raw": str(raw), "scenes": list(scale.scenes), "wall": "wall"}

    def process(ctx: dict[str, Any]) -> dict[str, Any]:
        staging = out / "raw-scenes"
        # process every captured scene except the wall (the wall is for validate-depth)
        staging.mkdir(parents=True, exist_ok=True)
        for scene in scale.scenes:
            link = staging / scene
            if not link.exists():
                link.symlink_to((raw / scene).resolve(), target_is_directory=True)
        skipped = []
        try:
            run_cli(["process", str(staging), "--out", str(processed), "--seed", str(seed)])
        except PartialFailureError:
            # as `dp5k process` does for a user: failed scenes are reported and skipped, the rest go on
            for scene in scale.scenes:
                path = processed / "reports" / scene / "report.json"
                rep = json.loads(path.read_text()) if path.is_file() else {}
                if rep.get("status") == "failed":
                    skipped.append({"scene": scene, "reason": rep.get("reason", "?")})
            if len(skipped) == len(scale.scenes) or not (processed / "dataset.json").is_file():
                raise
        return {"dataset": str(processed), "skipped": skipped}

    def validate(ctx: dict[str, Any]) -> dict[str, Any]:
        vout = out / "validate-depth"
        run_cli(["validate-depth", str(raw / "wall"), "--out", str(vout)])
        return {"out": str(vout)}

    def studio_train(ctx: dict[str, Any]) -> dict[str, Any]:
        args = ["studio", "make-dataset", "--out", str(train_ds), "--scenes", str(scale.train_scenes),
                "--size", f"{scale.train_size[0]}x{scale.train_size[1]}", "--f-numbers", scale.f_numbers,
                "--seed", str(seed + 1)]
        for e in TRAIN_EFFECTS:
            args += ["--effect", e]
        run_cli(args)
        return {"dataset": str(train_ds), "effects": list(TRAIN_EFFECTS)}

    def train(ctx: dict[str, Any]) -> dict[str, Any]:
        run_cli(["train", str(train_ds), "--out", str(run_dir), "--epochs", str(scale.epochs),
                 "--crop-size", str(scale.crop), "--set", f"model.base_channels={scale.base_channels}",
                 "--device", "cpu", "--seed", str(seed)])
        return {"run": str(run_dir), "checkpoint": str(run_dir / "best.pt")}

    def evaluate(ctx: dict[str, Any]) -> dict[str, Any]:
        specs = ("disk", "butterworth", "raytrace", "base", f"neural:{run_dir / 'best.pt'}")  # Table 2's columns
        simulators = [arg for spec in specs for arg in ("--simulator", spec)]
        results = {}
        for name, ds in (("studio", train_ds), ("processed", processed)):
            eout = out / f"evaluate-{name}"
            split = "test" if name == "studio" else _nonempty_split(ds)
            run_cli(["evaluate", str(ds), "--split", split, "--out", str(eout), *simulators,
                     "--max-pairs", str(scale.eval_pairs), "--fit-pairs", str(scale.eval_fit_pairs), "--figures", "1",
                     "--device", "cpu"])
            results[name] = {"out": str(eout), "split": split}
        return results

    def hidden(ctx: dict[str, Any]) -> dict[str, Any]:
        run_cli(["studio", "make-dataset", "--out", str(diag_ds), "--scenes", str(scale.diag_scenes),
                 "--size", f"{scale.train_size[0]}x{scale.train_size[1]}", "--f-numbers", scale.f_numbers,
                 "--seed", str(seed + 2), "--effect", f"{effect}=1"])
        return {"dataset": str(diag_ds)}

    def diagnose_base(ctx: dict[str, Any]) -> dict[str, Any]:
        dout = out / "diagnose-base"
        run_cli(["diagnose", str(diag_ds), "--simulator", "base", "--out", str(dout), *diag_fit])
        return {"out": str(dout)}

    def diagnose_neural(ctx: dict[str, Any]) -> dict[str, Any]:
        dout = out / "diagnose-neural"
        run_cli(["diagnose", str(diag_ds), "--simulator", f"neural:{run_dir / 'best.pt'}", "--out", str(dout), *diag_fit,
                 "--neural-steps", str(scale.neural_steps), "--device", "cpu"])
        return {"out": str(dout)}

    def synthesize(ctx: dict[str, Any]) -> dict[str, Any]:
        from .rgbd import write_rgbd_frames

        write_rgbd_frames(diag_ds, rgbd, scale.rgbd_frames)
        sout = out / "synthesized"
        run_cli(["synthesize", str(rgbd), "--out", str(sout), "--simulator", f"neural:{run_dir / 'best.pt'}",
                 "--encoding", "linear", "--seed", str(seed), "--device", "cpu"])
        return {"in": str(rgbd), "out": str(sout)}

    def report(ctx: dict[str, Any]) -> dict[str, Any]:
        from .build_report import build_report

        path = build_report(out, scale, ctx["records"], hidden=effect)
        return {"report": str(path)}

    return [
        Stage("capture", "Simulated capture (PTP bodies + ESC/VP21 projector + virtual studio)", capture,
              "check `dp5k capture --sim --scene demo01` on its own; delete OUT/raw/<scene> only if its manifest is corrupt"),
        Stage("process", "Processing raw sessions into dataset format v1", process,
              "run `dp5k -v process OUT/raw-scenes --out OUT/processed` to see which scene failed and why"),
        Stage("validate_depth", "Depth validation against a ChArUco wall (Eq. 4)", validate,
              "run `dp5k -v validate-depth OUT/raw/wall --out OUT/validate-depth`"),
        Stage("studio_train", "Studio training data with realistic effects", studio_train,
              "run `dp5k -v studio make-dataset` with the same arguments"),
        Stage("train", "Short Neural DP Simulator training", train,
              "run `dp5k -v train OUT/studio-train --out OUT/neural_dp`; add --overwrite to start over"),
        Stage("evaluate", "Evaluation of every simulator (Table 2)", evaluate,
              "run `dp5k -v evaluate OUT/studio-train --simulator neural:OUT/neural_dp/best.pt` (and the others)"),
        Stage("hidden_effect", "A dataset with a hidden physical effect", hidden,
              "run `dp5k -v studio make-dataset --out OUT/studio-hidden` with the same arguments"),
        Stage("diagnose_base", "Diagnosis of the physical base model", diagnose_base,
              "run `dp5k -v diagnose OUT/studio-hidden --simulator base`"),
        Stage("diagnose_neural", "Diagnosis of the Neural DP Simulator", diagnose_neural,
              "run `dp5k -v diagnose OUT/studio-hidden --simulator neural:OUT/neural_dp/best.pt`"),
        Stage("synthesize", "Synthesis of DP pairs from RGBD frames", synthesize,
              "run `dp5k -v synthesize OUT/rgbd-frames --out OUT/synthesized --simulator neural:OUT/neural_dp/best.pt`"),
        Stage("report", "Report", report, "rerun `dp5k -v demo --out OUT` (finished stages are reused)", always=True),
    ]


def _nonempty_split(dataset: Path) -> str:
    """The first non-empty split of a dataset, preferring test (a tiny processed set may have an empty test)."""
    index = json.loads((dataset / "dataset.json").read_text())
    for name in ("test", "val", "train"):
        if index["splits"].get(name):
            return name
    raise StageError("the dataset has no pairs", where=dataset)
