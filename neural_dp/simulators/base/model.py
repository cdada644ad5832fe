"""``BaseModel``: the ideal occlusion-aware thin-lens DP model, and ``Component``, one effect added to it."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from dp5k_learn.batch import DPBatch

from ..interface import DPSimulator
from .cache import TensorCache
from .field import field_coords, field_r2, field_y_units
from .fit import fit_parameters
from .psf import PSFShape, half_disc_kernels, stack_centred
from .render import RenderConfig, render_layers, render_layers_multi
from .sharp import sharp_radiance

__all__ = ["Component", "BaseModel", "FIELD_NODES_R2", "select_pairs"]


def select_pairs(batch: DPBatch, idx: Tensor) -> DPBatch:
    """The batch's pairs at indices ``idx`` (every per-pair tensor indexed along its first axis)."""
    kw = {}
    for f in dataclasses.fields(batch):
        v = getattr(batch, f.name)
        if isinstance(v, Tensor):
            kw[f.name] = v.index_select(0, idx)
        elif f.name == "pair_ids" and v:
            kw[f.name] = tuple(v[i] for i in idx.tolist())
    return dataclasses.replace(batch, **kw)

FIELD_NODES_X: tuple[float, float, float] = (-1.0, 0.0, 1.0)
"""Field x at which a PSF that changes along x (:attr:`Component.field_x_dependent`) is rendered; views in between
are blended linearly in x, and the right view at x is the left view's mirror at -x (a pupil cut off axis is
mirror-symmetric about the field's centre line, not about each view's split)."""

FIELD_NODES_Y: tuple[float, float, float] = (-1.0, 0.0, 1.0)
"""Field y at which a PSF that also changes along y (:attr:`Component.field_y_dependent`) is rendered, as
multiples of the batch's largest half-height on the sensor (:func:`~.field.field_y_units`; for a batch of one
frame size, its field y in [-1, 1]): the views are then blended bilinearly over the 3 x 3 nodes of
:data:`FIELD_NODES_X` x :data:`FIELD_NODES_Y` (the right view at (x, y) is the left view's mirror at (-x, y): a
left-right mirror keeps y). Crops of frames of different aspects share the nodes, each blended at its own
sensor y."""

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
    field_x_dependent: ClassVar[bool] = False
    """True when :meth:`shape` reads :attr:`field_x` (the field x of the node being rendered, in [-1, 1]): the
    model then renders at :data:`FIELD_NODES_X`."""
    field_y_dependent: ClassVar[bool] = False
    """True when :meth:`shape` also reads :attr:`field_y` (implies :attr:`field_x_dependent`): the model then renders
    at :data:`FIELD_NODES_X` x :data:`FIELD_NODES_Y`."""
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
    shape_needs_optics: ClassVar[bool] = False
    """True when :meth:`shape` reads :attr:`PSFShape.f_number` and :attr:`PSFShape.pixel_pitch_mm`: the model then
    renders the pairs of each f-number and pitch apart (their kernels differ)."""

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

    field_x: float = 0.0
    """The field x of the render in progress (:attr:`field_x_dependent`), set by the model."""
    field_y: float = 0.0
    """The field y of the render in progress (:attr:`field_y_dependent`), set by the model **in units of the
    field's half-width** (the unit of :attr:`field_x`): ``(field_x, field_y)`` points along the field vector on
    the sensor whatever the frame's aspect (node y = 1 of a 3:2 frame is ``field_y`` = 2/3)."""

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

    def render_state(self) -> tuple:
        """Everything of this component that the layered render reads, hashable (default: its class and
        ``params``): the key of :data:`_LAYERS_CACHE`. A component whose hooks read other state must add it."""
        return (type(self).__qualname__, tuple(sorted(self.params.items())))


_LAYERS_CACHE = TensorCache(256 * 2**20)
"""Layered renders of the last model states, by batch, field and :meth:`BaseModel.render_state`: a fit renders
the point it just accepted again for its Jacobian, a selection renders a confirmed model's crops again for the
next screen (one render in eight of a diagnosis was a repeat). Bounded by the renders' total size (bytes)."""


