"""``--sim-faults``: the text is parsed strictly and arms the simulated bodies' faults at the planned download."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_capture.capture import RigDevices, run_scene
from dp5k_capture.devices import open_bodies
from dp5k_capture.escvp21 import EpsonProjector, EscVp21Timing
from dp5k_capture.ptp.errors import DisconnectedError
from dp5k_capture.rawsession import RawSessionWriter
from dp5k_capture.rig import RigConfig
from dp5k_capture.sim.fault_spec import BodyFaultPlan, parse_sim_faults
from dp5k_capture.sim.world import make_sim_rig
from dp5k_cli import main
from dp5k_common.errors import BadInputError

from .conftest import FAST, FAST_SESSION

IDS = ("cam0", "cam1")


def test_spec_parses_per_body_and_for_all_bodies() -> None:
    plans = parse_sim_faults("disconnect@37, busy=0.1,cam1.hang@5,cam1.denied,cam0.held,cam0.full@3", IDS)
    assert plans["cam0"] == BodyFaultPlan(disconnect_at_download=37, busy_rate=0.1, held=True, full_at_release=3)
    assert plans["cam1"] == BodyFaultPlan(disconnect_at_download=37, hang_at_download=5, busy_rate=0.1, denied=True)
    assert parse_sim_faults("", IDS) == {"cam0": BodyFaultPlan(), "cam1": BodyFaultPlan()}
    for bad, why in (("explode@3", "use disconnect@K"), ("disconnect@0", "K >= 1"), ("busy=1.5", "0..1"),
                     ("cam7.stall@2", "no body 'cam7'"), ("disconnect", "NAME@K"), ("denied@2", "denied or held"),
                     ("full", "NAME@K"), ("full=0.5", "full@K")):
        with pytest.raises(BadInputError, match=why):
            parse_sim_faults(bad, IDS)


def test_cli_refuses_a_bad_spec_before_anything_starts(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(tmp_path / "raw"), "--sim", "--sim-faults", "boom@1"])
    assert res.exit_code == 3 and "--sim-faults: fault 'boom@1'" in res.output and not (tmp_path / "raw").exists()
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(tmp_path / "raw"), "--sim-faults", "busy=0.1", "--dry-run"])
    assert res.exit_code == 3 and "needs the simulated rig" in res.output


def test_disconnect_fires_in_the_planned_download_under_a_busy_storm(tmp_path: Path) -> None:
    sim = make_sim_rig(RigConfig(), raw_size_px=(48, 32), warmup_s=0.05, faults="cam1.disconnect@5,busy=0.1")
    try:
        writer = RawSessionWriter(tmp_path, "s1", sim.rig, "dng", extra={"simulated": True})
        proj = EpsonProjector(sim.rig.projector.port, timing=EscVp21Timing(poll_s=0.01, default_s=0.5))
        devices = RigDevices(open_bodies(sim.rig, backend=sim.backend, config=FAST_SESSION, timing=FAST), proj, sim.window, sim.optics)
        try:
            with pytest.raises(DisconnectedError) as err:
                run_scene(sim.rig, devices, writer)
        finally:
            devices.close()
        assert all(b.faults.busy_answers > 0 for b in sim.bodies.values())  # both bodies were busy, the client retried
    finally:
        sim.close()
    assert str(err.value).startswith("cam1 (") and "dp_f2" in str(err.value)  # cam1's 5th raw: charuco x3, f/1.8, f/2
    files = [f["path"] for f in json.loads((tmp_path / "s1/manifest.json").read_text())["files"]]
    assert len(files) == 9 and "cam0/dp_f2.dng" in files and "cam1/dp_f2.dng" not in files
