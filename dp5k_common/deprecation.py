"""Old command-line flags keep working for a while; each use prints one line saying what replaces it."""

from __future__ import annotations

import logging

logger = logging.getLogger("dp5k")


def warn_deprecated(old: str, new: str) -> None:
    """Log ``OLD is deprecated; use NEW`` once, at warning level (shown even with ``dp5k -q``).

    >>> warn_deprecated("--checkpoint CKPT", "--simulator neural:CKPT")
    """
    logger.warning("%s is deprecated; use %s", old, new)
