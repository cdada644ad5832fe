"""PTP/IP framing (CIPA DC-005) of the simulated body, for peer tests with real libgphoto2.

The same :class:`~dp5k_capture.sim.eos_body.SimulatedEOS` operation handler as the USB framing; only the
packets differ: ``u32 length | u32 type | payload`` on a command socket and an event socket.
Types: 1 InitCommandRequest, 2 InitCommandAck, 3 InitEventRequest, 4 InitEventAck, 5 InitFail,
6 OperationRequest (u32 data-phase, u16 op, u32 tid, params), 7 OperationResponse (u16 code, u32 tid,
params), 8 Event, 9 StartData (u32 tid, u64 total), 10 Data (u32 tid, bytes), 12 EndData (u32 tid, bytes),
13/14 Probe request/response.

Run as a separate process (python-gphoto2 holds the GIL in ``camera.exit()``)::

    python -m dp5k_capture.sim.ptpip --port 0 --state-dir DIR

It writes ``DIR/port`` once listening, and after every operation ``DIR/ops.txt`` (hex op codes) and,
after each exposure, ``DIR/last_object.bin``.
"""

from __future__ import annotations

import argparse
import socket
import struct
import threading
import uuid
from pathlib import Path

from .eos_body import DATA_OUT_OPS, SimulatedEOS

PKT = struct.Struct("<II")


def _recv_exact(conn: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed")
        buf += chunk
    return bytes(buf)


def recv_packet(conn: socket.socket, max_len: int = 64 << 20) -> tuple[int, bytes]:
    """One PTP/IP packet: (type, payload); the length is bounded before reading the payload."""
    length, ptype = PKT.unpack(_recv_exact(conn, 8))
    if length < 8 or length > max_len:
        raise ConnectionError(f"bad PTP/IP packet length {length}")
    return ptype, _recv_exact(conn, length - 8)


def send_packet(conn: socket.socket, ptype: int, payload: bytes) -> None:
    conn.sendall(PKT.pack(8 + len(payload), ptype) + payload)


class PtpIpServer:
    """Serves one :class:`SimulatedEOS` over PTP/IP on loopback (one client at a time)."""

    def __init__(self, core: SimulatedEOS, host: str = "127.0.0.1", port: int = 0, state_dir: Path | None = None) -> None:
        self.core = core
        self.state_dir = state_dir
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind((host, port))
        self.srv.listen(4)
        self.port = int(self.srv.getsockname()[1])
        self.guid = uuid.uuid5(uuid.NAMESPACE_DNS, core.serial).bytes
        self._event_conn: socket.socket | None = None

    def serve_forever(self) -> None:
        while True:
            conn, _ = self.srv.accept()
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            try:
                ptype, payload = recv_packet(conn)
            except ConnectionError:
                conn.close()
                continue
            if ptype == 1:  # InitCommandRequest
                name = "dp5k-sim".encode("utf-16-le") + b"\x00\x00"
                send_packet(conn, 2, struct.pack("<I", 1) + self.guid + name + struct.pack("<HH", 0, 1))
                threading.Thread(target=self._command_loop, args=(conn,), daemon=True).start()
            elif ptype == 3:  # InitEventRequest
                send_packet(conn, 4, b"")
                self._event_conn = conn
                threading.Thread(target=self._event_loop, args=(conn,), daemon=True).start()
            else:
                send_packet(conn, 5, struct.pack("<I", 0))
                conn.close()

    def _event_loop(self, conn: socket.socket) -> None:
        try:
            while True:
                ptype, _ = recv_packet(conn)
                if ptype == 13:  # probe
                    send_packet(conn, 14, b"")
        except (ConnectionError, OSError):
            conn.close()

    def _command_loop(self, conn: socket.socket) -> None:
        try:
            while True:
                ptype, payload = recv_packet(conn)
                if ptype == 13:
                    send_packet(conn, 14, b"")
                    continue
                if ptype != 6 or len(payload) < 10:
                    continue
                _phase, op, tid = struct.unpack_from("<IHI", payload, 0)
                nparams = min((len(payload) - 10) // 4, 5)
                params = struct.unpack_from(f"<{nparams}I", payload, 10)
                data = None
                if op in DATA_OUT_OPS:
                    data = self._receive_data(conn, tid)
                reply = self.core.handle(op, params, data)
                if reply.data is not None and reply.code == 0x2001:
                    send_packet(conn, 9, struct.pack("<IQ", tid, len(reply.data)))
                    send_packet(conn, 12, struct.pack("<I", tid) + reply.data)
                send_packet(conn, 7, struct.pack(f"<HI{len(reply.params)}I", reply.code, tid, *reply.params))
                self._record(op)
        except (ConnectionError, OSError):
            conn.close()

    def _receive_data(self, conn: socket.socket, tid: int) -> bytes:
        buf = bytearray()
        while True:
            ptype, payload = recv_packet(conn)
            if ptype == 9:
                continue
            if ptype in (10, 12):
                buf += payload[4:]
                if ptype == 12:
                    return bytes(buf)

    def _record(self, op: int) -> None:
        if self.state_dir is None:
            return
        with open(self.state_dir / "ops.txt", "a") as fh:
            fh.write(f"{op:04x}\n")
        if op in (0x9128, 0x910F) and self.core.last_object_bytes:
            tmp = self.state_dir / ".last_object.tmp"
            tmp.write_bytes(self.core.last_object_bytes)
            tmp.replace(self.state_dir / "last_object.bin")


def main(argv: list[str] | None = None) -> None:
    from .world import FlatOptics

    ap = argparse.ArgumentParser(description="Simulated Canon EOS 5D Mark IV over PTP/IP (loopback)")
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--state-dir", type=Path, required=True)
    ap.add_argument("--serial", default="SIM5D4000001")
    args = ap.parse_args(argv)
    core = SimulatedEOS(args.serial, FlatOptics((96, 64)), vendor_extension_id=0xB)
    server = PtpIpServer(core, port=args.port, state_dir=args.state_dir)
    tmp = args.state_dir / ".port.tmp"
    tmp.write_text(str(server.port))
    tmp.replace(args.state_dir / "port")
    server.serve_forever()


if __name__ == "__main__":
    main()
