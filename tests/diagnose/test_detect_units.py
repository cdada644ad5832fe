"""Unit checks of the detectors' building blocks: the noise measurement, the predictable-pixel mask, the tile
statistics and the linear algebra the selection of causes stands on (bounded Gauss-Newton refits, canonical
correlations of look-alikes, Hochberg's correction, informative pairs)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dp5k_diagnose import noise as detect_noise
from dp5k_diagnose import tiles
from dp5k_diagnose.config import DetectConfig
from dp5k_diagnose.data import Sample, predictable_mask
from neural_dp.registry import Linearization, jacobian, lm_fit
from neural_dp.simulators.base import BaseModel, field_coords
from tests.neural_dp.test_base_model import make_batch

SHOT, READ = 2.0e-5, 1.0e-3


def scene(seed: int, n: int = 4, H: int = 64, W: int = 96) -> torch.Tensor:
    """(n, 3, H, W) flat patches of random level with a band of fine texture (edges everywhere would hide noise)."""
    g = torch.Generator().manual_seed(seed)
    img = torch.zeros(n, 3, H, W)
    for i in range(n):
        for y0 in range(0, H, 16):
            for x0 in range(0, W, 24):
                img[i, :, y0 : y0 + 16, x0 : x0 + 24] = 0.1 + 0.7 * torch.rand(3, 1, 1, generator=g)
    img[:, :, :, : W // 4] += 0.2 * torch.rand(n, 3, H, W // 4, generator=g)
    return img.clamp(0, 1)


def noisy_views(sharp: torch.Tensor, var_factor: float, common: torch.Tensor | None, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Views = sharp / 2 (+ a pattern common to both) + independent noise of ``var_factor`` x nominal variance."""
    g = torch.Generator().manual_seed(seed)
    views = []
    for _ in range(2):
        v = sharp / 2 + (0 if common is None else common)
        sd = torch.sqrt(var_factor * (SHOT * v.clamp(min=0) + READ**2))
        views.append(v + sd * torch.randn(v.shape, generator=g))
    return views[0], views[1]


def samples(sharp: torch.Tensor, left: torch.Tensor, right: torch.Tensor, coc: torch.Tensor | None = None) -> list[Sample]:
    """One sample of every pair (CoC ``coc``, (B, 1, H, W) px; in focus by default)."""
    B, _, H, W = sharp.shape
    coc = torch.zeros(B, 1, H, W) if coc is None else coc
    b = dataclasses.replace(make_batch(sharp, coc, left, right), pair_ids=tuple(f"p{i}" for i in range(B)))
    return [Sample(b, field_coords(B, H, W))]


@pytest.mark.parametrize("factor", [1.0, 4.0])
def test_noise_measured_against_nominal(factor: float) -> None:
    sharp = scene(0)
    s = samples(sharp, *noisy_views(sharp, factor, None, 1))
    f = detect_noise.test_noise(BaseModel(), s, [], DetectConfig())
    assert f.params["variance_ratio"] == pytest.approx(factor, rel=0.15)
    assert f.detected is (factor > 1.5)
    assert f.params["shot_var"] == pytest.approx(factor * SHOT, rel=0.5)


def test_noise_ignores_structure_common_to_both_views() -> None:
    """Ringing or shifted texture is in both views alike; only independent noise counts (misregistration is not noise)."""
    sharp = scene(2)
    ring = 0.01 * torch.sin(torch.arange(sharp.shape[-1]) * 2.7)[None, None, None, :].expand_as(sharp)
    f = detect_noise.test_noise(BaseModel(), samples(sharp, *noisy_views(sharp, 1.0, ring, 3)), [], DetectConfig())
    assert f.params["variance_ratio"] == pytest.approx(1.0, rel=0.15) and not f.detected


def test_predictable_mask_drops_pixels_whose_blur_reaches_past_the_border() -> None:
    H, W = 40, 60
    coc = torch.zeros(1, 1, H, W)
    coc[..., :, 30:] = 16.0  # right half: 16 px discs (reach 8 px + margin)
    b = make_batch(torch.rand(1, 3, H, W), coc)
    m = predictable_mask(b, margin_px=1.0, window_px=1)[0, 0]
    assert m[20, 5] and not m[0, 5]  # sharp pixels only lose the 1 px rim
    assert m[20, 45] and not m[20, W - 5] and not m[4, 45]  # blurred ones lose 9 px at the border
    b.valid[..., 20, 20] = False
    assert not predictable_mask(b)[0, 0, 20, 20]


