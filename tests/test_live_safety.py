"""Nothing lost in live runs (issue 14, items 1, 2, 4, 5): captures are never overwritten, a
second writer never truncates one under the first, SIGTERM/SIGHUP end a run like Ctrl-C, a
missing port is reported while waiting, and a reconnect never reads another device's bytes.

Real parts only: real ptys (``os.openpty``), real signals to a real ``layoutkit live`` process,
real files. Each test states what it proves.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from layoutkit.live.capture import CaptureExists, CaptureWriter
from layoutkit.live.sources import ReconnectingSerial, device_identity, same_device

LAYOUT = str(Path(__file__).parent / "data" / "chen_layout.json")
EXE = [sys.executable, "-m", "layoutkit"]


def _live(*args, **kw):
    return subprocess.run(EXE + ["live", "--layout", LAYOUT, "--no-dashboard", *args], capture_output=True,
                          text=True, timeout=60, **kw)


@pytest.mark.slow
def test_record_onto_existing_capture_is_refused_and_file_untouched(tmp_path):
    """Regression (item 1): ``live --record`` onto an existing capture used to truncate it (453,600
    → 22,680 bytes). Now: exit 2, one error line naming the file, every byte unchanged; the
    ``--overwrite`` flag replaces it explicitly; ``--help`` says so."""
    cap = tmp_path / "old.lkcap"
    old = os.urandom(4096)
    cap.write_bytes(old)
    r = _live("--port", "loop://", "--record", str(cap), "--duration", "0.3")
    assert r.returncode == 2, r.stderr
    assert f"error: {cap}: a capture already exists (4,096 bytes)" in r.stderr and "--overwrite" in r.stderr
    assert "Traceback" not in r.stderr
    assert cap.read_bytes() == old
    r = _live("--port", "loop://", "--record", str(cap), "--duration", "0.3", "--overwrite")
    assert r.returncode == 0, r.stderr
    assert cap.read_bytes() == b""  # loop:// sends nothing: the capture was replaced, as asked
    h = subprocess.run(EXE + ["live", "--help"], capture_output=True, text=True).stdout
    assert "never overwritten" in " ".join(h.split()) and "--overwrite" in h


def test_second_writer_cannot_truncate_a_running_capture(tmp_path):
    """Cause of the zero bytes (item 5): a second writer used to truncate a capture while the first
    kept writing at its old offset, leaving a hole of zero bytes. Now the second writer is refused
    (exists; with overwrite: locked), and the capture is exactly the first writer's bytes."""
    cap = tmp_path / "c.lkcap"
    a = bytes(range(1, 256)) * 40
    w1 = CaptureWriter(cap, {})
    w1.write(a)
    with pytest.raises(CaptureExists, match="already exists"):
        CaptureWriter(cap, {})
    with pytest.raises(ValueError, match="being written by another process"):
        CaptureWriter(cap, {}, overwrite=True)
    w1.write(a)
    w1.close()
    data = cap.read_bytes()
    assert data == a + a and b"\0" not in data


def _start_live(tmp_path, *extra):
    rep = tmp_path / "rep"
    cap = tmp_path / "run.lkcap"
    p = subprocess.Popen(EXE + ["live", "--layout", LAYOUT, "--no-dashboard", "--port", "loop://", "--record",
                                str(cap), "--report", str(rep), *extra],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL)
    for _ in range(400):  # the run is reading once the capture's sidecar exists
        if Path(str(cap) + ".json").exists():
            break
        time.sleep(0.025)
    time.sleep(0.5)
    return p, cap, rep


