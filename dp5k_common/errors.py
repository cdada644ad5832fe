"""One error hierarchy for dp5k.

Every error a user can cause or meet (bad input, a device fault, a failed calibration) is a
:class:`DP5KError`. The CLI prints ``dp5k: error: <where>: <problem>`` on one line and exits with the
class's ``exit_code``; ``--verbose`` adds the traceback. Library code raises these; it never calls
``sys.exit`` and never configures logging handlers.

Exit codes (distinct per class, stable, documented in docs/cli.md):

====  ==========================  =====================================================
code  class                       meaning
====  ==========================  =====================================================
1     DP5KError                   any other dp5k failure
3     BadInputError               a file, folder or argument is missing or malformed
4     DatasetFormatError          a dataset does not follow format v1 (a BadInputError)
5     DeviceError                 a camera/projector fault, timeout or protocol error
6     CalibrationError            calibration failed or is worse than its bound
7     StageError                  a pipeline stage failed (processing, training, ...)
8     PartialFailureError         some items failed, the rest completed (see report)
9     LowQualityResultError       the result was written but is below its quality bound (see report)
130   (KeyboardInterrupt)         interrupted by the user; finished work is kept
====  ==========================  =====================================================
"""

from __future__ import annotations

from os import PathLike


class DP5KError(Exception):
    """Base of every dp5k error.

    Args:
        message: what went wrong, one line, no trailing period needed.
        where: the file, pair, device or stage it concerns (printed before the message).
    """

    exit_code: int = 1

    def __init__(self, message: str, *, where: str | PathLike[str] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.where = None if where is None else str(where)

    def one_line(self) -> str:
        """The single line the CLI prints (without the ``dp5k: error:`` prefix)."""
        text = " ".join(str(self.message).split())
        return f"{self.where}: {text}" if self.where else text

    def __str__(self) -> str:
        return self.one_line()


class BadInputError(DP5KError):
    """A file, folder or argument is missing, unreadable or malformed."""

    exit_code = 3


class DatasetFormatError(BadInputError):
    """A dataset does not follow the processed dataset format v1 (docs/data-format.md)."""

    exit_code = 4


class EmptySplitError(DatasetFormatError):
    """A dataset split (train, val or test) holds no pair; callers that can do without it catch this one."""


class DeviceError(DP5KError):
    """A camera or projector failed: protocol error, fault reply, disconnect."""

    exit_code = 5


class DeviceTimeoutError(DeviceError):
    """A device did not answer within its timeout."""


class CalibrationError(DP5KError):
    """Calibration could not be computed or is worse than its acceptance bound."""

    exit_code = 6


class StageError(DP5KError):
    """A pipeline stage (processing, training, evaluation, diagnose, demo) failed."""

    exit_code = 7


class PartialFailureError(DP5KError):
    """Some items (scenes, pairs, frames) failed; the others completed and were kept."""

    exit_code = 8


class LowQualityResultError(DP5KError):
    """The work finished and its result was written, marked as such, but it is below a documented quality bound
    (e.g. ``dp5k sl-depth``: depth coverage under ``--min-coverage``, or a calibration that the refinement could not
    make fit): nothing failed outright, but the result must not be used unseen."""

    exit_code = 9
