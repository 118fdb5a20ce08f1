"""Crazyflie microSD logs with the firmware's sweep-angle events (lhAngle / estSweepAngle, LH1 and
LH2) → `layoutkit replay LOG --system-config YAML --solve joint --json-lines`.

Proof kinds: (1) decoding — the simulator's own angles come back exactly as the float32 values the
firmware logs (round trip through the real byte format); (2) accuracy — on a simulated flight with
known truth, the joint poses are at least as accurate as the firmware's crossing-beam method
(``layoutkit.joint.crossing_beam_positions``, an independent two-ray construction) on the same
angles; (3) the log's own position estimates are carried: a known offset put into them is what the
comparison reports; (4) bad input: one ``error:`` line naming the file and what it holds, exit 2.
"""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.importers.cfusdlog import read_cfusdlog, sweep_events
from layoutkit.live.cf_events import event_frames

from _cf_events_sim import crossing_beam_reference, simulate_events, truth_position, write_event_log
from _cf_joint_sim import flying_motion
from cf_helpers import write_cfusdlog


def _replay(log, yml, *extra):
    r = CliRunner().invoke(main, ["replay", str(log), "--system-config", str(yml), "--solve", "joint",
                                  "--json-lines", *extra])
    assert r.exit_code == 0, r.output[-2000:]
    return [json.loads(x) for x in r.output.splitlines() if x.startswith("{")]


def _rms(sim, lines):
    ok = [x for x in lines if x["status"] == "ok" and x["n_stations"] == 2]
    t = np.array([x["t"] for x in ok])
    p = np.array([x["translation"] for x in ok])
    return float(np.sqrt(np.mean(np.sum((p - truth_position(sim, t)) ** 2, 1)))), len(ok)


@pytest.mark.parametrize("kind,event,version,mode", [("lh2", "lhAngle", 2, "crossing_beam"), ("lh1", "lhAngle", 1, "crossing_beam"),
                                                     ("lh2", "lhAngle", 2, "kalman"), ("lh2", "estSweepAngle", 2, "kalman"),
                                                     ("lh1", "estSweepAngle", 2, "kalman")])
def test_events_decode_to_the_simulators_angles(tmp_path, kind, event, version, mode):
    """Events logged as the firmware does (bursts sensor by sensor; crossing-beam mode: station 0's
    angles repeated in station 1's bursts) come back as exactly the simulator's new frames, in
    order, at the float32 values logged (LH1 in our convention pi/2 - angle, LH2 the light-plane
    angles); every repeat is dropped and counted, nothing else is; times on the log clock (ms in
    version 1, µs in version 2)."""
    from layoutkit.live.cf_events import REPEAT_REASON
    from layoutkit.live.frames import DecodeStats

    sim = simulate_events(kind, duration=1.0, seed=3, mode=mode)
    if mode == "crossing_beam":
        assert sim["repeats"] > 0.3 * len(sim["fresh"])        # the real logs: 40-47 % of events
    log, _ = write_event_log(sim, tmp_path, event=event, version=version)
    ev = sweep_events(read_cfusdlog(log))
    assert ev.source == event and len(ev.t) == len(sim["rows"])
    if event == "estSweepAngle":
        assert ev.kind == kind                    # told by the plane tilt
    st = DecodeStats()
    frames = event_frames(ev, kind, 4, stats=st)
    assert st.reasons.get(REPEAT_REASON, 0) == 8 * sim["repeats"] and st.dropped == 8 * sim["repeats"]
    for s in (0, 1):
        fs = [f for f in frames if f.station == s]
        got = np.array([(f.raw if kind == "lh2" else np.pi / 2 - f.angles) for f in fs])   # (F, 4, 2)
        exp = np.array([raw for s_, raw in sim["fresh"] if s_ == s])
        assert got.shape == exp.shape
        # float32 logged, float64 here: equal to float32 rounding (LH1 also pi/2 - (pi/2 - x))
        np.testing.assert_allclose(got, exp, rtol=0, atol=4e-7 if kind == "lh1" else 0)
        assert np.all(np.diff([f.t for f in fs]) > 0)


def test_kalman_mode_equal_angles_are_measurements():
    """In Kalman mode a deck at rest repeats its quantised angles (26-30 % of the events of the real
    Kalman jitter logs): single-station bursts are never dropped, even when every angle equals the
    station's previous frame; in a two-station burst the station that repeats is."""
    from layoutkit.importers.cfusdlog import SweepEvents
    from layoutkit.live.cf_events import REPEAT_REASON
    from layoutkit.live.frames import DecodeStats

    a0 = np.array([[0.2, -0.02], [0.21, -0.03], [0.22, -0.04], [0.23, -0.05]])
    bursts = [{0: a0}, {0: a0}, {1: a0 + 0.1}, {0: a0, 1: a0 + 0.11}]   # the last: station 0 held, station 1 new
    rows = []     # (t, station, sensor, sweep, angle), sensor by sensor
    for b, vals in enumerate(bursts):
        for i in range(4):
            for s in sorted(vals):
                for w in (0, 1):
                    rows.append((0.02 * b + 1e-5 * len(rows), s, i, w, vals[s][i, w]))
    c = list(zip(*rows))
    ev = SweepEvents("lhAngle", np.array(c[0]), np.array(c[1]), np.array(c[2]), np.array(c[3]), np.array(c[4]))
    st = DecodeStats()
    fr = event_frames(ev, "lh2", 4, stats=st)
    assert [f.station for f in fr] == [0, 0, 1, 1]
    np.testing.assert_array_equal(fr[3].raw, a0 + 0.11)
    assert len(fr) == 4 and st.reasons == {REPEAT_REASON: 8}


