"""The studio's pinhole radiance, the reference: what a camera's pixels receive from the scene's surfaces under a
projector image (albedo times ambient plus projected light, averaged over the supersampling grid), for the visible
and the hidden surfaces.

A readable version of ``dp5k_studio.render.ViewGeometry.radiance`` / ``hidden_radiance``; the package's version
must give the same images bit for bit (``tests/studio/test_reference_equivalence.py``). Not a test module.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class ReferenceGeometry:
    """The radiance of a :class:`~dp5k_studio.render.ViewGeometry` (its surfaces, projector indices and gains),
    computed the readable way: ``radiance`` / ``hidden_radiance`` as the package's ``ViewGeometry`` has them."""

    def __init__(self, geom) -> None:
        self.__dict__.update(geom.__dict__)

    def hidden_radiance(self, pattern: NDArray[np.float32] | None) -> NDArray[np.float32] | None:
        """(H, W, 3) radiance of the hidden surfaces under a projector image (None if not computed)."""
        if self.hidden is None:
            return None
        h = self.hidden
        light = np.repeat(h["base_light"][:, None], 3, axis=1)
        if pattern is not None:
            m = h["proj_index"] >= 0
            pat = pattern.reshape(pattern.shape[0] * pattern.shape[1], -1)
            light[m] += pat[h["proj_index"][m]] * h["proj_gain"][m][:, None]
        return (h["albedo"] * light).reshape(self.height, self.width, 3).astype(np.float32)

    def radiance(self, pattern: NDArray[np.float32] | None) -> NDArray[np.float32]:
        """(H, W, 3) float32 radiance under a projector image ((Hp, Wp[, 3]) in [0, 1]) or None (dark)."""
        light = np.repeat(self.base_light[:, None], 3, axis=1)
        if pattern is not None:
            m = self.proj_index >= 0
            pat = pattern.reshape(pattern.shape[0] * pattern.shape[1], -1)
            val = pat[self.proj_index[m]]
            light[m] += val * self.proj_gain[m][:, None]
        rad = self.albedo * light
        s = self.ss
        return rad.reshape(self.height, s, self.width, s, 3).mean(axis=(1, 3), dtype=np.float32)
