"""Gray-code projections from OpenCV contrib and the headless pattern window (SDL dummy driver)."""

from __future__ import annotations

import cv2
import numpy as np

from dp5k_capture.display import PatternWindow
from dp5k_capture.patterns import gray_code_patterns, projection, projection_count, projection_label


def test_46_projections_at_full_projector_resolution() -> None:
    assert projection_count(1920, 1200) == 46
    gen = cv2.structured_light.GrayCodePattern.create(1920, 1200)
    ok, ref = gen.generate()
    assert ok and len(ref) == 44
    for k in (0, 1, 21, 22, 43):
        assert np.array_equal(projection(k, 1920, 1200), ref[k])
    assert (projection(44, 1920, 1200) == 255).all() and (projection(45, 1920, 1200) == 0).all()
    assert projection_label(0, 1920, 1200) == "col bit 0 +" and projection_label(23, 1920, 1200) == "row bit 0 -"


def test_patterns_decode_back_to_projector_columns() -> None:
    """Decoding the column bits (pattern > inverse) recovers every projector column: the set is complete."""
    pats = gray_code_patterns(1920, 1200)
    bits = np.stack([pats[2 * b][0] > pats[2 * b + 1][0] for b in range(11)])  # (11, 1920) MSB first
    gray = np.zeros(1920, np.int64)
    for b in bits:
        gray = (gray << 1) | b
    binary = gray.copy()
    shift = gray >> 1
    while shift.any():
        binary ^= shift
        shift >>= 1
    assert np.array_equal(binary, np.arange(1920))
    # the coarser scale 1/2 is the first 10 bit pairs: column // 2
    assert np.array_equal(binary >> 1, np.arange(1920) // 2)


def test_window_shows_exactly_the_pattern() -> None:
    win = PatternWindow(1920, 1200, display_index=0, settle_s=0.0, headless=True)
    try:
        for k in (0, 7, 30, 44):
            img = projection(k, 1920, 1200)
            win.show(img, k)
            assert win.shown == k
            assert np.array_equal(win.frame(), img)
    finally:
        win.close()
