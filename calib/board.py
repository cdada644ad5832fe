"""The one ChArUco board dp5k uses: the rig's calibration board, the wall board for depth validation and
the board the virtual studio renders are all this definition.

Board frame (OpenCV): origin at the board's top-left outer corner, x to the right along the squares, y down,
z into the board (right-handed), units metres. ``board.getChessboardCorners()`` gives the inner corners at
``(square * (i + 1), square * (j + 1), 0)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board.

    Attributes:
        squares_x: number of chessboard squares along x.
        squares_y: number of chessboard squares along y.
        square_m: square side in metres.
        marker_m: ArUco marker side in metres (< square_m).
        dictionary: OpenCV predefined dictionary id (``cv2.aruco.DICT_*``).
    """

    squares_x: int = 12
    squares_y: int = 9
    square_m: float = 0.060
    marker_m: float = 0.045
    dictionary: int = cv2.aruco.DICT_5X5_1000

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the printed board area in metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (new 4.7+/5.0 API)."""
        dic = cv2.aruco.getPredefinedDictionary(self.dictionary)
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, dic)

    def image(self, px_per_square: int = 64) -> NDArray[np.uint8]:
        """The board's print image, uint8 (H, W), white paper = 255, no margin; 1 image px = square/px_per_square m."""
        size = (self.squares_x * px_per_square, self.squares_y * px_per_square)
        return self.cv_board().generateImage(size, marginSize=0, borderBits=1)

    def inner_corners_m(self) -> NDArray[np.float64]:
        """(N, 3) inner-corner positions in the board frame, metres, in OpenCV's id order."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


DEFAULT_BOARD = BoardSpec()
"""The calibration board (12 x 9 squares of 60 mm, 45 mm markers, DICT_5X5_1000: 0.72 x 0.54 m)."""

WALL_BOARD = BoardSpec()
"""The board pasted on the wall for ``dp5k validate-depth`` (same print as the calibration board)."""