def test_bounded_gauss_newton_refit_matches_least_squares_and_holds_parameters() -> None:
    """On a linear problem the linearization's refit is the least-squares solution; a held parameter stays at
    its value while the others absorb what they can; a bound is respected."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(200, 3))
    truth = np.array([0.5, -1.0, 2.0])
    y = J @ truth + 0.01 * rng.normal(size=200)

    class Owner:
        def __init__(self) -> None:
            self.params = {"a": 0.0, "b": 0.0, "c": 0.0}
            self.bounds = {"c": (-np.inf, 1.0)}
            self.steps = {}

    o = Owner()
    lin = Linearization([(o, "a"), (o, "b"), (o, "c")], np.zeros(3), torch.from_numpy(-y), torch.from_numpy(J))
    free = lin.solve(held={2: 1.0})
    ref = np.linalg.lstsq(J[:, :2], y - J[:, 2] * 1.0, rcond=None)[0]
    assert free[2] == 1.0 and np.allclose(free[:2], ref, atol=1e-8)
    bounded = lin.solve()
    assert bounded[2] == pytest.approx(1.0)  # c wants 2.0, its bound is 1.0
    unbounded = np.linalg.lstsq(J, y, rcond=None)[0]
    assert lin.predicted_sse(bounded) > lin.predicted_sse(unbounded) - 1e-12


def test_canonical_correlation_tells_look_alikes_from_independent_effects() -> None:
    """Two effects whose Jacobian columns span the same direction (up to a nuisance column) correlate at 1;
    independent ones near 0; projecting out the nuisance removes a correlation it alone carries."""
    from dp5k_diagnose.selection import canonical_corr

    rng = np.random.default_rng(1)
    n = rng.normal(size=(500, 1))
    a = rng.normal(size=(500, 1))
    b_same = 2.0 * a + 0.5 * n
    c = rng.normal(size=(500, 1))
    J = np.hstack([a, b_same, c, n])
    A = J.T @ J
    assert canonical_corr(A, [0], [1], [3]) == pytest.approx(1.0, abs=1e-6)
    assert canonical_corr(A, [0], [2], [3]) < 0.15
    shared = np.hstack([a + 3 * n, c + 3 * n, n])  # correlated only through the nuisance
    A2 = shared.T @ shared
    assert canonical_corr(A2, [0], [1], []) > 0.8 and canonical_corr(A2, [0], [1], [2]) < 0.15


def test_hochberg_step_up_keeps_the_family_wise_level() -> None:
    assert tiles.hochberg_passed([0.001, 0.02, 0.04], 0.05) == [True, True, True]  # 0.04 < 0.05: all pass
    assert tiles.hochberg_passed([0.001, 0.03, 0.04], 0.05) == [True, True, True]  # Holm stopped at 0.03 >= 0.025
    assert tiles.hochberg_passed([0.001, 0.03, 0.06], 0.05) == [True, False, False]  # 0.06 > 0.05, 0.03 > 0.025, 0.001 < 0.0167
    assert tiles.hochberg_passed([0.027, 0.042], 0.05) == [True, True]  # foreign_dp chromatic defocus + focus offset
    assert tiles.hochberg_passed([0.04, 0.001], 0.05) == [True, True]  # the largest is below alpha: both pass
    assert tiles.hochberg_passed([0.06, 0.02], 0.05) == [False, True]  # 0.06 > 0.05, 0.02 < 0.025
    assert tiles.hochberg_passed([], 0.05) == []
    rng = np.random.default_rng(2)  # under the null (independent tests), any pass among 8 happens at most alpha of the time
    rate = np.mean([any(tiles.hochberg_passed(list(rng.uniform(size=8)), 0.05)) for _ in range(2000)])
    assert rate < 0.065


def test_pairs_where_two_models_agree_do_not_vote() -> None:
    """A comparison counts only the pairs where the two models' predictions differ (by 1 % of the pair's noise
    energy): 6 pairs where an effect helps much and 8 where it changes nothing but whose tiny log ratios lean
    the other way. Counted, the 8 sink the test; left out, the 6 decide it."""
    from dp5k_diagnose.selection import informed_test

    owners = np.array([f"p{i:02d}" for i in range(14)])
    su_with = np.ones(14)
    su_without = su_with * np.exp(np.r_[np.full(6, 1.0), np.full(8, -1e-4)])
    diff = np.r_[np.full(6, 0.5), np.full(8, 1e-6)]
    noise = np.ones(14)
    informed = informed_test("x", su_without, su_with, diff, noise, np.full(14, 96.0), owners)
    assert informed.p_value < 0.05 and informed.effect_size > 0
    _, p_all = tiles.effect_test(tiles.clustered_delta(su_without, su_with, np.full(14, 96.0), owners))
    assert p_all > 0.05
    assert informed_test("x", su_without, su_with, np.zeros(14), noise, np.full(14, 96.0), owners).p_value == 1.0
    # the effect size is a share of what the model without the effect leaves beyond noise
    got = informed_test("x", np.full(14, 3.0), np.full(14, 2.0), diff, noise, np.full(14, 96.0), owners).effect_size
    assert got == pytest.approx((42 - 28) / (42 - 14))


def test_noise_on_too_little_data_is_a_plain_non_finding() -> None:
    sharp = scene(5, n=1, H=8, W=8)
    f = detect_noise.test_noise(BaseModel(), samples(sharp, *noisy_views(sharp, 4.0, None, 6)), [], DetectConfig())
    assert not f.detected and f.p_value == 1.0 and "too few" in f.explanation
    assert f.to_json()["effect"] == "noise"


def test_effect_sizes_are_shares_of_the_error_beyond_noise() -> None:
    """With a perfect model the base error is the views' noise: the systematic error is the floor. With a
    5 % gain error on top, it is the base error less the measured noise, i.e. the gain error's own energy."""
    sharp = scene(4)
    left, right = noisy_views(sharp, 2.0, None, 5)
    cfg = DetectConfig()
    for gain_error in (0.0, 0.05):
        s = samples(sharp, left * (1 + gain_error), right * (1 + gain_error))
        noise = detect_noise.test_noise(BaseModel(), s, [], cfg)
        base_su, _, _ = tiles.tile_mse(BaseModel(rim_softness_px=0.0), s, cfg.tile_px)
        total = float(base_su.sum())
        sys_sse = detect_noise.systematic_sse(total, s, noise, cfg)
        if gain_error == 0.0:
            assert sys_sse == pytest.approx(cfg.systematic_floor * total)
        else:
            truth = float(((torch.cat([left, right], 1) * gain_error) ** 2 * s[0].score).sum())  # over the scored pixels
            assert sys_sse == pytest.approx(truth, rel=0.1)


