"""``dp5k import sdirt`` on the real Canon data, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader

SDIRT = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "sdirt-canon-r6m2"


@pytest.fixture(scope="module")
def sdirt_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not (SDIRT / "real_sample_set" / "flat").is_dir():
        pytest.skip(f"shared Sdirt data absent ({SDIRT})")
    out = tmp_path_factory.mktemp("sdirt") / "ds"
    res = CliRunner().invoke(main, ["-q", "import", "sdirt", str(SDIRT), str(out), "--tile", "192x128"])
    assert res.exit_code == 0, res.output
    return out


def test_sdirt_import_tiles_into_valid_pairs(sdirt_dataset: Path) -> None:
    r = DatasetReader(sdirt_dataset)
    assert len(r) == 2 * 16  # two distances, 4 x 4 tiles of 192 x 128 from 768 x 512
    # split by photo, not by tile: one target is train, the other test, val is empty (and the report says why)
    assert len(r.ids("train")) == len(r.ids("test")) == 16 and not r.ids("val")
    for split in ("train", "test"):
        assert len({r.params(pid).source_id for pid in r.ids(split)}) == 1
    assert "only two source captures" in json.loads((sdirt_dataset / "report.json").read_text())["split_note"]
    p = r.load(r.ids("test")[0])
    assert p.params.image_size == (192, 128)
    assert p.params.extra["full_image_size"] == [768, 512]
    assert p.valid.all()
    # linear, and left + right matches the exposure-matched sharp frame on average
    assert abs(float((p.left + p.right).mean()) / float(p.sharp.mean()) - 1.0) < 0.05


def test_sdirt_measured_disparity_sign_matches_conventions(sdirt_dataset: Path) -> None:
    """Behind the focal plane (1.5 m, focus 1 m) R is displaced right of L; in front (0.6 m) to the left."""
    from dp5k_diagnose.analysis import tile_disparity

    r = DatasetReader(sdirt_dataset)
    med = {}
    for dist in ("0600", "1500"):
        ds = []
        for pid in r.ids():
            if f"_d{dist}_" in pid:
                p = r.load(pid)
                L = torch.from_numpy(p.left.transpose(2, 0, 1))[None]
                R = torch.from_numpy(p.right.transpose(2, 0, 1))[None]
                d, w = tile_disparity(L, R, torch.ones(1, 1, *L.shape[-2:], dtype=torch.bool), 32)
                ds.append(d[w > w.median()].numpy())
        med[dist] = float(np.median(np.concatenate(ds)))
        coc = r.load(next(pid for pid in r.ids() if f"_d{dist}_" in pid)).coc_px
        assert np.sign(med[dist]) == np.sign(float(np.median(coc))), med
    assert med["1500"] > 0.2 and med["0600"] < -0.2, med


def test_import_bad_inputs_give_one_line_errors(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(main, ["import", "sdirt", str(tmp_path / "nothing"), str(tmp_path / "out")])
    assert res.exit_code == 3 and "source folder not found" in res.output
    (tmp_path / "src" / "flat" / "001" / "0600" / "f4").mkdir(parents=True)
    res = runner.invoke(main, ["import", "sdirt", str(tmp_path / "src"), str(tmp_path / "out")])
    assert res.exit_code == 3 and "missing file" in res.output
    assert not (tmp_path / "out" / "dataset.json").exists()


def test_dp119_layout_box_and_casual_on_request(tmp_path: Path) -> None:
    """The full DP119 layout (box under box/rgbd/) from the real sample files: flat targets always; box and casual
    (depth, no sharp frame) only with --include-unsharp, sharp = left + right at the views' own f/4; the three
    depth encodings (box: 8-bit at full sensor resolution, iphone: 8-bit, orbbec: 16-bit mm); a broken scene is
    named and skipped (exit 8)."""
    real = SDIRT / "real_sample_set"
    if not (real / "box" / "001").is_dir():
        pytest.skip(f"shared Sdirt data absent ({SDIRT})")
    dp119 = tmp_path / "DP119"
    (dp119 / "flat" / "001").mkdir(parents=True)
    (dp119 / "flat" / "001" / "1500").symlink_to(real / "flat" / "001" / "1500")
    (dp119 / "box" / "rgbd").mkdir(parents=True)
    (dp119 / "box" / "rgbd" / "001").symlink_to(real / "box" / "001")
    (dp119 / "box" / "rgbd" / "009").mkdir()
    for name in ("l.png", "r.png"):
        (dp119 / "box" / "rgbd" / "009" / name).symlink_to(real / "box" / "001" / name)
    for kind in ("iphone", "orbbec"):
        (dp119 / "casual" / kind).mkdir(parents=True)
        (dp119 / "casual" / kind / "002").symlink_to(real / "casual" / kind / "002")
    runner = CliRunner()
    res = runner.invoke(main, ["-q", "import", "sdirt", str(dp119), str(tmp_path / "flat"), "--tile", "none"])
    assert res.exit_code == 0, res.output
    assert DatasetReader(tmp_path / "flat").ids() == ["flat001_d1500_r6m2_f4"]
    res = runner.invoke(main, ["-q", "import", "sdirt", str(dp119), str(tmp_path / "all"), "--tile", "none", "--include-unsharp"])
    assert res.exit_code == 8, res.output
    assert "scene box_009" in res.output and "box/rgbd/009/d.png: file not found" in res.output
    r = DatasetReader(tmp_path / "all")
    assert sorted(r.ids()) == ["box_001_r6m2_f4", "casual_iphone_002_r6m2_f4", "casual_orbbec_002_r6m2_f4",
                               "flat001_d1500_r6m2_f4"]
    box = r.load("box_001_r6m2_f4")
    assert box.params.sharp_f_number == 4.0 and box.params.extra["sharp_is_views_sum"] is True
    np.testing.assert_allclose(box.sharp, np.clip(box.left + box.right, 0, 1), atol=2e-5)
    d = box.depth_mm[box.valid]
    assert 0.5 < box.valid.mean() and 300 < np.median(d) < 3000 and d.max() < 10000  # 8-bit x 10 m / 255
    orb = r.load("casual_orbbec_002_r6m2_f4")
    import cv2
    raw = cv2.imread(str(real / "casual" / "orbbec" / "002" / "d.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(orb.depth_mm, np.where(raw < 10000, raw, 0))  # 16-bit mm as is
    iph = r.load("casual_iphone_002_r6m2_f4")
    step = 10000 / 255  # 8-bit gray / 255 x 10 m, stored in whole mm
    d = iph.depth_mm[iph.valid]
    assert iph.valid.mean() > 0.5 and np.all(np.abs(d - np.round(d / step) * step) <= 0.5 + 1e-3)
