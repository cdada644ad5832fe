"""``dp5k import dp5k``: studio scenes written in the DP5K release's layout come back as the studio's own pairs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_studio import make_dataset

from .layouts import SHARP_SCALE, VIEW_SCALE, write_dp5k_scene

SIZE = (96, 64)


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> DatasetReader:
    """The studio's own v1 output: two scenes, both cameras, f/1.4 (which the release's scripts know) and f/4."""
    out = tmp_path_factory.mktemp("studio") / "ds"
    make_dataset(out, scenes=["demo01", 7], size=SIZE, f_numbers=(1.4, 4.0), seed=3)
    return DatasetReader(out)


@pytest.fixture(scope="module")
def release(studio: DatasetReader, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The release layout: demo01 in test/, the other scene in train/, 16-bit."""
    root = tmp_path_factory.mktemp("release")
    scenes = sorted({studio.params(p).scene for p in studio.ids()})
    for scene, split in zip(scenes, ("train", "test")):
        write_dp5k_scene(studio, scene, root / split / scene)
    return root


def _import(args: list[str]) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["-q", "import", "dp5k", *args])
    return res.exit_code, res.output


def test_round_trip_gives_the_studio_pairs(studio: DatasetReader, release: Path, tmp_path: Path) -> None:
    code, out = _import([str(release), str(tmp_path / "ds"), "--crop", "none"])
    assert code == 0, out
    got = DatasetReader(tmp_path / "ds")
    assert sorted(got.ids()) == sorted(studio.ids())
    scene_split = {studio.params(p).scene: got.split_of(p) for p in got.ids()}
    assert sorted(scene_split.values()) == ["test", "train"]  # the release's own splits, by scene
    assert {got.params(p).f_number for p in got.ids()} == {1.4, 4.0}  # discovered from the file names
    for pid in studio.ids():
        a, b = studio.load(pid), got.load(pid)
        for key in ("scene", "camera", "f_number", "focus_distance_mm", "focal_length_mm", "image_size"):
            assert getattr(a.params, key) == pytest.approx(getattr(b.params, key)), key
        assert b.params.pixel_pitch_mm == pytest.approx(36.0 / SIZE[0])
        assert b.params.focus_point_px == a.params.focus_point_px
        assert b.params.sharp_f_number == 22.0
        np.testing.assert_array_equal(b.depth_mm, a.depth_mm)
        np.testing.assert_allclose(b.coc_px[a.valid], a.coc_px[a.valid], rtol=1e-5)
        # the views: measured back to the combined frame's scale (written at 1.6 x each), 16-bit sRGB quantisation
        np.testing.assert_allclose(b.left, a.left, atol=2e-4)
        np.testing.assert_allclose(b.right, a.right, atol=2e-4)
        exp = b.params.extra["exposure"]
        assert exp["views_gain"] == pytest.approx(1 / VIEW_SCALE, rel=1e-3)
        assert exp["combined_residual"] < 1e-3
        # sharp: brought to the mean of left + right, which the studio's own f/22 frame matches to ~1 %
        ratio = float((a.left + a.right).mean() / a.sharp.mean())
        assert exp["sharp_gain"] == pytest.approx(ratio / SHARP_SCALE, rel=2e-3)
        np.testing.assert_allclose(b.sharp, np.clip(a.sharp * ratio, 0, 1), atol=5e-4)
        assert abs(ratio - 1) < 0.015


def test_8bit_release_is_linearised_with_the_srgb_curve(studio: DatasetReader, tmp_path: Path) -> None:
    scene = studio.params(studio.ids()[0]).scene
    write_dp5k_scene(studio, scene, tmp_path / "rel" / "val" / scene, bits=8)
    code, out = _import([str(tmp_path / "rel"), str(tmp_path / "ds"), "--crop", "none"])
    assert code == 0, out
    got = DatasetReader(tmp_path / "ds")
    pid = f"{scene}_cam0_f4"
    a, b = studio.load(pid), got.load(pid)
    assert got.split_of(pid) == "val" and b.params.extra["bit_depth"] == 8
    assert b.params.extra["transfer_curve"] == "srgb"
    # an 8-bit sRGB step rounds by <= 0.5/255 encoded, ~2.4 x 0.5/255 / 0.5 = 0.9 % of a mid-grey linear value
    bright = a.left > 0.05
    assert np.median(np.abs(b.left[bright] - a.left[bright]) / a.left[bright]) < 0.006
    # reading them as linear instead is visibly wrong: the curve matters
    code, out = _import([str(tmp_path / "rel"), str(tmp_path / "lin"), "--crop", "none", "--curve", "linear"])
    assert code == 0, out
    c = DatasetReader(tmp_path / "lin").load(pid)
    assert np.median(np.abs(c.left[bright] - a.left[bright]) / a.left[bright]) > 0.05


