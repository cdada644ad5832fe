"""A base model (with its effect components) as an exact, JSON-serialisable dict, and back.

``dp5k diagnose`` writes the model it extended as ``report.json["extended_model_spec"]``; the ``diagnosed``
simulator (:mod:`neural_dp.simulators.diagnosed`) renders with :func:`model_from_spec` of it. Layout::

    {"format": "dp5k-base-model", "version": 1,
     "base": {"rim_softness_px": px, "gain": 1, "pixel_box": 0..1},
     "sharp_deblur_iters": int, "render": {RenderConfig fields},
     "components": [{"name": effect name, "params": {name: float}, "fit_names": [...],
                     "state": {other plain attributes, e.g. "mean_focus_mm"},
                     "buffers": {name: {"shape": [...], "values": [...]}}}, ...]}   # in application order

Floats that are not finite (a component's NaN "not yet measured") are written as the strings "nan", "inf",
"-inf", since report.json is strict JSON.
"""

from __future__ import annotations

import math
from dataclasses import asdict, fields
from typing import Any

import torch

from dp5k_common.errors import BadInputError

from .components import COMPONENTS
from .model import BaseModel
from .render import RenderConfig

SPEC_FORMAT = "dp5k-base-model"
SPEC_VERSION = 1
_BOOKKEEPING = ("training", "params", "fit_names", "bounds", "steps")
"""Component attributes that are not rendering state (nn.Module's flag, and what the spec stores by name)."""
_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def _encode(value: float | int | str | bool) -> float | int | str | bool:
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    return value


def _decode(value: Any) -> Any:
    return _NON_FINITE[value] if isinstance(value, str) and value in _NON_FINITE else value


def _component_spec(comp: torch.nn.Module) -> dict[str, Any]:
    state = {k: _encode(v) for k, v in vars(comp).items()
             if not k.startswith("_") and k not in _BOOKKEEPING and isinstance(v, (int, float, str, bool))}
    buffers = {k: {"shape": list(v.shape), "values": v.detach().cpu().double().flatten().tolist()}
               for k, v in comp.state_dict().items()}
    return {"name": comp.name, "params": {k: _encode(float(v)) for k, v in comp.params.items()},
            "fit_names": list(comp.fit_names), "state": state, "buffers": buffers}


def model_to_spec(model: BaseModel) -> dict[str, Any]:
    """The model's base parameters, renderer settings and components (in order) with all their values."""
    return {
        "format": SPEC_FORMAT, "version": SPEC_VERSION,
        "base": {k: _encode(float(v)) for k, v in model.params.items()},
        "sharp_deblur_iters": int(model.sharp_deblur_iters),
        "render": asdict(model.config),
        "components": [_component_spec(c) for c in model.components],
    }


def model_from_spec(spec: dict[str, Any], cls: type[BaseModel] = BaseModel) -> BaseModel:
    """Rebuild the model :func:`model_to_spec` described (an instance of ``cls``, a BaseModel subclass).

    Raises:
        BadInputError: not a spec of this format, an unknown component or parameter, or a malformed value.
    """
    if not isinstance(spec, dict) or spec.get("format") != SPEC_FORMAT or spec.get("version") != SPEC_VERSION:
        raise BadInputError(f"not a {SPEC_FORMAT} v{SPEC_VERSION} model spec", where="model spec")
    try:
        base = {k: float(_decode(v)) for k, v in spec["base"].items()}
        known = {f.name for f in fields(RenderConfig)}
        render = RenderConfig(**{k: v for k, v in spec["render"].items() if k in known})
        comps = []
        for c in spec["components"]:
            if c["name"] not in COMPONENTS:
                raise BadInputError(f"unknown component {c['name']!r} (known: {', '.join(COMPONENTS)})", where="model spec")
            comp = COMPONENTS[c["name"]]()
            unknown = set(c["params"]) - set(comp.params)
            if unknown:
                raise BadInputError(f"component {c['name']!r} has no parameter(s) {sorted(unknown)}", where="model spec")
            comp.params.update({k: float(_decode(v)) for k, v in c["params"].items()})
            comp.fit_names = list(c.get("fit_names", comp.fit_names))
            for k, v in c.get("state", {}).items():
                setattr(comp, k, _decode(v))
            if c.get("buffers"):
                comp.load_state_dict({k: torch.tensor(b["values"], dtype=torch.float64).view(b["shape"])
                                      for k, b in c["buffers"].items()})
            comps.append(comp)
        model = cls(base["rim_softness_px"], base["gain"], comps, render, int(spec["sharp_deblur_iters"]), base["pixel_box"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise BadInputError(f"malformed model spec ({type(exc).__name__}: {exc})", where="model spec") from exc
    model.eval()
    return model
