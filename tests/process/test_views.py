"""DP views from the raw frames: our half-size demosaic equals LibRaw's, views split as main - aux."""

from __future__ import annotations

import numpy as np
import rawpy

from dp5k_common.rawfile import read_dual_pixel, write_dual_pixel_dng
from dp5k_process.rawimage import dp_views, half_size_rgb


def test_half_size_matches_libraw_and_views_split(tmp_path):
    rng = np.random.default_rng(0)
    aux = rng.integers(600, 4000, (48, 64)).astype(np.uint16)
    main = (aux.astype(np.int32) * 2 - 512 + rng.integers(-40, 40, (48, 64))).clip(0, 16383).astype(np.uint16)
    p = tmp_path / "dp.dng"
    write_dual_pixel_dng(p, main, aux, 512, 16383, (2.0, 1.0, 1.5))
    fr = read_dual_pixel(p)
    ours = half_size_rgb(fr.main, fr.black_level)
    raw = rawpy.RawPy()
    raw.set_unpack_params(shot_select=0)
    raw.open_file(str(p))
    raw.unpack()
    ref = raw.postprocess(half_size=True, output_color=rawpy.ColorSpace.raw, gamma=(1, 1), no_auto_bright=True,
                          user_wb=[1, 1, 1, 1], output_bps=16, user_flip=0, no_auto_scale=True)
    np.testing.assert_allclose(ref.astype(np.float32), ours, atol=0.51)  # LibRaw rounds the green mean
    m, left, right = dp_views(fr, "left")
    np.testing.assert_allclose(left + right, m, atol=1e-6)
    scale = 1.0 / (16383 - 512)
    np.testing.assert_allclose(left[..., 0], (aux[0::2, 0::2].astype(np.float32) - 512) * 2.0 * scale, rtol=1e-5)
    m2, l2, r2 = dp_views(fr, "right")
    np.testing.assert_allclose(r2, left)
    np.testing.assert_allclose(l2, right)
