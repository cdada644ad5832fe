"""``measured:ATLAS``: a camera's kernels from a diagnose PSF atlas render its views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dp5k_common.errors import BadInputError
from dp5k_diagnose import atlas as A
from dp5k_diagnose.data import read_input
from dp5k_diagnose.measure import measured_views, pair_images
from dp5k_learn.metrics import view_metrics
from dp5k_testing.foreign_dp import write_dataset
from neural_dp.registry import SimulatorSpec


def test_the_measured_kernels_render_another_renderers_views(tmp_path: Path) -> None:
    """Another renderer (a scatter of half discs, box-sampled, a gain ramp L/R 1 + 0.08 (1 + 0.5 x)): the atlas of its
    train pairs renders its held-out pairs better than any peer, with its L/R brightness."""
    write_dataset(tmp_path / "ds", "lr_gain_imbalance", 1.0, scenes=8, size=(128, 96), seed=2)
    inp = read_input(tmp_path / "ds", None, 96, 1, 0)
    train = inp.samples(inp.splits["fit"])
    A.save_atlas(tmp_path / "atlas.npz", A.measure_atlas(pair_images(train), {"measured": measured_views(train)}, n_boot=10))
    sim = SimulatorSpec.parse(f"measured:{tmp_path / 'atlas.npz'}").load()
    scores: dict[str, list[float]] = {"measured": [], "disk": [], "butterworth": [], "base": []}
    ratio = []
    for s in inp.samples(inp.splits["held"]):
        b = s.batch
        with torch.no_grad():
            for name in scores:
                peer = sim if name == "measured" else SimulatorSpec.parse(name).load()
                pl, pr = peer(b)
                scores[name].append(float(view_metrics(pl, pr, b.left, b.right, s.score)["psnr"].mean()))
                if name == "measured":
                    m = s.score.float()
                    ratio.append(float((pl * m).sum() / (pr * m).sum() / ((b.left * m).sum() / (b.right * m).sum())))
    mean = {k: float(np.mean(v)) for k, v in scores.items()}
    assert mean["measured"] > max(mean["disk"], mean["butterworth"], mean["base"]) + 2, mean
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.01)  # the measured L/R brightness, kept


def test_a_missing_or_foreign_file_is_a_one_line_error(tmp_path: Path) -> None:
    with pytest.raises(BadInputError, match="PSF atlas not found"):
        SimulatorSpec.parse(f"measured:{tmp_path / 'none.npz'}").load()
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(BadInputError, match="not a dp5k PSF atlas"):
        SimulatorSpec.parse(f"measured:{tmp_path / 'other.npz'}").load()
    with pytest.raises(BadInputError, match="needs a PSF atlas"):
        SimulatorSpec.parse("measured")
