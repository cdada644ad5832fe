"""Capture one scene from Python: the device wiring shared by the real rig and the simulated rig.

``dp5k capture`` is a thin click shell over :func:`capture_scene`; tests and the demo call it directly.
Both paths do the same thing once their devices exist: open the session writer, open the two bodies
by serial, run the scene sequence (:func:`~dp5k_capture.capture.run_scene`) and close every device;
they differ only in where the devices come from (USB + serial port + an SDL window on the projector's
display, or the simulated rig) and in who places the ChArUco board (the operator, or the studio).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .canon import CaptureTiming
from .capture import BoardPositioner, OperatorBoard, RigDevices, run_scene
from .devices import open_bodies
from .display import PatternWindow
from .escvp21 import EpsonProjector, EscVp21Timing
from .paths import check_out_dir, check_scene_name
from .ptp.session import SessionConfig
from .rawsession import RawSessionWriter, count_prior_runs
from .rig import RigConfig

log = logging.getLogger(__name__)

SIM_PROJECTOR_POLL_S = 0.05  # the simulated EB-U42 answers at once: poll its state faster than the real one


@dataclass(frozen=True)
class SimSpec:
    """A capture from the simulated rig (``--sim``).

    Attributes:
        scale: studio scale (``"small"`` = 336 x 224 raw, ``"medium"``, ``"paper"`` or a sensor downscale factor).
        seed: studio seed (rig jitter, noise).
        faults: ``--sim-faults`` text (:mod:`dp5k_capture.sim.fault_spec`), e.g. ``disconnect@37,busy=0.1``.
        server: the Unix socket of a simulated rig in its own process (:mod:`dp5k_capture.sim.server`); then
            ``scale`` and ``seed`` are the server's, and the bodies outlive this client.
    """

    scale: float | str = "small"
    seed: int = 0
    faults: str = ""
    server: Path | None = None


@dataclass(frozen=True)
class CaptureResult:
    """What :func:`capture_scene` did: the session folder and how many raw files were written by this run."""

    dir: Path
    written: int


@dataclass
class _Rig:
    """The opened non-body devices of one run and what differs between the real and simulated rig."""

    rig: RigConfig
    projector: EpsonProjector
    window: PatternWindow
    board: BoardPositioner
    writer: RawSessionWriter
    backend: Any = None
    before_complete: Callable[[Path], None] | None = None


def capture_scene(scene: str, out: Path, rig: RigConfig, *, sim: SimSpec | None = None,
                  prompt: Callable[[str], None] | None = None, session: SessionConfig | None = None,
                  timing: CaptureTiming | None = None) -> CaptureResult:
    """Capture (or resume) scene ``scene`` into ``out/scene`` on the real rig, or the simulated one if ``sim``.

    Args:
        scene: scene name (validated by the session writer).
        out: the raw session root (``--out``).
        rig: the rig (``rig.toml``); for ``sim`` its exposure plan and ids are kept, serials and ports replaced.
        sim: simulate the rig (bodies on a simulated USB bus, projector on a pty, the virtual studio), in this
            process or, with ``sim.server``, in a sim-rig server process.
        prompt: how the operator is asked to move the ChArUco board on the real rig (shows a message, waits).
        session: PTP session bounds for the bodies (default: rig.toml ``[timeouts] transaction_s``).
        timing: EOS capture-loop bounds (default: rig.toml ``[timeouts]``).

    Raises:
        dp5k_common.errors.BadInputError: a hostile scene name or an unwritable ``out`` (before any device is touched).
        dp5k_common.errors.DP5KError: bad input, a device fault (naming the device and step), storage errors.
    """
    check_scene_name(scene)
    check_out_dir(Path(out), create=True)  # before any device is touched
    opener = _simulated if sim is not None else _real
    with opener(scene, Path(out), rig, sim, prompt) as r:
        devices = RigDevices({}, r.projector, r.window, r.board)
        try:
            devices.bodies = open_bodies(r.rig, backend=r.backend,
                                         config=session or SessionConfig(timeout_s=r.rig.timeouts.transaction_s),
                                         timing=timing or CaptureTiming.from_timeouts(r.rig.timeouts))
            written = run_scene(r.rig, devices, r.writer, before_complete=r.before_complete)
        finally:
            devices.close()
    return CaptureResult(r.writer.dir, written)


@contextmanager
def _real(scene: str, out: Path, rig: RigConfig, sim: SimSpec | None, prompt: Callable[[str], None] | None) -> Iterator[_Rig]:
    if not all(b.serial for b in rig.bodies):
        log.warning("rig.toml gives no body serials: bodies are taken in USB order")
    writer = RawSessionWriter(out, scene, rig, "CR2", extra={"simulated": False})
    projector = EpsonProjector(rig.projector.port)
    try:
        window = PatternWindow(rig.projector.width, rig.projector.height, rig.projector.display_index, rig.projector.settle_s)
    except BaseException:
        projector.close()
        raise
    board = OperatorBoard(prompt or (lambda msg: input(f"{msg}: ")))
    yield _Rig(rig, projector, window, board, writer)


@contextmanager
def _simulated(scene: str, out: Path, rig: RigConfig, sim: SimSpec | None, prompt: Callable[[str], None] | None) -> Iterator[_Rig]:
    from .sim.world import StudioOptics, make_sim_rig, sim_studio_scene, write_ground_truth_once

    assert sim is not None
    if sim.server is not None:
        with _served(scene, out, rig, sim) as r:
            yield r
        return
    studio_scene = sim_studio_scene(scene)
    run = count_prior_runs(out / scene)  # new bodies and a new board placement each run: the world of a later run
    srig = make_sim_rig(rig, optics_factory=lambda proj, win: StudioOptics(studio_scene, proj, sim.scale, sim.seed, run=run),
                        seed=sim.seed, faults=sim.faults, run=run)
    try:
        writer = RawSessionWriter(out, scene, srig.rig, "dng", extra={
            "simulated": True, "studio": {"scene": str(studio_scene), "scale": sim.scale, "seed": sim.seed}})
        projector = EpsonProjector(srig.rig.projector.port, timing=EscVp21Timing(poll_s=SIM_PROJECTOR_POLL_S))
        assert srig.window is not None
        yield _Rig(srig.rig, projector, srig.window, srig.optics, writer, backend=srig.backend,
                   before_complete=lambda session_dir: write_ground_truth_once(srig.optics, session_dir))
    finally:
        srig.close()


@contextmanager
def _served(scene: str, out: Path, rig: RigConfig, sim: SimSpec) -> Iterator[_Rig]:
    from .sim.remote import connect_sim_rig

    assert sim.server is not None
    remote = connect_sim_rig(sim.server, rig, sim.faults)
    try:
        writer = RawSessionWriter(out, scene, remote.rig, "dng", extra={"simulated": True, "sim_rig": remote.describe})
        projector = EpsonProjector(remote.rig.projector.port, timing=EscVp21Timing(poll_s=SIM_PROJECTOR_POLL_S))
        yield _Rig(remote.rig, projector, remote.window, remote.board, writer, backend=remote.backend,  # type: ignore[arg-type]
                   before_complete=remote.write_ground_truth_once)
    finally:
        remote.close()


__all__ = ["CaptureResult", "SimSpec", "capture_scene"]
