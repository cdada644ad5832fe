"""Simulators by name: ``get_simulator("disk")`` and friends.

========== ===================================================== =========================
name       simulator                                             needs
========== ===================================================== =========================
disk       translating-disk PSF, layered (Punnappurath 2020)     -
butterworth Butterworth PSF, layered (Abuolaim 2021)             -
raytrace   thin-lens ray tracing, aperture points (Pan 2021)     -
base       the physical base model (``neural_dp.simulators.base``) -
neural     the Neural DP Simulator (Li et al. 2023)              a checkpoint
diagnosed  the base model + the effects a diagnose report fitted ``diagnosed:REPORT.json``
========== ===================================================== =========================

Every simulator is the project's own code, so an import error is a bug and propagates: it is never taken
for an absent simulator (none of them depends on an optional third-party extra).
"""

from __future__ import annotations

import os
from collections.abc import Callable

from dp5k_common.errors import BadInputError

from .interface import DPSimulator


def _disk() -> type[DPSimulator]:
    from .disk import TranslatingDiskSimulator

    return TranslatingDiskSimulator


def _butterworth() -> type[DPSimulator]:
    from .butterworth import ButterworthSimulator

    return ButterworthSimulator


def _raytrace() -> type[DPSimulator]:
    from .raytrace import RayTracingSimulator

    return RayTracingSimulator


def _base() -> type[DPSimulator]:
    from .base import BaseModel

    return BaseModel


def _neural() -> type[DPSimulator]:
    from .neural import NeuralDPSimulator

    return NeuralDPSimulator


def _diagnosed() -> type[DPSimulator]:
    from .diagnosed import DiagnosedSimulator

    return DiagnosedSimulator


_FACTORIES: dict[str, Callable[[], type[DPSimulator]]] = {
    "disk": _disk,
    "butterworth": _butterworth,
    "raytrace": _raytrace,
    "base": _base,
    "neural": _neural,
    "diagnosed": _diagnosed,
}
DIAGNOSED_PREFIX = "diagnosed:"
"""``diagnosed:REPORT.json`` names the diagnosed simulator together with its report."""
PEERS: tuple[str, ...] = ("disk", "butterworth", "raytrace")
"""The handcrafted peers of the paper's Table 2, in its column order."""


def available_simulators(with_neural: bool = True) -> list[str]:
    """Names in Table 2 order (peers, base, then neural when a checkpoint is at hand)."""
    return list(PEERS) + ["base"] + (["neural"] if with_neural else [])


def simulator_class(name: str) -> type[DPSimulator]:
    """The class registered under ``name``.

    Raises:
        BadInputError: unknown name.
    """
    if name.startswith(DIAGNOSED_PREFIX):
        name = "diagnosed"
    if name not in _FACTORIES:
        raise BadInputError(f"unknown simulator {name!r} (known: {', '.join(_FACTORIES)})", where="simulator")
    return _FACTORIES[name]()


def get_simulator(name: str, checkpoint: str | os.PathLike[str] | None = None) -> DPSimulator:
    """A ready simulator instance (published defaults; ``neural`` loaded from ``checkpoint``).

    Raises:
        BadInputError: unknown name, ``neural`` without a checkpoint, or an unreadable checkpoint;
            ``diagnosed`` without a report, or a report without ``extended_model_spec``.
    """
    cls = simulator_class(name)
    if cls.name == "diagnosed":
        report = name[len(DIAGNOSED_PREFIX):] if name.startswith(DIAGNOSED_PREFIX) else ""
        if not report:
            raise BadInputError("the diagnosed simulator needs a report: diagnosed:REPORT.json (from 'dp5k diagnose')",
                                where="simulator")
        return cls.from_report(report)  # type: ignore[attr-defined]
    if name == "neural":
        if checkpoint is None:
            raise BadInputError("the neural simulator needs a checkpoint (train one with 'dp5k train')", where="simulator")
        return cls.from_checkpoint(checkpoint)  # type: ignore[attr-defined]
    sim = cls()
    sim.eval()
    return sim