def _versions(batch: DPBatch, field: Tensor | None) -> tuple[int, ...]:
    """The in-place version counters of the tensors a render reads (a cached render of a changed batch is stale)."""
    ts = [getattr(batch, f.name) for f in dataclasses.fields(batch)] + [field]
    return tuple(t._version for t in ts if isinstance(t, Tensor))


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
            that :func:`dp5k_diagnose.fitting.fit_base` fits with the rim softness and the gain.
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
        self._optics: tuple[float, float] = (0.0, 0.0)
        """(f-number, pixel pitch mm) of the pairs being rendered, for :attr:`Component.shape_needs_optics`."""

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
            f_number=self._optics[0],
            pixel_pitch_mm=self._optics[1],
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

    def _kernel_fn_at(self, x: float, y: float):
        """:meth:`_kernel_fn` at field node (x, y) (y in units of the half-width, :attr:`Component.field_y`): the
        components see that node while the kernels are built."""
        fn = self._kernel_fn(x * x)

        def at(nodes: Tensor) -> Tensor:
            for c in self.components:
                c.field_x, c.field_y = x, y
            try:
                return fn(nodes)
            finally:
                for c in self.components:
                    c.field_x = c.field_y = 0.0

        return at

    def render_state(self) -> tuple:
        """Everything the layered render reads of the model, hashable: base parameters, discretisation and each
        component's :meth:`Component.render_state`."""
        return (tuple(sorted(self.params.items())), self.sharp_deblur_iters, dataclasses.astuple(self.config),
                tuple(c.render_state() for c in self.components))

    def render_layers_only(self, batch: DPBatch, field: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The layered render before gain and post hooks: (left, right), each ``H * sharp``.

        Where a component's PSF depends on the aperture (:attr:`Component.shape_needs_optics`), the pairs of
        each (f-number, pixel pitch) are rendered apart, with that optics as the kernels' context. Without
        autograd the result is cached (:data:`_LAYERS_CACHE`) for the same batch, field and
        :meth:`render_state`; callers must not change it in place."""
        if torch.is_grad_enabled():
            return self._render_layers_by_optics(batch, field)
        key = (id(batch), id(field), _versions(batch, field), self.render_state())
        hit = _LAYERS_CACHE.get(key, (batch, field))
        if hit is not None:
            return hit
        return _LAYERS_CACHE.put(key, (batch, field), self._render_layers_by_optics(batch, field))

    def _render_layers_by_optics(self, batch: DPBatch, field: Tensor | None) -> tuple[Tensor, Tensor]:
        B, _, H, W = batch.sharp.shape
        if field is None:
            field = field_coords(B, H, W, batch.sharp.device)
        if not any(c.shape_needs_optics for c in self.components):
            return self._render_layers(batch, field)
        keys = list(zip(batch.f_number.tolist(), batch.pixel_pitch_mm.tolist()))
        radiance = sharp_radiance(batch, self.sharp_deblur_iters, self.config)  # cached per batch
        out_l = out_r = None
        for key in sorted(set(keys)):
            idx = torch.tensor([i for i, k in enumerate(keys) if k == key], device=batch.sharp.device)
            self._optics = (float(key[0]), float(key[1]))
            try:
                l, r = self._render_layers(select_pairs(batch, idx), field.index_select(0, idx), radiance.index_select(0, idx))
            finally:
                self._optics = (0.0, 0.0)
            if out_l is None:
                out_l, out_r = l.new_zeros((B, *l.shape[1:])), r.new_zeros((B, *r.shape[1:]))
            out_l[idx], out_r[idx] = l, r
        return out_l, out_r

    def _render_layers(self, batch: DPBatch, field: Tensor, radiance: Tensor | None = None) -> tuple[Tensor, Tensor]:
        coc = batch.coc_px.float()
        sharp = sharp_radiance(batch, self.sharp_deblur_iters, self.config) if radiance is None else radiance
        for c in self.components:
            coc = c.coc(coc, batch, field)
            sharp = c.sharp(sharp, batch)
        valid = batch.valid
        if any(c.field_x_dependent for c in self.components):
            return self._render_over_field(sharp, coc, valid, field)
        if any(c.field_dependent and c.changes_psf for c in self.components):
            renders = render_layers_multi(sharp, coc, valid, [(self._kernel_fn(r2), ("l", "r")) for r2 in FIELD_NODES_R2], self.config)
            r2 = field_r2(field).clamp(0.0, 1.0)
            w0 = (1 - 2 * r2).clamp(min=0)
            w2 = (2 * r2 - 1).clamp(min=0)
            w1 = 1 - w0 - w2
            left = w0 * renders[0][0] + w1 * renders[1][0] + w2 * renders[2][0]
            right = w0 * renders[0][1] + w1 * renders[1][1] + w2 * renders[2][1]
        else:
            left, right = render_layers(sharp, coc, valid, self._kernel_fn(0.0), self.config)
        return left, right

    def _render_over_field(self, sharp: Tensor, coc: Tensor, valid: Tensor, field: Tensor) -> tuple[Tensor, Tensor]:
        """Render at :data:`FIELD_NODES_X` (and :data:`FIELD_NODES_Y` where a component's PSF also changes along
        y) and blend linearly in field x (bilinearly in x and y); the right view at node (x, y) is the right output
        of the render at node (-x, y). A node's view that no pixel of the batch weighs is not rendered (a crop
        right of the centre needs the left view of node 1 and the right view of node -1, not the other two): the
        same output, with fewer views. All nodes are rendered in one :func:`render_layers_multi` call: the layer
        decomposition is shared and only the kernels differ."""
        def tent(t: Tensor) -> dict[float, Tensor]:
            w = {-1.0: (-t).clamp(min=0), 1.0: t.clamp(min=0)}
            w[0.0] = 1 - w[-1.0] - w[1.0]
            return w

        wx = tent(field[:, :1].clamp(-1.0, 1.0))
        along_y = any(c.field_y_dependent for c in self.components)
        span = 0.0
        if along_y:  # nodes at sensor y = -span, 0, span (units of the half-width), shared by frames of any aspect
            units = field_y_units(field)
            span = float(units.max())
            wy: dict[float, Tensor | float] = tent((field[:, 1:2] * (units / span).view(-1, 1, 1, 1)).clamp(-1.0, 1.0))
        else:
            wy = {0.0: 1.0}
        nodes = [(x, y) for x in FIELD_NODES_X for y in wy]
        w = {(x, y): wx[x] * wy[y] for x, y in nodes}
        used = {n: bool((w[n] > 0).any()) for n in nodes}

        def mirror(n: tuple[float, float]) -> tuple[float, float]:
            return (-n[0] if n[0] else 0.0, n[1])

        asked = {}
        for x, y in nodes:
            views = tuple(v for v, on in (("l", used[(x, y)]), ("r", used[mirror((x, y))])) if on)
            if views:
                asked[(x, y)] = (self._kernel_fn_at(x, y * span), views)
        # one layer decomposition for every node: only the kernels differ between them
        renders = dict(zip(asked, render_layers_multi(sharp, coc, valid, list(asked.values()), self.config)))
        left = sum(w[n] * renders[n][0] for n in nodes if used[n])
        right = sum(w[n] * renders[mirror(n)][1] for n in nodes if used[n])
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
