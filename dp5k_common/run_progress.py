"""How far an interrupted command got, kept in OUT so that running it again continues instead of starting over.

A command that resumes by item (``studio make-dataset`` by view, ``evaluate`` by pair) writes a small hidden JSON
file into OUT after each finished item: the settings it runs with and its state (what is done, the random
generators' states). Run again with the same settings, it continues from that state, and its result is the one an
uninterrupted run writes. The file is removed once the result is complete.

>>> import tempfile
>>> d = Path(tempfile.mkdtemp())
>>> p = RunProgress(d / ".progress.json", {"seed": 1, "size": (48, 32)})
>>> p.earlier() is None
True
>>> p.save({"done": 3})
>>> RunProgress(d / ".progress.json", {"seed": 1, "size": [48, 32]}).earlier()
{'done': 3}
>>> RunProgress(d / ".progress.json", {"seed": 2, "size": [48, 32]}).other_settings()
{'seed': 1, 'size': [48, 32]}
>>> p.finish(); p.path.exists()
False
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .errors import DP5KError
from .io import read_json, write_json_atomic

__all__ = ["RunProgress", "canonical"]


def canonical(obj: Any) -> Any:
    """``obj`` as it reads back from JSON (tuples become lists), so that settings compare equal across runs."""
    return json.loads(json.dumps(obj, allow_nan=False))


class RunProgress:
    """The progress file ``path`` of a run with ``settings`` (JSON-able)."""

    def __init__(self, path: Path, settings: Mapping[str, Any]) -> None:
        self.path = Path(path)
        self.settings = canonical(dict(settings))

    def _read(self) -> dict[str, Any] | None:
        if not self.path.is_file():
            return None
        try:
            obj = read_json(self.path)
        except DP5KError:  # a torn or foreign file: nothing to continue from
            return None
        return obj if isinstance(obj, dict) and isinstance(obj.get("settings"), dict) else None

    def earlier(self) -> dict[str, Any] | None:
        """The state an interrupted run with the same settings saved; None when there is none (or it ran with other
        settings: :meth:`other_settings`)."""
        obj = self._read()
        if obj is None or obj["settings"] != self.settings:
            return None
        return obj.get("state") or {}

    def other_settings(self) -> dict[str, Any] | None:
        """The settings of an interrupted run that differ from these; None when there is none or they are the same."""
        obj = self._read()
        if obj is None or obj["settings"] == self.settings:
            return None
        return obj["settings"]

    def save(self, state: Mapping[str, Any]) -> None:
        """Record ``state`` (JSON-able) atomically: an interruption leaves the previous state or this one."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.path, {"settings": self.settings, "state": canonical(dict(state))})

    def finish(self) -> None:
        """The result is complete: nothing to resume any more."""
        self.path.unlink(missing_ok=True)

    def differences(self, other: Mapping[str, Any]) -> str:
        """``key: earlier -> now`` for each setting that differs from ``other`` (for an error line)."""
        keys = sorted(set(other) | set(self.settings))
        return "; ".join(f"{k}: {other.get(k)!r} -> {self.settings.get(k)!r}" for k in keys
                         if other.get(k) != self.settings.get(k))
