"""A base model with components survives model_to_spec -> JSON -> model_from_spec exactly (values and renders)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from dp5k_common.errors import BadInputError
from dp5k_learn.batch import DPBatch
from neural_dp.simulators.base import BaseModel
from neural_dp.simulators.base.components import COMPONENTS
from neural_dp.simulators.base.spec import model_from_spec, model_to_spec


def small_batch(H: int = 24, W: int = 32) -> DPBatch:
    g = torch.Generator().manual_seed(0)
    depth = torch.linspace(900.0, 3000.0, W).expand(1, 1, H, W).clone()
    coc = (depth - 1500.0) / 150.0
    return DPBatch(sharp=torch.rand(1, 3, H, W, generator=g), coc_px=coc, depth_mm=depth,
                   valid=torch.ones(1, 1, H, W, dtype=torch.bool), f_number=torch.tensor([2.0]),
                   focus_distance_mm=torch.tensor([1500.0]), focal_length_mm=torch.tensor([50.0]),
                   pixel_pitch_mm=torch.tensor([0.05]), focus_point_px=torch.tensor([[W / 2, H / 2]]))


def planted_model() -> BaseModel:
    lr, fb, mis, focus = (COMPONENTS[n]() for n in ("lr_gain_imbalance", "front_back_asymmetry", "misregistration", "focus_offset"))
    lr.params.update(a0=0.2, ax=-0.05)
    fb.params.update({k: 0.1 * (i + 1) for i, k in enumerate(fb.params)})
    mis.params.update(left_dx_px=0.7, right_dy_px=-0.3)
    focus.params.update(focus_factor=1.1)
    focus.mean_focus_mm = 1234.5
    return BaseModel(rim_softness_px=0.9, gain=1.3, pixel_box=0.4, sharp_deblur_iters=1).replaced([lr, fb, mis, focus])


def test_round_trip_is_exact_through_json() -> None:
    model = planted_model()
    spec = model_to_spec(model)
    again = model_from_spec(json.loads(json.dumps(spec, allow_nan=False)))
    assert model_to_spec(again) == spec
    assert [c.name for c in again.components] == ["lr_gain_imbalance", "front_back_asymmetry", "misregistration", "focus_offset"]
    assert again.components[3].mean_focus_mm == 1234.5 and again.params["pixel_box"] == 0.4
    b = small_batch()
    for x, y in zip(model(b), again(b)):
        assert torch.equal(x, y)
    assert not torch.allclose(BaseModel()(b)[0], again(b)[0], atol=1e-3)  # the components matter for the render


def test_not_finite_state_is_kept_and_bad_specs_are_named() -> None:
    spec = model_to_spec(BaseModel().with_component(COMPONENTS["focus_offset"]()))
    json.dumps(spec, allow_nan=False)  # strict JSON despite the NaN "not yet measured"
    assert math.isnan(model_from_spec(spec).components[0].mean_focus_mm)
    with pytest.raises(BadInputError, match="unknown component 'warp'"):
        model_from_spec({**spec, "components": [{"name": "warp", "params": {}}]})
    with pytest.raises(BadInputError, match="not a dp5k-base-model"):
        model_from_spec({"base": {}})