@pytest.mark.parametrize("kind", ["lh2", "lh1"])
def test_replay_flight_at_least_as_accurate_as_crossing_beam(tmp_path, kind):
    """A 0.5 m/s flight: the joint poses (default: motion compensated) are closer to the truth
    than the firmware's crossing-beam positions on the same angles, and static jitter is no worse
    than the crossing beam's (both within 10 % of each other: the same 16 angles)."""
    sim = simulate_events(kind, duration=3.0, motion=flying_motion(0.5), seed=5)
    log, yml = write_event_log(sim, tmp_path / "fly")
    lines = _replay(log, yml)
    assert lines and all(x["station"] == "joint" for x in lines)
    ours, n_ok = _rms(sim, lines)
    tc, pc = crossing_beam_reference(sim)
    cb = float(np.sqrt(np.mean(np.sum((pc - truth_position(sim, tc)) ** 2, 1))))
    assert n_ok >= 0.9 * len(tc)
    assert ours <= cb, (ours, cb)
    st = simulate_events(kind, duration=2.0, seed=6)
    log, yml = write_event_log(st, tmp_path / "static")
    lines = _replay(log, yml)
    p = np.array([x["translation"] for x in lines if x["status"] == "ok" and x["n_stations"] == 2])
    tc, pc = crossing_beam_reference(st)
    jit = lambda q: float(np.sqrt(np.mean(np.sum((q - q.mean(0)) ** 2, 1))))  # noqa: E731
    assert jit(p) <= 1.10 * jit(pc), (jit(p), jit(pc))


def test_firmware_estimates_carried_to_the_report(tmp_path):
    """The log's estPosition (crossing beam) and stateEstimate rows are compared with our poses on
    the same clock: an estimate put 20 mm off the truth is reported ~20 mm off; poses.csv gets the
    interpolated firmware columns."""
    sim = simulate_events("lh2", duration=2.0, seed=7)
    t = np.arange(12.6, 14.4, 0.01)
    truth = truth_position(sim, t)
    off = np.array([0.02, 0.0, 0.0])
    log, yml = write_event_log(sim, tmp_path, firmware={"estPosition": (t, truth + off),
                                                        "fixedFrequency": (t, truth)})
    rep = tmp_path / "rep"
    r = CliRunner().invoke(main, ["replay", str(log), "--system-config", str(yml), "--solve", "joint",
                                  "--report", str(rep), "--json"])
    assert r.exit_code == 0, r.output[-2000:]
    s = json.loads((rep / "report.json").read_text())
    fw = s["summary"]["firmware_vs_ours"] if "summary" in s else s["firmware_vs_ours"]
    assert fw["crossing_beam"]["event"] == "estPosition" and fw["crossing_beam"]["compared_poses"] > 50
    assert abs(fw["crossing_beam"]["rms_distance_m"] - 0.02) < 1e-3
    assert fw["state_estimate"]["rms_distance_m"] < 1e-3
    head = (rep / "poses.csv").read_text().splitlines()[0]
    assert "firmware_crossing_beam_x" in head and "firmware_state_estimate_z" in head


def test_unsupported_or_bad_logs_one_error_line(tmp_path):
    """No sweep data, an angle log without the station type, an LH1 system with UART frames only,
    an event lacking a variable: one ``error:`` line naming the file and what it has, exit 2."""
    sim = simulate_events("lh2", duration=0.3, seed=1)
    other = tmp_path / "imu.log"
    write_cfusdlog(other, {"fixedFrequency": (np.arange(5) * 0.01, [(1.0, 2.0)] * 5)},
                   types={"fixedFrequency": [("acc.x", "f"), ("acc.z", "f")]})
    log, yml = write_event_log(sim, tmp_path / "ok")
    lh1 = tmp_path / "lh1.yaml"
    lh1.write_text(yml.read_text().replace("systemType: 2", "systemType: 1"))
    uart = tmp_path / "uart.log"
    write_cfusdlog(uart, {"lhUartFrame": (np.array([0.1]), [(0, 0, 4, 1000, 1000)])})
    bad = tmp_path / "bad.log"
    write_cfusdlog(bad, {"estSweepAngle": (np.array([0.1]), [(0, 0, 1.0)])},
                   types={"estSweepAngle": [("sensorId", "B"), ("sweepId", "B"), ("sweepAngle", "f")]})
    cases = [([str(other), "--system-config", str(yml)], ["imu.log", "fixedFrequency (5)", "lhAngle"]),
             ([str(log), "--layout", "models/crazyflie_lighthouse_deck.layout.json"], ["log00", "LH1 from LH2"]),
             ([str(uart), "--system-config", str(lh1)], ["uart.log", "LH1", "lhUartFrame (1)"]),
             ([str(bad), "--system-config", str(yml)], ["bad.log", "basestationId|baseStationId"])]
    for args, words in cases:
        r = CliRunner().invoke(main, ["replay", *args])
        lines = [x for x in r.output.splitlines() if x.strip()]
        assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:"), r.output
        for w in words:
            assert w in lines[0], (w, lines[0])


