"""Old command-line spellings keep working for a release; each use prints one line saying what replaces it.

Inside a ``dp5k`` command (``dp5k_cli`` opens :func:`collect_deprecations` around it) the lines are held back
and printed once the command is done: after its output when it succeeds, and folded into its one error line
when it fails, so the error policy (a failed command prints exactly one line) holds for old spellings too.
Outside a command (library calls, the demo's in-process stages) the line is logged at once.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

logger = logging.getLogger("dp5k")

_held: list[list[str]] = []  # one list per open collect_deprecations(), innermost last


def deprecation_line(old: str, new: str) -> str:
    """``OLD is deprecated; use NEW``: the wording of every deprecation notice."""
    return f"{old} is deprecated; use {new}"


def warn_deprecated(old: str, new: str) -> None:
    """Say once that ``old`` is deprecated in favour of ``new``, at warning level (shown even with ``dp5k -q``).

    >>> warn_deprecated("--checkpoint CKPT", "--simulator neural:CKPT")
    """
    line = deprecation_line(old, new)
    if _held:
        if line not in _held[-1]:
            _held[-1].append(line)
    else:
        logger.warning("%s", line)


class HeldNotes:
    """The deprecation lines of one command run, held until it ends."""

    def __init__(self, lines: list[str]) -> None:
        self._lines = lines

    def take_suffix(self) -> str:
        """The held lines as a suffix of an error line (`` (also: A; B)``), emptied; '' when none."""
        lines, self._lines[:] = list(self._lines), []
        return f" (also: {'; '.join(lines)})" if lines else ""

    def flush(self) -> None:
        """Log every held line (one each) and forget them."""
        lines, self._lines[:] = list(self._lines), []
        for line in lines:
            logger.warning("%s", line)


@contextmanager
def collect_deprecations() -> Iterator[HeldNotes]:
    """Hold :func:`warn_deprecated` lines for the duration of one command; whatever the caller did not take is
    logged when the block ends (success, or an exception the caller does not handle)."""
    lines: list[str] = []
    _held.append(lines)
    notes = HeldNotes(lines)
    try:
        yield notes
    finally:
        _held.pop()  # blocks nest: the innermost is the last
        notes.flush()
