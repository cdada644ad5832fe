"""Analytic primitives and vectorized ray casting (metres, world frame; see rig.py for the axes).

Each primitive answers two questions for a batch of rays, both vectorized over N rays:

* ``intersect(o, d) -> t``: (N,) ray parameter of the nearest hit with ``t > T_MIN`` (``inf`` = miss),
  for rays ``o + t d`` from one (3,) origin with (N, 3) unit directions (so ``t`` is metres along the ray);
* ``surface(p) -> (u_m, v_m, n)``: surface coordinates in metres (for the texture) and the unit normal
  at (N, 3) points on the primitive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .textures import TextureSpec, evaluate

T_MIN = 1e-6
"""Smallest accepted ray parameter (m): avoids self-hits of shadow rays."""

Arr = NDArray[np.float64]


def _orthonormal(u_axis: Arr, v_axis: Arr) -> tuple[Arr, Arr, Arr]:
    u = np.asarray(u_axis, float) / np.linalg.norm(u_axis)
    v = np.asarray(v_axis, float) - np.dot(v_axis, u) * u
    v = v / np.linalg.norm(v)
    return u, v, np.cross(u, v)


@dataclass(frozen=True)
class Quad:
    """A planar rectangle ``origin + a*u + b*v``, ``0 <= a <= size_u``, ``0 <= b <= size_v`` (inf = unbounded).

    Surface coordinates are ``(a, b)`` in metres; the normal is ``u x v``.
    """

    origin: Arr
    u_axis: Arr
    v_axis: Arr
    size_m: tuple[float, float]
    texture: TextureSpec = field(default_factory=TextureSpec)
    name: str = "quad"

    def _frame(self) -> tuple[Arr, Arr, Arr]:
        return _orthonormal(self.u_axis, self.v_axis)

    def bounds(self) -> tuple[Arr, float] | None:
        """Bounding sphere (centre, radius in m), or None when unbounded/huge (walls)."""
        if not (np.isfinite(self.size_m[0]) and np.isfinite(self.size_m[1])) or max(self.size_m) > 3.0:
            return None
        u, v, _ = self._frame()
        c = np.asarray(self.origin) + 0.5 * self.size_m[0] * u + 0.5 * self.size_m[1] * v
        return c, 0.5 * float(np.hypot(*self.size_m))

    def intersect(self, o: Arr, d: Arr) -> Arr:
        u, v, n = self._frame()
        q = np.asarray(o, float) - np.asarray(self.origin)
        dn = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(q @ n) / dn
        a = q @ u + t * (d @ u)
        b = q @ v + t * (d @ v)
        ok = (np.abs(dn) > 1e-12) & (t > T_MIN) & (a >= 0) & (a <= self.size_m[0]) & (b >= 0) & (b <= self.size_m[1])
        return np.where(ok, t, np.inf)

    def surface(self, p: Arr) -> tuple[Arr, Arr, Arr]:
        u, v, n = self._frame()
        q = p - np.asarray(self.origin)
        return q @ u, q @ v, np.broadcast_to(n, p.shape)


@dataclass(frozen=True)
class Box:
    """An oriented box: ``center`` (3,), ``R`` (3, 3) with the box axes as columns, ``half_m`` (3,) half sizes."""

    center: Arr
    R: Arr
    half_m: Arr
    texture: TextureSpec = field(default_factory=TextureSpec)
    name: str = "box"

    def bounds(self) -> tuple[Arr, float] | None:
        return np.asarray(self.center, float), float(np.linalg.norm(self.half_m))

    def intersect(self, o: Arr, d: Arr) -> Arr:
        R = np.asarray(self.R)
        c = np.asarray(self.center)
        h = np.asarray(self.half_m)
        tn = np.full(d.shape[0], -np.inf)
        tf = np.full(d.shape[0], np.inf)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for k in range(3):
                ax = R[:, k]
                ok = float((np.asarray(o, float) - c) @ ax)
                dk = d @ ax
                inv = 1.0 / np.where(np.abs(dk) < 1e-15, 1e-15, dk)
                t1 = (-h[k] - ok) * inv
                t2 = (h[k] - ok) * inv
                np.maximum(tn, np.minimum(t1, t2), out=tn)
                np.minimum(tf, np.maximum(t1, t2), out=tf)
        hit = (tn <= tf) & (tf > T_MIN)
        t = np.where(tn > T_MIN, tn, tf)
        return np.where(hit, t, np.inf)

    def surface(self, p: Arr) -> tuple[Arr, Arr, Arr]:
        R = np.asarray(self.R)
        h = np.asarray(self.half_m)
        pl = (p - np.asarray(self.center)) @ R
        rel = np.abs(pl) / h
        face = np.argmax(rel, axis=1)
        nl = np.zeros_like(pl)
        nl[np.arange(len(pl)), face] = np.sign(pl[np.arange(len(pl)), face])
        # surface coords: the two other local axes, offset by the face index so faces differ
        ua = np.take_along_axis(pl, ((face + 1) % 3)[:, None], axis=1)[:, 0]
        va = np.take_along_axis(pl, ((face + 2) % 3)[:, None], axis=1)[:, 0]
        off = face * 3.7 + (nl.sum(axis=1) > 0) * 1.3
        return ua + off, va - off, nl @ R.T


@dataclass(frozen=True)
class Sphere:
    """A sphere; surface coordinates are (longitude, latitude) arc lengths in metres."""

    center: Arr
    radius_m: float
    texture: TextureSpec = field(default_factory=TextureSpec)
    name: str = "sphere"

    def bounds(self) -> tuple[Arr, float] | None:
        return np.asarray(self.center, float), float(self.radius_m)

    def intersect(self, o: Arr, d: Arr) -> Arr:
        oc = np.asarray(o, float) - np.asarray(self.center)
        b = d @ oc
        c = float(oc @ oc) - self.radius_m**2
        disc = b * b - c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0 = -b - sq
        t1 = -b + sq
        t = np.where(t0 > T_MIN, t0, t1)
        return np.where((disc >= 0) & (t > T_MIN), t, np.inf)

    def surface(self, p: Arr) -> tuple[Arr, Arr, Arr]:
        q = p - np.asarray(self.center)
        n = q / self.radius_m
        lon = np.arctan2(n[:, 0], n[:, 2])
        lat = np.arcsin(np.clip(-n[:, 1], -1.0, 1.0))
        return lon * self.radius_m, lat * self.radius_m, n


@dataclass(frozen=True)
class Cylinder:
    """A vertical closed cylinder standing on ``base`` (3,) (its axis points up, i.e. world -y)."""

    base: Arr
    radius_m: float
    height_m: float
    texture: TextureSpec = field(default_factory=TextureSpec)
    name: str = "cylinder"

    def bounds(self) -> tuple[Arr, float] | None:
        c = np.asarray(self.base, float) - np.array([0.0, self.height_m / 2, 0.0])
        return c, float(np.hypot(self.radius_m, self.height_m / 2))

    def intersect(self, o: Arr, d: Arr) -> Arr:
        base = np.asarray(self.base)
        o = np.asarray(o, float)
        ox, oz = o[0] - base[0], o[2] - base[2]
        dx, dz = d[:, 0], d[:, 2]
        a = dx * dx + dz * dz
        b = ox * dx + oz * dz
        c = ox * ox + oz * oz - self.radius_m**2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = np.stack([(-b - sq) / a, (-b + sq) / a], axis=1)
        hgt = -(o[1] + ts * d[:, 1:2] - base[1])  # height above the base
        ok_side = (disc >= 0)[:, None] & (a > 1e-15)[:, None] & (ts > T_MIN) & (hgt >= 0) & (hgt <= self.height_m)
        t_side = np.where(ok_side, ts, np.inf).min(axis=1)
        caps = []
        for level in (0.0, self.height_m):
            y = base[1] - level
            with np.errstate(divide="ignore", invalid="ignore"):
                tc = (y - o[1]) / d[:, 1]
            px = ox + tc * dx
            pz = oz + tc * dz
            okc = (np.abs(d[:, 1]) > 1e-15) & (tc > T_MIN) & (px * px + pz * pz <= self.radius_m**2)
            caps.append(np.where(okc, tc, np.inf))
        return np.minimum(t_side, np.minimum(caps[0], caps[1]))

    def surface(self, p: Arr) -> tuple[Arr, Arr, Arr]:
        base = np.asarray(self.base)
        q = p - base
        hgt = -q[:, 1]
        rad = np.hypot(q[:, 0], q[:, 2])
        on_cap = ((np.abs(hgt) < 1e-7) | (np.abs(hgt - self.height_m) < 1e-7)) & (rad < self.radius_m * (1 - 1e-7))
        ang = np.arctan2(q[:, 0], q[:, 2])
        n_side = np.stack([q[:, 0], np.zeros_like(rad), q[:, 2]], axis=1) / np.maximum(rad, 1e-12)[:, None]
        top = hgt > self.height_m / 2
        n_cap = np.zeros_like(p)
        n_cap[:, 1] = np.where(top, -1.0, 1.0)
        n = np.where(on_cap[:, None], n_cap, n_side)
        u = np.where(on_cap, q[:, 0] + 5.0, ang * self.radius_m)
        v = np.where(on_cap, q[:, 2], hgt)
        return u, v, n


Primitive = Quad | Box | Sphere | Cylinder


def _cone_cull(prim, o: Arr, d: Arr) -> NDArray[np.int64] | None:
    """Indices of the rays (all from ``o``) that can hit ``prim``'s bounding sphere, or None (test all)."""
    b = prim.bounds() if hasattr(prim, "bounds") else None
    if b is None:
        return None
    c, r = b
    w = c - o
    dist = float(np.linalg.norm(w))
    if dist <= r * 1.001:
        return None  # origin inside the bounding sphere
    cos_lim = np.sqrt(1.0 - (r / dist) ** 2) - 1e-9
    return np.nonzero(d @ (w / dist) >= cos_lim)[0]


