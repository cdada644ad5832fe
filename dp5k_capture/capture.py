"""The capture sequence of one scene on the two-body + projector rig.

Order (per scene, focus fixed): autofocus both bodies once at their focus points and lock the focus; 3 ChArUco
views for stereo recalibration (the operator, or the simulated studio, places the board); Dual Pixel RAW at each
DP aperture and the sharp f/22 frame with the projector blanked; then the 46 structured-light projections
(projector unblanked), each shot by both bodies. Every file is checked to be a two-frame Dual Pixel RAW
before it gets its final name; a scene whose raws are not DP stops at the first file. Completed files are
skipped when the scene is resumed, after the checks of :mod:`~dp5k_capture.resume` (focus unchanged, whole
ChArUco pairs, nothing left on the bodies).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from dp5k_common.progress import progress

from .canon import EosCamera
from .display import PatternWindow
from .escvp21 import EpsonProjector
from .patterns import projection, projection_label
from .rawsession import RawSessionWriter, plan_scene
from .resume import prepare_run
from .rig import RigConfig
from .steps import dual_pixel_check, keep_bodies_awake, shoot, step

log = logging.getLogger(__name__)


class BoardPositioner(Protocol):
    """Puts the ChArUco board in view (pose ``view``) or takes it away."""

    def place(self, view: int) -> None: ...
    def clear(self) -> None: ...


@dataclass
class OperatorBoard:
    """The real rig: ask the operator to move the board (``ask`` shows a message and waits)."""

    ask: Callable[[str], None]

    def place(self, view: int) -> None:
        self.ask(f"Place the ChArUco board in pose {view + 1} (visible to both cameras, near the focus distance), then press Enter")

    def clear(self) -> None:
        self.ask("Remove the ChArUco board from the scene, then press Enter")


@dataclass
class RigDevices:
    """Open devices of the rig."""

    bodies: dict[str, EosCamera]
    projector: EpsonProjector
    window: PatternWindow
    board: BoardPositioner
    closers: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        for cam in self.bodies.values():
            cam.close()
        for fn in (self.projector.close, self.window.close, *self.closers):
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - closing must not hide the original error
                log.warning("closing: %s", exc)


def describe_plan(rig: RigConfig, scene: str, out: Path, ext: str) -> list[str]:
    """The plan as text lines (``--dry-run``)."""
    shots = plan_scene(rig)
    lines = [f"scene {scene} -> {out / scene} ({len(shots) * len(rig.bodies)} raw files, .{ext})"]
    for b in rig.bodies:
        lines.append(f"  {b.id}: {b.model} serial {b.serial or '?'} {b.lens}, focus point {list(b.focus_point_px)}")
    p = rig.projector
    lines.append(f"  projector: {p.model} on {p.port}, HDMI display {p.display_index}, {p.width}x{p.height}, source {p.source}")
    for s in shots:
        extra = f"  pattern {s.index} ({projection_label(s.index, p.width, p.height)})" if s.kind == "sl" else (
            f"  board pose {s.index + 1}" if s.kind == "charuco" else "")
        lines.append(f"  {s.stem:<10} {s.kind:<8} f/{s.f_number:g}  {_shutter_text(s.shutter_s)}  ISO {s.iso}{extra}")
    return lines


def _shutter_text(s: float) -> str:
    return f"{s:g} s" if s >= 0.3 else f"1/{round(1 / s)} s"


def run_scene(rig: RigConfig, devices: RigDevices, writer: RawSessionWriter, *, check_dp: bool = True,
              before_complete: Callable[[Path], None] | None = None) -> int:
    """Capture (or resume) one scene. Returns the number of files written now.

    Errors name the device and the step (``cam1 (...): dp_f2.8: ...``); files completed before the
    error are kept and the next run resumes after them. ``before_complete(session_dir)`` runs after the
    last shot and before the session is marked complete (the simulated rig writes ``ground_truth/`` there),
    so an interruption in between leaves an incomplete session that the next run finishes.
    """
    shots = plan_scene(rig)
    todo = [(s, b.id) for s in shots for b in rig.bodies if not writer.done(b.id, s)]
    if not todo:
        if before_complete is not None:
            before_complete(writer.dir)
        writer.finish(rig)
        return 0
    proj = devices.projector
    step("projector start-up", proj.prepare, rig.projector.source)
    step("blank projector", proj.blank, True)

    def clear_board() -> None:
        with keep_bodies_awake(devices.bodies.values()):
            devices.board.clear()

    prepare_run(rig, devices.bodies, writer, clear_board, check_dp=check_dp)
    todo = [(s, b.id) for s in shots for b in rig.bodies if not writer.done(b.id, s)]  # the checks may add re-shoots
    written = 0
    board_out = True
    blanked = True
    bar = progress(total=len(todo), desc=f"capture {writer.scene}", unit="file")
    try:
        for shot in shots:
            pending = [b.id for b in rig.bodies if not writer.done(b.id, shot)]
            if not pending:
                continue
            if shot.kind == "charuco":
                writer.set_board(int(shot.index or 0))  # recorded first: a resume clears a board left in the scene
                with keep_bodies_awake(devices.bodies.values()):
                    devices.board.place(int(shot.index or 0))
                board_out = False
            elif not board_out:
                clear_board()
                writer.set_board(None)
                board_out = True
            if shot.kind == "sl":
                if blanked:
                    step("unblank projector", proj.blank, False)
                    blanked = False
                img = projection(int(shot.index or 0), rig.projector.width, rig.projector.height)
                devices.window.show(img, shot.index)
            for cam_id in pending:
                shoot(devices.bodies[cam_id], cam_id, shot, writer, check_dp)
                written += 1
                bar.update(1)
        if not board_out:
            clear_board()
            writer.set_board(None)
        step("blank projector", proj.blank, True)
    finally:
        bar.close()
    if before_complete is not None:
        before_complete(writer.dir)
    writer.finish(rig)
    return written


__all__ = ["run_scene", "describe_plan", "RigDevices", "OperatorBoard", "BoardPositioner", "keep_bodies_awake",
           "dual_pixel_check"]
