"""Writes a small simulated raw capture session with the virtual studio (test fixture for ``dp5k process``).

The layout follows docs/data-format.md; files go through ``dp5k_common.rawfile.write_dual_pixel_dng``. The
studio's ground truth is returned in memory (and written under ground_truth/, which processing never reads).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from calib.board import DEFAULT_BOARD
from dp5k_capture.patterns import projection, projection_count
from dp5k_studio.rig import make_rig
from dp5k_studio.scenes import make_scene, plane_scene
from dp5k_studio.studio import Studio
from dp5k_common.io import sha256_file
from dp5k_common.rawfile import write_dual_pixel_dng


def board_pose(center: tuple[float, float, float], yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0):
    """Board -> world pose (R, t) with the board centre at ``center`` (metres)."""
    R = (cv2.Rodrigues(np.radians([0.0, yaw_deg, 0.0]))[0] @ cv2.Rodrigues(np.radians([pitch_deg, 0.0, 0.0]))[0]
         @ cv2.Rodrigues(np.radians([0.0, 0.0, roll_deg]))[0])
    w, h = DEFAULT_BOARD.size_m
    return R, np.asarray(center, float) - R @ np.array([w / 2, h / 2, 0.0])


CHARUCO_POSES = [board_pose((0.0, 0.0, 2.1), 18.0, 8.0, 3.0), board_pose((0.03, 0.02, 2.3), -20.0, -10.0, -4.0),
                 board_pose((-0.03, -0.02, 2.0), 5.0, 15.0, 8.0)]
"""Board poses at 2.0-2.3 m. The fixture renders them in front of a far plain wall (the rig's calibration
shots; a hand-held board in front of the scene would be partly hidden by the scene's objects)."""


def wall_scene(yaw_deg: float, occluder: bool = False):
    """The "wall" preset's wall at 2.2 m turned by ``yaw_deg``; ``occluder`` adds a box hiding part of the board."""
    from dp5k_studio.geometry import Box
    from dp5k_studio.scenes import Scene, _wall
    from dp5k_studio.textures import TextureSpec

    tex = TextureSpec("noise", (0.8, 0.78, 0.74), (0.55, 0.53, 0.5), 0.2, seed=5)
    prims = [_wall(2.2, yaw_deg, tex, name="wall")]
    if occluder:
        prims.append(Box(np.array([-0.2, -0.12, 1.7]), np.eye(3), np.array([0.12, 0.1, 0.05]),
                         TextureSpec("noise", (0.6, 0.5, 0.4), (0.3, 0.3, 0.3), 0.05, seed=7), "occluder"))
    return Scene(f"wall{yaw_deg:g}{'_hidden' if occluder else ''}", tuple(prims), np.array([0.0, 0.0, 2.2]))


def knocked(rig, rotation_deg: tuple[float, float, float]):
    """The rig with cam1 turned about its own centre by the rotation vector ``rotation_deg`` (degrees, in cam1's
    frame: x = pitch, y = yaw, z = roll), as a knocked tripod or a refocused lens would leave it."""
    import dataclasses

    if not any(rotation_deg):
        return rig
    c0, c1 = rig.cameras
    Rd = cv2.Rodrigues(np.radians(np.asarray(rotation_deg, float)))[0]
    return dataclasses.replace(rig, cameras=(c0, dataclasses.replace(c1, R=Rd @ c1.R, t=Rd @ c1.t)))


def write_session(root: Path, scene_name, scale: str = "small", f_numbers=(1.8, 4.0), seed: int = 1,
                  projector_size: tuple[int, int] = (1920, 1200), board_on_wall: bool = False,
                  manifest_intrinsics: bool = True, charuco_rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  reuse: Path | None = None) -> dict:
    """Render and write RAW/<scene>/...; returns the studio's ground truth per camera (raw resolution).

    ``scene_name`` is a studio preset / seed, or a ``Scene`` (its ``name`` names the folder).
    ``charuco_rotation_deg``: the ChArUco shots are taken with cam1 turned by this rotation vector (:func:`knocked`)
    and the scene with the true rig: the session's own calibration is then that far off.
    ``reuse``: a session folder of the same scene, rig and seed written before; its scene frames (DP, sharp,
    structured light) are copied instead of rendered again, only the ChArUco shots are rendered."""
    rig = make_rig(scale, seed=seed, projector_size=projector_size)
    if isinstance(scene_name, str):
        scene = make_scene(scene_name, rig)
    else:
        scene, scene_name = scene_name, scene_name.name
    studio = Studio(scene, rig, seed=seed)
    rng = np.random.default_rng(seed)
    out = root / scene_name
    files = []

    def shoot(cam: int, name: str, kind: str, N: float, shutter: float, focus_m: float, **extra) -> None:
        e = studio.expose(cam, N, focus_m, shutter, 100, rng)
        p = out / f"cam{cam}" / f"{name}.dng"
        write_dual_pixel_dng(p, e.main, e.aux, e.black_level, e.white_level, e.wb_gains, e.metadata)
        files.append(dict(path=p.relative_to(out).as_posix(), kind=kind, camera=f"cam{cam}", f_number=N,
                          shutter_s=shutter, iso=100, size=p.stat().st_size, sha256=sha256_file(p), **extra))

    if board_on_wall:
        from dp5k_studio.scenes import wall_board_pose
        studio.set_board_pose(wall_board_pose(scene, DEFAULT_BOARD.size_m))
    focus_px = [studio.focus_point_px(c) for c in (0, 1)]
    focus_m = [studio.focus_distance_m(c, focus_px[c]) for c in (0, 1)]
    calib_studio = Studio(plane_scene(8.0), knocked(rig, charuco_rotation_deg), seed=seed + 1)
    for k, pose in enumerate(CHARUCO_POSES):
        calib_studio.set_board_pose(pose)
        for c in (0, 1):
            e = calib_studio.expose(c, 22.0, focus_m[c], 1 / 4, 100, rng)
            p = out / f"cam{c}" / f"charuco_{k}.dng"
            write_dual_pixel_dng(p, e.main, e.aux, e.black_level, e.white_level, e.wb_gains, e.metadata)
            files.append(dict(path=p.relative_to(out).as_posix(), kind="charuco", camera=f"cam{c}", f_number=22.0,
                              shutter_s=0.25, iso=100, size=p.stat().st_size, sha256=sha256_file(p)))
    Wp, Hp = projector_size
    if reuse is not None:  # the scene's frames as rendered before (same scene, rig, seed)
        import shutil

        old = json.loads((Path(reuse) / "manifest.json").read_text())
        for f in old["files"]:
            if f["kind"] != "charuco":
                (out / f["path"]).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(Path(reuse) / f["path"], out / f["path"])
                files.append(f)
    else:
        studio.set_projector_image(None)
        for c in (0, 1):
            for N in f_numbers:
                shoot(c, f"dp_f{N:g}", "dp", N, 1 / 500 * (N / 1.8) ** 2, focus_m[c])
            shoot(c, "sharp_f22", "sharp", 22.0, 1 / 4, focus_m[c])
        for k in range(projection_count(Wp, Hp)):
            studio.set_projector_image(projection(k, Wp, Hp))
            for c in (0, 1):
                shoot(c, f"sl_{k:02d}", "sl", 22.0, 1 / 4, focus_m[c], pattern=k)
        studio.set_projector_image(None)
    truth = {f"cam{c}": studio.ground_truth(c) for c in (0, 1)}
    gt = out / "ground_truth"
    gt.mkdir(parents=True, exist_ok=True)
    for c in (0, 1):
        np.save(gt / f"depth_cam{c}.npy", truth[f"cam{c}"]["depth_m"])
    cams = []
    for c, cm in enumerate(rig.cameras):
        body = dict(id=cm.name, serial=cm.serial, model=cm.model, lens=cm.lens, sensor_size_mm=list(cm.sensor_size_mm),
                    raw_size_px=[cm.width, cm.height], focus_point_px=list(focus_px[c]))
        if manifest_intrinsics:
            body.update(K=cm.K.tolist(), dist=cm.dist.tolist())
        cams.append(body)
    manifest = dict(format="dp5k-raw-session", version=1, scene=scene_name,
                    rig=dict(bodies=cams, projector=dict(model="EPSON EB-U42", resolution=[Wp, Hp]), aux_view="left"),
                    focus_point_px={f"cam{c}": list(focus_px[c]) for c in (0, 1)},
                    focus_distance_true_m=focus_m, files=files, complete=True)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    truth["focus_distance_m"] = focus_m
    truth["focus_point_px"] = focus_px
    return truth


def capture_and_process(tmp_path: Path, scene: str) -> tuple[Path, dict, "DatasetReader"]:
    """``dp5k capture --sim`` of ``scene`` at the small scale, then ``dp5k process`` with the defaults (asserted
    to succeed). Returns (the session's ground_truth folder, its truth.json, a reader of the processed dataset)."""
    from click.testing import CliRunner

    from dp5k_cli import main
    from dp5k_common.dataset import DatasetReader
    from dp5k_process.package import process_sessions
    from dp5k_process.pipeline import ProcessConfig

    res = CliRunner().invoke(main, ["-q", "capture", "--scene", scene, "--sim", "--sim-scale", "small",
                                    "--out", str(tmp_path / "raw")])
    assert res.exit_code == 0, res.output
    outcomes = process_sessions(tmp_path / "raw", tmp_path / "out", ProcessConfig())
    assert [o.status for o in outcomes] == ["ok"], [o.reason for o in outcomes]
    gt = tmp_path / "raw" / scene / "ground_truth"
    return gt, json.loads((gt / "truth.json").read_text()), DatasetReader(tmp_path / "out")


def assert_depth_and_focus(pair, gt: Path, truth: dict, cam: str) -> None:
    """Median abs. relative depth error <= 0.5 % against the true depth (at the output's half resolution) and the
    focus distance within 0.5 % of the truth (``pair`` a processed :class:`~dp5k_common.dataset.Pair` of ``cam``)."""
    from .truth import half

    z = cv2.imread(str(gt / f"{cam}_depth_mm.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    zh = half(np.where(z > 0, z, np.nan), "mean")
    ok = pair.valid & np.isfinite(zh)
    assert np.median(np.abs(pair.depth_mm[ok] - zh[ok]) / zh[ok]) <= 0.005
    F = truth["cameras"][cam]["focus_distance_true_m"] * 1000
    assert abs(pair.params.focus_distance_mm - F) / F <= 0.005


def export_sl_images(session_dir: Path, dest: Path, cam: str, colour_tiff: bool = False) -> tuple[int, int]:
    """A session's structured-light frames of ``cam`` as an ``sl-depth`` input folder: ``dest/im1 ... im46``
    (projection order, natural names), the main raw frame's counts as 16-bit gray PNG, or with ``colour_tiff`` as
    16-bit 3-channel TIFF (gray replicated). Returns (black level, white level) of the raws."""
    import tifffile

    from dp5k_common.rawfile import read_frame

    manifest = json.loads((Path(session_dir) / "manifest.json").read_text())
    sl = sorted((f for f in manifest["files"] if f["kind"] == "sl" and f["camera"] == cam), key=lambda f: f["pattern"])
    dest.mkdir(parents=True, exist_ok=True)
    black = white = 0
    for k, f in enumerate(sl):
        main, black, white = read_frame(Path(session_dir) / f["path"], 0)
        if colour_tiff:
            tifffile.imwrite(dest / f"im{k + 1}.tif", np.repeat(main[..., None], 3, axis=2))
        else:
            cv2.imwrite(str(dest / f"im{k + 1}.png"), main)
    return black, white
