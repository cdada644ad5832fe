"""The physics-first Neural DP Simulator and what ``dp5k train`` does by default (neural_dp/model.py, augment.py,
holdout.py, train.py): equal to the physical model at initialisation, bit for bit; the DP symmetries it and its
augmentations rely on; the choice between network and physical model; the refusals; the seeds."""

from __future__ import annotations

import json
import random
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader, PairParams, write_index, write_pair
from dp5k_common.optics import coc_diameter_px
from dp5k_learn.batch import DPBatch
from dp5k_learn.data import CropSpec, collate_dp
from neural_dp.augment import PhysicalPairs, batch_of
from neural_dp.config import AugmentConfig, load_config
from neural_dp.holdout import plan_holdout
from neural_dp.model import ModelConfig
from neural_dp.simulators.base import BaseModel
from neural_dp.simulators.base.spec import model_to_spec
from neural_dp.simulators.neural import NeuralDPSimulator
from neural_dp.train import decide, train
from dp5k_testing.tiny_dataset import make_tiny_dataset

TINY = ["model.base_channels=4", "model.levels=2", "data.crop_px=32", "data.batch_size=2", "data.samples_per_epoch=2",
        "optim.epochs=2", "device=cpu"]


def _batch(W: int = 40, H: int = 24, seed: int = 0) -> DPBatch:
    """A textured pair whose CoC runs from in front of focus to behind it (-6 .. +6 px) across the frame."""
    g = torch.Generator().manual_seed(seed)
    sharp = torch.rand(1, 3, H, W, generator=g) * 0.8 + 0.1
    coc = torch.linspace(-6.0, 6.0, W).view(1, 1, 1, W).expand(1, 1, H, W).contiguous()
    one = torch.ones(1)
    return DPBatch(sharp=sharp, coc_px=coc, depth_mm=torch.full((1, 1, H, W), 2000.0), valid=torch.ones(1, 1, H, W, dtype=torch.bool),
                   f_number=one * 1.8, focus_distance_mm=one * 2000, focal_length_mm=one * 85, pixel_pitch_mm=one * 0.02,
                   focus_point_px=torch.tensor([[W / 2, H / 2]]), left=sharp / 2, right=sharp / 2, sharp_f_number=one * 0)


def _physical_sim(prior: BaseModel, **model: object) -> NeuralDPSimulator:
    spec = json.dumps({**model_to_spec(prior), "fit_start": {"rim_softness_px": 0.5, "gain": 1.0, "pixel_box": 0.0}})
    cfg = ModelConfig(prior="physical", prior_spec=spec, base_channels=4, levels=2, **model)  # type: ignore[arg-type]
    return NeuralDPSimulator(cfg).eval()


def test_physics_first_network_equals_the_physical_model_at_initialisation() -> None:
    prior = BaseModel(rim_softness_px=0.8, gain=1.1)
    b = _batch()
    want_l, want_r = prior(b)
    for extra in ({}, {"kernel_per_channel": True}, {"multiscale_levels": 1}, {"tile_px": 16}):
        sim = _physical_sim(prior, **extra)
        for conv in sim.net.modules():  # a trained trunk: only the zero head and unit gains make it exact
            if isinstance(conv, torch.nn.Conv2d) and conv is not sim.net.head and conv is not sim.net.scale_head:
                torch.nn.init.normal_(conv.weight, std=0.5)
        left, right = sim(b)
        assert torch.equal(left, want_l) and torch.equal(right, want_r), extra


def test_evaluate_fits_it_exactly_as_the_base_model() -> None:
    """``dp5k evaluate`` fits ``base`` and a physics-first checkpoint on the same crops: at its initialisation the
    checkpoint then renders the fitted base model bit for bit (the physical checkpoint dp5k train keeps)."""
    truth = BaseModel(rim_softness_px=1.3, gain=0.9)
    b = _batch(seed=1)
    b.left, b.right = truth(b)
    base = BaseModel()
    base.fit([b])
    sim = _physical_sim(BaseModel(rim_softness_px=3.0, gain=2.0))  # trained from elsewhere; the fit starts as base's
    fitted = sim.fit([b])
    assert fitted["rim_softness_px"] == base.params["rim_softness_px"] and fitted["gain"] == base.params["gain"]
    left, right = sim(b)
    want_l, want_r = base(b)
    assert torch.equal(left, want_l) and torch.equal(right, want_r)


