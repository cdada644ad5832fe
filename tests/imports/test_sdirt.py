"""``dp5k import sdirt`` on the real Canon data, and bad input."""

from __future__ import annotations

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
    assert all(r.ids(s) for s in ("train", "val", "test"))
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
