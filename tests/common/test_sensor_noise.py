"""The shared sensor-noise model (dp5k_common/sensor_noise.py): its draws have the model's variance per channel and
intensity, are reproducible from a seed, parse and round-trip; a diagnose report's pooled noise is read; and the
noise of a dataset's views is measured without any model, from another renderer's planted noise."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from dp5k_common.dataset import DatasetReader, write_pair
from dp5k_common.errors import BadInputError
from dp5k_common.sensor_noise import NOMINAL, NoiseModel, measure_views, noise_from_spec

MODEL = NoiseModel((1e-4, 3e-4, 9e-4), (4e-3, 2e-3, 1e-3))
LEVELS = (0.05, 0.3, 0.8)
"""Linear intensities of the test image's three column blocks."""


def _blocks_image(n_rows: int = 200, block: int = 100) -> np.ndarray:
    """(n_rows, 3 block, 3) float32: column block j at intensity LEVELS[j] in every channel."""
    img = np.zeros((n_rows, 3 * block, 3), np.float32)
    for j, level in enumerate(LEVELS):
        img[:, j * block:(j + 1) * block] = level
    return img


def _check_variance(noise: np.ndarray, block: int = 100) -> None:
    """Per channel and intensity block, the sample variance of ``noise`` equals the model's within 4 standard errors
    (the standard error of a normal sample variance: sigma^2 sqrt(2 / (n - 1)))."""
    for c in range(3):
        for j, level in enumerate(LEVELS):
            x = noise[:, j * block:(j + 1) * block, c].astype(np.float64).ravel()
            want = MODEL.shot_var[c] * level + MODEL.read_sigma[c] ** 2
            se = want * math.sqrt(2.0 / (x.size - 1))
            assert abs(x.var(ddof=1) - want) < 4 * se, (c, level, x.var(ddof=1), want)
            assert abs(x.mean()) < 4 * math.sqrt(want / x.size)  # zero mean


def test_numpy_draws_have_the_models_variance_per_channel_and_intensity() -> None:
    img = _blocks_image()
    _check_variance(MODEL.sample(img, np.random.default_rng(0)) - img)
    # a wrong model would be caught: the same draws do not match twice the shot variance
    doubled = NoiseModel(tuple(2 * s for s in MODEL.shot_var), MODEL.read_sigma)
    with pytest.raises(AssertionError):
        _check_variance((doubled.sample(img, np.random.default_rng(0)) - img))


def test_torch_draws_have_the_models_variance_with_channels_first() -> None:
    img = torch.from_numpy(_blocks_image().transpose(2, 0, 1).copy())[None]  # (1, 3, H, W)
    noisy = MODEL.sample(img, torch.Generator().manual_seed(0))
    assert noisy.dtype == img.dtype and noisy.shape == img.shape
    _check_variance((noisy - img)[0].permute(1, 2, 0).numpy())


def test_draws_are_reproducible_from_the_seed_and_differ_with_another() -> None:
    img = _blocks_image(20, 10)
    a = MODEL.sample(img, np.random.default_rng(7))
    assert np.array_equal(a, MODEL.sample(img, np.random.default_rng(7)))
    assert not np.array_equal(a, MODEL.sample(img, np.random.default_rng(8)))
    t = torch.from_numpy(img.transpose(2, 0, 1).copy())
    ta = MODEL.sample(t, torch.Generator().manual_seed(7))
    assert torch.equal(ta, MODEL.sample(t, torch.Generator().manual_seed(7)))
    assert not torch.equal(ta, MODEL.sample(t, torch.Generator().manual_seed(8)))


def test_parse_json_and_specs() -> None:
    assert NoiseModel.parse("shot=2e-4,read=2e-3").shot_var == (2e-4,) * 3
    per = NoiseModel.parse("shot=1e-4:2e-4:3e-4, read=1e-3")
    assert per.shot_var == (1e-4, 2e-4, 3e-4) and per.read_sigma == (1e-3,) * 3
    assert NoiseModel.from_json(json.loads(json.dumps(per.to_json()))) == per
    for bad in ("shot=2e-4", "shot=-1,read=0", "shot=1:2,read=0", "shot=x,read=1", "gain=1,read=1"):
        with pytest.raises(BadInputError) as err:
            NoiseModel.parse(bad)
        assert err.value.where == "--noise" and "\n" not in err.value.one_line()
    assert noise_from_spec("none") is None and noise_from_spec("nominal") == NOMINAL
    assert NOMINAL.shot_var == (2e-5,) * 3 and NOMINAL.read_sigma == (1e-3,) * 3
    with pytest.raises(BadInputError, match="unknown noise"):
        noise_from_spec("loud")


