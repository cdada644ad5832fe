"""Every simulator by name, and :class:`SimulatorSpec`: a simulator named on a command line, parsed once.

========== ===================================================== =========================
name       simulator                                             spec
========== ===================================================== =========================
disk       translating-disk PSF, layered (Punnappurath 2020)     ``disk``
butterworth Butterworth PSF, layered (Abuolaim 2021)             ``butterworth``
raytrace   thin-lens ray tracing, aperture points (Pan 2021)     ``raytrace``
base       the physical base model (``neural_dp.simulators.base``) ``base``
neural     the Neural DP Simulator (Li et al. 2023)              ``neural:CKPT`` (a ``dp5k train`` checkpoint)
diagnosed  the base model + the effects a diagnose report fitted ``diagnosed:REPORT.json`` (``dp5k diagnose``)
measured   a camera's kernels from a diagnose PSF atlas          ``measured:ATLAS`` (``atlas.npz``)
========== ===================================================== =========================

Every command that takes a simulator (``evaluate``, ``synthesize``, ``diagnose``, ``study downstream``) takes it
as ``--simulator SPEC`` in this syntax and parses it here. Other stages reach this module through
:mod:`neural_dp.registry`.

Every simulator is the project's own code, so an import error is a bug and propagates: it is never taken
for an absent simulator (none of them depends on an optional third-party extra).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from dp5k_common.deprecation import warn_deprecated
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


def _measured() -> type[DPSimulator]:
    from .measured import MeasuredSimulator

    return MeasuredSimulator


_FACTORIES: dict[str, Callable[[], type[DPSimulator]]] = {
    "disk": _disk,
    "butterworth": _butterworth,
    "raytrace": _raytrace,
    "base": _base,
    "neural": _neural,
    "diagnosed": _diagnosed,
    "measured": _measured,
}
"""Name -> the simulator's class, imported when first asked for (ray tracing compiles with numba)."""
PEERS: tuple[str, ...] = ("disk", "butterworth", "raytrace")
"""The handcrafted peers of the paper's Table 2, in its column order."""
NEURAL_PREFIX = "neural:"
"""``neural:CKPT`` names the Neural DP Simulator together with its checkpoint."""
DIAGNOSED_PREFIX = "diagnosed:"
"""``diagnosed:REPORT.json`` names the diagnosed simulator together with its report."""
MEASURED_PREFIX = "measured:"
"""``measured:ATLAS`` names the measured simulator together with its PSF atlas (``atlas.npz`` of ``dp5k diagnose``)."""
_WITH_FILE = {"neural": NEURAL_PREFIX, "diagnosed": DIAGNOSED_PREFIX, "measured": MEASURED_PREFIX}
SYNTAX = "disk | butterworth | raytrace | base | neural:CKPT | diagnosed:REPORT.json | measured:ATLAS"
"""What ``--simulator`` accepts (every command's help shows it)."""


