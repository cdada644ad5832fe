"""Kill / Ctrl-C the capture client mid-transfer while the simulated bodies live on in their own process.

The sim-rig server (``python -m dp5k_capture.sim.server``, flat world) holds both bodies; ``dp5k capture
--sim-rig`` runs as a separate process with ``--sim-faults cam1.hang@30``: cam1 stops sending halfway
through its 30th raw file, so the client is blocked inside a transfer when the test kills it. A new
``dp5k capture`` must then reopen the same bodies, finish the scene, pass ``dp5k verify``, and leave every
file completed before the kill byte-identical.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from multiprocessing.connection import Client
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from dp5k_cli import main

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "SDL_VIDEODRIVER": "dummy", "DP5K_PROGRESS": "0", "OMP_NUM_THREADS": "1"}
WAIT_S = 60.0  # bound on every wait (a loaded 2-core machine)


def _status(sock: Path) -> dict[str, Any]:
    with Client(str(sock), family="AF_UNIX") as c:
        c.send(("status",))
        return c.recv()[1]


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Path]:
    sock = tmp_path / "rig.sock"
    proc = subprocess.Popen([sys.executable, "-m", "dp5k_capture.sim.server", "--socket", str(sock), "--world", "flat"],
                            cwd=REPO, env=ENV, stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + WAIT_S
        while not sock.exists():
            assert proc.poll() is None and time.monotonic() < deadline, "sim-rig server did not start"
            time.sleep(0.05)
        yield sock
    finally:
        proc.terminate()
        proc.wait(10)


def _default_sigint() -> None:
    """In the client before exec: SIGINT interrupts, as in a terminal. A test run started in the background
    of a non-interactive shell (``make test &``) ignores SIGINT, and an ignored signal stays ignored across
    exec, so the client would never see the test's Ctrl-C."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _capture(sock: Path, out: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "dp5k_cli", "capture", "--scene", "s1", "--out", str(out),
                             "--sim-rig", str(sock), *extra], cwd=REPO, env=ENV, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, preexec_fn=_default_sigint)


def _hashes(session: Path) -> dict[str, str]:
    files = json.loads((session / "manifest.json").read_text())["files"]
    return {f["path"]: hashlib.sha256((session / f["path"]).read_bytes()).hexdigest() for f in files}


def _interrupt_mid_transfer(sock: Path, out: Path, sig: signal.Signals) -> tuple[subprocess.Popen[str], dict[str, str]]:
    client = _capture(sock, out, "--sim-faults", "cam1.hang@30")
    deadline = time.monotonic() + WAIT_S
    while _status(sock)["hangs"] < 1:
        assert client.poll() is None, client.stdout.read() if client.stdout else ""
        assert time.monotonic() < deadline, "the client never reached the hanging transfer"
        time.sleep(0.1)
    assert _status(sock)["bodies"]["cam1"]["queued_in"] > 0  # the client is blocked halfway through the raw file
    kept = _hashes(out / "s1")
    client.send_signal(sig)
    client.wait(WAIT_S)
    return client, kept


def _resume_and_check(sock: Path, out: Path, kept: dict[str, str]) -> None:
    again = _capture(sock, out)
    output, _ = again.communicate(timeout=WAIT_S)
    assert again.returncode == 0, output
    assert "complete (" in output
    res = CliRunner().invoke(main, ["verify", str(out / "s1")])
    assert res.exit_code == 0 and "OK: 110 files" in res.output, res.output
    after = _hashes(out / "s1")
    assert {p: after[p] for p in kept} == kept  # no completed file changed
    assert (out / "s1/ground_truth/truth.json").is_file()
    # the raw whose download was cut off waited in cam1's buffer: rescued into quarantine and released, so nothing
    # piles up on the body (a clean scene leaves 0 images there)
    assert {c: b["objects"] for c, b in _status(sock)["bodies"].items()} == {"cam0": 0, "cam1": 0}
    m = json.loads((out / "s1/manifest.json").read_text())
    assert [(q["camera"], q["kind"]) for q in m["quarantined"]] == [("cam1", "leftover")]
    assert [c["verdict"] for c in (m["focus"]["cam0"]["checks"][-1], m["focus"]["cam1"]["checks"][-1])] == ["kept", "kept"]


@pytest.mark.slow
def test_sigkill_mid_transfer_then_a_new_capture_reopens_the_same_bodies(server: Path, tmp_path: Path) -> None:
    out = tmp_path / "raw"
    client, kept = _interrupt_mid_transfer(server, out, signal.SIGKILL)
    assert client.returncode == -signal.SIGKILL and len(kept) == 59
    st = _status(server)["bodies"]["cam1"]
    assert st["queued_in"] > 0 and st["remote_mode"] == 1  # the body still holds the half-sent file
    _resume_and_check(server, out, kept)
    assert _status(server)["bodies"]["cam1"]["resets"] == 1  # stale data -> Device Reset -> drain -> reopen


@pytest.mark.slow
def test_ctrl_c_mid_transfer_leaves_remote_mode_then_resumes(server: Path, tmp_path: Path) -> None:
    out = tmp_path / "raw"
    client, kept = _interrupt_mid_transfer(server, out, signal.SIGINT)
    output = client.stdout.read() if client.stdout else ""
    assert client.returncode == 130, output
    assert output.strip().splitlines()[-1] == (
        f"dp5k: interrupted: 59 completed files kept in {out / 's1'}; run the same command again to resume")
    bodies = _status(server)["bodies"]
    for cam in ("cam0", "cam1"):  # both bodies left remote mode; the interrupted transfer was cancelled
        assert (bodies[cam]["remote_mode"], bodies[cam]["event_mode"], bodies[cam]["queued_in"]) == (0, 0, 0)
    _resume_and_check(server, out, kept)
    assert _status(server)["bodies"]["cam1"]["resets"] == 0
