"""``dp5k import dpdd`` and ``dp5k import generic``: layouts built from studio pairs, round trips and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_studio import make_dataset

from .layouts import SHARP_SCALE, VIEW_SCALE, write_dpdd_scene, write_image


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> DatasetReader:
    out = tmp_path_factory.mktemp("studio") / "ds"
    make_dataset(out, scenes=["demo01"], size=(96, 64), f_numbers=(1.8, 4.0), seed=5)
    return DatasetReader(out)


def _run(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["-q", *args])
    return res.exit_code, res.output


def test_dpdd_pairs_have_views_but_no_depth(studio: DatasetReader, tmp_path: Path) -> None:
    root = tmp_path / "dd_dp_dataset_canon"
    ids = sorted(studio.ids())
    write_dpdd_scene(studio, ids[0], root, "train")
    write_dpdd_scene(studio, ids[1], root, "test")
    code, out = _run("import", "dpdd", str(tmp_path), str(tmp_path / "ds"))
    assert code == 0, out
    got = DatasetReader(tmp_path / "ds")
    assert got.ids("train") == [f"{ids[0]}_5d4_f4"] and got.ids("test") == [f"{ids[1]}_5d4_f4"]
    a, b = studio.load(ids[0]), got.load(f"{ids[0]}_5d4_f4")
    assert not b.valid.any() and (b.depth_mm == 0).all() and np.isnan(b.coc_px).all()
    assert b.params.extra["optics_known"] is False and b.params.extra["has_depth"] is False
    np.testing.assert_allclose(b.left, a.left, atol=2e-4)  # views back on the combined frame's scale
    assert b.params.extra["exposure"]["views_gain"] == pytest.approx(1 / VIEW_SCALE, rel=1e-3)
    ratio = float((a.left + a.right).mean() / a.sharp.mean())
    assert b.params.extra["exposure"]["sharp_gain"] == pytest.approx(ratio / SHARP_SCALE, rel=2e-3)
    code, out = _run("check", str(tmp_path / "ds"))  # the format's reader accepts pairs without valid depth
    assert code == 0, out
    # the simulators render from depth: evaluate says so in one line instead of writing NaN metrics
    code, out = _run("evaluate", str(tmp_path / "ds"), "--out", str(tmp_path / "ev"), "--simulator", "disk")
    assert code == 3 and "no pair of split 'test' has valid depth" in out, out
    assert not (tmp_path / "ev" / "metrics.json").exists()
    code, out = _run("import", "dpdd", str(tmp_path), str(tmp_path / "ds18"), "--f-number", "1.8")
    assert code == 0 and DatasetReader(tmp_path / "ds18").params(f"{ids[0]}_5d4_f1.8").f_number == 1.8
    # a missing view: the scene and file are named, the other scene is imported, exit 8
    (root / "test_r" / "source" / f"{ids[1]}.png").unlink()
    code, out = _run("import", "dpdd", str(tmp_path), str(tmp_path / "ds2"))
    assert code == 8 and f"scene {ids[1]}" in out and f"missing file {ids[1]}.png" in out and "test_r/source" in out
    assert DatasetReader(tmp_path / "ds2").ids() == [f"{ids[0]}_5d4_f4"]
    code, out = _run("import", "dpdd", str(tmp_path / "ds"), str(tmp_path / "ds3"))
    assert code == 3 and "no {train,val,test}_c/source folder" in out


def _write_generic(studio: DatasetReader, root: Path) -> None:
    """Scene A: one f-number, 16-bit sRGB PNG views, 16-bit PNG depth in mm, a combined frame. Scene B: two
    f-numbers in the file names, 16-bit linear TIFF, depth in metres (float TIFF, NaN invalid), its own optics.json
    (linear curve, depth_scale_mm 1000, camera cam1)."""
    a = studio.load("demo01_cam0_f4")
    p = a.params
    root.mkdir(parents=True)
    (root / "optics.json").write_text(json.dumps({
        "f_number": 4, "focus_distance_mm": p.focus_distance_mm, "focal_length_mm": p.focal_length_mm,
        "sensor_width_mm": 36, "focus_point_px": list(p.focus_point_px), "source": "my rig"}))
    sa = root / "sceneA"
    write_image(sa / "left.png", a.left * VIEW_SCALE)
    write_image(sa / "right.png", a.right * VIEW_SCALE)
    write_image(sa / "combined.png", a.left + a.right)
    write_image(sa / "sharp.png", a.sharp * SHARP_SCALE)
    cv2.imwrite(str(sa / "depth.png"), a.depth_mm.astype(np.uint16))
    sb = root / "sceneB"
    sb.mkdir()
    (sb / "optics.json").write_text(json.dumps({"curve": "linear", "depth_scale_mm": 1000.0, "camera": "cam1"}))
    for N in (1.8, 4.0):
        q = studio.load(f"demo01_cam1_f{N:g}")
        tifffile.imwrite(sb / f"left_f{N:g}.tif", np.rint(q.left * 65535).astype(np.uint16))
        tifffile.imwrite(sb / f"right_f{N:g}.tif", np.rint(q.right * 65535).astype(np.uint16))
    q = studio.load("demo01_cam1_f4")
    tifffile.imwrite(sb / "sharp.tif", np.rint(q.sharp * 65535).astype(np.uint16))
    tifffile.imwrite(sb / "depth.tiff", np.where(q.depth_mm > 0, q.depth_mm / 1000.0, np.nan).astype(np.float32))


def test_generic_folders_and_optics_json(studio: DatasetReader, tmp_path: Path) -> None:
    root = tmp_path / "mine"
    _write_generic(studio, root)
    code, out = _run("import", "generic", str(root), str(tmp_path / "ds"))
    assert code == 0, out
    got = DatasetReader(tmp_path / "ds")
    assert sorted(got.ids()) == ["sceneA_cam0_f4", "sceneB_cam1_f1.8", "sceneB_cam1_f4"]
    a, b = studio.load("demo01_cam0_f4"), got.load("sceneA_cam0_f4")
    np.testing.assert_allclose(b.left, a.left, atol=2e-4)
    np.testing.assert_array_equal(b.depth_mm, a.depth_mm)
    np.testing.assert_allclose(b.coc_px[a.valid], a.coc_px[a.valid], rtol=1e-5)
    assert b.params.focus_point_px == a.params.focus_point_px and b.params.extra["source"] == "my rig"
    assert b.params.pixel_pitch_mm == pytest.approx(a.params.pixel_pitch_mm)
    for N in (1.8, 4.0):
        a, b = studio.load(f"demo01_cam1_f{N:g}"), got.load(f"sceneB_cam1_f{N:g}")
        np.testing.assert_allclose(b.left, a.left, atol=2e-5)  # no combined frame: the views are kept as they are
        np.testing.assert_array_equal(b.depth_mm, a.depth_mm)  # metres x 1000, NaN -> 0
        assert b.params.extra["transfer_curve"] == "linear" and b.params.f_number == N
    # split folders keep their split
    (root / "val").mkdir()
    shutil.move(root / "sceneB", root / "val" / "sceneB")
    (root / "train").mkdir()
    shutil.move(root / "sceneA", root / "train" / "sceneA")
    code, out = _run("import", "generic", str(root), str(tmp_path / "ds2"))
    assert code == 0, out
    got = DatasetReader(tmp_path / "ds2")
    assert got.ids("train") == ["sceneA_cam0_f4"] and got.ids("val") == ["sceneB_cam1_f1.8", "sceneB_cam1_f4"]


def test_generic_bad_optics_and_files(studio: DatasetReader, tmp_path: Path) -> None:
    root = tmp_path / "mine"
    _write_generic(studio, root)
    (root / "sceneB" / "optics.json").write_text(json.dumps({"curve": "linear", "focal_mm": 50}))
    (root / "sceneA" / "right.png").unlink()
    code, out = _run("import", "generic", str(root), str(tmp_path / "ds"))
    assert code == 3 and "no scene could be imported" in out
    assert "sceneA: " in out and "missing right.<png|tif|jpg>" in out
    assert "sceneB/optics.json: unknown key(s) focal_mm" in out
    shutil.rmtree(root / "sceneB")
    write_image(root / "sceneA" / "right.png", studio.load("demo01_cam0_f4").right)
    (root / "optics.json").write_text(json.dumps({"f_number": 4, "focus_distance_mm": 900, "focal_length_mm": 85}))
    code, out = _run("import", "generic", str(root), str(tmp_path / "ds"))
    assert code == 3 and "mine/optics.json: optics lack 'sensor_width_mm'" in out
    assert not (tmp_path / "ds" / "dataset.json").exists()
    code, out = _run("import", "generic", str(tmp_path), str(tmp_path / "ds"))
    assert code == 3 and "missing optics.json" in out
