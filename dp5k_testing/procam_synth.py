"""Synthetic inputs for the processing tests: a board or a projector image seen by a pinhole camera."""

from __future__ import annotations

import cv2
import numpy as np

from calib.board import BoardSpec


def rot(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    """Rotation matrix from XYZ Euler angles in degrees."""
    return cv2.Rodrigues(np.radians([rx_deg, 0, 0]))[0] @ cv2.Rodrigues(np.radians([0, ry_deg, 0]))[0] @ \
        cv2.Rodrigues(np.radians([0, 0, rz_deg]))[0]


def pixel_rays(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W, 2) undistorted normalised coordinates of every pixel centre."""
    W, H = size
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([xs, ys], -1).reshape(-1, 1, 2)
    return cv2.undistortPoints(pts, K, dist).reshape(H, W, 2)


def render_plane_texture(texture: np.ndarray, m_per_px: float, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                         dist: np.ndarray, size: tuple[int, int], background: float = 255.0,
                         supersample: int = 2) -> np.ndarray:
    """Image of a planar texture (plane frame: x right, y down, z=0; texel (0,0) centred at m_per_px/2)
    posed by ``X_cam = R X_plane + t`` (metres), float32 (H, W)."""
    W, H = size
    s = supersample
    Ks = K.copy()
    Ks[:2] *= s
    Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    rays = pixel_rays(Ks, dist, (W * s, H * s))
    Hm = np.column_stack([R[:, 0], R[:, 1], t])  # plane (x, y, 1) -> ray (x, y, 1) up to scale
    Hinv = np.linalg.inv(Hm)
    r = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], -1) @ Hinv.T
    bx = r[..., 0] / r[..., 2] / m_per_px - 0.5
    by = r[..., 1] / r[..., 2] / m_per_px - 0.5
    img = cv2.remap(texture.astype(np.float32), bx.astype(np.float32), by.astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    return cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)


def render_board(spec: BoardSpec, R: np.ndarray, t: np.ndarray, K: np.ndarray, dist: np.ndarray,
                 size: tuple[int, int], px_per_square: int = 64) -> np.ndarray:
    """uint8 (H, W) image of the board posed by ``X_cam = R X_board + t``."""
    tex = spec.image(px_per_square)
    img = render_plane_texture(tex, spec.square_m / px_per_square, R, t, K, dist, size)
    return np.clip(img, 0, 255).astype(np.uint8)


class PlaneScene:
    """A world of planes ``n . X = d`` (world = camera-0 frame, metres); each plane optionally bounded in x, y."""

    def __init__(self, planes: list[tuple[np.ndarray, float, tuple[float, float, float, float] | None]]):
        self.planes = [(np.asarray(n, float) / np.linalg.norm(n), float(d), box) for n, d, box in planes]

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N, 3) nearest intersection of rays origin + l * dirs (NaN where none)."""
        best = np.full(dirs.shape[0], np.inf)
        for n, d, box in self.planes:
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = (d - n @ origin) / (dirs @ n)
            X = origin + lam[:, None] * dirs
            ok = lam > 0
            if box is not None:
                x0, x1, y0, y1 = box
                ok &= (X[:, 0] >= x0) & (X[:, 0] <= x1) & (X[:, 1] >= y0) & (X[:, 1] <= y1)
            best = np.where(ok & (lam < best), lam, best)
        best[~np.isfinite(best)] = np.nan
        return origin + best[:, None] * dirs


def world_points(scene: PlaneScene, K, dist, R, t, size, supersample=1):
    """World points seen by the (supersampled) pixels of a camera ``X_cam = R X_world + t``: (H*s, W*s, 3)."""
    W, H = size
    s = supersample
    Ks = K.copy()
    Ks[:2] *= s
    Ks[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    rays = pixel_rays(Ks, dist, (W * s, H * s)).reshape(-1, 2)
    d_cam = np.concatenate([rays, np.ones((rays.shape[0], 1))], 1)
    d_world = d_cam @ R  # R^T d
    origin = -R.T @ t
    return scene.hit(origin, d_world).reshape(H * s, W * s, 3)


def render_projection(patterns, proj, cam, scene, supersample=3, ambient=0.02, gain=1.0, albedo=None,
                      noise=0.0, rng=None, blur_sigma=0.0):
    """Images (float32 in [0, 1]) one camera sees of each projector image, and the camera's true z-depth (m).

    proj, cam: dicts with K, dist, R, t (world -> device) and size (W, H).
    """
    s = supersample
    Xw = world_points(scene, cam["K"], cam["dist"], cam["R"], cam["t"], cam["size"], s)
    flat = Xw.reshape(-1, 3)
    Xp = flat @ proj["R"].T + proj["t"]
    uv, _ = cv2.projectPoints(np.nan_to_num(Xp), np.zeros(3), np.zeros(3), proj["K"], proj["dist"])
    uv = uv.reshape(Xw.shape[:2] + (2,)).astype(np.float32)
    uv[~np.isfinite(Xw[..., 0]) | (Xp[:, 2].reshape(Xw.shape[:2]) <= 0)] = -10
    Xc = Xw.reshape(-1, 3) @ cam["R"].T + cam["t"]
    W, H = cam["size"]
    center = Xc.reshape(H * s, W * s, 3)[s // 2::s, s // 2::s, 2]
    out = []
    for pat in patterns:
        img = cv2.remap(pat.astype(np.float32) / 255.0, uv[..., 0], uv[..., 1], cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        a = 1.0 if albedo is None else albedo
        img = gain * a * img + ambient
        if noise > 0:
            img = img + rng.normal(0, noise, img.shape)
        out.append(img.astype(np.float32))
    return out, center.astype(np.float32)


def look_at_rig(baseline=0.1, z=1.2, f_px=300.0, size=(240, 160), proj_size=(320, 200), proj_f=None):
    """Two cameras (cam0 at the origin, cam1 at +x baseline, toed in) and a projector between them, all aimed at
    (0, 0, z). Returns cam0, cam1, projector dicts (world = cam0 frame)."""
    W, H = size
    K = np.array([[f_px, 0, (W - 1) / 2], [0, f_px, (H - 1) / 2], [0, 0, 1]])
    toe = np.degrees(np.arctan2(baseline, z))
    R1 = rot(0, -toe, 0)
    c1 = np.array([baseline, 0, 0])
    cam0 = dict(K=K, dist=np.zeros(5), R=np.eye(3), t=np.zeros(3), size=size)
    cam1 = dict(K=K, dist=np.array([-0.02, 0.0, 0, 0, 0]), R=R1, t=-R1 @ c1, size=size)
    Wp, Hp = proj_size
    fp = proj_f if proj_f is not None else f_px * Wp / W * 0.8
    Kp = np.array([[fp, 0, Wp / 2], [0, fp, Hp / 2], [0, 0, 1]])
    Rp = rot(2, -np.degrees(np.arctan2(baseline / 2, z)), 0)
    cp = np.array([baseline / 2, -0.03, 0])
    proj = dict(K=Kp, dist=np.zeros(5), R=Rp, t=-Rp @ cp, size=proj_size)
    return cam0, cam1, proj