def test_import_writes_a_frame_table_that_solve_reads(tmp_path):
    """`import cfusdlog` of an LH1 log (lhAngle bursts with crossing-beam repeats, and lhUartFrame
    events that all say "no channel", as the real LH1 logs) → no capture (never an LH2 capture of
    LH1 pulses; the summary says why) but frames.csv (one frame per new burst) + layout.json +
    stations.json; `solve --solve joint` on them gives poses at the truth (static, < 1 mm)."""
    sim = simulate_events("lh1", duration=1.0, seed=8)
    log, yml = write_event_log(sim, tmp_path)
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--system-config", str(yml),
                                  "--out", str(tmp_path / "imp"), "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["capture"] is None and s["kind"] == "lh1" and s["frames"] == len(sim["fresh"])
    assert s["uart_frames"] > 0 and any("LH1" in n for n in s["notes"])
    assert not (tmp_path / "imp" / "capture.bin").exists()
    from layoutkit.live.cf_events import firmware_angle_check

    assert firmware_angle_check(log)["status"] == "no_data"        # an LH2 check: no channel in an LH1 log
    imp = tmp_path / "imp"
    r = CliRunner().invoke(main, ["solve", str(imp / "frames.csv"), "--layout", str(imp / "layout.json"),
                                  "--stations", str(imp / "stations.json"), "--solve", "joint", "--json",
                                  "--out", str(tmp_path / "poses.csv")])
    assert r.exit_code == 0, r.output[-2000:]
    from layoutkit.io.poses import read_poses

    tab = read_poses(tmp_path / "poses.csv")
    ok = tab.ok
    assert ok.sum() >= 0.9 * len(tab)
    err = np.linalg.norm(tab.translation[ok] - truth_position(sim, tab.t[ok]), axis=1)
    assert np.median(err) < 1e-3


def test_zero_angle_is_no_measurement():
    """An angle of exactly 0 (the firmware's 'none') is not a measurement: NaN in its frame, counted."""
    from layoutkit.importers.cfusdlog import SweepEvents
    from layoutkit.live.frames import DecodeStats

    t = np.full(8, 1.0)
    ev = SweepEvents("lhAngle", t, np.zeros(8, int), np.repeat(np.arange(4), 2), np.tile([0, 1], 4),
                     np.array([0.1, -0.1, 0.0, -0.11, 0.12, -0.12, 0.13, -0.13]))   # sensor by sensor
    st = DecodeStats()
    (f,) = event_frames(ev, "lh2", 4, stats=st)
    assert np.isnan(f.raw[1, 0]) and np.isfinite(f.raw).sum() == 7
    assert sum(st.reasons.values()) == 1


def test_auto_source_prefers_complete_angles_over_dropped_uart_frames(tmp_path):
    """An LH2 log whose UART frames were dropped on the card (fewer than the angle events) is
    replayed from its angle events, and the summary says why; with as many UART frames as angles
    the UART frames are used (the deck clock times each plane)."""
    from cf_helpers import UART_VARS

    from _cf_events_sim import LHANGLE
    from layoutkit.workflows.importers import cfusdlog_replay_source

    sim = simulate_events("lh2", duration=0.5, seed=2)
    rows = sim["rows"]
    t = np.array([r[0] for r in rows])
    ang = [(r[2], r[1], r[3], r[4], r[5]) for r in rows]
    _, yml = write_event_log(sim, tmp_path)
    for keep, want in ((0.5, "lhAngle"), (1.0, "lhUartFrame")):
        n = int(keep * len(rows))
        uart = [(r[2], r[1], 0, 1000 + k, 0) for k, r in enumerate(rows[:n])]
        log = tmp_path / f"both{keep}"
        write_cfusdlog(log, {"lhAngle": (t, ang), "lhUartFrame": (t[:n], uart)},
                       types={"lhAngle": LHANGLE, "lhUartFrame": UART_VARS})
        src = cfusdlog_replay_source(log, system_config=yml)
        assert src["info"]["source"] == want
        assert ("source_choice" in src["info"]) == (want == "lhAngle")