def test_occlusion_free_mask_drops_pixels_within_blur_reach_of_depth_edges() -> None:
    from dp5k_diagnose.data import occlusion_free_mask

    H, W = 40, 80
    coc = torch.full((1, 1, H, W), 2.0)
    coc[..., :, 40:] = 10.0  # a jump of 8 px at x = 40: blur reaches 5 px + 1.5 px margin
    m = occlusion_free_mask(make_batch(torch.rand(1, 3, H, W), coc))[0, 0]
    assert m[20, 10] and m[20, 70]
    assert not m[20, 38] and not m[20, 44]
    smooth = torch.linspace(2.0, 10.0, W).expand(1, 1, H, W).contiguous()  # a slanted plane: no edge
    assert occlusion_free_mask(make_batch(torch.rand(1, 3, H, W), smooth)).all()


def test_gain_metrics_count_only_the_chosen_mask() -> None:
    """``predictable`` takes the Sample's score mask, ``valid`` every valid pixel: an error placed only outside
    the score mask leaves the predictable PSNR perfect and lowers the all-valid one."""
    from dp5k_diagnose.gain import pair_metrics_by_mask

    sharp = scene(6, n=2)
    left, right = sharp / 2, sharp / 2
    s = samples(sharp, left, right)[0]
    s.score = torch.zeros_like(s.batch.valid)
    s.score[..., 8:-8, 8:-8] = True

    def predict(smp: Sample) -> tuple[torch.Tensor, torch.Tensor]:
        bad_l, bad_r = smp.batch.left.clone(), smp.batch.right.clone()
        bad_l[..., :4, :] += 0.2  # wrong only in rows the score mask leaves out
        bad_r[..., :4, :] -= 0.2
        return bad_l, bad_r

    m = pair_metrics_by_mask(predict, [s])
    assert np.all(m["predictable"].psnr > 80) and np.all(m["valid"].psnr < 40)


def test_tile_statistics_keep_partly_scored_tiles() -> None:
    """An error confined to a tile a third scored (as tiles of blurred regions are beside the depth-edge mask)
    counts in full; a tile with one scored pixel in 1024 is left out. With the old rule (tiles at least half
    as scored as the best one) the first error vanished from every effect size."""
    H, W = 64, 96
    sharp = scene(7, n=1, H=H, W=W)
    b = make_batch(sharp, torch.zeros(1, 1, H, W))
    model = BaseModel(rim_softness_px=0.0)
    left, right = model.render(b, field_coords(1, H, W))
    left = left.clone()
    left[..., 0:32, 32:64] += 0.1  # error in a partly scored tile
    left[..., 32:64, 64:96] += 0.1  # error in a nearly empty tile
    score = torch.zeros(1, 1, H, W, dtype=torch.bool)
    score[..., :, 0:32] = True
    score[..., 32:64, 32:64] = True
    score[..., 0:32, 32:43] = True  # 11 of 32 columns
    score[..., 40, 70] = True
    s = Sample(dataclasses.replace(b, left=left, right=right, pair_ids=("p0",)), field_coords(1, H, W), score)
    su, co, _ = tiles.tile_mse(model, [s], 32)
    assert co.size == 4  # 3 full tiles + the partly scored one; the one-pixel tile is dropped
    assert float(su.sum()) == pytest.approx(0.1**2 * 32 * 11 * 3, rel=1e-3)


