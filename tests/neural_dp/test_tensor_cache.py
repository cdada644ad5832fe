"""The render caches' one mechanism (:class:`neural_dp.simulators.base.cache.TensorCache`): found only from the very
same source objects, bounded by the bytes of what it holds, least recently used out first."""

from __future__ import annotations

import torch

from neural_dp.simulators.base.cache import TensorCache, tensor_bytes


def test_a_hit_needs_the_same_objects_not_only_the_same_key() -> None:
    cache = TensorCache(1 << 20)
    a, b = torch.zeros(4), torch.zeros(4)
    value = torch.ones(8)
    cache.put(("k",), (a,), value)
    assert cache.get(("k",), (a,)) is value
    assert cache.get(("k",), (b,)) is None  # an equal tensor, another object (an id reused after a is gone)
    assert cache.get(("other",), (a,)) is None
    assert cache.get(("k",), (a, None)) is None


def test_the_byte_total_is_kept_and_the_oldest_goes_first() -> None:
    one = tensor_bytes((torch.zeros(10), torch.zeros(6)))
    assert one == 16 * 4
    cache = TensorCache(2 * one)
    src = [object() for _ in range(4)]
    for k in range(3):
        cache.put(k, (src[k],), (torch.full((10,), float(k)), torch.zeros(6)))
    assert len(cache) == 2 and cache.nbytes == 2 * one
    assert cache.get(0, (src[0],)) is None  # the oldest went
    assert cache.get(1, (src[1],)) is not None  # now the most recent: 2 goes next
    cache.put(3, (src[3],), (torch.zeros(10), torch.zeros(6)))
    assert cache.get(2, (src[2],)) is None and cache.get(1, (src[1],)) is not None
    cache.put(1, (src[1],), torch.zeros(2))  # replacing an entry replaces its bytes
    assert cache.nbytes == one + 8
    big = torch.zeros(1000)
    cache.put(9, (src[0],), big)  # larger than the bound: kept alone
    assert len(cache) == 1 and cache.get(9, (src[0],)) is big and cache.nbytes == 4000
