"""Camera-camera correspondences through the projector code, and ray-midpoint triangulation.

3DUNDERWORLD intersects every pair of camera pixels sharing a projector pixel (quadratic per bucket). Here the
other camera's pixels are first **averaged per projector pixel** (bucket centroids, ``np.bincount``), giving a
map projector pixel -> pixel of the other camera. Each reference pixel gets a sub-pixel projector coordinate
(valid-only Gaussian mean of its integer code over about one projector-pixel footprint), the centroid map is
sampled there bilinearly, the match is refined by Newton steps on the other camera's smoothed code maps, and the
two rays are intersected (midpoint of the common perpendicular, as 3DUNDERWORLD). The depth lands directly on the reference (DP) camera's own pixel grid,
so there is no rectify -> unrectify round trip (the rectification is still computed and saved with the
calibration).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration


def normalised_rays(cam: CameraCalibration) -> NDArray[np.float32]:
    """(H, W, 2) undistorted normalised coordinates ``(x/z, y/z)`` of every pixel centre of ``cam``."""
    W, H = cam.image_size
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    pts = np.stack([xs, ys], -1).reshape(-1, 2)
    return undistort_px(pts, cam).reshape(H, W, 2).astype(np.float32)


def undistort_px(points_px: NDArray[np.floating], cam: CameraCalibration) -> NDArray[np.float64]:
    """(N, 2) pixel positions -> (N, 2) float64 undistorted normalised coordinates ``(x/z, y/z)``.

    ``cv2.undistortPoints``; without lens distortion (all coefficients 0) its fixed-point iteration is the
    identity and the result is ``((u - cx) / fx, (v - cy) / fy)``, computed here directly (5-10x faster).
    """
    pts = np.asarray(points_px, np.float64).reshape(-1, 2)
    if np.any(np.asarray(cam.dist) != 0):
        return cv2.undistortPoints(pts.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)
    K = np.asarray(cam.K, np.float64)
    return np.column_stack([(pts[:, 0] - K[0, 2]) / K[0, 0], (pts[:, 1] - K[1, 2]) / K[1, 1]])


def smooth_code(code: NDArray[np.int32], valid: NDArray[np.bool_], sigma_px: float, min_support: float = 0.3
                ) -> NDArray[np.float32]:
    r"""Valid-only Gaussian mean of an integer code (normalised convolution), a sub-pixel projector coordinate.

    .. math:: \hat c = \frac{G_\sigma * (c\,m)}{G_\sigma * m}

    A Gaussian with sigma about half the stripe footprint suppresses the staircase ripple (its transfer at the
    stripe frequency 1/p is exp(-2 pi^2 sigma^2 / p^2)); the integer code of pixel centres gives the projector
    pixel-centre coordinate, so the smoothed code is unbiased on smooth surfaces. Defined (not NaN) where the
    valid pixels carry at least ``min_support`` of the kernel's weight, which also bridges isolated invalid pixels.
    """
    c = np.where(valid, code, 0).astype(np.float32)
    m = valid.astype(np.float32)
    num = cv2.GaussianBlur(c, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(m, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[~(den >= min_support)] = np.nan
    return out


def smooth_codes(col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_], sigma_px: float,
                 min_support: float = 0.3) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """:func:`smooth_code` of the column and the row code of one validity mask, its denominator (the blurred
    mask) computed once for both (bit-identical to two :func:`smooth_code` calls)."""
    den = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    undefined = ~(den >= min_support)
    out = []
    for code in (col, row):
        num = cv2.GaussianBlur(np.where(valid, code, 0).astype(np.float32), (0, 0), sigma_px,
                               borderType=cv2.BORDER_CONSTANT)
        with np.errstate(invalid="ignore", divide="ignore"):
            np.divide(num, den, out=num)
        num[undefined] = np.nan
        out.append(num)
    return out[0], out[1]


def bucket_centroids_px(
    col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_], proj_size: tuple[int, int]
) -> tuple[NDArray[np.float32], int]:
    """Mean pixel position (x, y) of the camera pixels of each projector pixel, (Hp, Wp, 2), NaN where none,
    and the number of distinct projector pixels seen.

    This is 3DUNDERWORLD's bucket, averaged instead of enumerating all pixel pairs (linear, ``np.bincount``).
    """
    Wp, Hp = proj_size
    ys, xs = np.nonzero(valid)
    idx = row[valid].astype(np.int64) * Wp + col[valid]  # the same pixels, in the same (row-major) order
    n = np.bincount(idx, minlength=Wp * Hp).astype(np.float32)
    cen = np.empty((Hp, Wp, 2), np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        cen[..., 0] = (np.bincount(idx, weights=xs, minlength=Wp * Hp).astype(np.float32) / n).reshape(Hp, Wp)
        cen[..., 1] = (np.bincount(idx, weights=ys, minlength=Wp * Hp).astype(np.float32) / n).reshape(Hp, Wp)
    return cen, int(np.count_nonzero(n))


def _remap(img: NDArray[np.float32], x: NDArray[np.float32], y: NDArray[np.float32]) -> NDArray[np.float32]:
    return cv2.remap(img, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _centroid_samplers(cen: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A NaN-holed centroid map as the two images :func:`sample_centroids` remaps: (centroids with 0 at the
    holes, 1 where a centroid exists)."""
    ok = np.isfinite(cen[..., 0])
    return np.where(ok[..., None], cen, 0).astype(np.float32), ok.astype(np.float32)


