"""Sources and capture files: loop://, pty, socket:// unplug/replug, capture write/replay."""
from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from layoutkit.layout import load_layout
from layoutkit.live.capture import CaptureReader, CaptureWriter, read_sidecar
from layoutkit.live.protocols import get_protocol
from layoutkit.live.simulator import run_fake_fpga, simulate_stream
from layoutkit.live.sources import ReconnectingSerial, SerialSource, open_source

LAYOUT = "tests/data/chen_layout.json"


def _stream(duration=1.0, seed=0, **kw):
    return simulate_stream(load_layout(LAYOUT), duration=duration, seed=seed, **kw)


def test_loop_url_roundtrip():
    """Bytes written to pyserial's loop:// come back unchanged through SerialSource (identity)."""
    src = open_source("loop://", timeout=0.05)
    assert isinstance(src, SerialSource)
    payload = bytes(range(256)) * 4
    src.port.write(payload)
    got = b""
    for _ in range(100):
        got += src.read(300)
        if len(got) == len(payload):
            break
    assert got == payload
    assert src.read(10) == b""  # timeout → b""
    src.close()


def test_open_source_bad_port_message():
    """A port that cannot be opened gives a ValueError naming it (no pyserial traceback)."""
    with pytest.raises(ValueError, match=r"^/dev/does-not-exist: cannot open serial port"):
        open_source("/dev/does-not-exist")


def test_capture_roundtrip_and_sidecar(tmp_path):
    """CaptureWriter stores every byte with its arrival time; CaptureReader returns them exactly."""
    path = tmp_path / "c.lkcap"
    chunks = [(0.01 * k, bytes([k % 256]) * (k + 1)) for k in range(50)]
    with CaptureWriter(path, {"protocol": "layoutkit", "layout": {"units": "m"}}) as w:
        for t, b in chunks:
            w.write(b, t)
    side = read_sidecar(path)
    assert side["protocol"] == "layoutkit" and side["bytes"] == sum(len(b) for _, b in chunks)
    assert "start_time_utc" in side and "end_time_utc" in side
    r = CaptureReader(path)
    assert [c for c in r.chunks()] == chunks
    data = b""
    while not r.eof:
        data += r.read(7)
    assert data == b"".join(b for _, b in chunks)
    assert r.read(10) == b""
    # realtime replay releases bytes no earlier than their recorded time (speed-up 10x)
    r2 = CaptureReader(path, realtime=True, speed=10.0)
    t0 = time.monotonic()
    got = b""
    while len(got) < len(data):
        got += r2.read(1 << 16)
    assert got == data
    assert time.monotonic() - t0 >= 0.49 / 10 * 0.9


def test_pty_stream_decodes_every_frame():
    """fake-fpga on a pty → SerialSource → decoder: every emitted frame arrives, in order."""
    chunks, sw = _stream(duration=1.0, seed=2)
    ready = threading.Event()
    box = {}

    def on_ready(path):
        box["path"] = path
        ready.set()

    th = threading.Thread(target=run_fake_fpga, args=(chunks,),
                          kwargs=dict(on_ready=on_ready, realtime=True, speed=4.0), daemon=True)
    th.start()
    assert ready.wait(5)
    src = open_source(box["path"], timeout=0.05)
    dec = get_protocol("layoutkit")(n_sensors=12)
    out = []
    deadline = time.monotonic() + 10
    while len(out) < len(chunks) and time.monotonic() < deadline:
        out += dec.feed(src.read(4096))
    src.close()
    th.join(10)
    assert len(out) == len(chunks) == dec.stats.good
    assert dec.stats.bad == 0 and dec.stats.dropped == 0
    np.testing.assert_array_equal([m.seq for m in out], sw.seq)


class _FlakyServer:
    """A TCP server that serves ``parts`` one per connection, dropping the connection after each."""

    def __init__(self, parts, pause=0.3):
        self.parts = list(parts)
        self.pause = pause
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", 0))
        self.port = s.getsockname()[1]
        s.close()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        for k, part in enumerate(self.parts):
            srv = socket.socket()
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind(("127.0.0.1", self.port))
            srv.listen(1)
            conn, _ = srv.accept()
            time.sleep(0.1)  # pyserial discards what is pending when it opens a port (as for a UART)
            for i in range(0, len(part), 500):
                conn.sendall(part[i:i + 500])
                time.sleep(0.001)
            time.sleep(0.05)
            conn.close()  # unplug
            srv.close()
            time.sleep(self.pause)  # device away: connection refused meanwhile


def test_unplug_replug_loses_nothing(tmp_path):
    """Unplug mid-run (socket:// closed, then refused for 0.3 s, then back): every byte sent reaches
    the capture file, the decoder recovers every frame, and the source reports the reconnect."""
    chunks, sw = _stream(duration=1.5, seed=5)
    data = b"".join(b for _, b in chunks)
    cut = [0, len(data) // 3 + 17, 2 * len(data) // 3 + 5, len(data)]  # cut inside frames
    parts = [data[cut[i]:cut[i + 1]] for i in range(3)]
    server = _FlakyServer(parts)
    server.thread.start()
    time.sleep(0.05)
    events = []
    src = ReconnectingSerial(f"socket://127.0.0.1:{server.port}", timeout=0.05, backoff=0.02,
                             backoff_max=0.2, on_event=lambda kind, st: events.append(kind))
    dec = get_protocol("layoutkit")(n_sensors=12)
    out = []
    cap = tmp_path / "u.lkcap"
    with CaptureWriter(cap, {"protocol": "layoutkit"}) as w:
        deadline = time.monotonic() + 15
        while w.bytes_written < len(data) and time.monotonic() < deadline:
            b = src.read(4096)
            w.write(b)
            out += dec.feed(b)
    src.close()
    assert cap.read_bytes() == data
    assert len(out) == len(chunks) and dec.stats.bad == 0
    assert src.state["disconnects"] >= 2 and src.state["connects"] >= 3
    assert events[:3] == ["connected", "disconnected", "connected"]


def test_pty_device_unplug_replug_via_link(tmp_path):
    """The simulated board is unplugged (its pty closes) and plugged in again (a new pty behind the
    same symlink): ReconnectingSerial on the link reads both sessions completely."""
    link = tmp_path / "fpga"
    chunks_a, _ = _stream(duration=0.5, seed=8)
    chunks_b, _ = _stream(duration=0.5, seed=9)

    def device():
        run_fake_fpga(chunks_a, link=link, realtime=True, speed=4.0, wait_reader=10)
        time.sleep(0.3)  # unplugged
        run_fake_fpga(chunks_b, link=link, realtime=True, speed=4.0, wait_reader=10)

    th = threading.Thread(target=device, daemon=True)
    th.start()
    for _ in range(100):
        if link.exists():
            break
        time.sleep(0.02)
    src = ReconnectingSerial(str(link), timeout=0.05, backoff=0.02, backoff_max=0.1)
    dec = get_protocol("layoutkit")(n_sensors=12)
    out = []
    deadline = time.monotonic() + 20
    while len(out) < len(chunks_a) + len(chunks_b) and time.monotonic() < deadline:
        out += dec.feed(src.read(4096))
    src.close()
    th.join(10)
    assert len(out) == len(chunks_a) + len(chunks_b) and dec.stats.bad == 0
    assert src.state["disconnects"] >= 1 and src.state["connects"] >= 2
