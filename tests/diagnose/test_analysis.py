"""Analysis and statistics helpers: disparity estimate, bootstrap CI, one-sided t, components' physics."""

from __future__ import annotations

import numpy as np
import torch

from dp5k_diagnose.analysis import tile_disparity
from neural_dp.simulators.base.components import COMPONENTS, DisparityScale, LRGainImbalance, shift_image
from dp5k_diagnose.tiles import one_sided_t
from dp5k_diagnose.gain import bootstrap_ci
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


def test_bootstrap_ci_and_t_test() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(1.0, 0.5, 40)
    lo, hi = bootstrap_ci(x)
    assert lo < x.mean() < hi and lo > 0.7 and hi < 1.3
    t, p = one_sided_t(x)
    assert t > 5 and p < 1e-6
    t0, p0 = one_sided_t(-x)
    assert p0 > 0.99
    assert bootstrap_ci(np.zeros(5)) == (0.0, 0.0)


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
