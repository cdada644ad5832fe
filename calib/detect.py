"""ChArUco detection with OpenCV 5.0's object API (``CharucoDetector.detectBoard``, ``board.matchImagePoints``)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from .board import DEFAULT_BOARD, BoardSpec


@dataclass(frozen=True)
class CharucoDetection:
    """ChArUco corners found in one image.

    Attributes:
        ids: (N,) int32 corner ids (OpenCV's inner-corner order).
        image_px: (N, 2) float32 corner positions in image pixels (x, y).
        board_m: (N, 3) float32 the same corners in the board frame, metres (z = 0).
        n_markers: number of ArUco markers found.
    """

    ids: NDArray[np.int32]
    image_px: NDArray[np.float32]
    board_m: NDArray[np.float32]
    n_markers: int

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def subset(self, ids: NDArray[np.int32]) -> CharucoDetection:
        """The detection restricted to ``ids`` (in that order; all must be present)."""
        index = {int(i): k for k, i in enumerate(self.ids)}
        sel = np.array([index[int(i)] for i in ids], dtype=np.int64)
        return CharucoDetection(self.ids[sel], self.image_px[sel], self.board_m[sel], self.n_markers)


def _to_uint8(image: NDArray) -> NDArray[np.uint8]:
    """Gray uint8 from an 8-bit, 16-bit or float image (min-max stretched over the 0.1..99.9 percentiles)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img.mean(axis=2) if img.dtype != np.uint8 else cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.dtype == np.uint8:
        return img
    img = img.astype(np.float32)
    lo, hi = np.percentile(img, (0.1, 99.9))
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((img - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def _detector_params() -> cv2.aruco.DetectorParameters:
    """Marker detection tuned for small markers (a few pixels per bit), sub-pixel corner refinement."""
    dp = cv2.aruco.DetectorParameters()
    dp.errorCorrectionRate = 0.8
    dp.perspectiveRemovePixelPerCell = 8
    dp.perspectiveRemoveIgnoredMarginPerCell = 0.2
    dp.minMarkerPerimeterRate = 0.01
    dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return dp


@lru_cache(maxsize=8)
def _board_detector(board: BoardSpec) -> tuple[cv2.aruco.CharucoBoard, cv2.aruco.CharucoDetector]:
    """The board and a detector whose dictionary holds only the board's markers (ids 0..n-1 of ``board``'s
    predefined dictionary).

    OpenCV identifies a marker candidate by scanning the dictionary in id order and taking the first id within
    the correction distance, so a candidate gets the same id (and rotation) from the truncated dictionary as from
    the full one whenever that id is on the board; candidates the full dictionary would name with an id off the
    board are rejected instead, and ChArUco interpolation ignores those anyway. The scan, per candidate, is what
    dominates detection with a 1000-marker dictionary (about 1.5 s of a 1344 x 896 image's 1.7 s); the board
    uses 54 of them.
    """
    full = cv2.aruco.getPredefinedDictionary(board.dictionary)
    n_markers = (board.squares_x * board.squares_y) // 2
    own = cv2.aruco.Dictionary(np.ascontiguousarray(full.bytesList[:n_markers]), full.markerSize,
                               full.maxCorrectionBits)
    cv_board = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_m, board.marker_m, own)
    return cv_board, cv2.aruco.CharucoDetector(cv_board, cv2.aruco.CharucoParameters(), _detector_params())


def detect_charuco(image: NDArray, board: BoardSpec = DEFAULT_BOARD, upsample: int | None = None
                   ) -> CharucoDetection | None:
    """Detect the ChArUco board in ``image`` (gray or RGB, any dtype); None when no corner is found.

    Args:
        image: (H, W) or (H, W, 3) image; linear raw data is stretched to 8 bit for detection.
        board: the board definition.
        upsample: detect on an image enlarged this many times (cubic), corners mapped back; None = 2 for
            images under 1000 px wide (markers of a few pixels per bit are found far more reliably), else 1.
    """
    gray = _to_uint8(image)
    up = upsample if upsample is not None else (2 if gray.shape[1] < 1000 else 1)
    if up > 1:
        gray = cv2.resize(gray, None, fx=up, fy=up, interpolation=cv2.INTER_CUBIC)
    cv_board, det = _board_detector(board)
    cc, ci, mc, _mi = det.detectBoard(gray)
    if ci is None or cc is None or len(ci) == 0:
        return None
    cc = np.asarray(cc, dtype=np.float32).reshape(-1, 2)
    if up > 1:
        cc = (cc + 0.5) / up - 0.5  # pixel centres at integer coordinates in both images
    ci = np.asarray(ci, dtype=np.int32).reshape(-1)
    obj, imgp = cv_board.matchImagePoints(cc.reshape(-1, 1, 2), ci.reshape(-1, 1))
    obj = np.asarray(obj, dtype=np.float32).reshape(-1, 3)
    return CharucoDetection(ci, cc, obj, 0 if mc is None else len(mc))