@dataclass(frozen=True)
class SimulatorSpec:
    """A parsed ``--simulator``: ``name`` is a key of the table above; ``path`` is the file it needs (the Neural
    DP checkpoint of ``neural``, the diagnose report of ``diagnosed``, the PSF atlas of ``measured``; None for the
    others).

    >>> spec = SimulatorSpec.parse("neural:run/best.pt")
    >>> spec.name, spec.path.as_posix(), spec.is_neural
    ('neural', 'run/best.pt', True)
    >>> str(SimulatorSpec.parse("diagnosed:r.json")), SimulatorSpec.parse("disk").is_peer
    ('diagnosed:r.json', True)
    """

    name: str = "base"
    path: Path | None = None

    def __post_init__(self) -> None:
        if self.name not in _FACTORIES:
            raise BadInputError(f"unknown simulator {self.name!r} ({SYNTAX})", where="--simulator")
        if (self.name in _WITH_FILE) != (self.path is not None):
            raise BadInputError(f"{self.name!r}: only neural:CKPT, diagnosed:REPORT.json and measured:ATLAS name a file ({SYNTAX})",
                                where="--simulator")

    @classmethod
    def parse(cls, text: str, checkpoint: str | os.PathLike[str] | None = None) -> SimulatorSpec:
        """``disk``, ``butterworth``, ``raytrace``, ``base``, ``neural:CKPT``, ``diagnosed:REPORT.json`` or
        ``measured:ATLAS``.

        ``checkpoint`` completes a bare ``neural`` (the deprecated ``--checkpoint`` flag and
        ``get_simulator("neural", checkpoint)``); it is ignored for any other name.

        Raises:
            BadInputError: an unknown name, ``neural`` / ``diagnosed`` / ``measured`` without their file, a file after
                another name.
        """
        text = text.strip()
        for name, prefix in _WITH_FILE.items():
            if text.startswith(prefix):
                path = text[len(prefix):]
                if not path:
                    raise BadInputError(f"{prefix}... needs a file path ({SYNTAX})", where="--simulator")
                return cls(name, Path(path))
        if text == "neural":
            if checkpoint is None:
                raise BadInputError("the neural simulator needs a checkpoint: neural:CKPT (train one with 'dp5k train')",
                                    where="--simulator")
            return cls("neural", Path(checkpoint))
        if text == "diagnosed":
            raise BadInputError("the diagnosed simulator needs a report: diagnosed:REPORT.json (from 'dp5k diagnose')",
                                where="--simulator")
        if text == "measured":
            raise BadInputError("the measured simulator needs a PSF atlas: measured:ATLAS (the atlas.npz of 'dp5k diagnose')",
                                where="--simulator")
        return cls(text)

    def __str__(self) -> str:
        return f"{_WITH_FILE[self.name]}{self.path}" if self.path is not None else self.name

    @property
    def is_base(self) -> bool:
        return self.name == "base"

    @property
    def is_peer(self) -> bool:
        return self.name in PEERS

    @property
    def is_neural(self) -> bool:
        return self.name == "neural"

    @property
    def checkpoint(self) -> Path | None:
        """The Neural DP checkpoint (``neural`` only; None otherwise)."""
        return self.path if self.is_neural else None

    def folder_name(self) -> str:
        """A folder-safe form of the whole spec (``neural_run_best.pt``), for default output folders."""
        return str(self).replace(":", "_").replace("/", "_")

    def check_files(self) -> None:
        """Raises BadInputError when the file the spec names is missing (before anything is computed or written)."""
        if self.path is not None and not self.path.is_file():
            what = {"neural": "Neural DP checkpoint", "diagnosed": "diagnose report", "measured": "PSF atlas"}[self.name]
            raise BadInputError(f"{what} not found", where=self.path)

    def simulator_class(self) -> type[DPSimulator]:
        return _FACTORIES[self.name]()

    def load(self) -> DPSimulator:
        """A ready simulator on the CPU in eval mode (published defaults; ``neural`` loaded from its checkpoint,
        ``diagnosed`` rebuilt from its report, ``measured`` from its atlas).

        Raises:
            BadInputError: an unreadable checkpoint, or a report without ``extended_model_spec``.
        """
        cls = self.simulator_class()
        if self.name == "diagnosed":
            return cls.from_report(self.path)  # type: ignore[attr-defined]
        if self.is_neural:
            return cls.from_checkpoint(self.path)  # type: ignore[attr-defined]
        if self.name == "measured":
            sim = cls(self.path)
            sim.eval()
            return sim
        sim = cls()
        sim.eval()
        return sim


def spec_texts(simulators: Sequence[str], legacy_names: str | None) -> list[str]:
    """The values of a repeatable ``--simulator``, or those of the deprecated ``--simulators A,B`` (with its
    deprecation line); empty when neither was given.

    Raises:
        BadInputError: both were given.
    """
    if legacy_names is None:
        return list(simulators)
    if simulators:
        raise BadInputError("give --simulator (repeatable) or the older --simulators, not both", where="--simulators")
    warn_deprecated("--simulators A,B", "--simulator A --simulator B")
    return [t.strip() for t in legacy_names.split(",") if t.strip()]


def default_simulators(checkpoint: str | os.PathLike[str] | None = None) -> list[SimulatorSpec]:
    """Table 2's columns: the peers, the base model, then ``neural:CKPT`` when a checkpoint is at hand."""
    specs = [SimulatorSpec(name) for name in (*PEERS, "base")]
    return specs + ([SimulatorSpec("neural", Path(checkpoint))] if checkpoint is not None else [])


def get_simulator(name: str, checkpoint: str | os.PathLike[str] | None = None) -> DPSimulator:
    """``SimulatorSpec.parse(name, checkpoint).load()``: a ready simulator from a spec's text.

    Raises:
        BadInputError: see :meth:`SimulatorSpec.parse` and :meth:`SimulatorSpec.load`.
    """
    return SimulatorSpec.parse(name, checkpoint).load()
