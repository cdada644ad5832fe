"""A least-recently-used cache of computed tensors, keyed by what they were computed from and bounded in bytes."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Hashable, Sequence

from torch import Tensor

__all__ = ["TensorCache", "tensor_bytes"]


def tensor_bytes(value: Any) -> int:
    """Bytes held by ``value``: a tensor, or the tensors in a tuple or list of them (other items count 0)."""
    if isinstance(value, Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, (tuple, list)):
        return sum(tensor_bytes(v) for v in value)
    return 0


class TensorCache:
    """Tensors computed from some objects (a batch, a field map), found again by the objects' ids and a hashable
    state, least recently used first out once the cached values pass ``max_bytes``.

    An id is reused once its object is gone, so every entry keeps its ``sources`` alive and a hit must find the
    very same objects (``is``). Tensors changed in place keep their id: callers put their ``_version`` counters
    in the key. The byte total is kept as entries come and go (values only: the sources are the callers'
    objects and alive anyway while they are in use). The newest entry is always kept, whatever its size.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self.nbytes = 0
        self._entries: "OrderedDict[Hashable, tuple[tuple[object, ...], Any, int]]" = OrderedDict()

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, key: Hashable, sources: Sequence[object]) -> Any | None:
        """The value stored under ``key`` from these very ``sources``, or None."""
        hit = self._entries.get(key)
        if hit is None or len(hit[0]) != len(sources) or any(a is not b for a, b in zip(hit[0], sources)):
            return None
        self._entries.move_to_end(key)
        return hit[1]

    def put(self, key: Hashable, sources: Sequence[object], value: Any) -> Any:
        """Store ``value`` (computed from ``sources``) under ``key``, evict the oldest entries past the bound and
        return ``value``."""
        old = self._entries.pop(key, None)
        if old is not None:
            self.nbytes -= old[2]
        size = tensor_bytes(value)
        self._entries[key] = (tuple(sources), value, size)
        self.nbytes += size
        while len(self._entries) > 1 and self.nbytes > self.max_bytes:
            self.nbytes -= self._entries.popitem(last=False)[1][2]
        return value