def _sample_centroid_images(data: NDArray[np.float32], okf: NDArray[np.float32], u: NDArray[np.float32],
                            v: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    mu, mv = np.nan_to_num(u, nan=-10).astype(np.float32), np.nan_to_num(v, nan=-10).astype(np.float32)
    num = _remap(data, mu, mv)
    den = _remap(okf, mu, mv)
    with np.errstate(invalid="ignore", divide="ignore"):
        pts = num / den[..., None]
    return pts, den


def sample_centroids(cen: NDArray[np.float32], u: NDArray[np.float32], v: NDArray[np.float32]
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Bilinear sample of a NaN-holed centroid map at projector coordinates (u, v), weights renormalised over
    the valid neighbours. Returns (points (..., 2), weight (...)); weight 0 = no neighbour."""
    return _sample_centroid_images(*_centroid_samplers(cen), u, v)


def midpoint_triangulate(
    a: NDArray[np.float64], b_other: NDArray[np.float64], R: NDArray[np.float64], T: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Midpoint of the common perpendicular of two rays (3DUNDERWORLD), in the reference frame.

    Args:
        a: (N, 3) ray directions in the reference camera (through its centre, the origin).
        b_other: (N, 3) ray directions in the other camera's frame; ``X_other = R X_ref + T``, T in metres.

    Returns:
        points (N, 3) metres in the reference frame (NaN behind a camera), gap (N,) metres between the rays.
    """
    C = -R.T @ T  # other camera centre in the reference frame
    b = b_other @ R  # rows R^T b
    ax, ay, az = a.T
    bx, by, bz = b.T
    aa = ax * ax + ay * ay + az * az  # per-component sums: half the time of einsum / norm on (N, 3)
    bb = bx * bx + by * by + bz * bz
    ab = ax * bx + ay * by + az * bz
    aC = a @ C
    bC = b @ C
    det = ab * ab - aa * bb
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = (ab * bC - bb * aC) / det
        mu = (aa * bC - ab * aC) / det
    pa = lam[:, None] * a
    pb = C[None, :] + mu[:, None] * b
    d = pa - pb
    gap = np.sqrt(np.einsum("ij,ij->i", d, d))
    pts = 0.5 * (pa + pb)
    pts[(lam <= 0) | (mu <= 0)] = np.nan
    return pts, gap


def midpoint_depth(
    xa: NDArray[np.float64], ya: NDArray[np.float64], xb: NDArray[np.float64], yb: NDArray[np.float64],
    R: NDArray[np.float64], T: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Depth z and ray gap of :func:`midpoint_triangulate` for rays given by normalised coordinates.

    The same formula written per component for rays ``(xa, ya, 1)`` in the reference camera and ``(xb, yb, 1)``
    in the other one, without the (N, 3) temporaries (about 3x faster; equal to float64 rounding).

    Args:
        xa, ya: (N,) reference normalised coordinates; xb, yb: (N,) the other camera's.
        R, T: ``X_other = R X_ref + T``, T in metres.

    Returns:
        z (N,) metres in the reference frame (NaN behind a camera), gap (N,) metres between the rays.

    Computed ``TRIANGULATE_CHUNK`` rays at a time (each ray on its own, so the chunking changes no bit) so that the
    twenty float64 temporaries stay in the CPU caches.
    """
    xa, ya, xb, yb = (np.asarray(x, np.float64) for x in (xa, ya, xb, yb))
    z = np.empty(xa.shape, np.float64)
    gap = np.empty(xa.shape, np.float64)
    for i in range(0, xa.size, TRIANGULATE_CHUNK):
        c = slice(i, i + TRIANGULATE_CHUNK)
        z[c], gap[c] = _midpoint_depth_chunk(xa[c], ya[c], xb[c], yb[c], R, T)
    return z, gap


TRIANGULATE_CHUNK = 32768
"""Rays per chunk of :func:`midpoint_depth` and :func:`depth_from_match`."""


def _midpoint_depth_chunk(
    xa: NDArray[np.float64], ya: NDArray[np.float64], xb: NDArray[np.float64], yb: NDArray[np.float64],
    R: NDArray[np.float64], T: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`midpoint_depth` of one chunk of rays."""
    C = -R.T @ np.asarray(T, np.float64).ravel()  # other camera centre in the reference frame
    bx = R[0, 0] * xb + R[1, 0] * yb + R[2, 0]  # b = R^T (xb, yb, 1)
    by = R[0, 1] * xb + R[1, 1] * yb + R[2, 1]
    bz = R[0, 2] * xb + R[1, 2] * yb + R[2, 2]
    aa = xa * xa + ya * ya + 1.0
    bb = bx * bx + by * by + bz * bz
    ab = xa * bx + ya * by + bz
    aC = xa * C[0] + ya * C[1] + C[2]
    bC = bx * C[0] + by * C[1] + bz * C[2]
    det = ab * ab - aa * bb
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = (ab * bC - bb * aC) / det
        mu = (aa * bC - ab * aC) / det
    dx = lam * xa - C[0] - mu * bx
    dy = lam * ya - C[1] - mu * by
    dz = lam - C[2] - mu * bz
    gap = np.sqrt(dx * dx + dy * dy + dz * dz)
    z = 0.5 * (lam + C[2] + mu * bz)
    z[(lam <= 0) | (mu <= 0)] = np.nan
    return z, gap


@dataclass(frozen=True)
class TriangulationConfig:
    """Settings.

    Attributes:
        max_gap_px: largest ray gap, in reference-camera pixels at the point's depth (epipolar check).
        max_code_residual: largest |code(q) - code(ref)| after refinement, in projector pixels of the scale.
        newton_iters: refinement steps of the match in the other camera.
        sigma_factor: Gaussian sigma of the code smoothing = sigma_factor x footprint (camera px), at least 0.7.
    """

    max_gap_px: float = 1.5
    max_code_residual: float = 0.35
    newton_iters: int = 3
    sigma_factor: float = 0.8


class _ScaleCoordinates:
    """Projector coordinates of a scale ``2^-scale`` <-> full-scale projector coordinates."""

    scale: int

    def to_full(self, u: NDArray[np.float32]) -> NDArray[np.float32]:
        """Smoothed scale-s code -> projector coordinate at scale 1 (pixel centres at integers).

        The mean of ``x >> s`` over a region is ``x / 2^s - (2^s - 1) / 2^(s+1)``."""
        k = float(1 << self.scale)
        return (u + (k - 1) / (2 * k)) * k

    def from_full(self, x: NDArray[np.float32]) -> NDArray[np.float32]:
        """Inverse of :meth:`to_full`."""
        k = float(1 << self.scale)
        return x / k - (k - 1) / (2 * k)


@dataclass
class CentroidMap(_ScaleCoordinates):
    """The part of a :class:`CodeView` that :func:`match_in_other` uses of its ``coarse`` view: the bucket
    centroids, the footprint and the scale (no smoothed codes or gradients, which cost most of a view).

    Attributes: as :class:`CodeView`'s of the same names.
    """

    centroids: NDArray[np.float32]
    footprint_px: float
    scale: int = 0


def centroid_map(col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_],
                 proj_size: tuple[int, int], scale: int = 0) -> CentroidMap:
    """Bucket centroids and footprint of one camera at projector scale ``2^-scale`` (those of :func:`code_view`)."""
    cen, n_codes = bucket_centroids_px(col, row, valid, proj_size)
    fp = float(np.sqrt(valid.sum() / n_codes)) if n_codes else 1.0  # camera px per projector px (side)
    return CentroidMap(cen, fp, scale)


@dataclass
class CodeView(_ScaleCoordinates):
    """One camera's codes at one scale, prepared for matching.

    Attributes:
        u, v: (H, W) smoothed (sub-pixel) projector column/row, NaN where invalid.
        valid: (H, W) bool decode validity.
        centroids: (Hp, Wp, 2) mean pixel position per projector pixel.
        grads: (H, W, 4) du/dx, du/dy, dv/dx, dv/dy of the smoothed codes.
        footprint_px: camera pixels per projector pixel (side).
        scale: the projector scale exponent s (codes are ``code >> s``).
    """

    u: NDArray[np.float32]
    v: NDArray[np.float32]
    valid: NDArray[np.bool_]
    centroids: NDArray[np.float32]
    grads: NDArray[np.float32]
    footprint_px: float
    scale: int = 0


def code_view(col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_],
              proj_size: tuple[int, int], cfg: TriangulationConfig = TriangulationConfig(), scale: int = 0,
              centroids: CentroidMap | None = None) -> CodeView:
    """Smooth codes, their gradients and bucket centroids of one camera at projector scale ``2^-scale``
    (``centroids``: this camera's :func:`centroid_map` at this scale, when already computed)."""
    cm = centroid_map(col, row, valid, proj_size, scale) if centroids is None else centroids
    cen, fp = cm.centroids, cm.footprint_px
    sigma = max(0.7, cfg.sigma_factor * fp)
    u, v = smooth_codes(col, row, valid, sigma)
    g = np.empty(u.shape + (4,), np.float32)  # written in place of np.stack of the four
    for k, c in enumerate((u, v)):
        z = np.nan_to_num(c)
        np.divide(cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3), 8.0, out=g[..., 2 * k])
        np.divide(cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3), 8.0, out=g[..., 2 * k + 1])
    return CodeView(u, v, valid, cen, g, fp, scale)


