"""dp5k synthesize puts the sensor's noise on the views (issue 33): by default the nominal sensor, drawn per frame
from the seed (same seed, same bytes; another seed, other noise; the optics never change with it), with the model's
variance; --noise none gives the noise-free views of before; measured:, diagnosed: and shot=,read= name the model,
which the dataset records; a resumed run refuses other noise."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError
from dp5k_common.sensor_noise import NOMINAL, NoiseModel
from dp5k_learn.batch import DPBatch
from neural_dp.registry import SimulatorSpec
from neural_dp.synthesize import SynthConfig, synthesize

from .test_synthesize import _frames

FIXED = dict(simulator="disk", f_numbers=(2.8,), focus_mm=1500.0, depth_scale=1000.0, max_coc_px=8.0)
"""Fixed optics, so that only the noise depends on the seed."""


def _views(root: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    reader = DatasetReader(root)
    return {pid: (reader.load(pid).left, reader.load(pid).right) for pid in reader.ids()}


def _pair_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted((root / "pairs").rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_another_seed_other_noise_and_the_same_optics(tmp_path: Path) -> None:
    _frames(tmp_path / "in")
    synthesize(tmp_path / "in", tmp_path / "a", SynthConfig(**FIXED))
    synthesize(tmp_path / "in", tmp_path / "b", SynthConfig(**FIXED, batch_size=1))  # other batches, same bytes
    assert _pair_bytes(tmp_path / "a") == _pair_bytes(tmp_path / "b")
    synthesize(tmp_path / "in", tmp_path / "c", SynthConfig(**FIXED, seed=1))
    a, c = _views(tmp_path / "a"), _views(tmp_path / "c")
    assert a.keys() == c.keys()
    for pid in a:
        assert not np.array_equal(a[pid][0], c[pid][0]) and not np.array_equal(a[pid][1], c[pid][1])
        assert np.abs(a[pid][0] - c[pid][0]).mean() < 0.02  # the same image under other noise
    # with drawn optics the noise never changes the draws: the parameters equal the noise-free run's
    synthesize(tmp_path / "in", tmp_path / "d", SynthConfig(simulator="disk", depth_scale=1000.0))
    synthesize(tmp_path / "in", tmp_path / "e", SynthConfig(simulator="disk", depth_scale=1000.0, noise="none"))
    rd, re_ = DatasetReader(tmp_path / "d"), DatasetReader(tmp_path / "e")
    for pid in rd.ids():
        pd, pe = rd.params(pid), re_.params(pid)
        assert (pd.f_number, pd.focus_distance_mm, pd.focus_point_px) == (pe.f_number, pe.focus_distance_mm, pe.focus_point_px)
        assert pd.extra["noise"] == NOMINAL.to_json() and pe.extra["noise"] is None


def test_noise_none_is_the_simulators_output_and_the_noise_has_the_models_variance(tmp_path: Path) -> None:
    _frames(tmp_path / "in")
    model = NoiseModel((1e-4, 4e-4, 2e-4), (3e-3, 1e-3, 2e-3))
    synthesize(tmp_path / "in", tmp_path / "none", SynthConfig(**FIXED, noise="none"))
    synthesize(tmp_path / "in", tmp_path / "noisy", SynthConfig(**FIXED, noise="shot=1e-4:4e-4:2e-4,read=3e-3:1e-3:2e-3"))
    reader = DatasetReader(tmp_path / "none")
    sim = SimulatorSpec.parse("disk").load().eval()
    z: list[list[np.ndarray]] = [[], [], []]
    for pid, (nl, nr) in _views(tmp_path / "noisy").items():
        pair = reader.load(pid)
        with torch.no_grad():
            left, right = sim(DPBatch.from_pairs([pair]))
        # --noise none: the simulator's own views (as before noise existed), up to the 16-bit files
        expect_l = np.clip(left[0].permute(1, 2, 0).numpy(), 0, 1)
        assert np.abs(pair.left - expect_l).max() < 1e-4
        assert np.abs(pair.right - np.clip(right[0].permute(1, 2, 0).numpy(), 0, 1)).max() < 1e-4
        for clean, noisy in ((pair.left, nl), (pair.right, nr)):
            sd = np.sqrt(model.variance(clean))
            inside = (noisy > 0) & (noisy < 1)  # clipping shrinks the noise at the ends of the range
            for c in range(3):
                z[c].append(((noisy - clean) / sd)[..., c][inside[..., c]])
    for c in range(3):
        zc = np.concatenate(z[c]).astype(np.float64)
        # unit variance per channel (each channel its own shot and read), within 4 standard errors
        assert abs(zc.var() - 1.0) < 4 * math.sqrt(2.0 / zc.size) + 2e-3, (c, zc.var())
    index = json.loads((tmp_path / "noisy" / "dataset.json").read_text())
    assert NoiseModel.from_json(index["noise_model"]) == NoiseModel(model.shot_var, model.read_sigma, index["noise_model"]["source"])
    assert index["synth_config"]["noise"] == "shot=1e-4:4e-4:2e-4,read=3e-3:1e-3:2e-3"
    assert json.loads((tmp_path / "none" / "dataset.json").read_text())["noise_model"] is None


def test_measured_and_diagnosed_noise_and_bad_specs_from_the_command_line(tmp_path: Path) -> None:
    from dp5k_testing.aperture_dp import write_dataset

    _frames(tmp_path / "in", n=2)
    write_dataset(tmp_path / "measured", "none", scenes=3, size=(160, 108), seed=0)  # another renderer's noisy views
    runner = CliRunner()
    base = ["-q", "synthesize", str(tmp_path / "in")]
    res = runner.invoke(main, [*base, str(tmp_path / "m"), "--simulator", "disk", "--depth-scale", "1000",
                               "--noise", f"measured:{tmp_path / 'measured'}"])
    assert res.exit_code == 0, res.output
    recorded = NoiseModel.from_json(json.loads((tmp_path / "m" / "dataset.json").read_text())["noise_model"])
    assert recorded == NoiseModel.measured(tmp_path / "measured")
    assert 1e-4 < recorded.shot_var[1] < 4e-4  # aperture_dp's nominal 2e-4

    report = tmp_path / "report.json"
    report.write_text(json.dumps({"noise_model": {"measured": True, "shot_var": 5e-5, "read_sigma": 2e-3}}))
    res = runner.invoke(main, [*base, str(tmp_path / "d"), "--simulator", "disk", "--depth-scale", "1000",
                               "--noise", f"diagnosed:{report}"])
    assert res.exit_code == 0, res.output
    params = json.loads(next((tmp_path / "d" / "pairs").glob("*/params.json")).read_text())
    assert params["noise"]["shot_var"] == [5e-5] * 3 and params["noise"]["source"] == f"diagnosed:{report}"

    for spec, words in ((f"diagnosed:{tmp_path / 'none.json'}", "file not found"), ("shot=1e-4", "both shot= and read="),
                        ("loud", "unknown noise")):
        res = runner.invoke(main, [*base, str(tmp_path / "bad"), "--simulator", "disk", "--noise", spec])
        assert res.exit_code == 3 and words in res.output and res.output.count("\n") == 1, res.output
        assert not (tmp_path / "bad").exists()  # checked before any work


def test_a_resumed_synthesis_refuses_other_noise(tmp_path: Path) -> None:
    _frames(tmp_path / "in", n=2)
    synthesize(tmp_path / "in", tmp_path / "out", SynthConfig(simulator="disk", depth_scale=1000.0))
    again = synthesize(tmp_path / "in", tmp_path / "out", SynthConfig(simulator="disk", depth_scale=1000.0))
    assert again["skipped"] == 2
    with pytest.raises(BadInputError, match="was synthesized with noise nominal; this run asks for --noise none"):
        synthesize(tmp_path / "in", tmp_path / "out", SynthConfig(simulator="disk", depth_scale=1000.0, noise="none"))
    synthesize(tmp_path / "in", tmp_path / "quiet", SynthConfig(simulator="disk", depth_scale=1000.0, noise="none"))
    with pytest.raises(BadInputError, match="was synthesized without noise"):
        synthesize(tmp_path / "in", tmp_path / "quiet", SynthConfig(simulator="disk", depth_scale=1000.0))
