"""Which share of a list of work items this process owns, under ``torchrun`` or alone.

``torchrun --nproc_per_node N -m dp5k_cli COMMAND ...`` starts N copies of a command with ``RANK`` and
``WORLD_SIZE`` in their environment; a stage that works item by item (frames, scenes) lets each rank take
every ``WORLD_SIZE``-th item of the sorted list. The split is a pure function of the sorted names, so each
item is owned by exactly one rank whatever the rank count, and a rank that is restarted finds and resumes
its own share. No process group is needed for the split itself (``torch.distributed`` is not imported).

:class:`RankInfo` is the project's one rank type and :func:`rank_info` its one reader of torchrun's environment
(``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``): sharded stages and the trainers (``dp5k_learn.distributed``, which
joins the process group and picks the device) all start from it.

>>> shard(["a", "b", "c", "d", "e"], RankInfo(1, 2))
['b', 'd']
>>> sorted(shard(["a", "b", "c"], RankInfo(0, 2)) + shard(["a", "b", "c"], RankInfo(1, 2)))
['a', 'b', 'c']
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar

from .errors import BadInputError

T = TypeVar("T")


@dataclass(frozen=True)
class RankInfo:
    """This process's global ``rank`` among ``world_size`` processes (0 of 1 when run alone), and its
    ``local_rank`` on its node (which device it takes)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1


def rank_info(environ: Mapping[str, str] | None = None) -> RankInfo:
    """Read torchrun's ``RANK`` / ``WORLD_SIZE`` / ``LOCAL_RANK`` (``RANK`` absent: a single process).

    Raises:
        BadInputError: a value is not an integer, ``RANK`` is not in ``0..WORLD_SIZE-1`` or ``LOCAL_RANK`` is
            negative (one line naming the variables).
    """
    env = os.environ if environ is None else environ
    if "RANK" not in env:
        return RankInfo()
    try:
        rank, world, local = int(env["RANK"]), int(env.get("WORLD_SIZE", "1")), int(env.get("LOCAL_RANK", "0"))
    except ValueError as exc:
        raise BadInputError(f"RANK={env.get('RANK')!r} / WORLD_SIZE={env.get('WORLD_SIZE')!r} / LOCAL_RANK="
                            f"{env.get('LOCAL_RANK')!r} are not integers", where="environment") from exc
    if world < 1 or not 0 <= rank < world:
        raise BadInputError(f"RANK={rank} is not in 0..WORLD_SIZE-1 (WORLD_SIZE={world})", where="environment")
    if local < 0:
        raise BadInputError(f"LOCAL_RANK={local} is negative", where="environment")
    return RankInfo(rank, world, local)


def shard(items: Sequence[T], info: RankInfo) -> list[T]:
    """The items this rank owns: every ``world_size``-th item starting at ``rank``, in the given order.

    Callers pass a list sorted by a stable key (file or scene names), so the owner of an item depends only on
    its position in that list and on the rank count.
    """
    return list(items[info.rank :: info.world_size])