def cast(prims: list, o: Arr, d: Arr, chunk: int = 1 << 19, exclude: NDArray[np.int32] | None = None
         ) -> tuple[Arr, NDArray[np.int32]]:
    """Nearest hit of each ray over all primitives (all rays leave one point: a camera or the projector).

    Args:
        prims: the primitives.
        o: (3,) the rays' common origin (m).
        d: (N, 3) unit ray directions.
        chunk: rays per batch (bounds memory).
        exclude: (N,) per-ray primitive index to ignore (-1 = none): the second hit behind a closed object.

    Returns:
        ``t`` (N,) metres along the ray (inf = no hit) and ``idx`` (N,) primitive index (-1 = no hit).
    """
    d = np.asarray(d, dtype=np.float64)
    N = d.shape[0]
    o = np.asarray(o, dtype=np.float64).reshape(3)
    t_best = np.full(N, np.inf)
    idx = np.full(N, -1, dtype=np.int32)
    for s in range(0, N, chunk):
        sl = slice(s, min(N, s + chunk))
        tb = t_best[sl]
        ib = idx[sl]
        ds = d[sl]
        ex = None if exclude is None else exclude[sl]
        for k, prim in enumerate(prims):
            sub = _cone_cull(prim, o, ds)
            if sub is None:
                t = prim.intersect(o, ds)
                better = t < tb
                if ex is not None:
                    better &= ex != k
                tb[better] = t[better]
                ib[better] = k
            elif sub.size:
                t = prim.intersect(o, ds[sub])
                better = t < tb[sub]
                if ex is not None:
                    better &= ex[sub] != k
                tb[sub[better]] = t[better]
                ib[sub[better]] = k
    return t_best, idx


def shade_albedo(prims: list, p: Arr, idx: NDArray[np.int32], albedo: bool = True) -> tuple[NDArray[np.float32], Arr]:
    """Albedo (N, 3) and unit normal (N, 3) at hit points ``p`` (N, 3) of primitives ``idx`` (N,), -1 = none
    (``albedo=False`` skips the textures and returns zeros for them)."""
    N = p.shape[0]
    alb = np.zeros((N, 3), np.float32)
    nrm = np.zeros((N, 3))
    for k, prim in enumerate(prims):
        m = np.nonzero(idx == k)[0]
        if m.size == 0:
            continue
        u, v, n = prim.surface(p[m])
        if albedo:
            alb[m] = evaluate(prim.texture, u, v)
        nrm[m] = n
    return alb, nrm
