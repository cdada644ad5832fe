"""Where a scene goes: scene names that are one safe folder name on every OS, and an ``--out`` that can be written.

Both checks run before any device is touched (and for ``--dry-run``), so a bad name or an unwritable
output folder costs the operator nothing: no projector warm-up, no autofocus, nothing written.
"""

from __future__ import annotations

import re

from dp5k_common.errors import BadInputError
from dp5k_common.outdir import check_out_dir  # shared with import and sl-depth

MAX_SCENE_NAME_CHARS = 100  # well under the 255-byte file-name limit of ext4/NTFS/APFS, room for temp prefixes
SCENE_NAME_CHARS = re.compile(r"[A-Za-z0-9._-]+")
# Windows reserves these device names, with any extension and in any case ("con.txt", "Lpt1")
WINDOWS_RESERVED = frozenset({"CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(10)), *(f"LPT{i}" for i in range(10))})


def check_scene_name(scene: str) -> str:
    """Return ``scene`` if it is one safe folder name; else raise a one-line :class:`BadInputError`.

    Allowed: 1..100 of ``A-Z a-z 0-9 . _ -``, not starting with ``.`` (``.``, ``..`` and hidden folders) or
    ``-`` (read as an option by other tools), not ending with ``.`` (Windows drops it), not a Windows
    device name (CON, PRN, AUX, NUL, COM0-9, LPT0-9, any case, with or without an extension).
    """
    shown = repr(scene) if len(scene) <= 40 else repr(scene[:40]) + f"... ({len(scene)} characters)"
    if not scene:
        problem = "is empty"
    elif len(scene) > MAX_SCENE_NAME_CHARS:
        problem = f"is longer than {MAX_SCENE_NAME_CHARS} characters"
    elif not SCENE_NAME_CHARS.fullmatch(scene):
        problem = "may only use letters, digits, '.', '_' and '-' (no '/', spaces or control characters)"
    elif scene[0] in ".-":
        problem = f"must not start with {scene[0]!r}"
    elif scene.endswith("."):
        problem = "must not end with '.'"
    elif scene.split(".")[0].upper() in WINDOWS_RESERVED:
        problem = "is a device name reserved on Windows"
    else:
        return scene
    raise BadInputError(f"scene name {shown} {problem}", where="--scene")


__all__ = ["check_scene_name", "check_out_dir", "MAX_SCENE_NAME_CHARS", "WINDOWS_RESERVED"]
