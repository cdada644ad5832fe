"""The simulated body's raw files open in rawpy with the DP frames selectable like Canon DPRAW."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rawpy

from dp5k_capture.sim.eos_body import ExposureSettings
from dp5k_capture.sim.world import FlatOptics, dng_bytes


def _frame(path: Path, shot: int) -> np.ndarray:
    raw = rawpy.RawPy()
    raw.set_unpack_params(shot_select=shot)  # before open_file: LibRaw picks the raw IFD while opening
    raw.open_file(str(path))
    raw.unpack()
    with raw:
        return raw.raw_image_visible.copy()


def test_set_before_open_selects_main_then_aux(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    main = rng.integers(2000, 9000, (32, 48)).astype(np.uint16)
    aux = ((main.astype(np.int64) - 512) // 2 + 512).astype(np.uint16)
    path = tmp_path / "dp.dng"
    path.write_bytes(dng_bytes(main, aux, 512, 16383, (2.0, 1.0, 1.5), {"f_number": 1.8}))
    assert np.array_equal(_frame(path, 0), main)
    assert np.array_equal(_frame(path, 1), aux)
    with rawpy.imread(str(path)) as r:
        assert r.raw_image_visible.shape == (32, 48)
    # the pitfall (rawpy 0.28): imread(shot_select=1) sets the frame after open_file and returns the MAIN frame
    with rawpy.imread(str(path), shot_select=1) as r:
        got = r.raw_image_visible.copy()
    assert np.array_equal(got, main), "rawpy's imread now honours shot_select: the set-before-open workaround can go"


def test_body_with_dpraw_off_writes_one_frame(tmp_path: Path) -> None:
    optics = FlatOptics((48, 32))
    s = ExposureSettings("X", 2.8, 1 / 60, 100, (24, 16), 1.4, False, 1)
    path = tmp_path / "single.dng"
    path.write_bytes(optics.expose(s))
    assert _frame(path, 0).shape == (32, 48)
    raw = rawpy.RawPy()
    raw.set_unpack_params(shot_select=1)
    try:
        raw.open_file(str(path))
        raw.unpack()
        opened_second = True
    except rawpy.LibRawRequestForNonexistentImageError:
        opened_second = False
    assert not opened_second
