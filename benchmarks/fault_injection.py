"""Fault injection for `layoutkit live --record` (issue 14): nothing lost, nothing foreign.

Each scenario runs the real CLIs: `fake-fpga` streams a seeded session on a pty behind a symlink,
`layoutkit live --record CAP --report REP` reads the symlink; then a fault is injected:

- ``sim-sigkill``  the simulator is SIGKILLed mid-run (its pty dies, its symlink stays), and
  another program then grabs ptys until it gets the same /dev/pts number and writes zero bytes
  into it (the reuse that once put 9.8 MB of zeros into a capture);
- ``sim-sigterm``  the simulator is SIGTERMed mid-run;
- ``unplug-replug`` the board is unplugged (session A ends, its pty closes), stays away 1 s, and
  is plugged in again behind the same symlink (session B);
- ``disk-full``    the capture goes to a 32 KiB tmpfs (smaller than one session) (needs root for `mount`; skipped otherwise),
  the report to another disk;
- ``live-sigterm`` `layoutkit live` itself gets SIGTERM mid-run.

After each: the capture must be a byte-exact prefix of what the simulator sends for that seed (the
reference stream regenerated with `fake-fpga --out`; for replug, session A's bytes then B's), and
the report must exist. Prints and writes ``benchmarks/results/fault_injection.json`` with the
number of runs, bytes the simulator would send, bytes kept, and the verdict per run.

    .venv/bin/python benchmarks/fault_injection.py [--rounds 1] [--duration 6]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXE = [sys.executable, "-m", "layoutkit"]
LAYOUT = str(ROOT / "tests/data/chen_layout.json")
SPEED = 2.0


def _reference(d: Path, seed: int, duration: float) -> bytes:
    out = d / f"ref{seed}.lkcap"
    if not out.exists():
        subprocess.run(EXE + ["fake-fpga", "--layout", LAYOUT, "--out", str(out), "--duration", str(duration),
                              "--seed", str(seed)], check=True, capture_output=True, cwd=ROOT)
    return out.read_bytes()


def _simulator(link: Path, seeds, duration: float, gap: float = 1.0) -> subprocess.Popen:
    runs = [" ".join(EXE + ["fake-fpga", "--layout", LAYOUT, "--link", str(link), "--duration", str(duration),
                            "--seed", str(s), "--speed", str(SPEED), "--wait-reader", "60"]) for s in seeds]
    cmd = f" ; sleep {gap} ; ".join(runs)
    if len(seeds) == 1:
        return subprocess.Popen(runs[0].split(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                cwd=ROOT)
    return subprocess.Popen(["bash", "-c", cmd], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=ROOT, start_new_session=True)


def _wait_for(path: Path, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not (path.exists() or path.is_symlink()) and time.monotonic() < end:
        time.sleep(0.02)


def _grab_pty_number(target: str, seconds: float) -> int:
    """Another program: take ptys until one gets ``target`` and write zeros into it for ``seconds``.
    Returns the number of zero bytes written (0 when the number was not given out again)."""
    held, m = [], None
    for _ in range(64):
        a, b = os.openpty()
        name = os.ttyname(b)
        os.close(b)
        held.append(a)
        if name == target:
            m = a
            break
    written = 0
    end = time.monotonic() + seconds
    while m is not None and time.monotonic() < end:
        try:
            written += os.write(m, b"\0" * 4096)
        except OSError:
            pass
        time.sleep(0.01)
    for a in held:
        os.close(a)
    return written


def run_scenario(name: str, d: Path, duration: float, seed: int) -> dict:
    d = d / name
    d.mkdir()
    link, cap, rep = d / "fpga", d / "cap.lkcap", d / "rep"
    refs = [_reference(d.parent, seed, duration)]
    mount = None
    if name == "unplug-replug":
        refs.append(_reference(d.parent, seed + 100, duration))
    if name == "disk-full":
        if os.geteuid() != 0:
            return {"scenario": name, "skipped": "needs root to mount a small tmpfs"}
        mount = d / "small"
        mount.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32k", "tmpfs", str(mount)], capture_output=True,
                           text=True)
        if r.returncode != 0:
            return {"scenario": name, "skipped": f"mount failed: {r.stderr.strip()}"}
        cap = mount / "cap.lkcap"
    seeds = [seed, seed + 100] if name == "unplug-replug" else [seed]
    sim = _simulator(link, seeds, duration)
    _wait_for(link)
    sim_wall = duration / SPEED
    live_wall = sim_wall * len(seeds) + 8.0  # + start-up on a loaded machine
    live = subprocess.Popen(EXE + ["live", "--port", str(link), "--layout", LAYOUT, "--record", str(cap),
                                   "--report", str(rep), "--no-dashboard", "--duration", str(live_wall)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    foreign = None
    try:
        if name in ("sim-sigkill", "sim-sigterm", "live-sigterm"):
            end = time.monotonic() + 60.0  # mid-stream: once the capture holds a few frames
            while time.monotonic() < end and not (cap.exists() and cap.stat().st_size > 3000):
                time.sleep(0.05)
            target = os.readlink(link) if link.is_symlink() else None
            if name == "live-sigterm":
                live.send_signal(signal.SIGTERM)
            else:
                sim.send_signal(signal.SIGKILL if name == "sim-sigkill" else signal.SIGTERM)
                sim.wait(10)
                if name == "sim-sigkill" and target:
                    time.sleep(0.3)  # the reader notices, closes, the number is free
                    foreign = _grab_pty_number(target, 2.0)
        out, err = live.communicate(timeout=live_wall + 60)
    finally:
        for p in (live, sim):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL) if p is sim and len(seeds) > 1 else p.kill()
                except ProcessLookupError:
                    pass
                p.wait()
    got = cap.read_bytes() if cap.exists() else b""
    want = b"".join(refs)
    res = {
        "scenario": name, "live_exit": live.returncode,
        "bytes_simulator_stream": len(want), "bytes_kept": len(got),
        "capture_is_prefix": want.startswith(got),
        "report_exists": (rep / "report.json").is_file(),
        "stderr_tail": err.strip().splitlines()[-3:],
    }
    if foreign is not None:
        res["foreign_zero_bytes_offered"] = foreign
    if name == "unplug-replug":
        res["complete"] = got == want
    if name == "disk-full":
        res["error_names_capture"] = f"error: {cap}: No space left on device" in err
        subprocess.run(["umount", str(mount)], capture_output=True)
    res["ok"] = bool(res["capture_is_prefix"] and res["report_exists"] and res.get("complete", True)
                     and res.get("error_names_capture", True) and len(got) > 0)
    return res


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=1, help="Repeat every scenario this many times.")
    ap.add_argument("--duration", type=float, default=6.0, help="Simulated seconds per session.")
    ap.add_argument("--scenarios", default="sim-sigkill,sim-sigterm,unplug-replug,disk-full,live-sigterm")
    args = ap.parse_args(argv)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rounds):
            rd = Path(tmp) / f"round{k}"
            rd.mkdir()
            for name in args.scenarios.split(","):
                r = run_scenario(name, rd, args.duration, seed=10 + k)
                r["round"] = k
                print(json.dumps(r), flush=True)
                runs.append(r)
    done = [r for r in runs if "skipped" not in r]
    res = {
        "what": "fault injection on `layoutkit live --record` (simulator SIGKILL/SIGTERM, unplug+replug, "
                "disk full, live SIGTERM): capture must be a byte-exact prefix of the simulator's stream, "
                "report must exist",
        "runs": len(done), "skipped": len(runs) - len(done), "ok": sum(r["ok"] for r in done),
        "bytes_simulator_stream": sum(r["bytes_simulator_stream"] for r in done),
        "bytes_kept": sum(r["bytes_kept"] for r in done),
        "runs_capture_not_prefix": sum(not r["capture_is_prefix"] for r in done),
        "runs_detail": runs,
        "command": f"python benchmarks/fault_injection.py --rounds {args.rounds} --duration {args.duration:g}",
    }
    out = ROOT / "benchmarks/results/fault_injection.json"
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps({k: v for k, v in res.items() if k != "runs_detail"}, indent=2))
    return 0 if res["ok"] == res["runs"] else 1


if __name__ == "__main__":
    sys.exit(main())
