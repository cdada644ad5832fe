"""The simulated rig in its own process: the bodies outlive their capture client, as real ones do.

``python -m dp5k_capture.sim.server --socket PATH [--world studio|flat] [--scene S] [--scale small] [--seed 0]
[--faults SPEC]`` builds the simulated rig and serves it on a Unix socket until it gets ``stop`` or SIGTERM:

* each body's USB side (bulk OUT / IN, class requests, clear halt, string descriptors), so the client's
  pyusb backend (:mod:`dp5k_capture.sim.remote`) runs the production transport, session and EOS code;
* the operator's hands (placing the ChArUco board) and the simulated session's ground truth;
* the projector stays on its pseudo-terminal (already cross-process); its HDMI input is a shared-memory
  framebuffer that the client's pattern window fills after each flip (the HDMI cable).

A client that dies mid-transfer leaves the body's half-sent data phase queued for the next client. One
request is served at a time (a lock), in one thread per client connection. A read that hits a ``hang@K``
fault is never answered, like a body that stops sending; the connection keeps serving later requests.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from multiprocessing import shared_memory
from multiprocessing.connection import Connection, Listener
from pathlib import Path
from typing import Any

import numpy as np
import usb.core

from ..rig import RigConfig, load_rig
from .fault_spec import parse_sim_faults
from .usb_device import SimHang
from .world import FlatOptics, SimRig, StudioOptics, make_sim_rig, sim_studio_scene, write_ground_truth_once

log = logging.getLogger(__name__)

FLAT_RAW_SIZE_PX = (48, 32)  # the flat world's raw frames (W, H): protocol and kill/resume tests
USB_METHODS = frozenset({"bulk_out", "bulk_in", "interrupt_in", "control", "clear_halt", "_check_present", "open", "claim"})


class SimRigServer:
    """Serves one simulated rig (see the module docstring).

    Args:
        socket_path: the Unix socket to listen on.
        world: ``studio`` (the virtual studio, scene ``scene``) or ``flat`` (a tiny textured plane).
        scene, scale, seed: the studio scene name, scale and seed (``studio``).
        faults: a ``--sim-faults`` text armed at start.
        rig: the rig (exposure plan, ids); serials, ports and sizes come from the simulation.
    """

    def __init__(self, socket_path: Path, *, world: str = "studio", scene: str = "demo01", scale: float | str = "small",
                 seed: int = 0, faults: str = "", rig: RigConfig | None = None) -> None:
        p = (rig or RigConfig()).projector
        self.hdmi_shm = shared_memory.SharedMemory(create=True, size=p.width * p.height)
        self.hdmi = np.ndarray((p.height, p.width), np.uint8, buffer=self.hdmi_shm.buf)
        self.hdmi[:] = 0
        if world == "flat":
            factory = None
        else:
            studio_scene = sim_studio_scene(scene)
            factory = lambda proj, win: StudioOptics(studio_scene, proj, scale, seed)  # noqa: E731
        self.describe = {"world": world, "scene": scene, "scale": scale, "seed": seed}
        self.sim: SimRig = make_sim_rig(rig, optics_factory=factory, raw_size_px=FLAT_RAW_SIZE_PX, seed=seed, faults=faults,
                                        hdmi=lambda: self.hdmi.copy())
        if world == "flat":
            self.sim.optics.lit_image = self.sim.projector.lit_image
        self.lock = threading.Lock()
        self.hangs = 0
        self.stopped = threading.Event()
        self.listener = Listener(str(socket_path), family="AF_UNIX")

    # ------------------------------------------------------------------ requests
    def _usb(self, cam_id: str, method: str, args: tuple[Any, ...]) -> tuple[Any, ...]:
        if method not in USB_METHODS:
            raise ValueError(f"no USB method {method!r}")
        try:
            return ("ok", getattr(self.sim.usb_devices[cam_id], method)(*args))
        except usb.core.USBTimeoutError as exc:
            return ("usb_timeout", str(exc))
        except usb.core.USBError as exc:
            return ("usb_error", exc.strerror or str(exc), exc.errno, exc.backend_error_code)

    def _faults(self, spec: str) -> None:
        for cam_id, plan in parse_sim_faults(spec, tuple(self.sim.usb_devices)).items():
            self.sim.usb_devices[cam_id].arm(plan)  # K counts downloads (releases) from now on

    def _status(self) -> dict[str, Any]:
        return {"hangs": self.hangs, "bodies": {c: {"downloads": d.downloads, "resets": d.resets, "queued_in": sum(map(len, d._in)),
                                                     "remote_mode": self.sim.bodies[c].remote_mode,
                                                     "objects": len(self.sim.bodies[c].objects),
                                                     "event_mode": self.sim.bodies[c].event_mode}
                                                 for c, d in self.sim.usb_devices.items()}}

    def handle(self, msg: tuple[Any, ...]) -> tuple[Any, ...] | None:
        """The reply to one request; None = never answer it (a hung body)."""
        kind = msg[0]
        if kind == "usb":
            try:
                return self._usb(msg[1], msg[2], msg[3])
            except SimHang:
                self.hangs += 1
                return None
        if kind == "hello":
            devs = [(c, d.vid, d.pid, d.bus, d.address, d.max_packet) for c, d in self.sim.usb_devices.items()]
            return ("ok", {"rig": self.sim.rig, "bodies": devs, "hdmi": self.hdmi_shm.name, "describe": self.describe})
        if kind == "faults":
            self._faults(msg[1])
            return ("ok", None)
        if kind == "board":
            getattr(self.sim.optics, {"place": "place", "clear": "clear"}[msg[1]])(*msg[2])
            return ("ok", None)
        if kind == "ground_truth":  # msg[2]: the client's new-file mode (its umask), not this process's
            mode = int(msg[2]) if len(msg) > 2 else None
            return ("ok", str(write_ground_truth_once(self.sim.optics, Path(msg[1]), file_mode=mode)))
        if kind == "status":
            return ("ok", self._status())
        if kind == "stop":
            self.stopped.set()
            return ("ok", None)
        return ("error", f"unknown request {kind!r}")

    def _serve(self, conn: Connection) -> None:
        with conn:
            while not self.stopped.is_set():
                try:
                    msg = conn.recv()
                except Exception:  # noqa: BLE001 - gone (EOF) or half a message from a client interrupted mid-send
                    return  # the bodies keep their state; the client reconnects
                seq = None
                if msg and msg[0] == "call":  # ("call", seq, request): the reply echoes seq (sim/remote.py)
                    seq, msg = msg[1], msg[2]
                with self.lock:
                    try:
                        reply = self.handle(msg)
                    except Exception as exc:  # noqa: BLE001 - a bad request must not take the rig down
                        log.exception("request %r", msg[:2])
                        reply = ("error", f"{type(exc).__name__}: {exc}")
                if reply is not None:
                    try:
                        conn.send(reply if seq is None else (seq, reply))
                    except OSError:
                        return

    def serve_forever(self) -> None:
        """Accept clients until ``stop`` (one thread each)."""
        accepter = threading.Thread(target=self._accept, daemon=True)
        accepter.start()
        self.stopped.wait()
        self.close()

    def _accept(self) -> None:
        while not self.stopped.is_set():
            try:
                conn = self.listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def close(self) -> None:
        self.listener.close()
        self.sim.close()
        self.hdmi_shm.close()
        self.hdmi_shm.unlink()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m dp5k_capture.sim.server", description=__doc__.split("\n")[0])
    ap.add_argument("--socket", type=Path, required=True, help="Unix socket path to serve on")
    ap.add_argument("--world", choices=("studio", "flat"), default="studio")
    ap.add_argument("--scene", default="demo01", help="studio scene (preset, number, or any name -> seed)")
    ap.add_argument("--scale", default="small", help="studio scale: small, medium, paper or a sensor downscale factor")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--faults", default="", help="--sim-faults text armed at start, e.g. disconnect@37,busy=0.1")
    ap.add_argument("--rig", type=Path, default=None, help="rig.toml (exposure plan, ids)")
    a = ap.parse_args(argv)
    scale: float | str = float(a.scale) if a.scale.replace(".", "", 1).isdigit() else a.scale
    server = SimRigServer(a.socket, world=a.world, scene=a.scene, scale=scale, seed=a.seed, faults=a.faults,
                          rig=load_rig(a.rig) if a.rig else None)
    signal.signal(signal.SIGTERM, lambda *_: server.stopped.set())
    print(f"sim-rig serving on {a.socket}", flush=True)
    server.serve_forever()


if __name__ == "__main__":
    main()
