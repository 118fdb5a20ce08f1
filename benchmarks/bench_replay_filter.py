"""Replay with the tracking filter, end to end (issue 30 item 3): real-time factor on one core.

    .venv/bin/python benchmarks/bench_replay_filter.py [--quick] [--bitcraze-log LOG]

Cases: ``layoutkit replay CAPTURE --filter ekf`` (session defaults: the adaptive bank) of a
simulated capture (fake FPGA, ``layoutkit`` protocol, one LH1 station, the ``fake-fpga`` tumble)
of

- the 4-sensor Crazyflie deck (``models/crazyflie_lighthouse_deck.layout.json``), target >= 100x
  (planar and seen by one station: its poses stay "uncertain", the two-fold PnP pose is never told
  apart in this slow motion — ``filter_share_ok`` 0 is the honest outcome, the work is the same);
- a 32-sensor headset-like layout (Fibonacci points on a 0.09 x 0.07 x 0.05 m half ellipsoid,
  generated here: no 32-sensor model is in the repository), target >= 30x;
- optionally a real Bitcraze LH2 log (``--bitcraze-log``: two stations, deck bytes decoded from
  the cfusdlog, joint windows solved as well).

Anchor in the same run: the same replay with ``--filter none`` (decode + frame solving only).
Reported per case: stream seconds / replay CPU seconds (``time.process_time``, median of the
rounds; the process is single-threaded), the filter's own CPU share, peak RSS. Writes
benchmarks/results/replay_filter.json (``--quick``: replay_filter_quick.json). Numbers on a loaded
machine are lower bounds; the lead reruns them on a quiet one.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import max_rss_bytes, write_result  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DECK = REPO / "models" / "crazyflie_lighthouse_deck.layout.json"


def headset_layout(n: int = 32):
    """``n`` sensors on the upper half of an ellipsoid (semi-axes 0.09, 0.07, 0.05 m), Fibonacci
    spaced, normals radial."""
    from layoutkit.layout import Layout

    k = np.arange(n) + 0.5
    phi = np.arccos(1.0 - k / n)
    th = np.pi * (1.0 + 5 ** 0.5) * k
    nrm = np.c_[np.sin(phi) * np.cos(th), np.sin(phi) * np.sin(th), np.cos(phi)]
    return Layout(nrm * [0.09, 0.07, 0.05], nrm, tuple(f"s{i}" for i in range(n)))


def _replay(capture, layout, filt: bool, **kw):
    from layoutkit.filter import EkfConfig
    from layoutkit.live.pipeline import LiveConfig
    from layoutkit.workflows.live import replay_capture

    cfg = LiveConfig()
    if filt:
        cfg = replace(cfg, filter=EkfConfig(sigma_theta=cfg.sigma_theta, rho=cfg.rho))
    c0 = time.process_time()
    with contextlib.redirect_stderr(io.StringIO()):
        s = replay_capture(capture, layout, options=cfg, json_out=io.StringIO(), **kw)
    return s, time.process_time() - c0


def measure(capture, layout, rounds: int, **kw) -> dict:
    _replay(capture, layout, True, **kw)  # warm: imports, numba cache
    cpu = {"none": [], "ekf": []}
    fcpu, s_ekf = [], None
    for _ in range(rounds):
        for name in ("none", "ekf"):
            s, c = _replay(capture, layout, name == "ekf", **kw)
            cpu[name].append(c)
            if name == "ekf":
                fcpu.append(s["filter"]["filter_cpu_seconds"])
                s_ekf = s
    span = float(s_ekf["stream_time_s"])
    med = {k: float(np.median(v)) for k, v in cpu.items()}
    f = s_ekf["filter"]
    return {"stream_s": span, "rounds": rounds, "cpu_s_median": med, "cpu_s_all": cpu,
            "x_real_time": {k: span / v for k, v in med.items()},
            "filter_cpu_s_median": float(np.median(fcpu)), "filter_x_real_time": span / float(np.median(fcpu)),
            "sweeps": f["counters"]["sweeps"], "filter_share_ok": f["share_ok"]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 s captures, 2 rounds (a smoke run)")
    ap.add_argument("--bitcraze-log", help="a Bitcraze LH2 cfusdlog (its system-config.yaml beside it)")
    a = ap.parse_args(argv)
    from layoutkit.layout import load_layout
    from layoutkit.live.simulator import run_fake_fpga, simulate_stream

    dur, rounds = (10.0, 2) if a.quick else (30.0, 5)
    out = {"cases": {}, "targets": {"deck_4": 100.0, "headset_32": 30.0}}
    with tempfile.TemporaryDirectory() as tmp:
        for name, lay in (("deck_4", load_layout(DECK)), ("headset_32", headset_layout())):
            cap = Path(tmp) / f"{name}.bin"
            chunks, _ = simulate_stream(lay, duration=dur, seed=3)
            run_fake_fpga(chunks, out=cap, sidecar={"protocol": "layoutkit", "layout": lay.to_dict()})
            r = measure(cap, lay, rounds)
            out["cases"][name] = r
            print(name, f"replay --filter ekf {r['x_real_time']['ekf']:.0f}x (none {r['x_real_time']['none']:.0f}x), "
                  f"filter alone {r['filter_x_real_time']:.0f}x", flush=True)
    if a.bitcraze_log:
        log = Path(a.bitcraze_log)
        r = measure(log, str(DECK), rounds, system_config=str(log.parent / "system-config.yaml"), solve="joint")
        out["cases"]["bitcraze_lh2_log"] = dict(r, log=f"{log.parent.name}/{log.name}")
        print("bitcraze", f"replay --filter ekf {r['x_real_time']['ekf']:.0f}x (none {r['x_real_time']['none']:.0f}x), "
              f"filter alone {r['filter_x_real_time']:.0f}x", flush=True)
    out["peak_rss_bytes"] = max_rss_bytes()
    try:
        import os

        out["load_average_1min"] = os.getloadavg()[0]
    except OSError:
        out["load_average_1min"] = None
    print("wrote", write_result("replay_filter_quick" if a.quick else "replay_filter", out))


if __name__ == "__main__":
    main()
