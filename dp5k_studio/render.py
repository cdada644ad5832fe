"""Pinhole radiance, depth and structured light by ray casting (exact geometry, vectorized).

``view_geometry`` casts ``s x s`` rays per pixel from the camera centre into the scene and keeps, per
ray, what does not depend on the projector image: albedo, the studio light, the projector pixel that
lights the hit point and that light's gain. The projector's line of sight is tested by casting a shadow
ray from the projector centre to the point. ``ViewGeometry.radiance(pattern)`` then forms

    L = albedo * (ambient + key * max(0, n . l) + P[x_p] * lumens_rel * max(0, n . w_p) * (2 m / d_p)^2)

with ``w_p`` the unit vector toward the projector, ``d_p`` its distance (m), ``P[x_p]`` the pattern at the
nearest projector pixel (0 where the projector does not see the point), box-averaged over the
supersamples. A new pattern costs one gather, so 92 structured-light frames cost little more than one.
Depth is z along the camera axis (metres) at pixel centres.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from .geometry import cast, shade_albedo
from .rig import CameraModel, ProjectorModel


@dataclass
class ViewGeometry:
    """Pattern-independent ray-cast result of one camera.

    Attributes:
        height, width, ss: image size (px) and supersampling factor.
        albedo: (N, 3) float32 per ray (N = H*ss*W*ss, row-major over (H, ss, W, ss)).
        base_light: (N,) float32 studio irradiance (ambient + key light).
        proj_index: (N,) int64 flat index ``iy * Wp + ix`` of the projector pixel lighting the ray's point,
            -1 where the projector does not see it.
        proj_gain: (N,) float32 projector irradiance per unit pattern value.
        depth_m: (H, W) float64 z-depth at pixel centres (inf = no surface).
        proj_xy: (H, W, 2) float64 continuous projector coordinates of the pixel-centre point (NaN = unlit).
        prim: (H, W) int32 primitive index at pixel centres (-1 = none).
        hidden: the surface behind the visible one at pixel centres (the next hit on another primitive),
            or None: dict with ``depth_m`` (H, W) (inf = none), ``albedo`` (H*W, 3), ``base_light``,
            ``proj_index``, ``proj_gain`` (H*W,). Used for partial occlusion at depth edges.
    """

    height: int
    width: int
    ss: int
    albedo: NDArray[np.float32]
    base_light: NDArray[np.float32]
    proj_index: NDArray[np.int64]
    proj_gain: NDArray[np.float32]
    depth_m: NDArray[np.float64]
    proj_xy: NDArray[np.float64]
    prim: NDArray[np.int32]
    hidden: dict | None = None

    @cached_property
    def _lit(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float32]]:
        """Rays the projector lights: their index, their projector pixel (flat) and gain (n, 1)."""
        lit = np.flatnonzero(self.proj_index >= 0)
        return lit, self.proj_index[lit], self.proj_gain[lit][:, None]

    @cached_property
    def _hidden_lit(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float32]]:
        """:attr:`_lit` of the hidden surfaces."""
        assert self.hidden is not None
        lit = np.flatnonzero(self.hidden["proj_index"] >= 0)
        return lit, self.hidden["proj_index"][lit], self.hidden["proj_gain"][lit][:, None]

    def hidden_radiance(self, pattern: NDArray[np.float32] | None) -> NDArray[np.float32] | None:
        """(H, W, 3) radiance of the hidden surfaces under a projector image (None if not computed)."""
        if self.hidden is None:
            return None
        h = self.hidden
        light = _lighting(h["base_light"], pattern, *self._hidden_lit)
        return (h["albedo"] * light).reshape(self.height, self.width, 3).astype(np.float32)

    def radiance(self, pattern: NDArray[np.float32] | None) -> NDArray[np.float32]:
        """(H, W, 3) float32 radiance under a projector image ((Hp, Wp[, 3]) in [0, 1]) or None (dark)."""
        rad = self.albedo * _lighting(self.base_light, pattern, *self._lit)
        s = self.ss
        if s == 1:
            return rad.reshape(self.height, self.width, 3)
        return rad.reshape(self.height, s, self.width, s, 3).mean(axis=(1, 3), dtype=np.float32)


def _lighting(base_light: NDArray[np.float32], pattern: NDArray[np.float32] | None, lit: NDArray[np.int64],
              proj_pixel: NDArray[np.int64], gain: NDArray[np.float32]) -> NDArray[np.float32]:
    """Irradiance per ray, (N, 1) for a grey (or no) projector image, (N, 3) for a colour one: the studio
    light plus the pattern at each lit ray's projector pixel times its gain."""
    if pattern is None:
        return base_light[:, None]
    pat = pattern.reshape(pattern.shape[0] * pattern.shape[1], -1)
    light = np.repeat(base_light[:, None], pat.shape[1], axis=1)
    light[lit] += pat[proj_pixel] * gain
    return light


