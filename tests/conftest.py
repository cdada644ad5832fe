"""Suite-wide settings.

Under pytest-xdist (``make test`` runs ``-n auto``) each worker gets an equal share of the cores for
PyTorch's intra-op threads: on this 2-core machine two workers at one thread each finish the suite's
rendering-bound diagnose runs about 1.4 x faster than one process at two threads (27.3 s vs 19.4 s per
run, i.e. two runs in 27 s instead of 39 s), and two workers at two threads each would contend.
"""

from __future__ import annotations

import os


def pytest_configure(config) -> None:  # noqa: ANN001 - pytest's Config
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if not workers:
        return
    import torch

    torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(workers)))


def pytest_collection_modifyitems(config, items) -> None:  # noqa: ANN001 - pytest's Config and Items
    """End-to-end runs (``@pytest.mark.slow``) first, each group in its collected order: collected last, one
    worker ran the slowest diagnose cells alone for the suite's final minutes. ``make test`` uses xdist's
    work stealing, which shares the long runs out (``--dist load`` would give one worker the first contiguous
    chunk, every slow test)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
