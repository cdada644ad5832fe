"""The direct route: make_dataset / pair_from_rgbd write valid format-v1 pairs with planted effects recorded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_studio import EffectSet, make_dataset, pair_from_rgbd
from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError
from dp5k_common.optics import coc_diameter_px


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "studio"
    make_dataset(out, scenes=3, effects=["misregistration=1", "disparity_scale=2"], size=(96, 64), f_numbers=(1.8, 4.0), seed=4)
    return out


def test_dataset_is_valid_and_split_by_scene(dataset: Path) -> None:
    r = DatasetReader(dataset)
    assert len(r) == 3 * 2 * 2
    scenes = {name: {r.params(pid).scene for pid in r.ids(name)} for name in ("train", "val", "test")}
    assert not (scenes["train"] & scenes["val"]) and not (scenes["train"] & scenes["test"]) and not (scenes["val"] & scenes["test"])
    for pid in r.ids():
        p = r.load(pid)
        assert pid == f"{p.params.scene}_{p.params.camera}_f{p.params.f_number:g}"
        assert p.params.image_size == (96, 64) and p.params.pixel_pitch_mm == pytest.approx(36.0 / 96)
        assert p.valid.all()
        assert p.params.extra["sharp_f_number"] == 22.0  # every pair of a scene and camera shares the f/22 render


def test_pairs_follow_eq6_eq2_and_record_the_planted_effects(dataset: Path) -> None:
    r = DatasetReader(dataset)
    idx = json.loads((dataset / "dataset.json").read_text())
    assert set(idx["effects"]) == {"misregistration", "disparity_scale"}
    for pid in r.ids():
        p = r.load(pid)
        pp = p.params
        coc = coc_diameter_px(p.depth_mm, pp.focus_distance_mm, pp.focal_length_mm, pp.f_number, pp.pixel_pitch_mm)
        assert np.allclose(p.coc_px, coc, rtol=1e-5, atol=1e-4)
        x, y = (int(v) for v in pp.focus_point_px)
        assert abs(p.depth_mm[y, x] - pp.focus_distance_mm) <= 0.5 + 1e-6  # depth.png is whole mm
        eff = pp.extra["effects"]
        assert eff["disparity_scale"]["disparity_factor"] == pytest.approx(1 / 3)
        assert eff["misregistration"]["shift_px"] == pytest.approx([0.003 * 96, -0.0015 * 64])
        # Eq. 2: the two views carry the sharp frame's light between them
        assert (p.left + p.right).mean() == pytest.approx(p.sharp.mean(), rel=0.03)
        assert p.left.mean() == pytest.approx(p.right.mean(), rel=0.1)  # defocus near the frame moves light in or out


def test_existing_dataset_is_not_overwritten(dataset: Path) -> None:
    with pytest.raises(BadInputError):
        make_dataset(dataset, scenes=1, size=(96, 64), f_numbers=(2.0,))


def test_rgbd_route_handles_invalid_depth() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((48, 64, 3)).astype(np.float32)
    depth = np.full((48, 64), 3000.0)
    depth[10:20, 10:20] = 0.0
    rp = pair_from_rgbd(img, depth, f_number=2.0, focus_distance_mm=1500.0, effects=EffectSet.of(noise=1.0))
    assert np.isnan(rp.coc_px[10:20, 10:20]).all() and (rp.depth_mm[10:20, 10:20] == 0).all()
    assert np.isfinite(rp.left).all() and np.isfinite(rp.coc_px[30:, 30:]).all()
    assert np.array_equal(rp.sharp, np.clip(img, 0, 1))
    with pytest.raises(BadInputError):
        pair_from_rgbd(img, depth[:10], f_number=2.0, focus_distance_mm=1500.0)


def test_cli_make_dataset_check_and_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    out = tmp_path / "cli_ds"
    res = runner.invoke(main, ["-q", "studio", "make-dataset", str(out), "--scenes", "1", "--size", "64x48",
                               "--f-numbers", "2.8", "--effect", "noise=2"])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "dataset.json").read_text())["effects"]["noise"]["strength"] == 2.0
    assert runner.invoke(main, ["-q", "check", str(out)]).exit_code == 0
    bad = runner.invoke(main, ["-q", "studio", "make-dataset", str(tmp_path / "x"), "--effect", "wobble=1"])
    assert bad.exit_code == 3 and "unknown effect 'wobble'" in bad.output
    assert not (tmp_path / "x" / "dataset.json").exists()
    png = tmp_path / "preview.png"
    res = runner.invoke(main, ["-q", "studio", "render", "boxes", str(png), "--scale", "60"])
    assert res.exit_code == 0, res.output
    assert png.stat().st_size > 1000


def test_rerender_an_rgbd_dataset_with_effects(dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "rerendered"
    res = CliRunner().invoke(main, ["-q", "studio", "make-dataset", str(out), "--from", str(dataset),
                                    "--effect", "lr_gain_imbalance=1", "--no-noise"])
    assert res.exit_code == 0, res.output
    src, new = DatasetReader(dataset), DatasetReader(out)
    assert new.splits == src.splits
    for pid in src.ids()[:4]:
        a, b = src.load(pid), new.load(pid)
        assert np.array_equal(a.sharp, b.sharp) and np.array_equal(a.depth_mm, b.depth_mm)
        assert np.allclose(a.coc_px, b.coc_px, atol=1e-4)
        assert set(b.params.extra["effects"]) == {"lr_gain_imbalance"}
        assert b.params.sharp_f_number == 0.0  # the source's sharp image was the radiance these views came from
        assert b.left.mean() / b.right.mean() == pytest.approx(1.2, abs=0.05)


def test_random_captures_draw_focus_f_number_sensor_format_and_gain(tmp_path: Path) -> None:
    """``--random-captures``: every capture its own focus, f-number, sensor format (99th-percentile |CoC| at f/1.8
    inside ``--coc-px``) and gain (inside ``--noise-gain``), recorded in params.json; the draws are seeded."""
    out = tmp_path / "rc"
    args = ["-q", "studio", "make-dataset", str(out), "--scenes", "3", "--size", "48x32", "--camera", "0",
            "--all-in-focus-sharp", "--random-captures", "3", "--coc-px", "2:6", "--noise-gain", "1:30", "--seed", "1"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    r = DatasetReader(out)
    ids = r.ids()
    assert len(ids) == 9 and all(pid.endswith(("_c0", "_c1", "_c2")) and "_cam0_" in pid for pid in ids)
    focus, fns, pitches, gains = [], [], [], []
    for pid in ids:
        p = r.load(pid)
        prm = p.params
        cap = prm.extra["capture"]
        assert 1.0 <= cap["noise_gain"] <= 30.0 and prm.extra["sharp_f_number"] == 0
        assert prm.f_number in (1.8, 2.0, 2.8, 4.0, 5.6)
        c = np.abs(p.coc_px[np.isfinite(p.coc_px)])
        p99_at_18 = np.percentile(c, 99) * prm.f_number / 1.8  # CoC ~ 1 / N
        assert 2.0 * 0.9 <= p99_at_18 <= 6.0 * 1.1, (pid, p99_at_18)  # depth.png rounds to whole mm
        focus.append(prm.focus_distance_mm); fns.append(prm.f_number); pitches.append(prm.pixel_pitch_mm); gains.append(cap["noise_gain"])
    assert len(set(np.round(focus))) >= 6 and len(set(fns)) >= 3 and len(set(pitches)) == 9 and len(set(gains)) == 9
    bad = CliRunner().invoke(main, [*args[:3], str(tmp_path / "bad"), *args[4:], "--coc-px", "6"])
    assert bad.exit_code != 0 and "--coc-px" in bad.output and not (tmp_path / "bad").exists()
    bad = CliRunner().invoke(main, [*args[:3], str(tmp_path / "bad"), *args[4:], "--noise-gain", "30:1"])
    assert bad.exit_code != 0 and "--noise-gain" in bad.output and not (tmp_path / "bad").exists()
