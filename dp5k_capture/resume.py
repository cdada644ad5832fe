"""Before a run shoots: one focus per body and scene, whole ChArUco pairs, nothing left behind on a body.

* **Focus, once per body and scene.** The first run AFs each body at its focus point and locks the focus
  (:meth:`~dp5k_capture.canon.EosCamera.lock_focus`: FocusMode MF where the body lets the PC set it; DoAf is
  never sent again and every release goes without AF); the AF result and what the body reports about the
  lock go to the manifest's ``focus`` record. A **resume does not AF**: it re-shoots one frame with the
  settings of the body's kept DP frame of widest aperture into ``focus/`` and compares the two in the focus
  window (:mod:`~dp5k_capture.focus_check`). Focus unchanged: everything is kept. Focus moved beyond the
  thresholds: every **focus-dependent** frame of that body (its DP apertures and its sharp frame, whose
  blur the focus distance sets: the dataset assumes one focus distance per camera and scene, Eq. 5 and 6)
  goes to ``quarantine/run<k>/``, the body AFs and locks again and the plan re-shoots them; the log and the
  manifest say so. Structured light and ChArUco views (f/22, geometry) are kept. The view itself moved
  (body, lens or scene): one body's re-shoot cannot repair the scene, the run stops with an error.
* **A ChArUco pose is a stereo pair**: one side kept without the other (an interruption between the two
  bodies' shots) goes to quarantine, and the board is placed again for both.
* **Nothing piles up on a body**: images a body announced to an interrupted run, and the one whose download
  a kill cut off (its handle is recorded before each download), are downloaded into
  ``quarantine/run<k>/leftover/`` and released from the body (TransferComplete; a card copy is deleted only
  with ``delete_from_card``); the count is logged and recorded.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from dp5k_common.errors import DeviceError
from dp5k_common.rawfile import read_dual_pixel

from .canon import EosCamera
from .focus_check import FocusThresholds, compare_focus
from .ptp.codes import EosEvent
from .ptp.eos_events import EosRecord
from .ptp.errors import ResponseError
from .rawsession import FOCUS_DIR, RawSessionWriter, now_iso, plan_scene
from .rig import BodyConfig, RigConfig
from .steps import capture_one, dual_pixel_check, step

log = logging.getLogger(__name__)

FOCUS_DEPENDENT_KINDS = ("dp", "sharp")
LEFTOVER_REASON = "announced by the body to an interrupted run and never stored; downloaded and released from the body on reopen"
PAIR_REASON = ("one side of a ChArUco pair: the other side was not captured before the interruption; a pose is a stereo "
               "pair, so the board is placed again and both sides are re-shot")


def complete_charuco_pairs(rig: RigConfig, writer: RawSessionWriter) -> list[str]:
    """Quarantine the kept side of every ChArUco view that only some bodies have; returns the views."""
    views = []
    for shot in (s for s in plan_scene(rig) if s.kind == "charuco"):
        done = [b.id for b in rig.bodies if writer.done(b.id, shot)]
        if done and len(done) < len(rig.bodies):
            moved = [writer.quarantine(writer.relpath(cam, shot), PAIR_REASON) for cam in done]
            text = (f"{shot.stem}: only {', '.join(done)} was captured before the interruption: the pose is re-shot on "
                    f"both bodies; the kept side moved to {', '.join(moved)}")
            log.warning(text)
            writer.note(text)
            views.append(shot.stem)
    return views


def rescue_leftovers(cam: EosCamera, cam_id: str, writer: RawSessionWriter) -> int:
    """Download images an interrupted run left on the body into quarantine and release them; returns the count."""
    recs = list(cam.stale)
    flight = writer.manifest["in_flight"].get(cam_id)
    if flight and flight.get("handle") is not None and flight["handle"] not in {r.handle for r in recs}:
        code = EosEvent.OBJECT_ADDED_EX if flight.get("on_card") else EosEvent.REQUEST_OBJECT_TRANSFER
        recs.append(EosRecord(code, handle=int(flight["handle"]), size=flight.get("size"), filename=flight.get("filename")))
    cam.stale = []
    saved = []
    for rec in recs:
        try:
            dl = cam.download(rec)
        except ResponseError as exc:  # already released (the kill came after TransferComplete), or gone with a power cycle
            log.info("%s: image %s of an interrupted run is no longer on the body (%s)", cam.name, rec.filename, exc.message)
            continue
        meta = {"camera_filename": dl.filename, "handle": dl.handle,
                **({"shot": flight.get("shot")} if flight and flight.get("handle") == dl.handle else {})}
        saved.append(writer.quarantine_data(cam_id, dl.filename, dl.data, LEFTOVER_REASON, meta))
        cam.release_card_copy(dl)
    writer.clear_in_flight(cam_id)
    if saved:
        text = (f"{cam_id}: {len(saved)} image(s) left on the body by an interrupted run moved to {', '.join(saved)} and "
                "released from the body")
        log.warning(text)
        writer.note(text)
    return len(saved)


def _autofocus_and_lock(cam: EosCamera, body: BodyConfig, writer: RawSessionWriter, why: str) -> None:
    step("autofocus", cam.focus_at, body.focus_point_px)
    lock = step("focus lock", cam.lock_focus)
    rec = writer.focus_record(body.id)
    rec["af"].append({"run": writer.run, "time": now_iso(), "point_px": list(cam.focus_point_px or body.focus_point_px),
                      "why": why, "af_state": lock["af_state"]})  # type: ignore[index]
    rec["lock"] = lock
    writer.set_focus_point(body.id, body.focus_point_px)


def _check_frame(cam: EosCamera, body: BodyConfig, ref: dict[str, Any], writer: RawSessionWriter, check_dp: bool) -> dict[str, Any]:
    """Re-shoot the kept reference's exposure into focus/ and return its stored path, size and hash."""
    name = f"{FOCUS_DIR}/{body.id}_check_run{writer.run}.{writer.ext}"
    dl = step("focus check", capture_one, cam, body.id, name, ref["f_number"], ref["shutter_s"], ref["iso"], writer)
    stored = writer.store_extra(name, dl.data, check=dual_pixel_check(cam.name) if check_dp else None)
    writer.clear_in_flight(body.id)
    cam.release_card_copy(dl)
    return stored


