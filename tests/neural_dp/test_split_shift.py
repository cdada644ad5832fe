"""The field-varying PSF's split shift: the photodiodes' split line moved off axis (psf.split_dx, split_share)."""

from __future__ import annotations

import math

import pytest
import torch

from dp5k_learn.batch import DPBatch
from neural_dp.simulators.base import BaseModel
from neural_dp.simulators.base.components import FieldVaryingPSF
from neural_dp.simulators.base.psf import _half_disc_kernel, _pushforward_kernel, split_share


@pytest.mark.parametrize("s", [-0.6, -0.2, 0.0, 0.35, 0.9])
def test_split_share_is_the_pupil_area_left_of_the_line(s: float) -> None:
    g = (torch.arange(2000, dtype=torch.float64) + 0.5) / 1000 - 1
    uy, ux = torch.meshgrid(g, g, indexing="ij")
    pupil = ux**2 + uy**2 <= 1
    counted = 2 * float((pupil & (ux < s)).sum()) / float(pupil.sum())
    assert float(split_share(torch.tensor(s, dtype=torch.float64))) == pytest.approx(counted, abs=2e-3)
    assert float(split_share(torch.tensor(s)) + split_share(torch.tensor(-s))) == pytest.approx(2.0, abs=1e-6)


def _centroid_px(k: torch.Tensor) -> float:
    x = torch.arange(k.shape[-1], dtype=k.dtype) - k.shape[-1] // 2
    return float((k.sum(0) * x).sum() / k.sum())


@pytest.mark.parametrize("coc", [12.0, -12.0])
@pytest.mark.parametrize("s", [-0.4, 0.3])
def test_a_moved_split_moves_the_half_disc_edge_and_both_builders_agree(coc: float, s: float) -> None:
    """Behind focus (c > 0) the left view is the disc part x < s R; in front it is mirrored. The centroid of the
    part of a uniform disc of radius R left of x = s R is -2 R (1 - s^2)^{3/2} / (3 pi A(s)) (A: its area share)."""
    R = abs(coc) / 2
    area = float(split_share(torch.tensor(s, dtype=torch.float64))) / 2
    want = -2 * R * (1 - s * s) ** 1.5 / (3 * math.pi * area) * (1 if coc > 0 else -1)
    thin = _half_disc_kernel(coc, 1.0, 0.0, 0.0, 0.0, 1.0, split_dx=s)
    pushed = _pushforward_kernel(coc, 1.0, 0.0, 0.0, 0.0, 1.0, split_dx=s)
    assert float(thin.sum()) == pytest.approx(1.0, abs=1e-5)
    assert _centroid_px(thin) == pytest.approx(want, abs=0.05 * R)
    assert _centroid_px(pushed) == pytest.approx(_centroid_px(thin), abs=0.03 * R)


def _flat_batch(H: int = 24, W: int = 64, coc_px: float = 6.0) -> DPBatch:
    z = torch.zeros(1)
    coc = torch.full((1, 1, H, W), coc_px)
    return DPBatch(sharp=torch.full((1, 3, H, W), 0.5), coc_px=coc, depth_mm=torch.full_like(coc, 1500.0),
                   valid=torch.ones(1, 1, H, W, dtype=torch.bool), f_number=z + 2.0, focus_distance_mm=z + 1500,
                   focal_length_mm=z + 50, pixel_pitch_mm=z + 0.05, focus_point_px=torch.zeros(1, 2))


def test_each_view_gets_its_share_of_the_pupil_across_the_field() -> None:
    """On a flat image the views' brightness is the pupil share on their side of the split line, which sits at
    u_x = split_shift x: the left view brightens where x > 0 for a positive shift, the right one mirrors it."""
    fvp = FieldVaryingPSF()
    fvp.params["split_shift"] = 0.4
    model = BaseModel(0.0, 1.0, [fvp])
    b = _flat_batch()
    left, right = model.render(b)
    W = b.sharp.shape[-1]
    x = (torch.arange(W, dtype=torch.float32) - (W - 1) / 2) / ((W - 1) / 2)  # field x (neural_dp...field.field_coords)
    inner = slice(8, W - 8)  # away from the frame's border, where the blur meets the edge
    want_l = 0.25 * split_share(0.4 * x)  # sharp 0.5, gain / 2
    want_r = 0.25 * split_share(-0.4 * x)
    row_l, row_r = left[0, 1, 12], right[0, 1, 12]
    torch.testing.assert_close(row_l[inner], want_l[inner], atol=4e-3, rtol=0)
    torch.testing.assert_close(row_r[inner], want_r[inner], atol=4e-3, rtol=0)
    assert float(row_l[-10] - row_l[10]) > 0.05  # the ramp is there, not a constant


def test_no_split_shift_renders_as_before() -> None:
    b = _flat_batch(coc_px=-5.0)
    b.sharp = torch.rand(1, 3, 24, 64, generator=torch.Generator().manual_seed(0))
    plain = BaseModel(0.0, 1.0, [FieldVaryingPSF()]).render(b)
    none = BaseModel(0.0, 1.0, []).render(b)
    for p, n in zip(plain, none):
        torch.testing.assert_close(p, n)
