"""Plain DistributedDataParallel plumbing for ``torchrun`` (one process per device, any number of nodes).

Launch::

    torchrun --nproc_per_node G [--nnodes N --rdzv_backend c10d --rdzv_endpoint HOST:PORT] \\
        -m dp5k_cli train DATASET --out DIR

Where a process sits is :class:`dp5k_common.sharding.RankInfo` (read and checked by
:func:`dp5k_common.sharding.rank_info`); this module only adds what needs ``torch.distributed``: joining the
process group, this process's device and the collective operations. Without torchrun's environment
(``RANK`` unset, or ``WORLD_SIZE`` 1) everything here is a no-op, so a CPU run or a test never touches
``torch.distributed``. The backend is NCCL with CUDA and gloo otherwise (CPU tests use gloo).
"""

from __future__ import annotations

import gc

import torch
import torch.distributed as dist

from dp5k_common.errors import BadInputError
from dp5k_common.sharding import RankInfo, rank_info


def resolve_device(requested: str | torch.device, local_rank: int = 0) -> torch.device:
    """``"auto"`` -> ``cuda:LOCAL_RANK`` when CUDA is present, else CPU; otherwise the named device.

    Raises:
        BadInputError: a name torch does not know, or a CUDA device this machine does not have (exit 3, before
            any work, instead of torch's traceback half-way).
    """
    if isinstance(requested, torch.device):
        return requested
    if requested == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    try:
        dev = torch.device(requested)
    except RuntimeError as exc:
        raise BadInputError(f"unknown device {requested!r} (auto, cpu, cuda or cuda:N)", where="--device") from exc
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device(f"cuda:{local_rank}")
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if dev.index is not None and dev.index >= count:
            have = f"{count} CUDA device(s)" if count else f"no CUDA device (torch {torch.__version__})"
            raise BadInputError(f"{requested} asked for, but torch sees {have}; use --device auto or cpu", where="--device")
    return dev


def setup(requested_device: str = "auto") -> tuple[RankInfo, torch.device]:
    """Join the process group when launched by torchrun with several processes; pick this process's device.

    Raises:
        BadInputError: torchrun's environment variables are malformed (:func:`~dp5k_common.sharding.rank_info`).
    """
    info = rank_info()
    device = resolve_device(requested_device, info.local_rank)
    if not info.enabled:
        return info, device
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return info, device


def teardown(info: RankInfo | None = None) -> None:
    """Leave the process group. With ``info`` (a run that ended normally on every rank), first free what is
    unreachable (a DistributedDataParallel wrapper's reducer, while the group it uses still exists) and wait at
    a barrier, so that no rank destroys its group while another is still talking to it: a rank that left
    first can make the other abort at exit in the two-rank gloo test ("terminate called without an active
    exception", SIGABRT, after both ranks had trained).
    Without ``info`` (an error on this rank) the group is destroyed at once: a barrier could wait for a rank
    that is gone (torchrun then stops the other ranks)."""
    if not (dist.is_available() and dist.is_initialized()):
        return
    if info is not None and info.enabled:
        gc.collect()
        dist.barrier()
    dist.destroy_process_group()


def barrier(info: RankInfo) -> None:
    if info.enabled:
        dist.barrier()


def all_reduce_sum(values: torch.Tensor, info: RankInfo) -> torch.Tensor:
    """Sum a tensor over all processes (identity when not distributed). Returns a new tensor."""
    out = values.detach().clone()
    if info.enabled:
        dist.all_reduce(out, op=dist.ReduceOp.SUM)
    return out