def pixel_rays(cam: CameraModel, xs: NDArray[np.float64], ys: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World unit directions (N, 3) for pixel coordinates (N,), and each ray's z-component in the camera
    frame (N,) (so z-depth = t * zc). Distortion-free pinhole."""
    K = cam.K
    xn = (xs - K[0, 2] - K[0, 1] * (ys - K[1, 2]) / K[1, 1]) / K[0, 0]
    yn = (ys - K[1, 2]) / K[1, 1]
    inv = 1.0 / np.sqrt(xn * xn + yn * yn + 1.0)
    R = cam.R
    d = np.empty((xs.shape[0], 3))
    for k in range(3):  # world = R^T cam
        d[:, k] = (R[0, k] * xn + R[1, k] * yn + R[2, k]) * inv
    return d, inv


def project(K: NDArray[np.float64], R: NDArray[np.float64], t: NDArray[np.float64], X: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pinhole projection of world points (N, 3): pixel coordinates (N, 2) and z in that frame (N,)."""
    Xc = [X[:, 0] * R[k, 0] + X[:, 1] * R[k, 1] + X[:, 2] * R[k, 2] + t[k] for k in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = Xc[0] / Xc[2]
        y = Xc[1] / Xc[2]
    uv = np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)
    return uv, Xc[2]


def projector_visibility(prims: list, proj: ProjectorModel, X: NDArray[np.float64], n: NDArray[np.float64]
                         ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float32]]:
    """For world points X (N, 3) with normals n (N, 3) facing the camera: continuous projector coordinates
    (N, 2) (NaN where unlit), flat nearest projector pixel index (N,) (-1 = unlit) and irradiance gain (N,)."""
    N = X.shape[0]
    uv, zp = project(proj.K, proj.R, proj.t, X)
    Cp = proj.center_m
    w = Cp[None, :] - X
    dist = np.sqrt(np.einsum("ij,ij->i", w, w))
    w /= np.maximum(dist, 1e-12)[:, None]
    with np.errstate(invalid="ignore"):
        ix = np.rint(uv[:, 0])
        iy = np.rint(uv[:, 1])
        inside = (zp > 0) & (ix >= 0) & (ix < proj.width) & (iy >= 0) & (iy < proj.height)
    sel = np.nonzero(inside)[0]
    lit = np.zeros(N, bool)
    if sel.size:
        t_hit, _ = cast(prims, Cp, -w[sel])
        lit[sel] = t_hit >= dist[sel] * (1.0 - 1e-7) - 1e-6
    cosf = np.clip(np.einsum("ij,ij->i", n, w), 0.0, 1.0)
    lit &= cosf > 0
    index = np.where(lit, iy * proj.width + ix, -1).astype(np.int64)
    gain = np.where(lit, proj.lumens_rel * cosf * (2.0 / np.maximum(dist, 1e-6)) ** 2, 0.0).astype(np.float32)
    return np.where(lit[:, None], uv, np.nan), index, gain