def test_crop_is_the_release_roi_or_a_given_box(studio: DatasetReader, release: Path, tmp_path: Path) -> None:
    code, out = _import([str(release), str(tmp_path / "rel"), ])
    assert code == 3 and "do not fit the 96x64 frame" in out  # the release ROI needs the 1680 x 1120 frames
    code, out = _import([str(release), str(tmp_path / "ds"), "--crop", "cam0=8:40,16:80", "--crop", "cam1=none"])
    assert code == 0, out
    got = DatasetReader(tmp_path / "ds")
    pid = next(p for p in studio.ids() if "cam0_f1.4" in p)
    a, b = studio.load(pid), got.load(pid)
    assert b.params.image_size == (64, 32)
    assert b.params.extra["crop_origin_px"] == [16, 8] and b.params.extra["full_image_size"] == [96, 64]
    assert b.params.focus_point_px == (a.params.focus_point_px[0] - 16, a.params.focus_point_px[1] - 8)
    np.testing.assert_array_equal(b.depth_mm, a.depth_mm[8:40, 16:80])
    np.testing.assert_allclose(b.left, a.left[8:40, 16:80], atol=2e-4)
    assert "crop_origin_px" not in got.params(pid.replace("cam0", "cam1")).extra


def test_malformed_scenes_are_named_and_the_others_imported(studio: DatasetReader, release: Path, tmp_path: Path) -> None:
    import h5py

    root = tmp_path / "rel"
    shutil.copytree(release, root)
    good = next(p for p in (root / "train").iterdir())
    bad_file = shutil.copytree(good, root / "train" / "scene_missing_view")
    (bad_file / "cam1" / "FN_4_r.png").unlink()
    bad_meta = shutil.copytree(good, root / "train" / "scene_bad_meta")
    with h5py.File(bad_meta / "meta_data.h5", "a") as f:
        del f["focus_dis_1"]
    bad_depth = shutil.copytree(good, root / "train" / "scene_8bit_depth")
    (bad_depth / "cam0" / "dep.png").write_bytes((bad_depth / "cam0" / "FN_22.png").read_bytes())
    code, out = _import([str(root), str(tmp_path / "ds"), "--crop", "none"])
    assert code == 8, out
    assert "3 of 5 scenes not imported" in out
    assert "scene scene_missing_view:" in out and "FN_4_r.png" in out
    assert "scene scene_bad_meta:" in out and "meta_data.h5: lacks 'focus_dis_1'" in out
    got = DatasetReader(tmp_path / "ds")
    assert sorted({got.params(p).scene for p in got.ids()}) == sorted({studio.params(p).scene for p in studio.ids()})
    assert not any("scene_" in p.name for p in (tmp_path / "ds" / "pairs").iterdir())  # no half scene left behind
    failures = json.loads((tmp_path / "ds" / "dataset.json").read_text())["import_failures"]
    assert {f["scene"] for f in failures} == {"scene_missing_view", "scene_bad_meta", "scene_8bit_depth"}
    assert "dep.png: expected single-channel 16-bit depth" in next(f["error"] for f in failures if f["scene"] == "scene_8bit_depth")
    # nothing importable: one line, exit 3, no dataset
    code, out = _import([str(tmp_path / "nothing"), str(tmp_path / "ds2")])
    assert code == 3 and "source folder not found" in out
    (tmp_path / "empty" / "val").mkdir(parents=True)
    code, out = _import([str(tmp_path / "empty"), str(tmp_path / "ds2")])
    assert code == 3 and "no scene folders" in out and not (tmp_path / "ds2" / "dataset.json").exists()
