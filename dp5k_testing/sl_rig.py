"""A small stereo Gray-code capture as ``dp5k sl-depth`` reads it (test support): two cameras and a projector
looking at a scene with depth structure, the images written as 8-bit PNG files, the true depth of camera 0 and
calibration files that are right or wrong in the ways a user's are (a drifted camera, T in metres, another rig).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dp5k_process.graycode import opencv_patterns

from .procam_synth import PlaneScene, look_at_rig, render_projection, rot

PROJECTOR = (320, 200)
"""The projector's resolution (``--projector 320x200``): 9 + 8 bits, 34 patterns + white + black."""


@dataclass(frozen=True)
class SLCapture:
    """A written capture.

    Attributes:
        images: the folder holding ``cam0/`` and ``cam1/`` (``im1.png`` ... ``im36.png``).
        depth_m: (H, W) true z-depth of camera 0 in metres (NaN where no surface).
        cam0, cam1: the rig (``procam_synth`` dicts: K, dist, R, t, size; world = camera 0).
    """

    images: Path
    depth_m: np.ndarray
    cam0: dict
    cam1: dict

    def write_calibration(self, path: Path, units: str = "mm", turn_deg: tuple[float, float, float] = (0, 0, 0),
                          T_m: np.ndarray | None = None) -> Path:
        """An OpenCV FileStorage YAML with K0, dist0, K1, dist1, R, T (T in ``units``): the true calibration, with
        cam1 turned by ``turn_deg`` (rotations about its x, y, z axes: pitch, yaw, roll) and/or another ``T_m``."""
        R = rot(*turn_deg) @ self.cam1["R"]
        T = self.cam1["t"] if T_m is None else np.asarray(T_m, float)
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        for k, cam in enumerate((self.cam0, self.cam1)):
            fs.write(f"K{k}", np.asarray(cam["K"], np.float64))
            fs.write(f"dist{k}", np.asarray(cam["dist"], np.float64))
        fs.write("R", R)
        fs.write("T", T * (1000.0 if units == "mm" else 1.0))
        fs.release()
        return path


def write_sl_capture(folder: Path, size: tuple[int, int] = (320, 240), gain: float = 0.8, ambient: float = 0.05,
                     albedo_sigma: float | None = None, seed: int = 0) -> SLCapture:
    """Render and write the capture: a turned back wall at ~1.6 m, a box face at 0.8 m and a sloping floor, seen by
    two cameras 0.12 m apart (f = size[0] px) and lit by a 320 x 200 projector between them.

    Args:
        gain, ambient: projector light and ambient light (fractions of full scale) on a white surface.
        albedo_sigma: None for a uniform scene; else the surfaces' reflectance falls off from the image centre as
            ``exp(-r^2 / sigma^2)`` (r in half image widths): a dark scene whose projector light clears the shadow
            threshold only in the middle.
    """
    W, H = size
    cam0, cam1, proj = look_at_rig(baseline=0.12, z=1.3, f_px=float(W), size=size, proj_size=PROJECTOR, proj_f=300.0)
    scene = PlaneScene([(np.array([0.3, 0.0, 1.0]), 1.7, None),
                        (np.array([0.0, 0.0, 1.0]), 0.9, (-0.4, 0.0, -0.3, 0.1)),
                        (np.array([-0.2, 0.0, 1.0]), 1.15, (0.1, 0.6, -0.35, 0.05)),
                        (np.array([0.0, -1.0, 0.3]), -0.12, (-2, 2, 0.1, 2))])
    Wp, Hp = PROJECTOR
    patterns = opencv_patterns(Wp, Hp) + [np.full((Hp, Wp), 255, np.uint8), np.zeros((Hp, Wp), np.uint8)]
    albedo = None
    if albedo_sigma is not None:
        ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
        r2 = ((xs - W / 2) ** 2 + (ys - H / 2) ** 2) / (W / 2) ** 2
        albedo = np.exp(-r2 / albedo_sigma**2).astype(np.float32)
    rng = np.random.default_rng(seed)
    depth = None
    for name, cam in (("cam0", cam0), ("cam1", cam1)):
        imgs, z = render_projection(patterns, proj, cam, scene, noise=0.004, rng=rng, gain=gain, ambient=ambient,
                                    albedo=albedo, blur_sigma=0.5)
        depth = z if depth is None else depth
        d = folder / name
        d.mkdir(parents=True, exist_ok=True)
        for k, im in enumerate(imgs):
            cv2.imwrite(str(d / f"im{k + 1}.png"), np.clip(np.rint(im * 255), 0, 255).astype(np.uint8))
    assert depth is not None
    return SLCapture(folder, depth, cam0, cam1)