def view_geometry(scene, cam: CameraModel, projector: ProjectorModel | None, extra_prims: tuple = (), supersample: int = 2,
                  chunk: int = 1 << 18, hidden: bool = True) -> ViewGeometry:
    """Ray-cast one camera (see module docstring).

    Args:
        scene: the :class:`~.scenes.Scene`.
        cam: the camera (its width/height set the resolution).
        projector: the projector model, or None to skip the projector (no shadow rays; proj_xy all NaN).
        extra_prims: more primitives (the ChArUco board).
        supersample: ``s`` x ``s`` rays per pixel for the radiance (box filter); with odd ``s`` the centre
            ray is one of them, with even ``s`` one more ray per pixel centre is cast for depth.
        hidden: also find the surface behind the visible one at each pixel centre (one more ray cast).
    """
    prims = list(scene.prims) + list(extra_prims)
    H, W = cam.height, cam.width
    s = max(1, int(supersample))
    off = (np.arange(s) + 0.5) / s - 0.5
    ys = (np.arange(H)[:, None] + off[None, :]).ravel()
    xs = (np.arange(W)[:, None] + off[None, :]).ravel()
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    N = yy.size
    albedo = np.zeros((N, 3), np.float32)
    base = np.zeros(N, np.float32)
    pidx = np.full(N, -1, np.int64)
    pgain = np.zeros(N, np.float32)
    depth_all = np.full(N, np.inf)
    puv_all = np.full((N, 2), np.nan)
    prim_all = np.full(N, -1, np.int32)
    xr, yr = xx.ravel(), yy.ravel()
    C = cam.center_m
    ldir = np.asarray(scene.light_dir, dtype=np.float64)
    odd = s % 2 == 1
    for s0 in range(0, N, chunk):
        sl = slice(s0, min(N, s0 + chunk))
        d, zc = pixel_rays(cam, xr[sl], yr[sl])
        t, idx = cast(prims, C, d)
        hit = idx >= 0
        X = C[None, :] + np.where(hit, t, 0.0)[:, None] * d
        alb, n = shade_albedo(prims, X, idx)
        flip = np.einsum("ij,ij->i", n, d) > 0
        n[flip] *= -1.0
        albedo[sl] = alb
        base[sl] = np.where(hit, scene.ambient + scene.key_light * np.clip(n @ ldir, 0.0, 1.0), 0.0)
        depth_all[sl] = np.where(hit, t * zc, np.inf)
        prim_all[sl] = idx
        if projector is not None:
            h = np.nonzero(hit)[0]
            uv, pi, pg = projector_visibility(prims, projector, X[h], n[h])
            pidx[s0 + h] = pi
            pgain[s0 + h] = pg
            puv_all[s0 + h] = uv
    if odd:
        # pixel centres are the middle supersamples
        c = s // 2
        depth = depth_all.reshape(H, s, W, s)[:, c, :, c].copy()
        puv = puv_all.reshape(H, s, W, s, 2)[:, c, :, c].copy()
        prim = prim_all.reshape(H, s, W, s)[:, c, :, c].copy()
    else:
        yc, xc = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
        d, zc = pixel_rays(cam, xc.ravel(), yc.ravel())
        t, idx = cast(prims, C, d)
        hit = idx >= 0
        depth = np.where(hit, t * zc, np.inf).reshape(H, W)
        prim = idx.reshape(H, W)
        puv = np.full((hit.size, 2), np.nan)
        if projector is not None:
            X = C[None, :] + np.where(hit, t, 0.0)[:, None] * d
            _, n = shade_albedo(prims, X, idx, albedo=False)
            flip = np.einsum("ij,ij->i", n, d) > 0
            n[flip] *= -1.0
            h = np.nonzero(hit)[0]
            puv[h] = projector_visibility(prims, projector, X[h], n[h])[0]
        puv = puv.reshape(H, W, 2)
    hid = _hidden_layer(prims, scene, cam, projector, prim) if hidden else None
    return ViewGeometry(H, W, s, albedo, base, pidx, pgain, depth, puv, prim, hid)


HIDDEN_BAND_FRAC = 0.06
"""Hidden surfaces are found within ``max(8 px, 0.06 W)`` of an occlusion edge (beyond that, a foreground's
blur that wide falls back to coverage normalization)."""


def _hidden_layer(prims: list, scene, cam: CameraModel, projector: ProjectorModel | None, prim: NDArray[np.int32]) -> dict:
    """Second hits at pixel centres near occlusion edges, skipping the visible primitive (so a closed
    object's back face is never taken for what lies behind it)."""
    import cv2

    H, W = prim.shape
    edge = np.zeros((H, W), bool)
    edge[:, 1:] |= prim[:, 1:] != prim[:, :-1]
    edge[:, :-1] |= prim[:, 1:] != prim[:, :-1]
    edge[1:, :] |= prim[1:, :] != prim[:-1, :]
    edge[:-1, :] |= prim[1:, :] != prim[:-1, :]
    band = max(8.0, HIDDEN_BAND_FRAC * W)
    dist = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3)
    sel = np.nonzero(((dist <= band) & (prim >= 0)).ravel())[0]
    depth = np.full(H * W, np.inf)
    alb = np.zeros((H * W, 3), np.float32)
    base = np.zeros(H * W, np.float32)
    pidx = np.full(H * W, -1, np.int64)
    pgain = np.zeros(H * W, np.float32)
    if sel.size:
        d, zc = pixel_rays(cam, (sel % W).astype(np.float64), (sel // W).astype(np.float64))
        C = cam.center_m
        t, idx = cast(prims, C, d, exclude=prim.ravel()[sel])
        hit = idx >= 0
        h = sel[hit]
        depth[h] = t[hit] * zc[hit]
        X = C[None, :] + t[hit][:, None] * d[hit]
        a, n = shade_albedo(prims, X, idx[hit])
        flip = np.einsum("ij,ij->i", n, d[hit]) > 0
        n[flip] *= -1.0
        alb[h] = a
        ldir = np.asarray(scene.light_dir, dtype=np.float64)
        base[h] = scene.ambient + scene.key_light * np.clip(n @ ldir, 0.0, 1.0)
        if projector is not None:
            _, pi, pg = projector_visibility(prims, projector, X, n)
            pidx[h] = pi
            pgain[h] = pg
    return {"depth_m": depth.reshape(H, W), "albedo": alb, "base_light": base, "proj_index": pidx, "proj_gain": pgain}
