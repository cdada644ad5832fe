"""``BaseModel``: the ideal occlusion-aware thin-lens DP model, and ``Component``, one effect added to it."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from dp5k_learn.batch import DPBatch

from ..interface import DPSimulator
from .field import field_coords, field_r2
from .fit import fit_parameters
from .psf import PSFShape, half_disc_kernels, stack_centred
from .render import RenderConfig, render_layers
from .sharp import sharp_radiance

__all__ = ["Component", "BaseModel", "FIELD_NODES_R2"]

FIELD_NODES_R2: tuple[float, float, float] = (0.0, 0.5, 1.0)
"""Squared field radii (corner = 1) at which a field-dependent PSF is rendered; views in between are blended
linearly in r^2 (:meth:`BaseModel.render_layers_only`)."""


class Component(torch.nn.Module):
    """One physical effect added to the base model, with parameters fitted on training data.

    Override any of the hooks. ``params`` holds the fitted parameters by name (floats);
    ``fit_names`` lists those the generic fitter adjusts, ``bounds`` their ranges, ``steps`` the finite
    difference step used for their Jacobian.
    """

    name: ClassVar[str] = "component"
    channel_dependent: ClassVar[bool] = False
    field_dependent: ClassVar[bool] = False
    changes_psf: ClassVar[bool] = False
    post_only: ClassVar[bool] = False
    """True when the component only has a :meth:`post` hook (its fit can reuse one layered render)."""
    stage: ClassVar[int] = 0
    """Where the component acts in the image chain: a model applies its components sorted by stage (stable),
    whatever order they were added in. -1: the lens' focus (CoC from the recorded optics, before any
    field or colour change of it); 0: blur and photodiode crosstalk; 1: per-view gains; 2: the views'
    registration; 3: noise. Crosstalk before gains is what the studio and dp5k_testing/foreign_dp.py do;
    both orders are 2 x 2 mixes of the views and differ only at second order, and diagnose refits earlier
    gain components with every later one."""
    needs_colour: ClassVar[bool] = False
    """True when the effect acts between colour channels: data with R = G = B cannot show it (not testable)."""

    def __init__(self) -> None:
        super().__init__()
        self.params: dict[str, float] = {}
        self.fit_names: list[str] = []
        self.bounds: dict[str, tuple[float, float]] = {}
        self.steps: dict[str, float] = {}
        self.field_box: tuple[float, float, float, float] = (-1.0, 1.0, -1.0, 1.0)
        """(x0, x1, y0, y1): the field (coordinates in [-1, 1]) the fit data covered; :meth:`describe` reports
        field-dependent ranges over it only (a fit says nothing about the field it did not see)."""

    def coc(self, coc_px: Tensor, batch: DPBatch, field: Tensor) -> Tensor:
        """(B, 1 or 3, H, W) signed CoC per colour channel, px (``field`` (B, 2, H, W)). Default: unchanged."""
        return coc_px

    def sharp(self, sharp: Tensor, batch: DPBatch) -> Tensor:
        """(B, 3, H, W) the sharp input as the renderer should see it. Default: unchanged."""
        return sharp

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        """The PSF shape for colour ``channel`` (0..2, or -1 for all) at squared field radius ``field_r2``."""
        return shape

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        """Change the rendered views (B, 3, H, W); ``field`` is (B, 2, H, W) in [-1, 1]."""
        return left, right

    def initial_guess(self, model: "BaseModel", batch: DPBatch, field: Tensor) -> None:
        """Set a starting point for the fitter from data (optional)."""

    def supported_names(self, samples: Sequence[object]) -> list[str]:
        """The ``fit_names`` the fit data ``samples`` can constrain (default: all); the rest stay neutral."""
        return list(self.fit_names)

    def describe(self) -> dict[str, float]:
        """Parameters to report (default: ``params``)."""
        return dict(self.params)


class BaseModel(DPSimulator):
    """The ideal occlusion-aware thin-lens DP model (half-aperture split) plus optional effect components.

    Args:
        rim_softness_px: standard deviation of the Gaussian that softens the disc (residual lens blur), px.
        gain: overall intensity gain (views are ``gain * H * sharp / 2``).
        components: effect components (see :class:`Component`), applied in order.
        config: renderer discretisation.
        sharp_deblur_iters: Van Cittert iterations that undo the sharp frame's own f/22 blur before
            rendering (:func:`sharp_radiance`; 0 treats the sharp frame as a pinhole image).
        pixel_box: how PSFs become pixel weights, 0 (2-px triangle: linear interpolation of the sharp image)
            to 1 (1-px box: pixel-area integration), :class:`PSFShape`; a renderer-discretisation parameter
            that :func:`dp5k_diagnose.detect.fit_base` fits with the rim softness and the gain.
    """

    name: ClassVar[str] = "base"

    def __init__(self, rim_softness_px: float = 0.5, gain: float = 1.0, components: Sequence[Component] = (), config: RenderConfig | None = None,
                 sharp_deblur_iters: int = 2, pixel_box: float = 0.0) -> None:
        super().__init__()
        self.sharp_deblur_iters = int(sharp_deblur_iters)
        self.params: dict[str, float] = {"rim_softness_px": float(rim_softness_px), "gain": float(gain), "pixel_box": float(pixel_box)}
        self.bounds: dict[str, tuple[float, float]] = {"rim_softness_px": (0.0, 6.0), "gain": (0.05, 20.0), "pixel_box": (0.0, 1.0)}
        self.steps: dict[str, float] = {"rim_softness_px": 0.15, "gain": 0.01, "pixel_box": 0.25}
        self.components = torch.nn.ModuleList(list(components))
        self.config = config or RenderConfig()

    # -- composition -----------------------------------------------------------------------------
    def with_component(self, comp: Component) -> "BaseModel":
        """A new model with the same base parameters and components plus ``comp``, placed by its
        :attr:`Component.stage`."""
        return self.replaced(sorted(list(self.components) + [comp], key=lambda c: c.stage))

    def component(self, name: str) -> Component:
        """The component named ``name`` (KeyError when the model has none)."""
        for c in self.components:
            if c.name == name:
                return c
        raise KeyError(name)

    def replaced(self, components: Sequence[Component] | None = None, **params: float) -> "BaseModel":
        """A new model with these ``components`` (default: the same) and base ``params`` changed, the rest kept."""
        p = {**self.params, **params}
        return BaseModel(p["rim_softness_px"], p["gain"], list(self.components) if components is None else list(components),
                         self.config, self.sharp_deblur_iters, p["pixel_box"])

    def describe(self) -> dict[str, object]:
        return {"base": dict(self.params), "sharp_deblur_iters": self.sharp_deblur_iters,
                "components": {c.name: c.describe() for c in self.components}}

    # -- rendering -------------------------------------------------------------------------------
    def _shape(self, nodes: Tensor, channel: int, r2: float) -> PSFShape:
        one = torch.ones((), device=nodes.device)
        shape = PSFShape(
            coc_px=nodes,
            scale=one,
            softness_px=one * self.params["rim_softness_px"],
            rim2=one * 0.0,
            rim4=one * 0.0,
            split=one,
            pixel_box=one * self.params["pixel_box"],
        )
        for c in self.components:
            shape = c.shape(shape, channel, r2)
        return shape

    def _kernel_fn(self, r2: float):
        chan = any(c.channel_dependent and c.changes_psf for c in self.components)
        ss = self.config.supersample

        def fn(nodes: Tensor) -> Tensor:
            if not chan:
                return half_disc_kernels(self._shape(nodes, -1, r2), ss)[:, None]
            return stack_centred([half_disc_kernels(self._shape(nodes, ch, r2), ss) for ch in range(3)], dim=1)

        return fn

    def render_layers_only(self, batch: DPBatch, field: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The layered render before gain and post hooks: (left, right), each ``H * sharp``."""
        B, _, H, W = batch.sharp.shape
        if field is None:
            field = field_coords(B, H, W, batch.sharp.device)
        coc = batch.coc_px.float()
        sharp = sharp_radiance(batch, self.sharp_deblur_iters, self.config)
        for c in self.components:
            coc = c.coc(coc, batch, field)
            sharp = c.sharp(sharp, batch)
        valid = batch.valid
        if any(c.field_dependent and c.changes_psf for c in self.components):
            renders = [render_layers(sharp, coc, valid, self._kernel_fn(r2), self.config) for r2 in FIELD_NODES_R2]
            r2 = field_r2(field).clamp(0.0, 1.0)
            w0 = (1 - 2 * r2).clamp(min=0)
            w2 = (2 * r2 - 1).clamp(min=0)
            w1 = 1 - w0 - w2
            left = w0 * renders[0][0] + w1 * renders[1][0] + w2 * renders[2][0]
            right = w0 * renders[0][1] + w1 * renders[1][1] + w2 * renders[2][1]
        else:
            left, right = render_layers(sharp, coc, valid, self._kernel_fn(0.0), self.config)
        return left, right

    def render(self, batch: DPBatch, field: Tensor | None = None, layers: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """(left, right), each (B, 3, H, W), linear, on the batch's scale.

        Args:
            field: (B, 2, H, W) field coordinates in [-1, 1] (default: the batch is the whole image).
            layers: a cached :meth:`render_layers_only` result to reuse (only gain and post hooks run).
        """
        B, _, H, W = batch.sharp.shape
        if field is None:
            field = field_coords(B, H, W, batch.sharp.device)
        left, right = layers if layers is not None else self.render_layers_only(batch, field)
        g = self.params["gain"] / 2.0
        left, right = left * g, right * g
        for c in self.components:
            left, right = c.post(left, right, batch, field)
        return left, right

    def forward(self, batch: DPBatch, field: Tensor | None = None) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        with torch.no_grad():
            return self.render(batch, field)

    # -- fitting ---------------------------------------------------------------------------------
    def fit(self, batches: list[DPBatch], fields: list[Tensor] | None = None) -> dict[str, float]:  # type: ignore[override]
        """Fit ``rim_softness_px`` and ``gain`` on training batches (measured views required)."""
        fit_parameters(self, [(self, "rim_softness_px"), (self, "gain")], batches, fields)
        return {k: self.params[k] for k in ("rim_softness_px", "gain")}
