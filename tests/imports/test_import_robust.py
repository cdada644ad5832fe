"""Imports people can trust and finish (issue 31): tiles never leak across splits and ``dp5k check`` catches a
dataset where they do; OUT is checked before any work; a partial import is finished with ``--resume``; folder names
with spaces or accents get safe ids; inconsistent files are flagged (or refused with ``--strict``); pair folders
follow the umask; and every import writes a report with a preview per source."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader, write_pair
from dp5k_studio import make_dataset

from .layouts import SHARP_SCALE, VIEW_SCALE, write_dpdd_scene, write_image

SCENES = ("alpha", "bravo", "charlie", "delta", "echo")


@pytest.fixture(scope="module")
def studio(tmp_path_factory: pytest.TempPathFactory) -> DatasetReader:
    out = tmp_path_factory.mktemp("studio") / "ds"
    make_dataset(out, scenes=["demo01"], size=(96, 64), f_numbers=(4.0,), seed=5)
    return DatasetReader(out)


def _run(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["-q", *args])
    return res.exit_code, res.output


def _generic(studio: DatasetReader, root: Path, scenes: tuple[str, ...] = SCENES) -> Path:
    """A generic layout of several scenes (each the studio pair, 16-bit sRGB PNG, with a combined frame)."""
    p = studio.load("demo01_cam0_f4")
    root.mkdir(parents=True, exist_ok=True)
    (root / "optics.json").write_text(json.dumps({
        "f_number": 4, "focus_distance_mm": p.params.focus_distance_mm, "focal_length_mm": p.params.focal_length_mm,
        "sensor_width_mm": 36}))
    for name in scenes:
        _scene(p, root / name)
    return root


def _scene(p, folder: Path, sharp_bits: int = 16, gray_sharp: bool = False) -> None:
    write_image(folder / "left.png", p.left * VIEW_SCALE)
    write_image(folder / "right.png", p.right * VIEW_SCALE)
    write_image(folder / "combined.png", p.left + p.right)
    sharp = p.sharp * SHARP_SCALE
    write_image(folder / "sharp.png", np.repeat(sharp.mean(-1, keepdims=True), 3, -1) if gray_sharp else sharp, sharp_bits)
    if gray_sharp:  # one channel on disk
        img = cv2.imread(str(folder / "sharp.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(folder / "sharp.png"), img[..., 0])
    cv2.imwrite(str(folder / "depth.png"), p.depth_mm.astype(np.uint16))


def _source_splits(root: Path) -> dict[str, set[str]]:
    r = DatasetReader(root)
    out: dict[str, set[str]] = {}
    for pid in r.ids():
        out.setdefault(r.params(pid).source_id, set()).add(r.split_of(pid))
    return out


def test_tiles_of_one_source_share_a_split_and_check_catches_a_leak(studio: DatasetReader, tmp_path: Path) -> None:
    src = _generic(studio, tmp_path / "mine")
    code, out = _run("import", "generic", str(src), str(tmp_path / "ds"), "--tile", "32x32")
    assert code == 0, out
    r = DatasetReader(tmp_path / "ds")
    assert len(r) == len(SCENES) * 6 and all(r.ids(s) for s in ("train", "val", "test"))
    per_source = _source_splits(tmp_path / "ds")
    assert sorted(per_source) == sorted(SCENES) and all(len(s) == 1 for s in per_source.values())
    p = r.params(r.ids("test")[0])
    assert p.extra["source_id"] == p.scene.rsplit("_t", 1)[0]  # tiles are scenes, their photo is the source
    code, out = _run("check", str(tmp_path / "ds"))
    assert code == 0 and "sources: {'train': 3, 'val': 1, 'test': 1}" in out, out
    # a leak: one tile of a test source moved to train (its scene id alone still crosses no split)
    index = json.loads((tmp_path / "ds" / "dataset.json").read_text())
    moved = index["splits"]["test"].pop(0)
    index["splits"]["train"].append(moved)
    (tmp_path / "ds" / "dataset.json").write_text(json.dumps(index))
    code, out = _run("check", str(tmp_path / "ds"))
    assert code == 4 and len(out.strip().splitlines()) == 1, out
    assert f"source(s) {r.params(moved).source_id} appear in both the 'train' and 'test' splits" in out


def test_two_sources_are_train_and_test(studio: DatasetReader, tmp_path: Path) -> None:
    src = _generic(studio, tmp_path / "mine", scenes=("one", "two"))
    code, out = _run("import", "generic", str(src), str(tmp_path / "ds"), "--tile", "32x32")
    assert code == 0, out
    r = DatasetReader(tmp_path / "ds")
    assert not r.ids("val") and len(r.ids("train")) == len(r.ids("test")) == 6
    assert {frozenset(s) for s in _source_splits(tmp_path / "ds").values()} == {frozenset({"train"}), frozenset({"test"})}
    rep = json.loads((tmp_path / "ds" / "report.json").read_text())
    assert "only two source captures" in rep["split_note"] and "val is empty" in rep["split_note"]
    assert "only two source captures" in (tmp_path / "ds" / "report.md").read_text()


def test_report_counts_gains_failures_and_previews(studio: DatasetReader, tmp_path: Path) -> None:
    src = _generic(studio, tmp_path / "mine", scenes=("one", "two", "three"))
    (src / "three" / "right.png").unlink()
    code, out = _run("import", "generic", str(src), str(tmp_path / "ds"))
    assert code == 8, out
    rep = json.loads((tmp_path / "ds" / "report.json").read_text())
    assert rep["sources"] == 3 and rep["imported"] == 2 and rep["failed"] == 1
    assert sum(rep["pairs"].values()) == 2 and rep["failures"][0]["scene"] == "three"
    gains = {s["source_id"]: s["captures"][0]["exposure"] for s in rep["scenes"]}
    assert gains["one"]["views_gain"] == pytest.approx(1 / VIEW_SCALE, rel=1e-3)
    for sid in ("one", "two"):
        img = cv2.imread(str(tmp_path / "ds" / "previews" / f"{sid}.png"))
        assert img is not None and img.shape[1] == 5 * 96  # sharp | left | right | depth | CoC
    assert not (tmp_path / "ds" / "previews" / "three.png").exists()
    md = (tmp_path / "ds" / "report.md").read_text()
    assert "## Not imported" in md and "`three`" in md and "![one](previews/one.png)" in md and "| 0.625 |" in md


def test_resume_keeps_good_scenes_and_retries_failed(studio: DatasetReader, tmp_path: Path) -> None:
    src = _generic(studio, tmp_path / "mine")
    (src / "delta" / "right.png").rename(src / "delta" / "right.bak")
    out_dir = tmp_path / "ds"
    code, out = _run("import", "generic", str(src), str(out_dir), "--tile", "32x32")
    assert code == 8 and "--resume" in out, out
    code, out = _run("check", str(out_dir))
    assert code == 0 and "import_failures: 1" in out and "WARNING: not imported: delta:" in out, out
    planned = json.loads((out_dir / "dataset.json").read_text())["import_failures"][0]["split"]
    kept = {p: (out_dir / "pairs" / p / "left.png").stat().st_mtime_ns for p in DatasetReader(out_dir).ids()}
    (src / "delta" / "right.bak").rename(src / "delta" / "right.png")  # the user fixes the scene
    code, out = _run("import", "generic", str(src), str(out_dir), "--tile", "32x32")
    assert code == 3 and "imports never overwrite" in out and "--resume" in out, out
    code, out = _run("import", "generic", str(src), str(out_dir), "--tile", "32x32", "--resume")
    assert code == 0, out
    r = DatasetReader(out_dir)
    assert len(r) == len(SCENES) * 6
    assert {p: (out_dir / "pairs" / p / "left.png").stat().st_mtime_ns for p in kept} == kept  # untouched
    assert _source_splits(out_dir)["delta"] == {planned}  # where it would have gone had it not failed
    assert json.loads((out_dir / "dataset.json").read_text())["import_failures"] == []
    code, out = _run("check", str(out_dir))
    assert code == 0 and "import_failures: 0" in out
    rep = json.loads((out_dir / "report.json").read_text())
    assert rep["resumed"] and rep["imported"] == len(SCENES) and rep["failed"] == 0


def test_folder_names_with_spaces_and_accents_get_safe_ids(studio: DatasetReader, tmp_path: Path) -> None:
    src = _generic(studio, tmp_path / "mine", scenes=("my scene", "scène 1", "scene_1"))
    code, out = _run("import", "generic", str(src), str(tmp_path / "ds"))
    assert code == 0, out
    r = DatasetReader(tmp_path / "ds")
    by_id = {r.params(p).source_id: r.params(p).extra.get("source_name") for p in r.ids()}
    assert by_id == {"my_scene": "my scene", "scene_1-2": "scène 1", "scene_1": None}
    assert "`my_scene` (my scene)" in (tmp_path / "ds" / "report.md").read_text()


def test_inconsistent_inputs_warn_or_refuse_with_strict(studio: DatasetReader, tmp_path: Path) -> None:
    p = studio.load("demo01_cam0_f4")
    src = _generic(studio, tmp_path / "mine", scenes=("fine",))
    _scene(p, src / "graysharp", gray_sharp=True)
    _scene(p, src / "eightbit", sharp_bits=8)
    code, out = _run("import", "generic", str(src), str(tmp_path / "ds"))
    assert code == 0, out
    assert "graysharp: gray sharp.png beside colour" in out and "eightbit: 8-bit and 16-bit files mixed" in out
    r = DatasetReader(tmp_path / "ds")
    warned = {r.params(pid).source_id: r.params(pid).extra.get("input_warnings", []) for pid in r.ids()}
    assert warned["fine"] == [] and len(warned["graysharp"]) == 1 and len(warned["eightbit"]) == 1
    assert "## Warnings about the input files" in (tmp_path / "ds" / "report.md").read_text()
    code, out = _run("import", "generic", str(src), str(tmp_path / "strict"), "--strict")
    assert code == 8 and "(--strict)" in out, out
    assert sorted(f["scene"] for f in json.loads((tmp_path / "strict" / "dataset.json").read_text())["import_failures"]) \
        == ["eightbit", "graysharp"]


def test_a_curve_that_does_not_linearise_is_measured(studio: DatasetReader, tmp_path: Path) -> None:
    """sRGB files read as linear: left + right no longer matches the combined frame; the importer measures how far
    and whether the other curve fits (DPDD layout, --curve linear)."""
    root = tmp_path / "dd"
    write_dpdd_scene(studio, "demo01_cam0_f4", root, "test")
    code, out = _run("import", "dpdd", str(root), str(tmp_path / "ok"))
    assert code == 0 and "does not reproduce the combined frame" not in out, out
    code, out = _run("import", "dpdd", str(root), str(tmp_path / "ds"), "--curve", "linear")
    assert code == 0 and "left + right does not reproduce the combined frame" in out, out
    assert "the images are probably srgb" in out
    code, out = _run("import", "dpdd", str(root), str(tmp_path / "strict"), "--curve", "linear", "--strict")
    assert code == 3 and "(--strict)" in out and "does not reproduce the combined frame" in out, out


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_pair_folders_follow_the_umask(studio: DatasetReader, tmp_path: Path, umask: int) -> None:
    """Pairs are written into a temporary folder (mkdtemp: 0700) and renamed: they must end with the umask's mode,
    or nobody else can read a shared dataset."""
    src = _generic(studio, tmp_path / "mine", scenes=("one",))
    old = os.umask(umask)
    try:
        code, out = _run("import", "generic", str(src), str(tmp_path / "ds"))
        p = studio.load("demo01_cam0_f4")
        write_pair(tmp_path / "direct", p.params, sharp=p.sharp, left=p.left, right=p.right, depth_mm=p.depth_mm,
                   coc_px=p.coc_px)
    finally:
        os.umask(old)
    assert code == 0, out
    for pair_dir in [tmp_path / "ds" / "pairs" / "one_cam0_f4", tmp_path / "direct" / "pairs" / p.params.pair_id]:
        assert stat.S_IMODE(pair_dir.stat().st_mode) == 0o777 & ~umask, pair_dir
        assert stat.S_IMODE((pair_dir / "left.png").stat().st_mode) == 0o666 & ~umask


def test_bad_out_is_one_line_exit_3_before_any_scene(studio: DatasetReader, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    import dp5k_import.writer as writer

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("a scene was read before OUT was checked")

    monkeypatch.setattr(writer, "_import_source", boom)
    src = _generic(studio, tmp_path / "mine", scenes=("one",))
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out_dir, why in ((a_file, "is a file"), (a_file / "ds", "is a file"), (Path("/proc/dp5k-ds"), "cannot write into /proc")):
        code, out = _run("import", "generic", str(src), str(out_dir))
        assert code == 3 and why in out and len(out.strip().splitlines()) == 1, (out_dir, out)
