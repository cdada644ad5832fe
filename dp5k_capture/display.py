"""Full-screen pattern window on the projector's output (pygame / SDL2).

On the rig the projector is a second display on HDMI; the window opens borderless and full screen on
that display (``display_index``) at the projector's native resolution. Under test SDL's dummy video
driver (``SDL_VIDEODRIVER=dummy``) gives a real SDL surface without a screen; :meth:`frame` reads back
what is on it (the simulated projector's HDMI input).
"""

from __future__ import annotations

import os
import time

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import DeviceError


class PatternWindow:
    """A full-screen SDL window showing one grey image at a time.

    Args:
        width, height: the projector's native resolution (pixels).
        display_index: SDL display number of the projector output.
        settle_s: wait after each flip (vsync + projector input lag; measure it once on the rig).
        headless: use SDL's dummy video driver (tests, simulated rig).
    """

    def __init__(self, width: int, height: int, display_index: int = 1, settle_s: float = 0.15, headless: bool = False) -> None:
        if headless:
            os.environ["SDL_VIDEODRIVER"] = "dummy"
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame

        self._pg = pygame
        self.width, self.height, self.settle_s = int(width), int(height), float(settle_s)
        try:
            pygame.display.init()
            n = pygame.display.get_num_displays()
            index = display_index if display_index < n else n - 1
            flags = pygame.NOFRAME if headless else (pygame.FULLSCREEN | pygame.NOFRAME)
            self.surface = pygame.display.set_mode((self.width, self.height), flags, display=index)
            pygame.mouse.set_visible(False)
        except pygame.error as exc:
            raise DeviceError(f"cannot open the pattern window ({exc})", where=f"display {display_index}") from exc
        self.shown: int | None = None
        self._frame: NDArray[np.uint8] | None = None

    def show(self, image: NDArray[np.uint8], tag: int | None = None) -> None:
        """Put a uint8 (height, width) or (height, width, 3) image on screen, flip, wait ``settle_s``."""
        img = np.asarray(image, dtype=np.uint8)
        if img.shape[:2] != (self.height, self.width):
            raise ValueError(f"pattern is {img.shape[1]}x{img.shape[0]}, window is {self.width}x{self.height}")
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        self._pg.surfarray.blit_array(self.surface, np.ascontiguousarray(img.transpose(1, 0, 2)))
        self._pg.display.flip()
        self._pg.event.pump()
        self._frame = None  # the screen changed: read it back again on the next frame()
        self.shown = tag
        if self.settle_s > 0:
            time.sleep(self.settle_s)

    def frame(self) -> NDArray[np.uint8]:
        """What the window shows now: uint8 (height, width) grey (the red channel), read back from the surface
        once per flip."""
        if self._frame is None:
            red = self._pg.surfarray.pixels_red(self.surface)  # (W, H) view, locks the surface
            try:
                self._frame = np.ascontiguousarray(red.T)
                self._frame.setflags(write=False)
            finally:
                del red
        return self._frame

    def close(self) -> None:
        self._pg.display.quit()
