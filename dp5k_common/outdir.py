"""Output folders checked before any work: a command that would fail to write its result refuses at once.

Every command that writes a folder (``capture --out``, ``import ... OUT``, ``sl-depth ... OUT``) calls
:func:`check_out_dir` before reading its inputs, so an OUT that is a file, lies under a file, or sits on a
read-only mount is one line and exit code 3 instead of a traceback after minutes of work.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from .errors import BadInputError


def check_out_dir(out: Path, *, create: bool, option: str = "--out") -> Path:
    """Check that the folder ``out`` can be written; create it if missing and ``create``.

    A missing ``out`` is accepted (and made, with its missing parents, when ``create``) if its nearest
    existing ancestor is a writable folder. Writability is probed by creating and removing a temporary
    file (permission bits alone miss read-only mounts and root).

    Args:
        out: the output folder.
        create: make it (and its missing parents) once it passed.
        option: how the command names it in the error's advice (``--out``, ``OUT``).

    Raises:
        BadInputError: ``out`` (or its nearest existing ancestor) is not a folder or cannot be written.
    """
    out = Path(out)
    probe_dir = out
    while not probe_dir.exists():
        if probe_dir.parent == probe_dir:
            break
        probe_dir = probe_dir.parent
    if not probe_dir.is_dir():
        raise BadInputError(f"not a folder ({probe_dir} is a file)", where=out)
    try:
        with tempfile.TemporaryFile(dir=probe_dir, prefix=".dp5k-write-probe."):
            pass
    except OSError as exc:
        raise BadInputError(f"cannot write into {probe_dir} ({exc.strerror or exc}); choose a writable {option}",
                            where=out) from exc
    if create and probe_dir != out:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise BadInputError(f"cannot create the folder ({exc.strerror or exc})", where=out) from exc
    return out
