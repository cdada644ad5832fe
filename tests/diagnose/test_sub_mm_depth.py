"""Format v1's optional ``depth.tif``: float32 millimetres read in place of depth.png's whole millimetres."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dp5k_common.dataset import DatasetReader, PairParams, write_index, write_pair
from dp5k_common.errors import DatasetFormatError
from dp5k_common.io import write_tiff_float32
from dp5k_common.optics import coc_diameter_px


def _write(root: Path, sub_mm: bool) -> np.ndarray:
    H, W = 8, 12
    depth = np.linspace(60.2, 90.7, H * W, dtype=np.float64).reshape(H, W)
    depth[0, 0] = 0.0  # invalid
    p = PairParams("p0", "s0", "cam0", 1.8, 70.0, 5.0, 0.0014, (W / 2, H / 2), (W, H))
    coc = np.nan_to_num(coc_diameter_px(np.where(depth > 0, depth, np.nan), 70.0, 5.0, 1.8, 0.0014))
    img = np.full((H, W, 3), 0.5)
    write_pair(root, p, sharp=img, left=img / 2, right=img / 2, depth_mm=depth, coc_px=coc, sub_mm_depth=sub_mm)
    write_index(root, {"train": ["p0"], "val": [], "test": []})
    return depth


@pytest.mark.parametrize("sub_mm", [True, False])
def test_depth_tif_gives_sub_millimetre_depth_and_depth_png_stays(tmp_path: Path, sub_mm: bool) -> None:
    depth = _write(tmp_path, sub_mm)
    assert (tmp_path / "pairs/p0/depth.png").is_file()
    assert (tmp_path / "pairs/p0/depth.tif").is_file() is sub_mm
    pair = DatasetReader(tmp_path).load("p0")
    want = depth if sub_mm else np.rint(depth)
    assert np.abs(pair.depth_mm - want).max() < 1e-4
    assert pair.depth_mm[0, 0] == 0 and not pair.valid[0, 0] and pair.valid[1:].all()


@pytest.mark.parametrize("bad, message", [
    (lambda d: d + 3.0, "disagrees with depth.png"),
    (lambda d: np.where(d > 70, np.nan, d), "not a positive finite depth"),
    (lambda d: d[:, :5], "disagrees with image_size"),
])
def test_a_bad_depth_tif_is_a_one_line_error_naming_the_file(tmp_path: Path, bad, message: str) -> None:
    depth = _write(tmp_path, True)
    write_tiff_float32(tmp_path / "pairs/p0/depth.tif", np.ascontiguousarray(bad(depth)).astype(np.float32))
    with pytest.raises(DatasetFormatError, match=message) as err:
        DatasetReader(tmp_path).load("p0")
    assert "depth.tif" in str(err.value)
