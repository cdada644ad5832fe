"""The two-way bootstrap of mean scores over test pairs (in clusters) and seeds (dp5k_learn/intervals.py)."""

from __future__ import annotations

import numpy as np
import pytest

from dp5k_common.errors import BadInputError
from dp5k_learn.intervals import Resampler, verdict


def width(e) -> float:  # noqa: ANN001
    return e.hi - e.lo


def test_one_seed_independent_pairs_give_the_textbook_interval() -> None:
    rng = np.random.default_rng(1)
    v = rng.normal(30.0, 2.0, 400)
    e = Resampler([str(i) for i in range(400)], 1).estimate(v)
    half = 1.96 * v.std(ddof=1) / np.sqrt(v.size)
    assert e.mean == pytest.approx(v.mean())
    assert e.lo == pytest.approx(v.mean() - half, abs=0.2 * half) and e.hi == pytest.approx(v.mean() + half, abs=0.2 * half)


def test_pairs_of_one_scene_are_resampled_together() -> None:
    """Four copies of each scene's score carry one scene's information: the interval must be as wide as that of the
    scenes alone, about twice what treating the 4 x 50 pairs as independent would give."""
    rng = np.random.default_rng(2)
    per_scene = rng.normal(0.0, 1.0, 50)
    v = np.repeat(per_scene, 4)
    scenes = [f"s{i}" for i in range(50) for _ in range(4)]
    clustered = Resampler(scenes, 1, seed=3).estimate(v)
    naive = Resampler([str(i) for i in range(200)], 1, seed=3).estimate(v)
    alone = Resampler([str(i) for i in range(50)], 1, seed=3).estimate(per_scene)
    assert width(clustered) == pytest.approx(width(alone), rel=0.15)
    assert width(clustered) > 1.6 * width(naive)


def test_seeds_widen_the_interval_and_a_seedless_row_broadcasts() -> None:
    rng = np.random.default_rng(4)
    pairs = rng.normal(0.0, 0.1, 24)
    seedy = pairs[None] + np.array([[-1.0], [0.0], [1.0]])  # training randomness dominates
    rs = Resampler([str(i) for i in range(24)], 3, seed=5)
    assert width(rs.estimate(seedy)) > 5 * width(rs.estimate(pairs))
    assert rs.estimate(pairs).mean == pytest.approx(rs.estimate(pairs[None]).mean)
    with pytest.raises(BadInputError, match="seeds, pairs"):
        rs.estimate(np.zeros((2, 24)))


def test_differences_are_paired_and_resolved_only_when_the_interval_excludes_zero() -> None:
    rng = np.random.default_rng(6)
    scene_effect = rng.normal(0.0, 3.0, (2, 30))  # large, shared by both settings
    a = scene_effect + 0.3 + rng.normal(0.0, 0.05, (2, 30))
    b = scene_effect
    rs = Resampler([str(i) for i in range(30)], 2, seed=7)
    ea, eb, d = rs.estimate(a), rs.estimate(b), rs.difference(a, b)
    assert ea.lo < eb.hi  # the rows' own intervals overlap ...
    assert d.resolved and d.lo > 0.2 and d.mean == pytest.approx(0.3, abs=0.05)  # ... their paired difference does not
    same = rs.difference(b, b)
    assert (same.mean, same.lo, same.hi) == (0.0, 0.0, 0.0) and not same.resolved
    assert rs.difference(b - 1.0, b).resolved


def test_non_finite_scores_are_left_out() -> None:
    v = np.array([1.0, 2.0, np.nan, 3.0])
    e = Resampler(["a", "b", "c", "d"], 1).estimate(v)
    assert e.mean == pytest.approx(2.0) and 1.0 <= e.lo <= e.hi <= 3.0
    with pytest.raises(BadInputError, match="no finite"):
        Resampler(["a"], 1).estimate([np.nan])


def test_comparisons_name_the_better_setting_first_and_say_whether_resolved() -> None:
    rs = Resampler([str(i) for i in range(10)], 1)
    base = np.linspace(20.0, 30.0, 10)
    worse = rs.compare("worse", base - 1.0, "better", base)
    assert (worse.a, worse.b) == ("better", "worse") and worse.estimate.mean == pytest.approx(1.0)
    assert worse.estimate.lo == pytest.approx(1.0) and worse.estimate.resolved
    tie = rs.compare("x", base + np.tile([0.1, -0.1], 5), "y", base)
    text = verdict([worse, tie])
    assert "**Resolved** (1 of 2" in text and "better +1.00 dB over worse" in text
    assert "**Not resolved** (1)" in text and "over y" in text.split("Not resolved")[1]
