"""Indoor-like studio scenes built from analytic primitives, seeded and deterministic.

Named presets (``make_scene(name, rig)``):

* ``"demo01"``: a room corner: slanted back wall, floor, a box, a sphere, a cylinder, a dark patch;
* ``"wall"``: a flat, nearly fronto-parallel textured wall at 2.2 m (the paper's depth-validation setup;
  place ``calib.board.WALL_BOARD`` on it with :func:`wall_board_pose`);
* ``"boxes"``: several textured boxes from 0.5 m to 4 m in front of a far wall;
* ``"near"``: close-up spheres from 0.26 m to 0.85 m in front of cam0, before a wall at 2.5 m;
* ``"plane"``: one fronto-parallel textured plane at 2.0 m (for optics tests).

Any ``int`` gives a random scene of that seed: a back wall 2.5..9 m away, slanted up to 30 deg, a floor,
sometimes a side wall, and 2..6 objects (boxes, spheres, cylinders) between 0.26 m and 4 m, textured with
noise, stripes, fine checkers and dark low-albedo blotches. Depth statistics over random scenes follow
the paper's (0.26 m .. 10 m, median near 2.7 m); ``tests/studio/test_rig_scenes.py`` checks it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError

from .geometry import Box, Cylinder, Quad, Sphere
from .rig import Rig
from .textures import TextureSpec

PRESETS: tuple[str, ...] = ("demo01", "wall", "boxes", "near", "plane")

FLOOR_Y_M = 0.45
"""Height of the cameras above the floor/table surface (floor plane at world y = +0.45 m)."""


@dataclass(frozen=True)
class Scene:
    """A static scene.

    Attributes:
        name: preset name or ``"rand<seed>"``.
        prims: the primitives (geometry.py).
        focus_target_m: (3,) world point the photographer focuses on (its image is the focus point).
        ambient: ambient irradiance (relative units; 1.0 = studio lights).
        light_dir: (3,) unit direction *towards* the key light (world frame).
        key_light: key light strength relative to ambient (Lambertian term).
        seed: the scene's seed.
    """

    name: str
    prims: tuple
    focus_target_m: NDArray[np.float64]
    ambient: float = 0.55
    light_dir: NDArray[np.float64] = field(default_factory=lambda: np.array([0.3, -0.8, -0.5]) / np.linalg.norm([0.3, -0.8, -0.5]))
    key_light: float = 0.45
    seed: int = 0


def _rand_color(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.85) -> tuple[float, float, float]:
    base = rng.uniform(lo, hi)
    tint = rng.normal(0.0, 0.12, 3)
    return tuple(float(x) for x in np.clip(base * (1 + tint), 0.03, 0.95))


def random_texture(rng: np.random.Generator, dark_p: float = 0.3) -> TextureSpec:
    """A random texture: noise, stripes or a fine checker, sometimes with dark blotches."""
    kind = rng.choice(["noise", "noise", "stripes", "checker"])
    scale = {"noise": rng.uniform(0.03, 0.3), "stripes": rng.uniform(0.01, 0.08), "checker": rng.uniform(0.004, 0.03)}[str(kind)]
    return TextureSpec(
        kind=str(kind),
        color_a=_rand_color(rng),
        color_b=_rand_color(rng),
        scale_m=float(scale),
        angle_deg=float(rng.uniform(0, 180)),
        dark_fraction=float(rng.uniform(0.1, 0.35)) if rng.random() < dark_p else 0.0,
        seed=int(rng.integers(0, 2**31 - 1)),
    )


def _wall(z_m: float, yaw_deg: float, tex: TextureSpec, half_w: float = 6.0, name: str = "wall") -> Quad:
    """A vertical wall through (0, 0, z) rotated by yaw about the vertical axis."""
    th = np.deg2rad(yaw_deg)
    u = np.array([np.cos(th), 0.0, -np.sin(th)])
    v = np.array([0.0, 1.0, 0.0])
    center = np.array([0.0, 0.0, z_m])
    origin = center - half_w * u - 4.0 * v
    return Quad(origin, u, v, (2 * half_w, 4.0 + FLOOR_Y_M), tex, name)


def _floor(tex: TextureSpec, z_far: float = 12.0) -> Quad:
    origin = np.array([-6.0, FLOOR_Y_M, 0.05])
    return Quad(origin, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), (12.0, z_far), tex, "floor")


def _yaw(deg: float) -> NDArray[np.float64]:
    th = np.deg2rad(deg)
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


RIG_HALF_BASELINE_M = 0.15
"""Half the default rig baseline; the bodies converge at 3 m (rig.py)."""


def _in_view(rng: np.random.Generator, z: float, margin: float = 0.7) -> tuple[float, float]:
    """A random (x, y) in view at depth z (half FOV ~11.6 x 7.8 deg). Closer than 0.8 m the two bodies'
    views no longer overlap, so near objects sit in front of one body (picked at random)."""
    x0 = 0.0
    if z < 0.8:
        x0 = float(rng.choice([-1.0, 1.0])) * RIG_HALF_BASELINE_M * (1.0 - z / 3.0)
    return x0 + float(rng.uniform(-0.2, 0.2) * z * margin), float(rng.uniform(-0.13, 0.13) * z * margin)


def _random_scene(seed: int) -> Scene:
    rng = np.random.default_rng(10007 + seed)
    prims: list = []
    z_back = float(np.exp(rng.uniform(np.log(2.5), np.log(9.0))))
    prims.append(_wall(z_back, float(rng.uniform(-30, 30)), random_texture(rng, 0.2), name="back_wall"))
    prims.append(_floor(random_texture(rng, 0.2)))
    if rng.random() < 0.5:
        side = rng.choice([-1.0, 1.0])
        x = side * rng.uniform(0.5, 1.2)
        origin = np.array([x, -3.0, 0.3])
        prims.append(Quad(origin, np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]), (12.0, 3.0 + FLOOR_Y_M),
                          random_texture(rng, 0.2), "side_wall"))
    n_obj = int(rng.integers(2, 7))
    targets = []
    for k in range(n_obj):
        z = float(np.exp(rng.uniform(np.log(0.26), np.log(0.8)))) if rng.random() < 0.25 else float(rng.uniform(0.8, min(4.0, z_back - 0.3)))
        x, y = _in_view(rng, z)
        size = float(rng.uniform(0.03, 0.12) * z + 0.005)
        tex = random_texture(rng)
        kind = rng.choice(["box", "sphere", "cylinder"])
        if kind == "box":
            half = np.array([size, size * rng.uniform(0.5, 1.5), size * rng.uniform(0.5, 1.5)])
            prims.append(Box(np.array([x, y, z + half[2]]), _yaw(float(rng.uniform(-45, 45))), half, tex, f"box{k}"))
        elif kind == "sphere":
            prims.append(Sphere(np.array([x, y, z + size]), size, tex, f"sphere{k}"))
        else:
            h = size * rng.uniform(1.5, 4.0)
            prims.append(Cylinder(np.array([x, y + h / 2, z + size]), size, h, tex, f"cylinder{k}"))
        targets.append(np.array([x, y, z]))
    focus = targets[int(rng.integers(0, len(targets)))] if rng.random() < 0.8 else np.array([0.0, 0.0, z_back])
    return Scene(f"rand{seed}", tuple(prims), focus, ambient=float(rng.uniform(0.45, 0.65)),
                 key_light=float(rng.uniform(0.3, 0.6)), seed=seed)


def _preset(name: str) -> Scene:
    rng = np.random.default_rng(sum(map(ord, name)))
    if name == "plane":
        tex = TextureSpec("noise", (0.75, 0.7, 0.6), (0.2, 0.25, 0.3), 0.05, seed=3)
        q = Quad(np.array([-5.0, -5.0, 2.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), (10.0, 10.0), tex, "plane")
        return Scene("plane", (q,), np.array([0.0, 0.0, 2.0]))
    if name == "wall":
        tex = TextureSpec("noise", (0.8, 0.78, 0.74), (0.55, 0.53, 0.5), 0.2, seed=5)
        return Scene("wall", (_wall(2.2, 8.0, tex, name="wall"), _floor(random_texture(rng, 0.0))), np.array([0.0, 0.0, 2.2]))
    if name == "demo01":
        prims = [
            _wall(5.0, 20.0, TextureSpec("noise", (0.8, 0.75, 0.65), (0.45, 0.4, 0.35), 0.25, dark_fraction=0.1, seed=11), name="back_wall"),
            _floor(TextureSpec("stripes", (0.55, 0.4, 0.25), (0.35, 0.24, 0.14), 0.06, angle_deg=90.0, seed=12)),
            Box(np.array([-0.25, 0.1, 2.4]), _yaw(25.0), np.array([0.2, 0.15, 0.2]),
                TextureSpec("checker", (0.85, 0.85, 0.8), (0.1, 0.1, 0.12), 0.02, seed=13), "box"),
            Sphere(np.array([0.3, 0.05, 1.6]), 0.12, TextureSpec("noise", (0.7, 0.2, 0.15), (0.9, 0.6, 0.3), 0.03, seed=14), "sphere"),
            Cylinder(np.array([0.05, 0.25, 3.5]), 0.15, 0.6, TextureSpec("stripes", (0.2, 0.5, 0.7), (0.8, 0.85, 0.9), 0.03, angle_deg=0.0, seed=15), "cylinder"),
            Box(np.array([-0.06, 0.03, 0.9]), _yaw(-10.0), np.array([0.05, 0.05, 0.03]),
                TextureSpec("noise", (0.03, 0.03, 0.03), (0.015, 0.015, 0.02), 0.01, seed=16), "dark_box"),
        ]
        return Scene("demo01", tuple(prims), np.array([-0.25, 0.1, 2.2]))
    if name == "boxes":
        prims = [_wall(7.0, -12.0, random_texture(rng, 0.0), name="back_wall"), _floor(random_texture(rng, 0.0))]
        for k, z in enumerate((0.5, 1.1, 1.9, 2.8, 4.0)):
            x, y = _in_view(rng, z, 0.6)
            s = 0.05 + 0.05 * z
            prims.append(Box(np.array([x, y, z + s]), _yaw(float(rng.uniform(-40, 40))), np.array([s, s, s]), random_texture(rng, 0.4), f"box{k}"))
        return Scene("boxes", tuple(prims), np.array([prims[4].center[0], prims[4].center[1], 1.9]))
    if name == "near":
        prims = [_wall(2.5, 5.0, random_texture(rng, 0.3), name="back_wall")]
        # close-ups spread across the view: the nearest at 0.26 m (the paper's minimum depth)
        spots = ((0.26, -0.35, 0.2), (0.4, 0.3, -0.3), (0.6, -0.1, 0.45), (0.85, 0.25, 0.1))
        for k, (z, fx, fy) in enumerate(spots):
            r = 0.006 + 0.03 * z
            # in front of cam0 (the bodies' views do not overlap this close)
            x, y = -RIG_HALF_BASELINE_M * (1 - z / 3.0) + fx * 0.2 * z, fy * 0.13 * z
            prims.append(Sphere(np.array([x, y, z + r]), r, random_texture(rng, 0.2), f"sphere{k}"))
        s3 = prims[3]
        return Scene("near", tuple(prims), np.asarray(s3.center) - np.array([0.0, 0.0, s3.radius_m]))
    raise BadInputError(f"unknown scene preset {name!r} (presets: {', '.join(PRESETS)}; or an integer seed)")


def make_scene(name_or_seed: str | int, rig: Rig | None = None) -> Scene:
    """A preset (by name) or a random scene (by integer seed, or a string of digits / ``"rand<seed>"``).

    ``rig`` is accepted for API symmetry (scenes are built in the rig's world frame, whose cameras sit at
    the origin looking down +z); the same scene serves every rig scale.
    """
    if isinstance(name_or_seed, (int, np.integer)):
        return _random_scene(int(name_or_seed))
    name = str(name_or_seed)
    if name.isdigit():
        return _random_scene(int(name))
    if name.startswith("rand") and name[4:].isdigit():
        return _random_scene(int(name[4:]))
    return _preset(name)


def plane_scene(z_m: float, texture: TextureSpec | None = None) -> Scene:
    """One fronto-parallel plane at world depth ``z_m`` (metres), for optics tests."""
    tex = texture or TextureSpec("noise", (0.75, 0.7, 0.6), (0.2, 0.25, 0.3), 0.05, seed=3)
    q = Quad(np.array([-50.0, -50.0, z_m]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), (100.0, 100.0), tex, "plane")
    return Scene(f"plane{z_m:g}", (q,), np.array([0.0, 0.0, z_m]))


def wall_board_pose(scene: Scene, board_size_m: tuple[float, float], offset_m: float = 0.001) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pose ``(R, t)`` (board -> world, ``X_w = R X_b + t``) that pastes a board on the ``"wall"`` preset.

    The board is centred on the wall's focus target, ``offset_m`` in front of the wall surface.
    """
    wall = next(p for p in scene.prims if isinstance(p, Quad) and p.name == "wall")
    u = np.asarray(wall.u_axis) / np.linalg.norm(wall.u_axis)
    v = np.asarray(wall.v_axis) / np.linalg.norm(wall.v_axis)
    n = np.cross(u, v)  # board z axis points into the wall, away from the camera
    if n[2] < 0:
        n = -n
    R = np.stack([u, v, n], axis=1)
    # point on the wall in front of the cameras
    o = np.asarray(wall.origin)
    t_hit = (o @ n) / n[2]
    center = np.array([0.0, 0.0, t_hit]) - offset_m * n
    t = center - R @ np.array([board_size_m[0] / 2, board_size_m[1] / 2, 0.0])
    return R, t