def settle_focus(cam: EosCamera, body: BodyConfig, rig: RigConfig, writer: RawSessionWriter, *, check_dp: bool = True,
                 thresholds: FocusThresholds | None = None) -> str:
    """Make the body's focus the scene's one focus: AF + lock on the first run, a focus check on a resume.

    Returns ``"af"`` (first AF), ``"kept"`` (check passed or nothing to check) or ``"moved"`` (frames re-shot).

    Raises:
        DeviceError: the view moved (body, lens or scene), so kept and new frames cannot form one scene.
    """
    rec = writer.focus_record(body.id)
    if not rec.get("lock"):
        if writer.kept(body.id, FOCUS_DEPENDENT_KINDS):
            log.warning("%s: the kept frames carry no focus record (captured by an older dp5k): AF runs again and they "
                        "cannot be checked against it", cam.name)
        _autofocus_and_lock(cam, body, writer, "first AF of the scene")
        return "af"
    cam.focus_point_px = tuple(rec["af"][-1]["point_px"]) if rec.get("af") else body.focus_point_px  # type: ignore[assignment]
    refs = sorted(writer.kept(body.id, ("dp",)), key=lambda f: f["f_number"])
    if not refs:  # nothing focus-dependent kept yet: hold the lock, nothing to compare
        rec["checks"].append({"run": writer.run, "time": now_iso(), "verdict": "nothing focus-dependent kept",
                              "lock": step("focus lock", cam.lock_focus)})
        writer.save_focus()
        return "kept"
    ref = refs[0]
    stored = _check_frame(cam, body, ref, writer, check_dp)
    cmp = compare_focus(read_dual_pixel(writer.dir / ref["path"]), read_dual_pixel(writer.dir / stored["path"]),
                        cam.focus_point_px or body.focus_point_px, thresholds, rig.aux_view)
    verdict = "view moved" if cmp.view_moved else "moved" if cmp.moved else "kept"
    rec["checks"].append({"run": writer.run, "time": now_iso(), **stored, "reference": ref["path"], "verdict": verdict,
                          "thresholds": vars(thresholds or FocusThresholds()), **cmp.to_json()})
    writer.save_focus()
    if cmp.view_moved:
        raise DeviceError(f"focus check: {cmp.reason}: the body, its lens or the scene moved since the kept frames; "
                          f"re-shooting one body cannot make them one scene again: capture it under a new --scene "
                          f"(the kept files stay in {writer.dir}, the check frame in {stored['path']})", where=cam.name)
    if not cmp.moved:
        text = f"{body.id}: focus unchanged since the kept frames ({cmp.reason}; check frame {stored['path']})"
        log.info(text)
        rec["checks"][-1]["lock"] = step("focus lock", cam.lock_focus)  # what the body reports now (MF held?)
        writer.note(text)
        return "kept"
    moved = [writer.quarantine(f["path"], f"focus moved since it was shot ({cmp.reason}); the body refocused and it was re-shot")
             for f in writer.kept(body.id, FOCUS_DEPENDENT_KINDS)]
    text = (f"{body.id}: focus moved since the kept frames ({cmp.reason}): its {len(moved)} focus-dependent frames "
            f"(DP apertures, sharp) moved to quarantine/run{writer.run}/ and are re-shot after a new AF")
    log.warning(text)
    writer.note(text)
    _autofocus_and_lock(cam, body, writer, f"refocus: focus moved ({cmp.reason})")
    return "moved"