@pytest.mark.parametrize("true_crosstalk", [0.1, -0.1])
def test_disparity_scale_is_at_most_the_ideal_split(true_crosstalk: float) -> None:
    """Crosstalk shrinks disparity, and the fit finds how much (0.8 of ideal for 0.1); views with more disparity
    than the ideal half-aperture split (what a rim-heavy aperture gives) fit at the bound 1, not above it:
    unbounded, it took the place of front_back_asymmetry on a planted set."""
    from dp5k_diagnose.selection import targets_of
    from neural_dp.simulators.base.components import COMPONENTS, crosstalk

    H, W = 48, 96
    sharp = torch.nn.functional.avg_pool2d(scene(8, n=2, H=H, W=W), 3, 1, 1)
    coc = torch.linspace(-8, 8, W).expand(2, 1, H, W).contiguous()
    b = make_batch(sharp, coc)
    base = BaseModel(rim_softness_px=0.0)
    left, right = crosstalk(*base.render(b, field_coords(2, H, W)), true_crosstalk, true_crosstalk)
    fit = [Sample(dataclasses.replace(b, left=left, right=right, pair_ids=("p0", "p1")), field_coords(2, H, W))]
    model = base.with_component(COMPONENTS["disparity_scale"]())
    lm_fit(model, targets_of(model, fit), fit, 6)
    got = model.components[-1].params["disparity_scale"]
    if true_crosstalk > 0:
        assert got == pytest.approx(1 - 2 * true_crosstalk, abs=0.03)
    else:
        assert got == pytest.approx(1.0, abs=1e-9)


def test_front_back_asymmetry_fits_only_the_sides_the_data_shows() -> None:
    """Fit data with no blur worth the name in front of focus (|CoC| < 1.5 px there) cannot tell the front
    blur's shape: the front parameters stay neutral even when near-focus front pixels would pull them (here
    they are rendered 0.6 x smaller, as a sharp frame that is itself slightly blurred makes them look), while
    the back rim gain is fitted. With content on both sides all three are fitted."""
    from dp5k_diagnose.findings import explanation
    from dp5k_diagnose.selection import targets_of
    from neural_dp.simulators.base.components import COMPONENTS, fittable_names

    H, W = 48, 96
    sharp = torch.nn.functional.avg_pool2d(scene(9, n=2, H=H, W=W), 3, 1, 1)
    truth = COMPONENTS["front_back_asymmetry"]()
    truth.params.update({"back_rim_gain": 1.0, "front_center_gain": 0.0, "front_size_factor": 0.6})
    fitted = {}
    for lo in (-1.4, -8.0):
        coc = torch.linspace(lo, 8.0, W).expand(2, 1, H, W).contiguous()
        b = make_batch(sharp, coc)
        left, right = BaseModel(0.0, 1.0, [truth]).render(b, field_coords(2, H, W))
        fit = [Sample(dataclasses.replace(b, left=left, right=right, pair_ids=("p0", "p1")), field_coords(2, H, W))]
        comp = COMPONENTS["front_back_asymmetry"]()
        one_side, both = ["back_rim_gain", "spherical_mm_f1"], ["back_rim_gain", "front_center_gain", "front_size_factor", "spherical_mm_f1"]
        assert comp.supported_names(fit) == (one_side if lo > -1.5 else both)  # spherical aberration shows on either side
        model = BaseModel(rim_softness_px=0.0).with_component(COMPONENTS["front_back_asymmetry"]())
        lm_fit(model, targets_of(model, fit), fit, 6)
        fitted[lo] = model.components[-1].params
        held = [n for n in comp.fit_names if n not in fittable_names(comp, fit)]
        held_said = "front_center_gain, front_size_factor not fitted" in explanation("front_back_asymmetry", comp.describe(), held)
        assert held_said == (lo > -1.5)  # the report says which parameters were held neutral
    assert fitted[-1.4]["front_size_factor"] == 1.0 and fitted[-1.4]["front_center_gain"] == 0.0
    assert fitted[-1.4]["back_rim_gain"] == pytest.approx(1.0, abs=0.3)
    assert fitted[-8.0]["front_size_factor"] < 0.85  # moves toward 0.6 (size and centre gain trade off)


