"""Eq. 6 and Eq. 7 against independent hand computations."""

from __future__ import annotations

import numpy as np
import pytest

from dp5k_common.errors import BadInputError
from dp5k_common.optics import coc_diameter_mm, coc_diameter_px, pinhole_focal_length_mm, thin_lens_focal_length_mm


def test_coc_is_aperture_times_magnification_times_relative_defocus() -> None:
    f, F, N = 85.0, 2000.0, 2.8
    d = np.array([1000.0, 2000.0, 5000.0])
    aperture = f / N
    v_focus = 1 / (1 / f - 1 / F)  # image distance of the focus plane
    v_d = 1 / (1 / f - 1 / d)
    expected = aperture * (v_focus - v_d) / v_d  # similar triangles behind the lens
    np.testing.assert_allclose(coc_diameter_mm(d, F, f, N), expected, rtol=1e-12)


def test_coc_sign_and_zero() -> None:
    c = coc_diameter_px([1000.0, 2000.0, 3000.0, 0.0], 2000.0, 85.0, 1.8, 0.02)
    assert c[0] < 0 and c[1] == 0 and c[2] > 0 and np.isnan(c[3])


def test_thin_and_pinhole_focal_lengths_invert() -> None:
    f_thin = thin_lens_focal_length_mm(90.0, 1500.0)
    assert f_thin < 90.0
    assert pinhole_focal_length_mm(f_thin, 1500.0) == pytest.approx(90.0)


def test_bad_optics_raise() -> None:
    with pytest.raises(BadInputError):
        coc_diameter_mm(1000.0, 50.0, 85.0, 1.8)
    with pytest.raises(BadInputError):
        coc_diameter_px(1000.0, 2000.0, 85.0, 1.8, 0.0)