def test_the_correction_follows_the_dp_symmetries() -> None:
    """Swapping the physical views and negating the CoC swaps the output (a point in front of focus sends to the left
    view what one behind focus sends to the right), for any weights of the optical correction; the sensor stage's
    gains stay with the photodiodes whatever the CoC and follow a mirrored item's swapped views."""
    sim = _physical_sim(BaseModel())
    with torch.no_grad():
        for conv in sim.net.modules():
            if isinstance(conv, torch.nn.Conv2d):
                torch.nn.init.normal_(conv.weight, std=0.2)
    b = _batch(seed=2)
    pl, pr = sim.prior(b)  # type: ignore[misc]
    b = replace(b, prior_left=pl, prior_right=pr)
    swapped = replace(b, coc_px=-b.coc_px, prior_left=pr, prior_right=pl)
    with torch.no_grad():
        l1, r1 = sim.net(b.sharp, sim.inputs(b))
        l2, r2 = sim.net(swapped.sharp, sim.inputs(swapped))
        assert not torch.allclose(l1, pl, atol=1e-3)  # the correction is not zero
        torch.testing.assert_close(l2, r1, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(r2, l1, atol=1e-5, rtol=1e-4)
        sim.net.sensor_gain[0, :, 0] = float(np.log(1.2))  # the left photodiode 1.2, the right 0.8 (log-gains)
        sim.net.sensor_gain[1, :, 0] = float(np.log(0.8))
        l3, r3 = sim.net(b.sharp, sim.inputs(b))
        flagged = replace(b, mirrored=torch.tensor([True]))
        l4, r4 = sim.net(flagged.sharp, sim.inputs(flagged))
    assert float(l3.mean()) > float(l1.mean()) and float(r3.mean()) < float(r1.mean())
    assert float(l4.mean()) < float(l1.mean()) and float(r4.mean()) > float(r1.mean())  # a mirrored item's L is the R photodiode
    with torch.no_grad():
        l5, r5 = sim.net(swapped.sharp, sim.inputs(swapped))  # in front of focus the left photodiode is still 1.2
    torch.testing.assert_close(l5, r1 * 1.2, atol=1e-5, rtol=1e-4)


def test_mirror_and_swap_augmentation_matches_the_physical_model(tmp_path: Path) -> None:
    """Rendering mirrored inputs equals rendering and then mirroring + swapping the views, so an item mirrored with its
    physical views is what the physical model would render for the mirrored scene."""
    prior = BaseModel(rim_softness_px=0.7)
    b = _batch(seed=3)
    left, right = prior(b)
    mirrored = replace(b, sharp=b.sharp.flip(-1), coc_px=b.coc_px.flip(-1), depth_mm=b.depth_mm.flip(-1), valid=b.valid.flip(-1))
    ml, mr = prior(mirrored)
    torch.testing.assert_close(ml, right.flip(-1), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(mr, left.flip(-1), atol=1e-5, rtol=1e-5)

    root = tmp_path / "ds"
    make_tiny_dataset(root, scenes=3, W=40, H=24)
    pid = DatasetReader(root).ids("train")[0]
    ds = PhysicalPairs(root, [pid], prior, crop=CropSpec(0, vflip=False), augment=AugmentConfig(hflip_swap=1.0, exposure=0.2))
    item = ds[0]
    assert bool(item["mirrored"])
    pair = ds.pair(pid)
    whole = batch_of(pair)
    g = float(item["sharp"][0, 0, 0] / whole.sharp[0, 0, 0, -1])  # the exposure factor drawn for this item
    torch.testing.assert_close(item["sharp"], whole.sharp[0].flip(-1) * g)
    torch.testing.assert_close(item["left"], whole.right[0].flip(-1) * g)  # views mirrored and swapped
    it = collate_dp([item])
    rl, rr = prior(it)
    torch.testing.assert_close(it.prior_left, rl, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(it.prior_right, rr, atol=1e-5, rtol=1e-4)
    # the mirrored item sits where the mirror puts it in the frame: field x negated and reversed, y kept
    torch.testing.assert_close(it.field[0, 0], -whole.field[0, 0].flip(-1))
    torch.testing.assert_close(it.field[0, 1], whole.field[0, 1])
    assert float(it.coc_px.min()) == float(whole.coc_px.min())  # the CoC keeps its sign


def test_keep_the_better_decision_rule() -> None:
    clusters = [f"t{i}" for i in range(8)]
    phys = {"psnr": [30.0 + i for i in range(8)], "ssim": [0.9] * 8}
    better = {"psnr": [31.0 + i + 0.1 * (i % 3) for i in range(8)], "ssim": [0.91] * 8}
    noisy = {"psnr": [30.0 + i + (0.5 if i % 2 else -0.5) for i in range(8)], "ssim": [0.91] * 8}
    lower_ssim = {"psnr": better["psnr"], "ssim": [0.89] * 8}
    assert decide(better, phys, clusters, "better", "base", "tiles")["kept"] == "network"
    d = decide(noisy, phys, clusters, "better", "base", "tiles")
    assert d["kept"] == "physical" and "not resolved" in d["why"]
    assert decide(lower_ssim, phys, clusters, "better", "base", "tiles")["kept"] == "physical"
    assert decide(noisy, phys, clusters, "network", "base", "tiles")["kept"] == "network"
    one_scene = decide(noisy, phys, ["s"] * 8, "better", "base", "val split")  # one scene: its pairs are resampled
    assert one_scene["kept"] == "physical" and "as if independent" in one_scene["why"]
    single = decide({"psnr": [40.0], "ssim": [0.99]}, {"psnr": [30.0], "ssim": [0.9]}, ["s"], "better", "base", "tiles")
    assert single["kept"] == "physical" and "one validation pair" in single["why"]


def _exact_dataset(root: Path, truth: BaseModel, n: int = 8, W: int = 48, H: int = 32) -> None:
    """Tiles of one photo whose views the physical model renders exactly (no noise)."""
    ids = []
    for i in range(n):
        rng = np.random.default_rng(i)
        params = PairParams(pair_id=f"p_t0{i}_cam0", scene=f"p_t0{i}", camera="cam0", f_number=2.0, focus_distance_mm=1500.0,
                            focal_length_mm=50.0, pixel_pitch_mm=0.02, focus_point_px=(W / 2, H / 2), image_size=(W, H),
                            extra={"source_id": "p", "crop_origin_px": [i * W, 0], "full_image_size": [n * W, H],
                                   "sharp_f_number": 0.0})
        depth = np.full((H, W), 2500.0)
        coc = coc_diameter_px(depth, 1500.0, 50.0, 2.0, 0.02).astype(np.float32)
        sharp = rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float32)
        pair = {"sharp": sharp, "left": sharp / 2, "right": sharp / 2, "depth_mm": depth, "coc_px": coc}
        write_pair(root, params, **pair)
        ids.append(params.pair_id)
    write_index(root, {"train": ids, "val": [], "test": []}, source="tests")
    reader = DatasetReader(root)
    for pid in ids:  # views = the physical model's render of each whole tile
        left, right = truth(batch_of(reader.load(pid)))
        pair = reader.load(pid)
        write_pair(root, reader.params(pid), sharp=pair.sharp, left=left[0].numpy().transpose(1, 2, 0),
                   right=right[0].numpy().transpose(1, 2, 0), depth_mm=pair.depth_mm, coc_px=pair.coc_px, overwrite=True)


def test_training_does_not_replace_a_physical_model_that_is_exact(tmp_path: Path) -> None:
    root = tmp_path / "exact"
    _exact_dataset(root, BaseModel())
    h = plan_holdout(root)
    assert h.kind == "tiles" and set(h.val).isdisjoint(h.train) and len(h.val) == 2 and any("photo" in w for w in h.warnings)
    run = train(root, tmp_path / "run", load_config(None, TINY + ["data.crop_px=24", "optim.lr=1e-2"]))
    assert run.report["kept"] == "physical", run.report["why"]
    sim = NeuralDPSimulator.from_checkpoint(tmp_path / "run" / "best.pt")
    b = collate_dp([PhysicalPairs(root, h.val[:1], sim.prior)[0]])  # type: ignore[arg-type]
    b = replace(b, prior_left=None, prior_right=None)
    left, right = sim(b)
    want_l, want_r = sim.prior(b)  # type: ignore[misc]
    assert torch.equal(left, want_l) and torch.equal(right, want_r)
    assert json.loads((tmp_path / "run" / "report.json").read_text())["kept"] == "physical"


def test_cli_default_training_two_steps_then_evaluate(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=6, W=48, H=32)
    state = (np.random.get_state()[1].copy(), torch.get_rng_state().clone(), random.getstate())
    args = ["-q", "train", str(ds), "--out", str(tmp_path / "run")]
    for item in TINY:
        args += ["--set", item]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "kept the " in res.output.splitlines()[-1]
    assert np.array_equal(np.random.get_state()[1], state[0]) and torch.equal(torch.get_rng_state(), state[1])
    assert random.getstate() == state[2]  # training draws from its own generators only
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["steps"] == 2 and report["kept"] in ("network", "physical") and report["why"]
    res = CliRunner().invoke(main, ["-q", "evaluate", str(ds), "--out", str(tmp_path / "e"), "--simulator", "base",
                                    "--simulator", f"neural:{tmp_path / 'run' / 'best.pt'}", "--figures", "0"])
    assert res.exit_code == 0, res.output
    fitted = json.loads((tmp_path / "e" / "metrics.json").read_text())["fitted_parameters"]
    assert fitted["neural"]["gain"] == fitted["base"]["gain"] and 0 <= fitted["neural"]["correction_scale"] <= 1


def test_refusals_are_one_line_exit_3_and_touch_nothing(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "best.pt").write_bytes(b"an earlier run")
    one = tmp_path / "one"  # one photo, one pair: nothing to validate on
    make_tiny_dataset(one, scenes=1, W=48, H=32)
    res = CliRunner().invoke(main, ["train", str(one), "--out", str(run), "--overwrite"])
    assert res.exit_code == 3 and "nothing to validate on" in res.output and len(res.output.strip().splitlines()) == 1
    nodepth = tmp_path / "nodepth"  # pairs without a pixel of valid depth (as a DPDD import)
    make_tiny_dataset(nodepth, scenes=3, W=48, H=32)
    reader = DatasetReader(nodepth)
    for pid in reader.ids():
        p = reader.load(pid)
        write_pair(nodepth, p.params, sharp=p.sharp, left=p.left, right=p.right, depth_mm=np.zeros_like(p.depth_mm),
                   coc_px=np.full_like(p.coc_px, np.nan), overwrite=True)
    res = CliRunner().invoke(main, ["train", str(nodepth), "--out", str(run), "--overwrite"])
    assert res.exit_code == 3 and "valid depth" in res.output and len(res.output.strip().splitlines()) == 1
    assert (run / "best.pt").read_bytes() == b"an earlier run" and sorted(p.name for p in run.iterdir()) == ["best.pt"]


def test_calibrated_pretraining_of_the_papers_network_learns_refocused_physical_renders(tmp_path: Path) -> None:
    from neural_dp.pretrain import calibrated_pairs, coc_targets

    root = tmp_path / "exact"
    _exact_dataset(root, BaseModel(), n=4)
    reader = DatasetReader(root)
    pairs = calibrated_pairs(reader, reader.ids("train")[:1], BaseModel(), coc_targets(3, 6.0))
    medians = sorted(float(np.median(p.coc_px[p.valid])) for p in pairs.values())
    np.testing.assert_allclose(medians, [-6.0, 0.0, 6.0], atol=1e-3)  # refocused to CoCs of both signs
    run = train(root, tmp_path / "run", load_config(None, TINY + ["data.crop_px=24", "model.prior=none",
                                                                  "pretrain.simulator=base", "pretrain.epochs=1",
                                                                  "pretrain.variants=2"]))
    assert run.steps == 2 and (tmp_path / "run" / "pretrain" / "best.pt").is_file()


def _unit_sums(d: dict, e: dict) -> tuple[dict, dict, dict]:
    return ({u: float((d[u] * e[u]).sum()) for u in d}, {u: float((d[u] * d[u]).sum()) for u in d},
            {u: float((e[u] * e[u]).sum()) for u in d})


def test_the_correction_is_kept_only_where_it_predicts_data_it_was_not_fitted_on() -> None:
    from neural_dp.simulators.neural import cross_validated_scale

    rng = np.random.default_rng(3)
    units = [(p, k) for p in "abcd" for k in range(4)]  # (pair, vertical strip)
    d = {u: rng.standard_normal(200) for u in units}  # the network's correction of the physical views
    # the measured error is half the correction everywhere: it generalises, the least-squares scale (~0.5) is kept
    num, den, sse = _unit_sums(d, {u: 0.5 * d[u] + 0.1 * rng.standard_normal(200) for u in units})
    a, gains = cross_validated_scale(num, den, sse)
    assert 0.45 < a < 0.55 and gains["pairs"] > 0.5 and gains["strips"] > 0.5
    # it helps a lot in strip 1 of every pair and harms the rest: on the crops it lowers the squared error (a > 0 by
    # least squares), every pair looks alike (leaving a pair out keeps it), but fitted without strip 1 it is 0 and
    # fitted with it, it harms the strip left out: the physical model is kept
    big = {u: (3.0 if u[1] == 1 else 1.0) * d[u] for u in units}
    e = {u: (0.8 if u[1] == 1 else -0.3) * big[u] for u in units}
    num, den, sse = _unit_sums(big, e)
    assert sum(num.values()) > 0
    a, gains = cross_validated_scale(num, den, sse)
    assert a == 0.0 and gains["pairs"] > 0 and gains["strips"] < 0
    # the strips' held-out change, computed directly: each strip's squared error at the others' scale
    change = 0.0
    for k in range(4):
        held = [u for u in units if u[1] == k]
        rest = [u for u in units if u[1] != k]
        a_k = min(1.0, max(0.0, sum(num[u] for u in rest) / sum(den[u] for u in rest)))
        change += sum(float(((e[u] - a_k * big[u]) ** 2).sum() - (e[u] ** 2).sum()) for u in held)
    assert gains["strips"] == pytest.approx(-change / sum(sse.values()))
    # one pair, one strip: nothing to hold out, the least-squares scale is kept
    u = ("a", 0)
    a, gains = cross_validated_scale({u: num[u]}, {u: den[u]}, {u: sse[u]})
    assert a == pytest.approx(min(1.0, max(0.0, num[u] / den[u]))) and gains == {}
