"""Analysis and statistics helpers: disparity estimate, bootstrap CI, components' physics."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from dp5k_diagnose.analysis import tile_disparity
from neural_dp.simulators.base.components import COMPONENTS, DisparityScale, LRGainImbalance, shift_image
from dp5k_diagnose.gain import TileErrors, bootstrap_ci, tile_bootstrap_ci, tile_errors, tile_psnr
from dp5k_diagnose.data import Sample
from dp5k_learn.metrics import view_metrics
from dp5k_common.effects import EFFECT_NAMES
from neural_dp.simulators.base import field_coords


def smooth_texture(seed: int, H: int = 64, W: int = 96) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, H, W, generator=g)
    return torch.nn.functional.avg_pool2d(x, 5, 1, 2)


def test_tile_disparity_recovers_a_known_shift_with_sign() -> None:
    L = smooth_texture(0)
    for d in (0.6, -0.8):
        R = shift_image(L, d, 0.0)  # R content moved right by d
        est, w = tile_disparity(L, R, torch.ones(1, 1, 64, 96, dtype=torch.bool), 16)
        core = est[:, 1:-1, 1:-1]
        assert abs(float(core.median()) - d) < 0.05


def test_bootstrap_ci() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(1.0, 0.5, 40)
    lo, hi = bootstrap_ci(x)
    assert lo < x.mean() < hi and lo > 0.7 and hi < 1.3
    assert bootstrap_ci(np.zeros(5)) == (0.0, 0.0)


def test_tile_psnr_is_each_pairs_masked_psnr_over_partial_tiles_too() -> None:
    from tests.neural_dp.test_base_model import make_batch

    g = torch.Generator().manual_seed(1)
    views = torch.rand(3, 2, 3, 40, 52, generator=g)  # 32 px tiles leave a partial row and column
    batch = dataclasses.replace(make_batch(views[0], torch.zeros(2, 1, 40, 52), views[1], views[2]), pair_ids=["a", "b"])
    pred_l, pred_r = (batch.left + 0.05 * torch.randn(batch.left.shape, generator=g)).clamp(0, 1), batch.right * 0.9
    score = torch.rand(2, 1, 40, 52, generator=g) > 0.3
    s = Sample(batch, None, score)
    e = tile_errors(lambda _: (pred_l, pred_r), [s], 32)
    assert e.pair_ids == ["a", "b"] and e.sse.shape == (2, 2, 4) and e.count.shape == (2, 4)
    want = view_metrics(pred_l, pred_r, batch.left, batch.right, score)["psnr"].numpy()
    assert np.allclose(tile_psnr(e), want, atol=1e-4)


def _noisy_tiles(rng: np.random.Generator, factor: float, pairs: int = 4, tiles: int = 40) -> tuple[TileErrors, TileErrors]:
    """Tile SSEs of a model before and after a change that scales each tile's expected error by ``factor``:
    chi-square noise of 3 x 256 values per tile, tile contents differing by up to 4 x in error."""
    level = rng.uniform(1.0, 4.0, (pairs, 1, tiles))
    n = 768
    before = level * rng.chisquare(n, (pairs, 2, tiles)) / n
    after = factor * level * rng.chisquare(n, (pairs, 2, tiles)) / n
    ids = [f"p{i}" for i in range(pairs)]
    count = np.full((pairs, tiles), float(n))
    return TileErrors(ids, before * n, count), TileErrors(ids, after * n, count)


def test_tile_bootstrap_ci_finds_a_small_real_gain_and_keeps_its_false_positives_near_five_percent() -> None:
    rng = np.random.default_rng(0)
    # a 0.1 dB gain on 4 held-out pairs: above 0 on the tiles' evidence
    hits = [tile_bootstrap_ci(*_noisy_tiles(rng, 10 ** (-0.01)), n_boot=400, seed=k)[0] > 0 for k in range(20)]
    assert sum(hits) >= 18
    # no gain: the lower bound lies above 0 in about 2.5 % of sets (one-sided), not much more
    null = [tile_bootstrap_ci(*_noisy_tiles(rng, 1.0), n_boot=400, seed=k) for k in range(300)]
    false = sum(lo > 0 for lo, _ in null) / len(null)
    assert false <= 0.06, false
    assert sum(lo < 0 < hi for lo, hi in null) / len(null) >= 0.9


def test_every_effect_has_a_component() -> None:
    assert set(COMPONENTS) == set(EFFECT_NAMES)


def test_crosstalk_keeps_left_plus_right_and_scales_disparity() -> None:
    L, R = smooth_texture(1), smooth_texture(2)
    c = DisparityScale()
    c.params["disparity_scale"] = 0.4
    l2, r2 = c.post(L, R, None, field_coords(1, 64, 96))  # type: ignore[arg-type]
    assert torch.allclose(l2 + r2, L + R, atol=1e-6)
    assert torch.allclose(l2 - r2, 0.4 * (L - R), atol=1e-6)


def test_lr_gain_ratio_follows_the_field_model() -> None:
    c = LRGainImbalance()
    c.params.update(a0=0.18, ax=0.1)
    one = torch.ones(1, 3, 8, 16)
    f = field_coords(1, 8, 16)
    l, r = c.post(one, one, None, f)  # type: ignore[arg-type]
    ratio = (l / r)[0, 0]
    assert abs(float(ratio[4, 0]) - np.exp(0.18 - 0.1)) < 1e-4 and abs(float(ratio[4, -1]) - np.exp(0.28)) < 1e-4
    assert abs(c.describe()["lr_ratio_center"] - np.exp(0.18)) < 1e-9