@pytest.mark.parametrize("sig,code", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_sighup_end_live_like_ctrl_c(tmp_path, sig, code):
    """Regression (item 2): SIGTERM / SIGHUP used to kill ``live`` with no report. Now the run stops
    reading, closes the capture (sidecar with end time and the signal), writes the report and the
    summary, and exits 128 + signal number."""
    import json

    p, cap, rep = _start_live(tmp_path)
    p.send_signal(sig)
    out, err = p.communicate(timeout=30)
    assert p.returncode == code, err
    assert (rep / "report.json").is_file()
    side = json.loads(Path(str(cap) + ".json").read_text())
    assert side.get("end_time_utc") and side.get("stopped_by") == signal.Signals(sig).name
    assert "frames 0" in out and f"stopped by {signal.Signals(sig).name}" in err


def test_waiting_for_a_port_that_never_opens_is_reported(tmp_path):
    """Regression (item 4): without a terminal and without --duration, ``live`` on a port that never
    opens used to wait silently forever. Now stderr says at once what it waits for and why (one
    line; the next would come 10 s later)."""
    port = tmp_path / "no-such-port"
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err_fh:
        p = subprocess.Popen(EXE + ["live", "--layout", LAYOUT, "--port", str(port)], stdout=subprocess.DEVNULL,
                             stderr=err_fh, stdin=subprocess.DEVNULL)
        deadline = time.monotonic() + 30.0  # start-up (imports) can be slow on a loaded machine
        while time.monotonic() < deadline and "waiting for" not in err_path.read_text():
            time.sleep(0.1)
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    lines = [ln for ln in err_path.read_text().splitlines() if ln.startswith(f"waiting for {port}")]
    assert len(lines) == 1 and "not connected yet" in lines[0] and "No such file" in lines[0]


def test_waiting_state_repeats_at_a_bounded_interval(tmp_path):
    """The waiting line repeats every ``status_interval`` s (not once per retry, not never):
    a 1.1 s run at 0.25 s interval prints 4–6 lines (first at once)."""
    from layoutkit.workflows.live import run_live

    msgs = []
    run_live(str(tmp_path / "nothing"), LAYOUT, duration=1.1, on_status=msgs.append, status_interval=0.25)
    assert 4 <= len(msgs) <= 6 and all("not connected yet" in m for m in msgs)


def _pty_with_path(path: str, tries: int = 64):
    """Open ptys until one gets the device path ``path`` (the kernel reuses the lowest free
    number); returns (master, opened masters) or (None, opened)."""
    held = []
    for _ in range(tries):
        m, s = os.openpty()
        name = os.ttyname(s)
        os.close(s)
        held.append(m)
        if name == path:
            return m, held
    return None, held


def test_reconnect_refuses_a_pty_number_reused_by_another_program(tmp_path):
    """Regression (item 5): the simulator is SIGKILLed (its pty dies, its --link stays), the system
    gives the same /dev/pts/N to another program; the reconnecting reader used to open it and
    record that program's bytes. Now it refuses (same path, but a node made anew) and reads none."""
    import tty

    m, s = os.openpty()
    tty.setraw(s)
    path = os.ttyname(s)
    os.close(s)
    link = tmp_path / "fpga"
    link.symlink_to(path)
    src = ReconnectingSerial(str(link), timeout=0.05, backoff=0.02, backoff_max=0.05)
    assert src.connected
    time.sleep(0.1)
    os.write(m, b"board!" * 10)
    got = b""
    for _ in range(40):
        got += src.read(4096)
        if len(got) >= 60:
            break
    assert got == b"board!" * 10
    os.close(m)  # SIGKILL of the simulator: the pty dies, nobody removes the link
    for _ in range(40):
        src.read(4096)
        if not src.connected:
            break
    assert not src.connected
    m2, held = _pty_with_path(path)
    try:
        if m2 is None:
            pytest.skip(f"{path} was not given out again (other processes hold ptys)")
        foreign = b""
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            try:
                os.write(m2, b"\0" * 64)  # the other program's output
            except OSError:
                pass
            foreign += src.read(4096)
        assert foreign == b"" and src.state["refusals"] >= 1
        assert "refusing" in src.state["last_error"] and path in src.state["last_error"]
    finally:
        src.close()
        for fd in held:
            os.close(fd)


def test_same_device_rules(tmp_path):
    """The identity rules on real nodes: a node is the same device as itself; after the device died
    and a new pty was made, an unchanged symlink to it is refused but a symlink re-made by its owner
    (``fake-fpga --link`` replug) is accepted; URLs carry no OS identity."""
    m, s = os.openpty()
    path = os.ttyname(s)
    link = tmp_path / "l"
    link.symlink_to(path)
    a = device_identity(str(link))
    assert same_device(a, device_identity(str(link))) == (True, "same device node")
    os.close(s)
    os.close(m)
    time.sleep(0.02)  # a new node gets a later creation time
    m2, s2 = os.openpty()
    path2 = os.ttyname(s2)
    if path2 == path:  # the number came back: the unchanged link leads to a new node → refused
        ok, why = same_device(a, device_identity(str(link)))
        assert not ok and "refusing" in why
    tmp = tmp_path / "l.tmp"
    tmp.symlink_to(path2)
    os.replace(tmp, link)  # re-made by its owner
    ok, why = same_device(a, device_identity(str(link)))
    assert ok and "re-made" in why
    assert device_identity("socket://localhost:1") is None
    os.close(s2)
    os.close(m2)


def test_fake_fpga_out_refuses_an_existing_capture_before_writing_anything(tmp_path):
    """`fake-fpga --out` onto an existing capture: refused (exit 2) and its --truth is not written."""
    cap = tmp_path / "c.lkcap"
    cap.write_bytes(b"keep")
    r = subprocess.run(EXE + ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--truth", str(tmp_path / "t.csv"),
                              "--duration", "0.2"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "a capture already exists (4 bytes)" in r.stderr
    assert cap.read_bytes() == b"keep" and not (tmp_path / "t.csv").exists()
