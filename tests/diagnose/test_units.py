"""Unit checks of diagnose's building blocks: the noise measurement and its signature, the predictable-pixel and
occlusion masks, the fit crops' context, the gain's masks, the bounded Gauss-Newton refit and the components' fits
that naming relies on."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dp5k_diagnose.config import DiagnoseConfig
from dp5k_diagnose.measure import noise_signature
from dp5k_diagnose.noise import measure_noise
from dp5k_diagnose.data import Sample, predictable_mask
from neural_dp.registry import Linearization, jacobian, lm_fit
from neural_dp.simulators.base import BaseModel, field_coords
from tests.neural_dp.test_base_model import make_batch

SHOT, READ = 2.0e-5, 1.0e-3


@dataclasses.dataclass
class NoiseFinding:
    ratio: float
    shot_var: float
    named: bool
    measured: bool
    note: str


def noise_finding(model: BaseModel, s: list[Sample]) -> NoiseFinding:
    """The views' noise measured against ``model`` (:func:`measure_noise`) and whether its signature names ``noise``."""
    cfg = DiagnoseConfig()
    n = measure_noise(model, s, cfg)
    return NoiseFinding(n.variance_ratio, n.shot_var, noise_signature(n, cfg).differs(cfg.alpha), n.measured, n.note)


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
    f = noise_finding(BaseModel(), s)
    assert f.ratio == pytest.approx(factor, rel=0.15)
    assert f.named is (factor > 1.5)
    assert f.shot_var == pytest.approx(factor * SHOT, rel=0.5)


def test_noise_ignores_structure_common_to_both_views() -> None:
    """Ringing or shifted texture is in both views alike; only independent noise counts (misregistration is not noise)."""
    sharp = scene(2)
    ring = 0.01 * torch.sin(torch.arange(sharp.shape[-1]) * 2.7)[None, None, None, :].expand_as(sharp)
    f = noise_finding(BaseModel(), samples(sharp, *noisy_views(sharp, 1.0, ring, 3)))
    assert f.ratio == pytest.approx(1.0, rel=0.15) and not f.named


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


def test_noise_on_too_little_data_is_a_plain_non_finding() -> None:
    sharp = scene(5, n=1, H=8, W=8)
    f = noise_finding(BaseModel(), samples(sharp, *noisy_views(sharp, 4.0, None, 6)))
    assert not f.named and not f.measured and "too few" in f.note


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


@pytest.mark.parametrize("true_crosstalk", [0.1, -0.1])
def test_disparity_scale_is_at_most_the_ideal_split(true_crosstalk: float) -> None:
    """Crosstalk shrinks disparity, and the fit finds how much (0.8 of ideal for 0.1); views with more disparity
    than the ideal half-aperture split (what a rim-heavy aperture gives) fit at the bound 1, not above it:
    unbounded, it took the place of front_back_asymmetry on a planted set."""
    from dp5k_diagnose.naming import targets_of
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
    from dp5k_diagnose.explain import explanation
    from dp5k_diagnose.naming import targets_of
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
    f = noise_finding(truth, s)
    assert f.ratio == pytest.approx(1.0, abs=0.2) and not f.named
    # the same views with 4 x the nominal variance are still found
    loud = [v + torch.sqrt(3 * (SHOT * v.clamp(min=0) + READ**2)) * torch.randn(v.shape, generator=g) for v in noisy]
    f4 = noise_finding(truth, [Sample(dataclasses.replace(b, left=loud[0], right=loud[1]), fld)])
    assert f4.ratio == pytest.approx(4.0, rel=0.2) and f4.named


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
    against_base = noise_finding(base, s)
    assert not against_base.named and 1.0 < against_base.ratio < 1.4
    against_truth = noise_finding(truth, s)
    assert against_truth.ratio == pytest.approx(1.0, abs=0.1) and not against_truth.named
    assert against_truth.ratio < against_base.ratio


