"""Ctrl-C at any moment gives one line, never a traceback; a read that blocks still lets Ctrl-C through within about
a second; ``ground_truth/`` written by a sim-rig server follows the client's umask.

The 50 random Ctrl-Cs run the capture client in this process (the command exactly as ``dp5k capture --sim-rig``
runs it, without 50 interpreter start-ups) against a sim-rig server process with a tiny plan (a 2 x 2 projector,
one ChArUco view, one DP aperture: 18 files), so each try takes a fraction of a second. The signal is real
(``os.kill(getpid(), SIGINT)`` from a timer thread); it counts as a Ctrl-C of the command only while the command
runs (a handler that finds no dp5k or click frame on the stack ignores it, so it never hits the test itself).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import FrameType

import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_capture.ptp.session import SessionConfig
from dp5k_cli import main

from .conftest import Body

REPO = Path(__file__).resolve().parents[2]
TRIES = 50
TINY_RIG = '[projector]\nwidth = 2\nheight = 2\n[exposure]\ndp_f_numbers = [1.8]\ncharuco_views = 1\n'


@pytest.fixture
def tiny_server(tmp_path: Path) -> Iterator[tuple[Path, Path]]:
    """A sim-rig server (flat world, tiny plan) running under umask 077; yields (socket, rig.toml)."""
    rig = tmp_path / "tiny.toml"
    rig.write_text(TINY_RIG)
    sock = tmp_path / "rig.sock"

    def child() -> None:
        os.umask(0o077)
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the test's Ctrl-Cs are for the client only

    env = {**os.environ, "PYTHONPATH": str(REPO), "SDL_VIDEODRIVER": "dummy", "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "dp5k_capture.sim.server", "--socket", str(sock), "--world", "flat",
                             "--rig", str(rig)], cwd=REPO, env=env, stdout=subprocess.DEVNULL, preexec_fn=child)
    try:
        deadline = time.monotonic() + 60
        while not sock.exists():
            assert proc.poll() is None and time.monotonic() < deadline, "sim-rig server did not start"
            time.sleep(0.05)
        yield sock, rig
    finally:
        proc.terminate()
        proc.wait(10)


def _in_command(frame: FrameType | None) -> bool:
    while frame is not None:
        if frame.f_globals.get("__name__", "").startswith(("dp5k", "click.core")):
            return True
        frame = frame.f_back
    return False


def _ctrl_c(signum: int, frame: FrameType | None) -> None:
    if _in_command(frame):
        raise KeyboardInterrupt


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")  # a Ctrl-C "ignored" in a finalizer
def test_fifty_random_ctrl_cs_with_sim_rig_never_give_a_traceback(tiny_server: tuple[Path, Path], tmp_path: Path) -> None:
    sock, rig = tiny_server
    out = tmp_path / "raw"
    runner = CliRunner()
    old_mask, old_handler = os.umask(0o022), signal.signal(signal.SIGINT, _ctrl_c)
    try:
        args = ["-q", "capture", "--out", str(out), "--sim-rig", str(sock), "--rig", str(rig)]
        first = runner.invoke(main, [*args, "--scene", "s0"])  # imports, pygame: the later runs are faster
        assert first.exit_code == 0, first.output
        t0 = time.monotonic()
        second = runner.invoke(main, [*args, "--scene", "s1"])  # one whole scene: how long a run takes
        assert second.exit_code == 0, second.output
        whole_runs_s = [time.monotonic() - t0]  # new scenes that no Ctrl-C reached: how long a whole run takes
        rng = np.random.default_rng(32)
        scene, outcomes, fresh = 2, [], True
        for _ in range(TRIES):
            # A run takes longer while the machine warms up or is busy: drawing over 1.2 x the median whole run so
            # far keeps about 5 in 6 Ctrl-Cs inside a run on a fast machine and on a loaded one alike (a run
            # that resumes an interrupted scene is shorter and is not counted).
            delay_s = float(rng.uniform(0.0, 1.2 * float(np.median(whole_runs_s))))
            timer = threading.Timer(delay_s, os.kill, (os.getpid(), signal.SIGINT))
            timer.start()
            t0, started = time.monotonic(), scene
            try:
                res = runner.invoke(main, [*args, "--scene", f"s{scene}"])
            finally:
                timer.cancel()
                timer.join()
            if res.exit_code == 0 and fresh:
                whole_runs_s.append(time.monotonic() - t0)
            lines = res.output.strip().splitlines()
            assert res.exception is None or isinstance(res.exception, SystemExit), res.output
            assert "Traceback" not in res.output and res.exit_code in (0, 130), res.output
            assert all(x.startswith(("dp5k: ", "WARNING ", "/")) for x in lines), res.output  # -q: warnings and one result line
            if res.exit_code == 130 and not lines[-1].endswith("nothing to resume"):
                assert lines[-1].startswith("dp5k: interrupted") and lines[-1].endswith("run the command again to resume") \
                    or lines[-1].endswith("run the same command again to resume"), lines
            elif res.exit_code == 130:  # the Ctrl-C came after the session was marked complete
                assert lines[-1] == f"dp5k: interrupted: {out / f's{scene}'} is complete ({lines[-1].split('(')[1]}"
                scene += 1
            else:
                assert lines[-1] == f"{out / f's{scene}'}: complete ({lines[-1].split('(')[1]}"
                scene += 1
            outcomes.append(res.exit_code)
            fresh = scene != started  # the next run starts a new scene
    finally:
        signal.signal(signal.SIGINT, old_handler)
        os.umask(old_mask)
    assert outcomes.count(130) >= TRIES // 2 and outcomes.count(0) >= 1, outcomes  # interrupts landed all over the runs
    res = runner.invoke(main, ["verify", "--no-dp-check", *(str(out / f"s{k}") for k in range(scene))])
    assert res.exit_code == 0, res.output
    gt = out / "s0" / "ground_truth"  # written by the server (umask 077) with the client's umask (022)
    assert gt.stat().st_mode & 0o777 == 0o755 and (gt / "truth.json").stat().st_mode & 0o777 == 0o644


def test_ctrl_c_during_a_read_that_blocks_returns_within_a_second() -> None:
    body = Body(blocking=True)  # a read with nothing to send waits out its timeout, holding SIGINT back as libusb does
    body.session.config = SessionConfig(timeout_s=5.0)
    body.camera.open()
    body.usb.faults.drop_next_response = True  # the body never answers the next operation
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    old_handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # a suite run in the background ignores SIGINT
    t0 = time.monotonic()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            body.camera.poll_events()
        waited_s = time.monotonic() - t0
    finally:
        timer.cancel()
        timer.join()
        signal.signal(signal.SIGINT, old_handler)
    assert waited_s < 1.2  # not the read's 5 s: it waits in slices of 0.5 s and Ctrl-C gets through between them
