"""DP views of one camera under a sequence of projector images, from the linearity of the optics.

The pinhole radiance under a projector image ``P`` (values in [0, 1]) is affine in ``P`` (render.py):
``L(P) = L(0) + L_lin(P)``. The DP render of a fixed depth map (:class:`~.dp_optics.DPPlan`), the per-view
effects and diffraction are linear in radiance, so the views are ``V(P) = V(0) + V_lin(P)`` and, for a
binary image and its complement (the Gray-code ``+``/``-`` pairs), ``V_lin(1 - P) = V_lin(1) - V_lin(P)``.
Of the 46 structured-light projections, black, white and every ``-`` pattern then cost one addition each:
24 renders per camera instead of 46 (the dark views, the full projector light's views and one per ``+``
pattern). The result equals a direct render to float32 rounding (tests/studio/test_reference_equivalence.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .dp_optics import DPPlan
from .render import ViewGeometry

F32 = NDArray[np.float32]
Views = tuple[F32, F32]
"""(left, right) linear DP views (H, W, 3) float32 before diffraction."""


def _is_binary(pattern: F32) -> bool:
    """Whether every value of a projector image is exactly 0 or 1."""
    return bool(np.all((pattern == 0.0) | (pattern == 1.0)))


class PatternViews:
    """The views of one camera's plan under any projector image, reusing what is linear.

    Keeps the dark views ``V(0)``, the full projector light's share ``V_lin(1)`` (made when a complement
    first needs it) and the last binary image's share ``V_lin(P)`` with that image; at paper scale that is
    up to 6 images of 90 MB per camera.

    Args:
        plan: the camera's DP plan (depth, lens, effects).
        geometry: the camera's ray-cast geometry (the plan's depth map).
    """

    def __init__(self, plan: DPPlan, geometry: ViewGeometry) -> None:
        self.plan = plan
        self.geometry = geometry
        self._dark_rad = geometry.radiance(None)
        self._dark_hidden = geometry.hidden_radiance(None)
        self._dark: Views | None = None
        self._white_lin: Views | None = None
        self._last: tuple[F32, Views] | None = None

    def _render(self, radiance: F32, hidden: F32 | None) -> Views:
        out = self.plan.render(radiance, hidden)
        return out.left, out.right

    def _lin(self, pattern: F32) -> Views:
        """``V_lin(P)``: the views of the projector's share of the radiance alone."""
        g = self.geometry
        hidden = None if self._dark_hidden is None else g.hidden_radiance(pattern) - self._dark_hidden
        return self._render(g.radiance(pattern) - self._dark_rad, hidden)

    def dark(self) -> Views:
        """``V(0)``: the views with the projector dark (cached)."""
        if self._dark is None:
            self._dark = self._render(self._dark_rad, self._dark_hidden)
        return self._dark

    def views(self, pattern: F32 | None) -> Views:
        """(left, right) views (new arrays) under ``pattern`` ((Hp, Wp[, 3]) float32 in [0, 1]) or None (dark)."""
        dl, dr = self.dark()
        if pattern is None or not np.any(pattern):
            return dl.copy(), dr.copy()
        if not _is_binary(pattern):
            ll, lr = self._lin(pattern)
            return dl + ll, dr + lr
        if np.all(pattern == 1.0):
            wl, wr = self._white(pattern.shape)
            return dl + wl, dr + wr
        if self._last is not None and np.array_equal(pattern, 1.0 - self._last[0]):
            (ll, lr), (wl, wr) = self._last[1], self._white(pattern.shape)
            return dl + (wl - ll), dr + (wr - lr)
        lin = self._lin(pattern)
        self._last = (pattern, lin)
        return dl + lin[0], dr + lin[1]

    def _white(self, shape: tuple[int, ...]) -> Views:
        """``V_lin(1)``: the full projector light's share (cached; ``shape`` that of the projector image)."""
        if self._white_lin is None:
            self._white_lin = self._lin(np.ones(shape, np.float32))
        return self._white_lin