def test_diagnosed_reads_the_pooled_noise_of_a_diagnose_report(tmp_path: Path) -> None:
    from types import SimpleNamespace

    import numpy as np

    from dp5k_diagnose.config import DiagnoseConfig
    from dp5k_diagnose.noise import NoiseMeasure
    from dp5k_diagnose.run import noise_model

    measured = NoiseMeasure(True, 3.0, np.full(10, 3.0), 6e-5, 2.5e-3)
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"noise_model": noise_model(SimpleNamespace(noise=measured), DiagnoseConfig())}))  # what diagnose writes
    model = noise_from_spec(f"diagnosed:{report}")
    assert model is not None and model.shot_var == (6e-5,) * 3 and model.read_sigma == (2.5e-3,) * 3
    assert model.source == f"diagnosed:{report}"

    unmeasured = NoiseMeasure(False, note="too few flat valid pixels to measure noise")
    report.write_text(json.dumps({"noise_model": noise_model(SimpleNamespace(noise=unmeasured), DiagnoseConfig())}))  # noise not measured
    with pytest.raises(BadInputError, match="measured no noise model") as err:
        NoiseModel.from_report(report)
    assert err.value.where == str(report)
    with pytest.raises(BadInputError, match="file not found"):
        NoiseModel.from_report(tmp_path / "none.json")


def test_measured_recovers_noise_planted_by_another_renderer(tmp_path: Path) -> None:
    """aperture_dp (no code shared with dp5k) plants shot 1e-4 and read 4e-3 on both views. Over 6 seeds of this
    set (2026-11-28) the measurement ranged over 0.75-1.34 x the shot variance, 0.86-1.22 x the read sigma and
    0.93-1.23 x the variance at intensities 0.1 and 0.4 (the read term is a small part of the variance, so the two
    trade off); the test allows 1.4, 1.3 and 1.3. Noise-free views measure as nearly noise free."""
    from dp5k_testing.aperture_dp import write_dataset

    shot, read = 1e-4, 4e-3
    write_dataset(tmp_path / "noisy", "none", scenes=8, size=(160, 108), seed=0, shot_var=shot, read_sigma=read)
    found = measure_views(tmp_path / "noisy")
    assert found.pairs == 16 and found.samples > 10000
    m = found.model
    assert m.source == f"measured:{tmp_path / 'noisy'}"
    for c in range(3):
        assert 1 / 1.4 < m.shot_var[c] / shot < 1.4, m
        assert 1 / 1.3 < m.read_sigma[c] / read < 1.3, m
        for level in (0.1, 0.4):
            assert 1 / 1.3 < (m.shot_var[c] * level + m.read_sigma[c] ** 2) / (shot * level + read**2) < 1.3, m

    write_dataset(tmp_path / "clean", "none", scenes=3, size=(160, 108), seed=0, noise=False)
    clean = measure_views(tmp_path / "clean").model
    assert max(clean.shot_var) < 0.1 * shot and max(clean.read_sigma) < 0.5 * read, clean  # the renderer's own error


def test_measured_tells_the_channels_apart(tmp_path: Path) -> None:
    """Noise planted per channel (shot 1e-4, 3e-4, 9e-4) on another renderer's noise-free views is measured per
    channel (each within 1.4 x, so the factor 3 between channels is resolved)."""
    from dp5k_testing.aperture_dp import write_dataset

    write_dataset(tmp_path / "ds", "none", scenes=6, size=(160, 108), seed=1, noise=False)
    reader = DatasetReader(tmp_path / "ds")
    rng = np.random.default_rng(0)
    for pid in reader.ids():
        p = reader.load(pid)
        write_pair(tmp_path / "ds", p.params, sharp=p.sharp, left=np.clip(MODEL.sample(p.left, rng), 0, 1),
                   right=np.clip(MODEL.sample(p.right, rng), 0, 1), depth_mm=p.depth_mm, coc_px=p.coc_px,
                   overwrite=True, sub_mm_depth=True)
    m = measure_views(tmp_path / "ds").model
    ratios = np.array(m.shot_var) / np.array(MODEL.shot_var)
    assert np.all((ratios > 1 / 1.4) & (ratios < 1.4)), m
    assert m.shot_var[0] < m.shot_var[1] < m.shot_var[2]


def test_measuring_a_dataset_without_flat_pixels_or_a_missing_one_is_a_clear_error(tmp_path: Path) -> None:
    from dp5k_testing.tiny_dataset import make_tiny_dataset

    make_tiny_dataset(tmp_path / "tiny", scenes=1)
    with pytest.raises(BadInputError, match="too few flat pixels"):
        measure_views(tmp_path / "tiny")
    with pytest.raises(BadInputError, match="not found"):
        noise_from_spec(f"measured:{tmp_path / 'missing'}")