MATCH_BLOCK_PX = 65536
"""Reference pixels per block of :func:`match_in_other` (whole rows): its per-pixel temporaries then stay in the
CPU caches instead of making a dozen full-image arrays per Newton step."""


def camera_px_per_projector_px(view: CodeView) -> float:
    """Side of one projector pixel of ``view``'s scale in camera pixels: median over the valid pixels of
    ``1 / sqrt(|det d(u, v)/d(x, y)|)`` of the smoothed codes (below 1: the camera cannot resolve that scale's
    finest stripes). NaN when no pixel is valid."""
    a, b, c, d = (view.grads[..., k] for k in range(4))
    det = np.abs(a * d - b * c)[view.valid & np.isfinite(view.u) & np.isfinite(view.v)]
    det = det[det > 0]
    return float(1.0 / np.sqrt(np.median(det))) if det.size else float("nan")


def match_in_other(ref: CodeView, other: CodeView, cfg: TriangulationConfig = TriangulationConfig(),
                   coarse: CodeView | CentroidMap | None = None, block_px: int = MATCH_BLOCK_PX
                   ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """For every valid reference pixel, the sub-pixel point of the other camera with the same projector code.

    Start at the other camera's bucket centroid sampled at the reference's smoothed code, then Newton steps on
    the other camera's smoothed code maps: ``q <- q + J^-1 ((u, v)_ref - (u, v)_other(q))``. Where camera pixels
    are larger than this scale's projector pixels the centroid map is sparse; ``coarse`` (the other camera at a
    coarser scale, whose map is dense; only its centroids are used) then gives the start.

    Each reference pixel's match depends only on its own codes and the other camera's maps, so the reference
    grid is processed in blocks of whole rows (``block_px`` pixels or more; the result does not depend on it).

    Returns:
        q (H, W, 2) pixel coordinates in the other camera (NaN where unmatched), ok (H, W) bool.
    """
    H, W = ref.valid.shape
    cen_data, cen_ok = _centroid_samplers((other if coarse is None else coarse).centroids)
    # the other camera's code u, v and its validity in one 3-channel image: one remap per step samples all three
    # (each channel with the same bilinear weights as a remap of its own)
    codes_o = np.dstack([np.nan_to_num(other.u), np.nan_to_num(other.v),
                         (np.isfinite(other.u) & np.isfinite(other.v)).astype(np.float32)])
    step_max = 2.0 * max(1.0, other.footprint_px, 0.0 if coarse is None else coarse.footprint_px)
    q = np.empty((H, W, 2), np.float32)
    ok = np.empty((H, W), bool)
    rows = max(1, block_px // max(W, 1))
    for y0 in range(0, H, rows):
        b = slice(y0, min(H, y0 + rows))
        u, v = ref.u[b], ref.v[b]
        if coarse is None:
            qb, w = _sample_centroid_images(cen_data, cen_ok, u, v)
        else:
            qb, w = _sample_centroid_images(cen_data, cen_ok, coarse.from_full(ref.to_full(u)),
                                            coarse.from_full(ref.to_full(v)))
        okb = ref.valid[b] & np.isfinite(u) & np.isfinite(v) & (w > 0) & np.isfinite(qb[..., 0])
        q[b], ok[b] = _newton_block(qb, okb, np.nan_to_num(u), np.nan_to_num(v), codes_o, other.grads, step_max, cfg)
    return q, ok


def _newton_block(q: NDArray[np.float32], ok: NDArray[np.bool_], ur: NDArray[np.float32], vr: NDArray[np.float32],
                  codes_o: NDArray[np.float32], grads_o: NDArray[np.float32], step_max: float,
                  cfg: TriangulationConfig) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """:func:`match_in_other`'s Newton steps and residual test for one block of reference pixels: start ``q``
    (..., 2), where to match ``ok``, the reference codes ``ur, vr`` (0 where invalid), the other camera's
    3-channel codes image and its gradients."""
    qx, qy = np.ascontiguousarray(q[..., 0]), np.ascontiguousarray(q[..., 1])
    off = np.float32(-10)  # a map coordinate outside the image: samples 0 (invalid)
    for _ in range(max(1, cfg.newton_iters)):
        mx, my = np.where(ok, qx, off), np.where(ok, qy, off)
        sampled = _remap(codes_o, mx, my)
        gr = _remap(grads_o, mx, my)
        du = ur - sampled[..., 0]
        dv = vr - sampled[..., 1]
        a, b, c, d = gr[..., 0], gr[..., 1], gr[..., 2], gr[..., 3]
        det = a * d - b * c
        good = ok & (sampled[..., 2] > 0.999) & (np.abs(det) > 1e-8)
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = (d * du - b * dv) / det
            sy = (-c * du + a * dv) / det
        good &= (np.abs(sx) <= step_max) & (np.abs(sy) <= step_max)
        qx = np.where(good, qx + sx, qx)
        qy = np.where(good, qy + sy, qy)
        ok = good
    # residual after the last step
    sampled = _remap(codes_o, np.where(ok, qx, off), np.where(ok, qy, off))
    res = np.hypot(ur - sampled[..., 0], vr - sampled[..., 1])
    ok &= (sampled[..., 2] > 0.999) & (res <= cfg.max_code_residual)
    q = np.stack([qx, qy], -1)
    q[~ok] = np.nan
    return q, ok


def depth_from_match(
    ref_rays: NDArray[np.float32], ref_fx_px: float, q_px: NDArray[np.float32], ok: NDArray[np.bool_],
    other: CameraCalibration, R: NDArray[np.float64], T: NDArray[np.float64],
    cfg: TriangulationConfig = TriangulationConfig(),
) -> NDArray[np.float32]:
    """Depth z (metres, NaN invalid) on the reference grid by ray-midpoint triangulation of matched pixels.

    Args:
        ref_rays: (H, W, 2) reference normalised coordinates; ref_fx_px its focal length (px).
        q_px: (H, W, 2) matched pixel in the other camera; ok (H, W) where matched.
        other: the other camera's intrinsics; R, T: ``X_other = R X_ref + T`` (metres).
    """
    H, W = ok.shape
    depth = np.full((H, W), np.nan, np.float32)
    idx = np.flatnonzero(ok)  # row-major, as ``depth[ok]``
    if idx.size == 0:
        return depth
    q_flat, rays_flat, out = q_px.reshape(-1, 2), ref_rays.reshape(-1, 2), depth.reshape(-1)
    z_ok = np.empty(idx.size, np.float32)
    for i in range(0, idx.size, TRIANGULATE_CHUNK):  # each pixel on its own: the chunks change no bit
        c = slice(i, i + TRIANGULATE_CHUNK)
        qn = undistort_px(q_flat[idx[c]], other)
        a = rays_flat[idx[c]].astype(np.float64)
        z, gap = _midpoint_depth_chunk(a[:, 0], a[:, 1], qn[:, 0], qn[:, 1], R, T)
        with np.errstate(invalid="ignore", divide="ignore"):
            good = np.isfinite(z) & (z > 0) & (gap / z * ref_fx_px <= cfg.max_gap_px)
        z_ok[c] = np.where(good, z, np.nan)
    out[idx] = z_ok
    return depth