def describe_resume(manifest: dict[str, Any]) -> list[str]:
    """What a resume of this manifest's session checks and re-shoots before it continues (``--dry-run``)."""
    files = manifest.get("files", [])
    by_cam: dict[str, set[str]] = {}
    for f in files:
        by_cam.setdefault(f["camera"], set()).add(f["path"].split("/", 1)[-1].rsplit(".", 1)[0])
    lines = []
    for cam, stems in sorted(by_cam.items()):
        if any(s.startswith("dp_") for s in stems):
            lines.append(f"{cam}: one frame at its widest kept DP aperture into focus/ to check the focus; if it moved, "
                         "its DP and sharp frames go to quarantine/ and are re-shot after a new AF")
    views = {s for stems in by_cam.values() for s in stems if s.startswith("charuco_")}
    for view in sorted(views):
        have = [c for c, stems in sorted(by_cam.items()) if view in stems]
        if len(have) < len(manifest.get("rig", {}).get("bodies", [])):
            lines.append(f"{view}: only {', '.join(have)} kept: both sides re-shot (the kept side goes to quarantine/)")
    for cam, flight in sorted(manifest.get("in_flight", {}).items()):
        lines.append(f"{cam}: the image of {flight.get('shot')} cut off by the interruption is moved to quarantine/ "
                     "and released from the body")
    return lines


def prepare_run(rig: RigConfig, bodies: dict[str, EosCamera], writer: RawSessionWriter, clear_board: Callable[[], None],
                *, check_dp: bool = True) -> None:
    """Everything a run does before its first planned shot (the projector is on and blanked): whole ChArUco
    pairs, the board out of the scene, leftovers rescued, each body's focus settled (see the module docstring)."""
    complete_charuco_pairs(rig, writer)
    if writer.manifest.get("board_in_view") is not None:  # the last run stopped with the board in the scene
        clear_board()
        writer.set_board(None)
    for b in rig.bodies:
        rescue_leftovers(bodies[b.id], b.id, writer)
    for b in rig.bodies:
        settle_focus(bodies[b.id], b, rig, writer, check_dp=check_dp)


__all__ = ["prepare_run", "describe_resume", "settle_focus", "rescue_leftovers", "complete_charuco_pairs", "FOCUS_DEPENDENT_KINDS"]