def test_crops_carry_the_sharp_context_their_blur_needs() -> None:
    """A 96 px crop of a 320 px frame whose discs are 60 px wide: the crop is cut with enough sharp context
    around it that its scored pixels are predictable (their blur stays inside the cut), and only the 96 px
    core is scored. Without the context no core pixel is predictable and the fallback scored them all."""
    from dp5k_common.dataset import Pair, PairParams
    from dp5k_diagnose.data import crop_samples

    H, W = 192, 320
    rng = np.random.default_rng(0)
    img = rng.uniform(0.2, 0.8, (H, W, 3)).astype(np.float32)
    coc = np.full((H, W), 60.0, np.float32)
    params = PairParams("p", "s", "cam0", 1.8, 1000.0, 50.0, 36.0 / W, (W / 2, H / 2), (W, H), {"sharp_f_number": 20.0})
    pair = Pair(params, img, img / 2, img / 2, np.full((H, W), 3000.0, np.float32), coc)
    samples = crop_samples([pair], 96, 3, np.random.default_rng(1))
    for s in samples:
        assert s.batch.sharp_f_number is not None and bool((s.batch.sharp_f_number == 20.0).all())
        h, w = s.score.shape[-2:]
        assert h > 96 and w > 96  # context was added
        for score in s.score[:, 0]:
            ys, xs = torch.nonzero(score, as_tuple=True)
            assert ys.numel() > 0.5 * 96 * 96  # most of the core is predictable
            assert int(ys.max() - ys.min()) < 96 and int(xs.max() - xs.min()) < 96  # only the core is scored
            reach = 60.0 / 2
            dist = torch.minimum(torch.minimum(ys, h - 1 - ys), torch.minimum(xs, w - 1 - xs)).float()
            assert bool((dist >= reach).all())  # every scored pixel's blur lies inside the cut


def test_gain_report_leaves_out_a_pair_without_pixels_and_stays_valid_json() -> None:
    import json

    from dp5k_common.errors import BadInputError
    from dp5k_diagnose.gain import PairMetrics, gain_report

    nan = float("nan")
    before = PairMetrics(["a", "b", "c"], np.array([30.0, nan, 32.0]), np.array([0.9, nan, 0.92]), np.array([0.01, nan, 0.012]))
    after = PairMetrics(["a", "b", "c"], np.array([31.0, nan, 34.0]), np.array([0.91, nan, 0.95]), np.array([0.009, nan, 0.01]))
    g = gain_report(before, after, "test", n_boot=200)
    json.dumps(g, allow_nan=False)  # report.json is written with allow_nan=False
    assert g["n_pairs"] == 2 and g["per_pair_psnr_gain"] == {"a": 1.0, "b": None, "c": 2.0}
    assert g["psnr_before"] == pytest.approx(31.0) and g["psnr_after"] == pytest.approx(32.5)
    assert 1.0 <= g["psnr_gain_ci95"][0] <= g["psnr_gain_ci95"][1] <= 2.0
    empty = PairMetrics(["b"], np.array([nan]), np.array([nan]), np.array([nan]))
    with pytest.raises(BadInputError, match="no pair of the test split"):
        gain_report(empty, empty, "test")


def test_detection_thresholds_are_per_effect() -> None:
    """chromatic_defocus has its own, lower threshold (renderer mismatch that is the same in every channel
    cannot feed it); every other predictable effect uses min_effect, noise its own."""
    cfg = DetectConfig()
    assert cfg.threshold("chromatic_defocus") < cfg.min_effect
    assert cfg.threshold("psf_profile") == cfg.min_effect and cfg.threshold("noise") == cfg.noise_min_effect
    assert DetectConfig(min_effect_by_effect={}).threshold("chromatic_defocus") == cfg.min_effect


