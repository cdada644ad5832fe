"""Nothing piles up on a body: an image announced to a run that was interrupted (the one whose download was cut off,
or one announced and never polled) is downloaded into quarantine on reopen and released from the body."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dp5k_capture.devices import open_bodies
from dp5k_capture.ptp.errors import DisconnectedError
from dp5k_capture.rawsession import verify_session
from dp5k_capture.sim.fault_spec import BodyFaultPlan
from dp5k_capture.sim.world import SimRig

from .conftest import FAST, FAST_SESSION, client_run, replug


def _leftovers(out: Path) -> list[dict]:
    return [q for q in json.loads((out / "s1/manifest.json").read_text())["quarantined"] if q["kind"] == "leftover"]


def test_the_image_a_disconnect_cut_off_is_rescued_and_released(sim_rig: SimRig, tmp_path: Path) -> None:
    body = sim_rig.bodies["cam1"]
    sim_rig.usb_devices["cam1"].arm(BodyFaultPlan(disconnect_at_download=5))
    with pytest.raises(DisconnectedError):
        client_run(sim_rig, tmp_path)
    [cut_off] = body.objects.values()  # the image whose download was cut off waits in the body's buffer
    assert json.loads((tmp_path / "s1/manifest.json").read_text())["in_flight"]["cam1"]["handle"] == cut_off.handle
    replug(sim_rig, "cam1")
    client_run(sim_rig, tmp_path)
    assert body.objects == {}  # released: the count did not grow (a clean scene leaves 0 in the buffer)
    [q] = _leftovers(tmp_path)
    assert q["path"] == f"quarantine/run2/leftover/cam1/{cut_off.name}" and q["shot"] == "dp_f2"
    assert (tmp_path / "s1" / q["path"]).read_bytes() == cut_off.data  # moved to the PC, never lost
    m = json.loads((tmp_path / "s1/manifest.json").read_text())
    assert m["in_flight"] == {} and any("cam1: 1 image(s) left on the body" in t for t in m["runs"][1]["notes"])
    assert verify_session(tmp_path / "s1").problems == []


def test_an_image_announced_but_never_polled_is_rescued_on_reopen(sim_rig: SimRig, tmp_path: Path) -> None:
    client_run(sim_rig, tmp_path / "first")  # a whole scene: the bodies are in use and their buffers are empty
    assert all(b.objects == {} for b in sim_rig.bodies.values())
    cams = open_bodies(sim_rig.rig, backend=sim_rig.backend, config=FAST_SESSION, timing=FAST)
    cams["cam1"].set_exposure(4.0, 1 / 60, 100)
    cams["cam1"].release()  # ... and the client is killed before it polled the announcement: nothing is closed
    assert len(sim_rig.bodies["cam1"].objects) == 1
    client_run(sim_rig, tmp_path)
    assert all(b.objects == {} for b in sim_rig.bodies.values())
    [q] = _leftovers(tmp_path)
    assert q["camera"] == "cam1" and "shot" not in q and (tmp_path / "s1" / q["path"]).is_file()
