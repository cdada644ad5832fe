"""ChArUco boards rendered in pose are detected by OpenCV where the truth says; focus truth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.board import DEFAULT_BOARD, WALL_BOARD
from dp5k_studio import Studio, make_rig, make_scene, wall_board_pose


def _detect(img_green: np.ndarray):
    g = (np.clip(img_green, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    det = cv2.aruco.CharucoDetector(DEFAULT_BOARD.cv_board())
    corners, ids, _, _ = det.detectBoard(g)
    return corners, ids


def _project(gt: dict, X: np.ndarray) -> np.ndarray:
    Xc = X @ gt["R"].T + gt["t"]
    return (Xc[:, :2] / Xc[:, 2:]) @ gt["K"][:2, :2].T + gt["K"][:2, 2]


@pytest.mark.parametrize("rvec", [(0.0, 0.0, 0.0), (0.1, 0.25, 0.02), (-0.15, -0.2, 0.05)])
def test_charuco_board_is_detected_at_its_true_corners(rvec) -> None:
    rig = make_rig("small")
    st = Studio(make_scene("wall", rig), rig, supersample=2)
    R, _ = cv2.Rodrigues(np.asarray(rvec, float))
    w, h = DEFAULT_BOARD.size_m
    t = np.array([0.0, 0.0, 1.9]) - R @ np.array([w / 2, h / 2, 0.0])
    st.set_board_pose((R, t))
    F = st.focus_distance_m(0, (168, 112))
    assert F == pytest.approx(1.9, abs=0.15)
    dp = st.render_views(0, 22.0, F)
    corners, ids = _detect((dp.left + dp.right)[:, :, 1])
    assert ids is not None and len(ids) >= 30
    truth = _project(st.ground_truth(0), DEFAULT_BOARD.inner_corners_m()[ids.ravel()] @ R.T + t)
    err = np.linalg.norm(corners.reshape(-1, 2) - truth, axis=1)
    assert err.mean() < 0.2 and err.max() < 0.5
    st.set_board_pose(None)
    assert _detect(st.render_views(0, 22.0, F).left[:, :, 1] * 2)[1] is None


def test_wall_board_lies_on_the_wall_for_depth_validation() -> None:
    rig = make_rig("small")
    st = Studio(make_scene("wall", rig), rig, supersample=1)
    wall_depth = st.ground_truth(0)["depth_m"].copy()
    R, t = wall_board_pose(st.scene, WALL_BOARD.size_m)
    st.set_board_pose((R, t))
    gt = st.ground_truth(0)
    on_board = np.abs(gt["depth_m"] - wall_depth) > 0
    assert on_board.mean() > 0.2
    assert np.abs(gt["depth_m"] - wall_depth)[on_board].max() < 0.002  # 1 mm in front of the wall
    assert gt["board_pose"] is not None


def test_focus_distance_truth_is_the_depth_at_the_focus_point() -> None:
    rig = make_rig("small")
    st = Studio(make_scene("demo01", rig), rig, supersample=1)
    for cam in (0, 1):
        x, y = st.focus_point_px(cam)
        F = st.focus_distance_m(cam, (x, y))
        assert F == pytest.approx(st.ground_truth(cam)["depth_m"][int(y), int(x)], abs=1e-9)
        assert 0.26 < F < 10.0
