"""Unit checks of what makes diagnose's parameters usable for calibration: intervals clustered over pairs, the
noise model's bootstrap intervals, L/R ranges only over the covered field, colour effects only where colour
exists, and the focus offset recomputed from the float CoC rather than rounded depth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dp5k_common.optics import coc_diameter_px
from dp5k_diagnose import findings as F
from dp5k_diagnose import noise as N
from dp5k_diagnose.config import DetectConfig, SelectConfig
from dp5k_diagnose.data import Sample
from neural_dp.registry import clustered_intervals, lm_fit
from neural_dp.simulators.base import BaseModel, field_coords
from neural_dp.simulators.base.components import FocusOffset, LRGainImbalance
from tests.diagnose.test_detect_units import noisy_views, samples, scene
from tests.neural_dp.test_base_model import make_batch


def _lr_samples(a0: float, n_pairs: int, sigma: float, seed: int) -> list[Sample]:
    """In-focus pairs whose views carry an L/R gain ratio exp(a0) and white noise ``sigma``."""
    g = torch.Generator().manual_seed(seed)
    sharp = scene(seed, n=n_pairs, H=32, W=48)
    B, _, H, W = sharp.shape
    rho = float(np.exp(a0))
    left = sharp / 2 * 2 * rho / (1 + rho) + sigma * torch.randn(sharp.shape, generator=g)
    right = sharp / 2 * 2 / (1 + rho) + sigma * torch.randn(sharp.shape, generator=g)
    b = dataclasses.replace(make_batch(sharp, torch.zeros(B, 1, H, W), left, right), pair_ids=tuple(f"p{i}" for i in range(B)))
    return [Sample(b, field_coords(B, H, W))]


def _fit_lr(s: list[Sample]) -> tuple[BaseModel, LRGainImbalance, tuple[float, float]]:
    """The a0 of an L/R gain ratio fitted with the gain, and its 95 % interval clustered over pairs."""
    comp = LRGainImbalance()
    model = BaseModel(rim_softness_px=0.0).with_component(comp)
    lin = lm_fit(model, [(comp, "a0"), (model, "gain")], s, 6)
    lo, hi = clustered_intervals(lin, s)[0]
    return model, comp, (float(lo), float(hi))


def test_parameter_interval_covers_the_truth_and_shrinks_with_less_noise() -> None:
    a0 = 0.12
    _, comp, (lo, hi) = _fit_lr(_lr_samples(a0, 6, 0.02, 1))
    assert lo < a0 < hi and lo < comp.params["a0"] < hi
    _, comp2, (lo2, hi2) = _fit_lr(_lr_samples(a0, 6, 0.002, 1))
    assert 0 < hi2 - lo2 < 0.3 * (hi - lo)  # the interval measures the data's scatter
    _, comp1, iv1 = _fit_lr(_lr_samples(a0, 1, 0.02, 1))
    assert np.isnan(iv1).all()  # one pair: no spread between pairs to measure


def test_lr_ratio_range_is_reported_over_the_covered_field_only() -> None:
    comp = LRGainImbalance()
    comp.params.update(a0=0.1, ax=0.3, axx=0.8)
    whole = comp.describe()
    comp.field_box = (-0.5, 0.5, -0.5, 0.5)
    inner = comp.describe()
    assert whole["lr_ratio_max"] == pytest.approx(float(np.exp(0.1 + 0.3 + 0.8)), rel=1e-5)
    assert inner["lr_ratio_max"] == pytest.approx(float(np.exp(0.1 + 0.15 + 0.2)), rel=1e-5)
    assert (inner["field_x0"], inner["field_x1"]) == (-0.5, 0.5)


def test_noise_model_has_bootstrap_intervals_around_its_values() -> None:
    sharp = scene(3, n=6)
    s = samples(sharp, *noisy_views(sharp, 4.0, None, 2))
    f = N.test_noise(BaseModel(), s, [], DetectConfig())
    for k in ("shot_var", "read_sigma", "variance_ratio"):
        lo, hi = f.intervals[k]
        assert lo <= f.params[k] <= hi and hi > lo, (k, lo, f.params[k], hi)
    assert f.intervals["variance_ratio"][0] > 1.5  # 4 x nominal is resolved from 1


def test_colour_effects_are_not_testable_on_grey_data() -> None:
    sharp = scene(5, n=2)
    colour = samples(sharp, *noisy_views(sharp, 1.0, None, 4))
    grey_sharp = sharp.mean(1, keepdim=True).expand_as(sharp).contiguous()
    l, r = noisy_views(grey_sharp, 1.0, None, 4)
    grey = samples(grey_sharp, l.mean(1, keepdim=True).expand_as(l).contiguous(), r.mean(1, keepdim=True).expand_as(r).contiguous())
    assert F.colour_contrast(colour) > 10 * F.GREY_MAX_COLOUR_CONTRAST
    assert F.colour_contrast(grey) < 1e-6
    from dp5k_diagnose.selection import select_causes

    sel = select_causes(BaseModel(rim_softness_px=0.0), grey, grey, DetectConfig(), SelectConfig(), ("chromatic_defocus", "disparity_scale"))
    found = {f.effect: f for f in sel.findings}
    assert not found["chromatic_defocus"].testable and not found["chromatic_defocus"].detected
    assert found["chromatic_defocus"].stage == "not testable" and "not testable" in found["chromatic_defocus"].explanation
    assert found["disparity_scale"].testable and found["disparity_scale"].stage != "not testable"


def test_focus_offset_recomputes_the_coc_from_the_float_coc_not_rounded_depth() -> None:
    F, f, N, pitch = 70.0, 5.0, 1.8, 0.0014  # a phone close-up: 0.25-0.9 px of CoC per mm of depth
    depth = torch.linspace(60.0, 90.0, 48).repeat(8, 1).double()
    coc = torch.tensor(coc_diameter_px(depth.numpy(), F, f, N, pitch), dtype=torch.float32)
    B = make_batch(torch.zeros(1, 3, 8, 48), coc[None, None], None, None)
    b = dataclasses.replace(B, depth_mm=depth.round().float()[None, None], f_number=torch.tensor([N]), focus_distance_mm=torch.tensor([F]),
                            focal_length_mm=torch.tensor([f]), pixel_pitch_mm=torch.tensor([pitch]))
    comp = FocusOffset()
    comp.params["focus_factor"] = 1.03
    got = comp.coc(b.coc_px, b, field_coords(1, 8, 48))[0, 0].double().numpy()
    want = coc_diameter_px(depth.numpy(), 1.03 * F, f, N, pitch)
    rounded = coc_diameter_px(depth.round().numpy(), 1.03 * F, f, N, pitch)
    assert np.abs(got - want).max() < 1e-3
    assert np.abs(rounded - want).max() > 0.1  # what whole millimetres of depth would have cost


def test_causes_put_noise_after_every_structural_cause_and_add_up_the_step_gains() -> None:
    from dp5k_diagnose.findings import Finding
    from dp5k_diagnose.gain import TileErrors
    from dp5k_diagnose.run import DiagnoseConfig, cause_entries
    from dp5k_diagnose.selection import Selection
    from neural_dp.simulators.base.components import DisparityScale, Noise

    base = BaseModel()
    lr, ds = LRGainImbalance(), DisparityScale()
    m1 = base.with_component(lr)
    m2 = m1.with_component(ds)
    assert [c.name for c in m2.components] == ["disparity_scale", "lr_gain_imbalance"]  # crosstalk acts before gains
    noise_model = base.with_component(Noise())
    noise = Finding("noise", 5.0, 1e-6, 3.0, True, {"shot_var": 1e-4, "read_sigma": 2e-3}, "noise", noise_model,
                    intervals={"shot_var": (8e-5, 1.2e-4)})
    named = [Finding("lr_gain_imbalance", 4.0, 1e-4, 0.9, True, {}, "lr", m2), Finding("disparity_scale", 3.0, 1e-3, 0.8, True, {}, "ds", m2)]
    sel = Selection(["lr_gain_imbalance", "disparity_scale"], m2, [m1, m2], [m1, m1], named + [noise], noise=noise)
    assert sel.names == ["lr_gain_imbalance", "disparity_scale", "noise"]
    assert sel.extended().component("noise") is not None
    ids = [f"p{i}" for i in range(4)]
    rng = np.random.default_rng(0)

    def tiles(psnr: np.ndarray) -> TileErrors:
        """Tile errors whose pairs have these PSNRs (dB), spread unevenly over 6 tiles of 300 values each."""
        share = rng.uniform(0.5, 1.5, (4, 2, 6))
        share /= share.sum(-1, keepdims=True)
        count = np.full((4, 6), 300.0)
        return TileErrors(ids, share * (10.0 ** (-psnr / 10.0) * 1800.0)[:, None, None], count)

    before_psnr = np.array([30.0, 31.0, 32.0, 33.0])
    after1_psnr = before_psnr + np.array([10.0, 11.0, 9.0, 10.0])
    after2_psnr = after1_psnr + np.array([2.0, 1.0, 3.0, 2.0])
    before, after1, after2 = tiles(before_psnr), tiles(after1_psnr), tiles(after2_psnr)
    out = cause_entries(sel, before, [after1, after2], DiagnoseConfig(n_boot=200))
    assert [c["name"] for c in out] == ["lr_gain_imbalance", "disparity_scale", "noise"]
    assert out[0]["step_gain_db"] == pytest.approx(10.0) and out[1]["step_gain_db"] == pytest.approx(2.0)
    assert out[1]["cumulative_gain_db"] == pytest.approx(12.0) and out[1]["step_gain_ci_db"][0] > 0
    assert out[2]["gain_db"] == 0.0 and out[2]["gain_ci_db"] == [0.0, 0.0] and out[2]["cumulative_gain_db"] == pytest.approx(12.0)
    assert out[2]["step_gain_db"] == 0.0 and out[2]["step_gain_ci_db"] == [0.0, 0.0]
    assert out[2]["param_intervals"]["shot_var"] == [8e-5, 1.2e-4]
    assert out[0]["effect_size"] == 0.9 and out[1]["p_value"] == 1e-3  # each cause's test given the others
    # given the others: the final model against the final model without the cause (here the first cause adds
    # 4 dB to a model that has the second, whatever it added alone at step 1)
    without_lr = tiles(after2_psnr - np.array([4.0, 5.0, 3.0, 4.0]))
    without_ds = after1
    out = cause_entries(sel, before, [after1, after2], DiagnoseConfig(n_boot=200), [without_lr, without_ds])
    assert out[0]["gain_db"] == pytest.approx(4.0) and out[0]["step_gain_db"] == pytest.approx(10.0)
    assert out[1]["gain_db"] == pytest.approx(2.0) and out[0]["gain_ci_db"][0] > 0
    assert out[0]["gain_per_pair_db"]["p1"] == pytest.approx(5.0) and out[0]["gain_ci_pairs_db"][0] >= 3.0 - 1e-9