def test_noise_on_texture_everywhere_is_not_the_views_dp_disparity() -> None:
    """A scene textured everywhere (no flat patch in sharp) and blurred by 3-9 px discs, with nominal noise:
    flatness is judged on the views the base model predicts and their L - R is taken out, so the DP
    disparity of the blurred texture does not read as noise (judged on sharp it read as 37 x nominal)."""
    g = torch.Generator().manual_seed(7)
    B, H, W = 4, 64, 96
    sharp = (0.15 + 0.7 * torch.rand(B, 3, H // 2, W // 2, generator=g)).repeat_interleave(2, -1).repeat_interleave(2, -2)
    coc = torch.linspace(3.0, 9.0, W).expand(B, 1, H, W).clone()
    coc[:, :, : H // 2] *= -1  # front of focus above, behind below
    truth = BaseModel(rim_softness_px=0.0)
    b = dataclasses.replace(make_batch(sharp, coc), pair_ids=tuple(f"p{i}" for i in range(B)))
    fld = field_coords(B, H, W)
    with torch.no_grad():
        left, right = truth.render(b, fld)
    noisy = []
    for v in (left, right):
        noisy.append(v + torch.sqrt(SHOT * v.clamp(min=0) + READ**2) * torch.randn(v.shape, generator=g))
    s = [Sample(dataclasses.replace(b, left=noisy[0], right=noisy[1]), fld)]
    f = detect_noise.test_noise(truth, s, [], DetectConfig())
    assert f.params["variance_ratio"] == pytest.approx(1.0, abs=0.2) and not f.detected
    # the same views with 4 x the nominal variance are still found
    loud = [v + torch.sqrt(3 * (SHOT * v.clamp(min=0) + READ**2)) * torch.randn(v.shape, generator=g) for v in noisy]
    f4 = detect_noise.test_noise(truth, [Sample(dataclasses.replace(b, left=loud[0], right=loud[1]), fld)], [], DetectConfig())
    assert f4.params["variance_ratio"] == pytest.approx(4.0, rel=0.2) and f4.detected


def test_noise_is_nominal_against_the_model_that_explains_the_views() -> None:
    """Too little DP disparity (crosstalk) on texture that is nowhere flat: against the base model the views'
    L - R error leaks into the noise reading, but the white-noise filter (second differences in x and y)
    keeps it below the 1.5 x threshold (the 3 x 3 high-pass read it as > 1.5 x, named ``noise``); against the
    base model with the planted disparity_scale, which the selection measures noise against once it names
    that cause, it is the nominal noise."""
    from neural_dp.simulators.base.components import COMPONENTS

    g = torch.Generator().manual_seed(11)
    B, H, W = 4, 64, 96
    sharp = (0.15 + 0.7 * torch.rand(B, 3, H // 2, W // 2, generator=g)).repeat_interleave(2, -1).repeat_interleave(2, -2)
    coc = torch.linspace(3.0, 9.0, W).expand(B, 1, H, W).clone()
    b = dataclasses.replace(make_batch(sharp, coc), pair_ids=tuple(f"p{i}" for i in range(B)))
    fld = field_coords(B, H, W)
    base = BaseModel(rim_softness_px=0.0)
    comp = COMPONENTS["disparity_scale"]()
    comp.params["disparity_scale"] = 0.4
    truth = base.with_component(comp)
    with torch.no_grad():
        left, right = truth.render(b, fld)
    noisy = [v + torch.sqrt(SHOT * v.clamp(min=0) + READ**2) * torch.randn(v.shape, generator=g) for v in (left, right)]
    s = [Sample(dataclasses.replace(b, left=noisy[0], right=noisy[1]), fld)]
    cfg = DetectConfig()
    against_base = detect_noise.test_noise(base, s, [], cfg)
    assert not against_base.detected and 1.0 < against_base.params["variance_ratio"] < 1.4
    against_truth = detect_noise.test_noise(truth, s, [], cfg)
    assert against_truth.params["variance_ratio"] == pytest.approx(1.0, abs=0.1) and not against_truth.detected
    assert against_truth.params["variance_ratio"] < against_base.params["variance_ratio"]


def test_effect_test_is_not_fooled_by_a_few_pairs_with_large_gains() -> None:
    """Per-pair log MSE ratios of a planted focus offset on another renderer's set: two pairs gain a lot, the
    rest a little. The t test's p is 0.065; the signed-rank test names it. With fewer than 6 units the t test
    is used (the signed-rank test's smallest p would be 2^-n); a null sample stays insignificant."""
    d = np.array([-0.023, -0.001, 0.003, 0.003, 0.004, 0.02, 0.023, 0.023, 0.065, 0.067, 0.082, 0.176, 2.015, 2.669])
    assert tiles.one_sided_t(d)[1] > 0.05
    z, p = tiles.effect_test(d)
    assert p < 0.01 and z > 2
    assert tiles.effect_test(-d)[1] > 0.9
    small = np.array([0.5, 0.6, 0.7, 0.8])
    assert tiles.effect_test(small) == tiles.one_sided_t(small)
    rng = np.random.default_rng(1)
    rate = np.mean([tiles.effect_test(rng.normal(0, 1, 16))[1] < 0.05 for _ in range(400)])
    assert rate < 0.08


def test_an_effect_inside_a_named_cause_is_reported_as_possibly_present_too() -> None:
    """A correlated effect that alone would pass its threshold but adds nothing beyond the named cause is a
    look-alike of kind "also" (the data cannot exclude it); one that alone explains little is not."""
    from dp5k_diagnose.config import SelectConfig
    from dp5k_diagnose.selection import Confirmed, Screen, find_lookalikes

    names = ["lr_gain_imbalance", "field_varying_psf", "focus_offset"]
    corr = {("field_varying_psf", "lr_gain_imbalance"): 0.998, ("focus_offset", "lr_gain_imbalance"): 0.95,
            ("field_varying_psf", "focus_offset"): 0.1}

    def screen(alone_fvp: float, unique_fvp: float) -> Screen:
        alone = {"lr_gain_imbalance": 0.9, "field_varying_psf": alone_fvp, "focus_offset": 0.01}
        unique = {"lr_gain_imbalance": 0.2, "field_varying_psf": unique_fvp, "focus_offset": 0.001}
        return Screen(dict(alone), alone, unique, corr, {}, ["lr_gain_imbalance"])

    conf = Confirmed(["lr_gain_imbalance"], BaseModel(), None, None, {}, {}, {})  # type: ignore[arg-type]
    comps = {n: None for n in names}
    sel = SelectConfig(lookalike_tries=0)  # no swaps: only the containment rule
    groups = find_lookalikes(conf, comps, screen(0.685, 0.002), [], None, DetectConfig(), sel)  # type: ignore[arg-type]
    assert len(groups) == 1 and groups[0]["names"] == ["lr_gain_imbalance", "field_varying_psf"], groups
    assert groups[0]["kinds"] == ["also"] and groups[0]["captures"][0]
    # alone below its threshold (0.15): nothing to hide; a unique part above the screen's bar: it would be screened
    assert find_lookalikes(conf, comps, screen(0.10, 0.002), [], None, DetectConfig(), sel) == []  # type: ignore[arg-type]
    assert find_lookalikes(conf, comps, screen(0.685, 0.2), [], None, DetectConfig(), sel) == []  # type: ignore[arg-type]


def test_the_full_model_starts_no_worse_than_the_model_it_extends() -> None:
    """A full model's Levenberg-Marquardt start is the screen's step where that fits the fit crops at least as
    well as the nested model, a fraction of it where the step overshoots, and never worse than the nested
    model (a re-screen's full model once started 10 x worse and ended there)."""
    from dp5k_diagnose.selection import start_full_model
    from neural_dp.registry import COMPONENTS, residual_vector

    sharp = scene(3, n=2)
    B, _, H, W = sharp.shape
    planted = BaseModel(rim_softness_px=0.5, gain=1.0).with_component(COMPONENTS["misregistration"]())
    planted.component("misregistration").params.update(left_dx_px=1.0, right_dx_px=1.0)
    coc = torch.full((B, 1, H, W), 3.0)
    with torch.no_grad():
        left, right = planted.render(make_batch(sharp, coc), field_coords(B, H, W))
    fit = samples(sharp, left, right, coc)
    nested_model = BaseModel(rim_softness_px=0.5, gain=1.0)
    nested = {("base", k): float(v) for k, v in nested_model.params.items()}

    def sse(m: BaseModel) -> float:
        r = residual_vector(m, fit)
        return float(r @ r)

    def full() -> BaseModel:
        return nested_model.with_component(COMPONENTS["misregistration"]())

    nested_sse = sse(nested_model)
    good = {("misregistration", "left_dx_px"): 0.9, ("misregistration", "right_dx_px"): 0.9}
    m = full()
    assert start_full_model(m, nested, good, fit) == 1.0
    assert m.component("misregistration").params["left_dx_px"] == pytest.approx(0.9)
    overshoot = {("misregistration", "left_dx_px"): 6.0, ("misregistration", "right_dx_px"): 6.0}
    m = full()
    t = start_full_model(m, nested, overshoot, fit)
    assert 0.0 < t < 1.0  # 6 px overshoots, a fraction of it (<= 1.5 px) gets closer to the planted 1 px
    assert sse(m) <= nested_sse
    wrong = {("misregistration", "left_dx_px"): -4.0, ("misregistration", "right_dx_px"): -4.0}
    m = full()
    assert start_full_model(m, nested, wrong, fit) == 0.0  # every fraction of a wrong-way step is worse
    assert m.component("misregistration").params["left_dx_px"] == 0.0 and sse(m) == pytest.approx(nested_sse)


def test_a_partner_beside_a_strong_effect_is_measured_on_at_most_the_sensor_noise() -> None:
    """The least systematic error an effect's size is a share of: 5 % of the base model's where that is
    below a healthy sensor's noise energy on the same pixels (numerical remainders stay crumbs), that noise
    energy where a strong effect makes 5 % of the base error larger (a partner is judged on a scale real
    captures have)."""
    from dp5k_diagnose.selection import least_systematic

    sharp = scene(4)
    left, right = noisy_views(sharp, 1.0, None, 5)
    s = samples(sharp, left, right)
    cfg = DetectConfig()
    nominal = detect_noise.noise_sse(s, cfg.nominal_shot_var, cfg.nominal_read_sigma, cfg.tile_px)
    assert nominal > 0
    weak, strong = 0.5 * nominal / cfg.remaining_floor, 100.0 * nominal / cfg.remaining_floor
    assert least_systematic(weak, s, cfg) == pytest.approx(cfg.remaining_floor * weak)
    assert least_systematic(strong, s, cfg) == pytest.approx(nominal)
    quieter = dataclasses.replace(cfg, nominal_shot_var=cfg.nominal_shot_var / 4, nominal_read_sigma=cfg.nominal_read_sigma / 2)
    assert least_systematic(strong, s, quieter) == pytest.approx(nominal / 4, rel=1e-6)


def test_a_re_screen_model_is_kept_only_when_the_detection_pairs_prefer_it() -> None:
    """A re-screen's confirmed model replaces the confirmed model it extends only when it predicts the
    detection pairs better (lower summed squared error over their tiles): a larger full model once lost two
    confirmed causes to a look-alike and ended worse."""
    from dp5k_diagnose.selection import Confirmed, Eval, predicts_better

    def confirmed(names: list[str], tile_sse: list[float]) -> Confirmed:
        return Confirmed(names, BaseModel(), None, Eval(np.array(tile_sse), []), {}, {}, {})

    exact = confirmed(["lr_gain_imbalance", "focus_offset", "front_back_asymmetry"], [1.0, 2.0, 1.5])
    stand_in = confirmed(["lr_gain_imbalance", "chromatic_defocus"], [1.2, 2.1, 1.5])
    better = confirmed(["lr_gain_imbalance", "focus_offset", "front_back_asymmetry", "psf_profile"], [0.9, 1.9, 1.5])
    assert not predicts_better(stand_in, exact)
    assert predicts_better(better, exact)
    assert not predicts_better(exact, exact)  # a tie keeps what was confirmed


def test_report_md_says_why_the_simpler_look_alike_is_named() -> None:
    """report.md's look-alike line says the named cause was chosen for its fewer parameters only where the
    selection did so (``fewer_parameters_than``), and not for a look-alike the data merely cannot tell apart."""
    from dp5k_diagnose.report import suspects_lines

    group = {"names": ["psf_profile", "front_back_asymmetry", "focus_offset"], "captures": ["a slanted plane", "a focus bracket"],
             "correlation": [1.0, 0.95], "effect_size_lost": [0.015, 0.02], "p_value": [1.0, 0.5], "kinds": ["instead", "instead"],
             "fewer_parameters_than": ["front_back_asymmetry"]}
    lines = [line for line in suspects_lines({"lookalikes": [group]}) if line]
    assert len(lines) == 2
    assert "`psf_profile` or `front_back_asymmetry`" in lines[0] and "`psf_profile` is named: it fits fewer parameters." in lines[0]
    assert "`psf_profile` or `focus_offset`" in lines[1] and "fewer parameters" not in lines[1]


def test_the_first_order_re_screen_reuses_the_last_screens_columns() -> None:
    """The check before a re-screen (:func:`first_order_rescreen`): around the model the last screen was measured
    at, it is that screen (the same columns, found by owner and name); around a model holding a confirmed
    gain ramp, the planted psf_profile it left still carries a share near the exact re-screen's, and an effect
    the last screen did not hold gives no check (None: the exact screen runs)."""
    from dp5k_diagnose.config import SelectConfig
    from dp5k_diagnose.selection import first_order_rescreen, neutral_components, screen_effects
    from neural_dp.registry import COMPONENTS

    sharp = scene(5, n=2)
    B, _, H, W = sharp.shape
    planted = BaseModel(rim_softness_px=0.5, gain=1.0).with_component(COMPONENTS["lr_gain_imbalance"]()).with_component(COMPONENTS["psf_profile"]())
    planted.component("lr_gain_imbalance").params.update(a0=0.08, ax=0.1)
    planted.component("psf_profile").params.update(rim_gain=0.8)
    coc = torch.linspace(-8.0, 8.0, W).expand(B, 1, H, W).contiguous()
    with torch.no_grad():
        left, right = planted.render(make_batch(sharp, coc), field_coords(B, H, W))
    fit = samples(sharp, left, right, coc)
    cfg, sel = DetectConfig(nominal_shot_var=SHOT, nominal_read_sigma=READ), SelectConfig()
    base = BaseModel(rim_softness_px=0.5, gain=1.0)
    names = ["lr_gain_imbalance", "psf_profile", "misregistration"]
    first = screen_effects(base, neutral_components(names, fit), fit, None, cfg, sel)
    assert first.lin is not None and len(first.keys) == first.lin.J.shape[1]

    same = first_order_rescreen(first, base, neutral_components(names, fit), fit, None, cfg, dataclasses.replace(sel, prescreen_margin=1.0))
    assert same is not None and same.candidates == first.candidates
    for n in names:
        assert same.share[n] == pytest.approx(first.share[n], rel=1e-9, abs=1e-12)

    confirmed = base.with_component(COMPONENTS["lr_gain_imbalance"]())
    confirmed.component("lr_gain_imbalance").params.update(a0=0.08, ax=0.1)
    rest = neutral_components(["psf_profile", "misregistration"], fit)
    cheap = first_order_rescreen(first, confirmed, rest, fit, None, cfg, sel)
    exact = screen_effects(confirmed, neutral_components(["psf_profile", "misregistration"], fit), fit, None, cfg, sel)
    assert cheap is not None and "psf_profile" in cheap.candidates and "psf_profile" in exact.candidates
    assert cheap.share["psf_profile"] == pytest.approx(exact.share["psf_profile"], rel=0.3)
    assert cheap.share["misregistration"] < 0.25 * exact.share["psf_profile"]

    assert first_order_rescreen(first, confirmed, neutral_components(["focus_offset"], fit), fit, None, cfg, sel) is None
