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
