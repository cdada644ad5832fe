"""Does a deblurrer trained on studio pairs transfer to pairs that another renderer made? (issue 33, section 2)

The pieces the transfer test (``tests/deblur/test_transfer.py``) and its benchmark (``benchmarks/deblur_transfer.py``)
share:

* :data:`SUITE_TRAIN_ARGS`: the suite's deblurrer and budget, as ``dp5k deblur train`` options (300 Adam steps of 8
  crops of 48 px, a U-Net of 12 channels x 3 levels, lr 2e-3, Charbonnier epsilon 0.1);
* :func:`diverse_studio_pairs`: studio training pairs that transfer (``dp5k studio make-dataset --random-captures``:
  random focus, f-number, sensor format and gain, sensor noise);
* :func:`narrow_studio_pairs`: the training pairs that did not (10 scenes at f/2 and f/4, each scene's own focus, the
  rig's full-frame sensor, no noise);
* :func:`foreign_pairs`: test pairs from a renderer that shares no code with dp5k (:mod:`.aperture_dp`,
  :mod:`.foreign_dp`);
* :func:`transfer_gain`: the PSNR gain of a trained deblurrer over the blurred input ``L + R`` on every pair of a
  dataset, per scene, with a t interval over scenes.

Units: PSNR in dB against ``sharp`` (linear intensity, peak 1), on each pair's valid-depth mask.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from dp5k_common.dataset import DatasetReader
from dp5k_deblur.evaluate import score
from dp5k_deblur.train import load_deblurrer

SUITE_TRAIN_ARGS: tuple[str, ...] = (
    "--crop", "48", "--batch-size", "8", "--lr", "2e-3", "--epochs", "30", "--device", "cpu",
    "--set", "data.samples_per_epoch=80", "--set", "model.base_channels=12", "--set", "charbonnier_eps=0.1")
"""30 epochs x 10 steps = 300 Adam steps on 48 px crops; a Charbonnier epsilon quadratic below about 0.1 (at the
paper's 1e-3, nearly L1, 300 steps barely move off the blurred input: docs/deblur.md)."""

STUDIO_SIZE = (96, 64)
"""(W, H) of the studio training pairs, px."""

DIVERSE_ARGS: tuple[str, ...] = ("--scenes", "60", "--size", "96x64", "--camera", "0", "--all-in-focus-sharp",
                                 "--random-captures", "1")
"""``dp5k studio make-dataset`` options of :func:`diverse_studio_pairs` (with the defaults of ``--f-numbers``
1.8-5.6, ``--coc-px 0.2:12`` and ``--noise-gain 1:30``)."""


def diverse_studio_pairs(out: Path, seed: int = 3, extra: tuple[str, ...] = ()) -> Path:
    """60 studio scenes at 96 x 64, one random capture each (:data:`DIVERSE_ARGS`), through the command a user runs.
    ``extra`` adds or overrides options (e.g. ``("--no-noise",)`` to take one ingredient out)."""
    from click.testing import CliRunner

    from dp5k_cli import main

    res = CliRunner().invoke(main, ["-q", "studio", "make-dataset", str(out), *DIVERSE_ARGS, "--seed", str(seed), *extra])
    if res.exit_code != 0:
        raise RuntimeError(f"dp5k studio make-dataset failed: {res.output}")
    return out


def narrow_studio_pairs(out: Path, seed: int = 3, scenes: int = 10) -> Path:
    """The issue's training pairs: ``scenes`` studio scenes at 96 x 64, f/2 and f/4 at each scene's own focus, the
    rig's sensor, noise-free views, the all-in-focus radiance as ``sharp``."""
    from dp5k_studio import make_dataset

    return make_dataset(out, scenes=scenes, size=STUDIO_SIZE, f_numbers=(2.0, 4.0), cameras=(0,), seed=seed, noise=False,
                        all_in_focus_sharp=True)


RENDERERS = ("aperture", "aperture-50mm", "foreign", "foreign-tent")
"""Test renderers of :func:`foreign_pairs`."""


def foreign_pairs(out: Path, renderer: str = "aperture", scenes: int = 24, seed: int = 0) -> Path:
    """``scenes`` scenes x f/1.8 and f/4 at 128 x 86 from a renderer dp5k never saw, with its own sensor noise:

    * ``aperture``: :mod:`.aperture_dp` (sub-aperture gather with occlusion; 35 mm lens on a 17.3 mm sensor; noise
      ``2e-4 I + (2e-3)^2`` on the views and on its f/22 ``sharp``);
    * ``aperture-50mm``: the same with a 50 mm lens (about twice the blur);
    * ``foreign``: :mod:`.foreign_dp` (per-pixel scattered half discs; 50 mm on 24 mm; noise ``2e-5 I + (1e-3)^2``;
      all-in-focus ``sharp``; textures of stripes and checkers down to 2 px periods), its default ``box`` PSF
      sampling: a disc is integrated over pixels as if all of a pixel's light left from its centre, so a disc under
      about 1 px stays inside its own pixel and leaves it unblurred;
    * ``foreign-tent``: the same scenes with foreign_dp's ``tent`` sampling, the pixel integration of its own
      radiance (constant over each canvas pixel: a uniform square of light spread by the disc and integrated over the
      pixels is the disc convolved with a tent), which blurs sub-pixel discs as the studio does (docs/deblur.md,
      "Why foreign_dp lost").
    """
    if renderer.startswith("aperture"):
        from .aperture_dp import write_dataset

        write_dataset(out, "none", scenes=scenes, size=(128, 86), f_numbers=(1.8, 4.0), seed=seed,
                      focal_length_mm=50.0 if renderer == "aperture-50mm" else 35.0)
    elif renderer in ("foreign", "foreign-tent"):
        from .foreign_dp import write_dataset as write_foreign

        write_foreign(out, None, scenes=scenes, size=(128, 86), f_numbers=(1.8, 4.0), seed=seed,
                      sampling="tent" if renderer == "foreign-tent" else "box")
    else:
        raise ValueError(f"unknown renderer {renderer!r}; known: {', '.join(RENDERERS)}")
    return out


@dataclass(frozen=True)
class TransferGain:
    """A deblurrer's PSNR gain over ``L + R`` on every pair of a dataset.

    Attributes:
        pairs: pair id -> (PSNR of the prediction, PSNR of L + R), dB.
        scene_gain: scene -> mean gain of its pairs, dB.
        mean: mean of the scenes' gains (every scene has as many pairs: the mean over pairs), dB.
        ci95: 95 % t interval of the mean gain over scenes (the unit of independence), dB.
    """

    pairs: dict[str, tuple[float, float]]
    scene_gain: dict[str, float]
    mean: float
    ci95: tuple[float, float]

    @property
    def input_psnr(self) -> float:
        return float(np.mean([b for _, b in self.pairs.values()]))


def transfer_gain(checkpoint: str | os.PathLike[str], dataset: Path) -> TransferGain:
    """Score ``checkpoint`` on every split of ``dataset`` (a deblurrer never trained on any of it)."""
    net = load_deblurrer(checkpoint)
    reader = DatasetReader(dataset)
    pairs: dict[str, tuple[float, float]] = {}
    for split in reader.splits:
        if reader.ids(split):
            for row in score(net, dataset, split).pairs:
                pairs[row["pair_id"]] = (row["prediction"]["psnr"], row["input"]["psnr"])
    by_scene: dict[str, list[float]] = {}
    for pid, (a, b) in pairs.items():
        by_scene.setdefault(reader.params(pid).scene, []).append(a - b)
    scene_gain = {s: float(np.mean(g)) for s, g in by_scene.items()}
    g = np.array(list(scene_gain.values()))
    half = float(stats.t.ppf(0.975, len(g) - 1) * g.std(ddof=1) / math.sqrt(len(g))) if len(g) > 1 else math.inf
    return TransferGain(pairs, scene_gain, float(g.mean()), (float(g.mean()) - half, float(g.mean()) + half))
