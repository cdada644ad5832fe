"""Simulators by name: ``get_simulator("disk")`` and friends.

========== ===================================================== =========================
name       simulator                                             needs
========== ===================================================== =========================
disk       translating-disk PSF, layered (Punnappurath 2020)     -
butterworth Butterworth PSF, layered (Abuolaim 2021)             -
raytrace   thin-lens ray tracing, aperture points (Pan 2021)     -
base       the physical base model (``neural_dp.simulators.base``) the module (optional)
neural     the Neural DP Simulator (Li et al. 2023)              a checkpoint
========== ===================================================== =========================
"""

from __future__ import annotations

import importlib
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
    module = importlib.import_module("neural_dp.simulators.base")
    return module.BaseModel


def _neural() -> type[DPSimulator]:
    from .neural import NeuralDPSimulator

    return NeuralDPSimulator


_FACTORIES: dict[str, Callable[[], type[DPSimulator]]] = {
    "disk": _disk,
    "butterworth": _butterworth,
    "raytrace": _raytrace,
    "base": _base,
    "neural": _neural,
}
PEERS: tuple[str, ...] = ("disk", "butterworth", "raytrace")
"""The handcrafted peers of the paper's Table 2, in its column order."""


def base_available() -> bool:
    """Whether the physical base model module exists (it is written by another part of the project)."""
    try:
        _base()
    except (ImportError, AttributeError):
        return False
    return True


def available_simulators(with_neural: bool = True) -> list[str]:
    """Names usable right now, in Table 2 order (peers, base when present, neural)."""
    names = list(PEERS)
    if base_available():
        names.append("base")
    if with_neural:
        names.append("neural")
    return names


def simulator_class(name: str) -> type[DPSimulator]:
    """The class registered under ``name``.

    Raises:
        BadInputError: unknown name, or the base model module is missing.
    """
    if name not in _FACTORIES:
        raise BadInputError(f"unknown simulator {name!r} (known: {', '.join(_FACTORIES)})", where="simulator")
    try:
        return _FACTORIES[name]()
    except (ImportError, AttributeError) as exc:
        raise BadInputError(f"simulator {name!r} is not available ({exc})", where="simulator") from None


def get_simulator(name: str, checkpoint: str | os.PathLike[str] | None = None) -> DPSimulator:
    """A ready simulator instance (published defaults; ``neural`` loaded from ``checkpoint``).

    Raises:
        BadInputError: unknown name, ``neural`` without a checkpoint, or an unreadable checkpoint.
    """
    cls = simulator_class(name)
    if name == "neural":
        if checkpoint is None:
            raise BadInputError("the neural simulator needs a checkpoint (train one with 'dp5k train')", where="simulator")
        return cls.from_checkpoint(checkpoint)  # type: ignore[attr-defined]
    sim = cls()
    sim.eval()
    return sim
