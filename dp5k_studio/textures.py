"""Procedural albedo textures, evaluated on surface coordinates in metres.

Every texture is a pure function of ``(u_m, v_m)`` (surface coordinates, metres) and its own integer seed,
so a scene renders identically from any viewpoint and on any run. Albedo is linear RGB reflectance in
[0, 1]. Kinds (``TextureSpec.kind``):

* ``"noise"``: fractal value noise (4 octaves, base period ``scale_m``) blending two colours;
* ``"stripes"``: sinusoidal stripes of period ``scale_m`` at ``angle_deg`` blending two colours;
* ``"checker"``: fine checkerboard with squares of ``scale_m`` (fine detail);
* ``"image"``: an image mapped onto ``[0, size_u_m] x [0, size_v_m]`` (the ChArUco board print);
* any kind may carry ``dark_fraction`` > 0: dark low-albedo (0.01..0.03) blotches covering about that
  fraction of the surface, the patches that defeat structured light in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class TextureSpec:
    """An albedo texture (see module docstring for the kinds).

    Attributes:
        kind: ``"noise"``, ``"stripes"``, ``"checker"``, ``"image"`` or ``"flat"``.
        color_a, color_b: the two linear RGB albedos blended by the pattern.
        scale_m: pattern period / square size in metres.
        angle_deg: stripe orientation.
        dark_fraction: fraction of the surface covered by dark blotches (0 = none).
        seed: the texture's own seed.
        image: (H, W) or (H, W, 3) float albedo in [0, 1] for kind ``"image"``.
        size_m: (width, height) of the image on the surface, metres.
    """

    kind: str = "noise"
    color_a: tuple[float, float, float] = (0.6, 0.6, 0.6)
    color_b: tuple[float, float, float] = (0.3, 0.3, 0.3)
    scale_m: float = 0.1
    angle_deg: float = 0.0
    dark_fraction: float = 0.0
    seed: int = 0
    image: NDArray[np.float32] | None = field(default=None, compare=False, repr=False)
    size_m: tuple[float, float] = (1.0, 1.0)


@lru_cache(maxsize=256)
def _lattice(seed: int) -> NDArray[np.float32]:
    """The noise lattice of one seed: (256, 256) uniform values in [0, 1) (period 256 cells)."""
    return np.random.default_rng(np.uint32(seed & 0xFFFFFFFF)).random((256, 256), dtype=np.float32)


def value_noise(u: NDArray[np.float64], v: NDArray[np.float64], seed: int) -> NDArray[np.float32]:
    """Smooth value noise in [0, 1] with unit lattice period (smoothstep interpolation), float32."""
    lat = _lattice(int(seed))
    fu_ = np.floor(u)
    fv_ = np.floor(v)
    fu = (u - fu_).astype(np.float32)
    fv = (v - fv_).astype(np.float32)
    iu = fu_.astype(np.int64) & 255
    iv = fv_.astype(np.int64) & 255
    iu1 = (iu + 1) & 255
    iv1 = (iv + 1) & 255
    su = fu * fu * (3.0 - 2.0 * fu)
    sv = fv * fv * (3.0 - 2.0 * fv)
    a = lat[iv, iu]
    b = lat[iv, iu1]
    c = lat[iv1, iu]
    d = lat[iv1, iu1]
    return (a + (b - a) * su) * (1 - sv) + (c + (d - c) * su) * sv


def fbm(u: NDArray[np.float64], v: NDArray[np.float64], seed: int, octaves: int = 4) -> NDArray[np.float64]:
    """Fractal sum of value noise, normalized to [0, 1]."""
    total = np.zeros(u.shape, np.float32)
    amp, norm, freq = 1.0, 0.0, 1.0
    for o in range(octaves):
        total += amp * value_noise(u * freq + 17.3 * o, v * freq - 9.1 * o, seed + 101 * o)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm


@lru_cache(maxsize=1)
def _fbm_samples() -> NDArray[np.float32]:
    """Sorted samples of 3-octave fbm (its distribution, for area-calibrated thresholds)."""
    g = np.linspace(0.0, 64.0, 400)
    u, v = np.meshgrid(g, g)
    return np.sort(fbm(u.ravel(), v.ravel(), 12345, octaves=3))


def _fbm_quantile(q: float) -> float:
    """Value below which a fraction ``q`` of 3-octave fbm lies."""
    s = _fbm_samples()
    return float(s[int(np.clip(q, 0.0, 1.0) * (len(s) - 1))])


def evaluate(tex: TextureSpec, u_m: NDArray[np.float64], v_m: NDArray[np.float64]) -> NDArray[np.float32]:
    """Albedo of ``tex`` at surface coordinates.

    Args:
        tex: the texture.
        u_m, v_m: (N,) surface coordinates in metres.

    Returns:
        (N, 3) float32 linear albedo in [0, 1].
    """
    a = np.asarray(tex.color_a, dtype=np.float64)
    b = np.asarray(tex.color_b, dtype=np.float64)
    if tex.kind == "flat":
        w = np.zeros_like(u_m)
    elif tex.kind == "noise":
        w = fbm(u_m / tex.scale_m, v_m / tex.scale_m, tex.seed)
        w = np.clip((w - 0.5) * 2.2 + 0.5, 0.0, 1.0)
    elif tex.kind == "stripes":
        th = np.deg2rad(tex.angle_deg)
        s = (u_m * np.cos(th) + v_m * np.sin(th)) / tex.scale_m
        w = 0.5 + 0.5 * np.sin(2.0 * np.pi * s)
    elif tex.kind == "checker":
        w = ((np.floor(u_m / tex.scale_m) + np.floor(v_m / tex.scale_m)) % 2.0).astype(np.float64)
    elif tex.kind == "image":
        return _sample_image(tex, u_m, v_m)
    else:
        raise ValueError(f"unknown texture kind {tex.kind!r}")
    out = a[None, :] * (1.0 - w[:, None]) + b[None, :] * w[:, None]
    if tex.dark_fraction > 0:
        m = fbm(u_m / (3.0 * tex.scale_m + 0.05), v_m / (3.0 * tex.scale_m + 0.05), tex.seed + 7777, octaves=3)
        thr = _fbm_quantile(1.0 - tex.dark_fraction)
        dark = np.clip((m - thr) / 0.02, 0.0, 1.0)[:, None]
        out = out * (1.0 - dark) + dark * np.array([0.02, 0.018, 0.015])[None, :]
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _sample_image(tex: TextureSpec, u_m: NDArray[np.float64], v_m: NDArray[np.float64]) -> NDArray[np.float32]:
    """Bilinear lookup of the texture image; outside the image: white paper (0.85)."""
    img = np.asarray(tex.image, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    Hi, Wi = img.shape[:2]
    x = u_m / tex.size_m[0] * Wi - 0.5
    y = v_m / tex.size_m[1] * Hi - 0.5
    inside = (u_m >= 0) & (u_m <= tex.size_m[0]) & (v_m >= 0) & (v_m <= tex.size_m[1])
    x0 = np.clip(np.floor(x), 0, Wi - 1).astype(np.int64)
    y0 = np.clip(np.floor(y), 0, Hi - 1).astype(np.int64)
    x1 = np.minimum(x0 + 1, Wi - 1)
    y1 = np.minimum(y0 + 1, Hi - 1)
    fx = np.clip(x - x0, 0.0, 1.0)[:, None]
    fy = np.clip(y - y0, 0.0, 1.0)[:, None]
    val = (img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy) + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy
    val = np.where(inside[:, None], val, 0.85)
    if val.shape[1] == 1:
        val = np.repeat(val, 3, axis=1)
    return val.astype(np.float32)
