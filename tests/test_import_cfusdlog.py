"""cfusdlog deck pulses (``lhUartFrame``) with the conventions of the real logs (tests/cf_helpers.py:
no channel on each block's first pulse written as the value past the real channels, one offset per
block, the log clock at -1.094 % of the deck's with the UART queue, lhAngle bursts of the rotations
the firmware accepts) → `layoutkit import cfusdlog` → decode and `layoutkit replay`.

Proof kinds: the simulator's exact plane angles (to the deck's 6 MHz offset quantum) and poses;
the simulated clock (offset and rate); the firmware's own lhAngle values written by the simulator in
the firmware's float32 arithmetic (the same check on the real logs: docs/real-data.md); the
firmware's block-offset derivation (without it only ~1 pulse in 4 has an angle).
"""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.importers.cfusdlog import fit_deck_clock, no_channel_value, read_cfusdlog, uart_frames
from layoutkit.io.sidecar import read_sidecar
from layoutkit.io.systemconfig import LH2_CYCLE_PERIODS
from layoutkit.layout import load_layout
from layoutkit.live.cf_events import firmware_angle_check
from layoutkit.live.protocols.bitcraze import BitcrazeLh2Decoder
from layoutkit.live.protocols.bitcraze_lh2 import PROCESSORS, plane_angles

from _cf_events_sim import simulate_uart_log, truth_position
from cf_helpers import LOG_RATE, NO_CHANNEL, simulate_deck_session, write_cfusdlog

DECK = "models/crazyflie_lighthouse_deck.layout.json"
Q6 = 2 * np.pi * 4 / LH2_CYCLE_PERIODS[0]    # one 6 MHz tick of channel 0's rotor (rad)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("cf")
    lay = load_layout(DECK)
    R = 150  # 3 s at ~50 Hz
    k = np.arange(R)
    # the deck 0.7-0.9 m in front of the station, tilted ~35 deg, drifting slowly (station frame: z =
    # boresight). Face-on at 1.4 m the 30 x 15 mm planar deck is often 'ambiguous' (IPPE two-fold)
    tr = np.column_stack([0.2 * np.sin(k / 40), 0.1 * np.cos(k / 50), 0.8 + 0.1 * np.sin(k / 70)])
    rv = np.column_stack([np.pi + 0.6 + 0.1 * np.sin(k / 30), 0.1 * np.cos(k / 45), 0.3 * np.sin(k / 60)])
    events, alpha, starts, off = simulate_deck_session(lay.positions, rv, tr)
    log = d / "log00"
    write_cfusdlog(log, events)
    return d, log, alpha, starts, off, rv, tr


@pytest.fixture(scope="module")
def two_station(tmp_path_factory):
    """A static deck ~3 m from two calibrated LH2 stations, 3 s, with the pulse habits of the real
    logs: 5 % of blocks lose a sensor, 10 % carry two offsets, 3 % have no channel at all, 1 % a
    mis-decoded offset, 5 % a second undecoded hit of a sensor 1.5 mrad early."""
    d = tmp_path_factory.mktemp("cf2")
    log, yml, sim = simulate_uart_log(d, seed=4, duration=3.0, p_missing=0.05, p_two_offsets=0.1, p_no_channel=0.03,
                                      p_garbage=0.01, p_stray=0.05)
    return d, log, yml, sim


def test_reader_round_trip(session):
    """The log reads back: header types, CRC, every event, times in s on the log clock."""
    d, log, alpha, starts, off, _, _ = session
    ul = read_cfusdlog(log)
    assert ul.version == 2 and ul.crc_ok and ul.ended is None
    ev = ul.events["lhUartFrame"]
    assert len(ev["t"]) == alpha.shape[0] * 8
    assert np.sum(ev["offset"] > 0) == alpha.shape[0] * 2  # one offset per block
    assert ev["t"].min() > off


def test_no_channel_value_is_found_in_the_log(two_station):
    """The value past the real channels means "no channel" (it never carries an offset); the first
    pulse of each block has it. An LH1 log (every frame that value) has no channel at all; a top
    value that carries offsets is a channel; >= 16 is never a channel."""
    _, log, _, sim = two_station
    u = uart_frames(read_cfusdlog(log))
    assert u.no_channel == NO_CHANNEL
    assert set(np.unique(u.channel)) == {-1, 0, 1}
    assert not np.any(u.offset[u.channel < 0])
    assert (u.channel < 0).mean() > 0.2                     # ~1 pulse in 4: the first of each block
    assert no_channel_value([2, 2, 2], [0, 0, 0]) == 2      # LH1: no channel anywhere
    assert no_channel_value([0, 1, 1], [0, 0, 40]) is None  # the top value carries an offset: a channel
    assert no_channel_value([0, 16], [40, 0]) == 16


def test_clock_offset_and_rate_fitted(two_station, tmp_path):
    """The deck-to-log clock: rate within 5 ppm of the simulated -10940 ppm, offset within 0.1 ms
    (the simulator adds U(0, 50 us) logging jitter), the UART queue seen (~0.52 ms per frame);
    `import` prints it and records it in the summary and the sidecar, whose decoder options put the
    replay on the log clock."""
    _, log, _, sim = two_station
    u = uart_frames(read_cfusdlog(log))
    c = fit_deck_clock(u.deck_s, u.t)
    assert c.status == "ok"
    assert abs(c.rate_ppm - (LOG_RATE - 1) * 1e6) < 5
    assert abs(c.offset_s - sim["uart"]["log_offset_s"] - 2.5e-5) < 1e-4
    assert 0.4e-3 < c.queue_s < 0.65e-3
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(tmp_path / "imp")])
    import re

    m = re.search(r"clock: log t = [\d.]+ s \+ deck t x \(1 ([-+][\d.]+) ppm\)", r.output)
    assert r.exit_code == 0 and m and abs(float(m.group(1)) - (LOG_RATE - 1) * 1e6) < 5, r.output
    sc = read_sidecar(tmp_path / "imp" / "capture.bin")
    assert abs(sc.protocol_options["time_rate"] - LOG_RATE) < 5e-6
    assert sc.extra["clock"]["status"] == "ok"
    few = fit_deck_clock(u.deck_s[:10], u.t[:10])
    assert few.status == "inaccurate"


def test_firmware_processor_reproduces_the_firmwares_angles(two_station):
    """The firmware processor (pulse_processor_v2.c at e9ff096) gives every lhAngle frame the
    simulated firmware logged, to float32 rounding; so does ours (phase), while decoding more."""
    _, log, _, sim = two_station
    fw = firmware_angle_check(log, pulse_processor="firmware")
    ph = firmware_angle_check(log, pulse_processor="phase")
    n = len(sim["uart"]["fw_frames"])
    assert n > 150 and fw["firmware_frames"] == n and fw["matched"] == n and fw["max_abs_diff_rad"] < 1e-6
    assert ph["matched"] == n
    assert ph["rotations"] > 1.2 * fw["rotations"]
    assert fw["repeats_dropped"] == 0


def _decode(log, name):
    u = uart_frames(read_cfusdlog(log))
    p = PROCESSORS[name](4)
    rots = []
    for s, tk, off, ch in zip(u.sensor.tolist(), u.ticks.tolist(), u.offset.tolist(), u.channel.tolist()):
        rots += p.push(s, tk, off, None if ch < 0 else ch)
    return rots + p.flush(), p.stats


def test_phase_processor_angles_equal_the_truth(two_station):
    """Every angle of our processor is the simulated one to the deck's quantisation (1 timestamp
    tick + the 6 MHz offset: < 1.5 offset quanta), none is an outlier (the mis-decoded offsets are
    rejected, the undecoded second hits dropped, both counted), blocks without channel placed by the
    rotor phase, blocks with a lost sensor or two offsets kept: >= 95 % of the simulated plane
    crossings decoded (the firmware: < 70 %)."""
    _, log, _, sim = two_station
    rots, stats = _decode(log, "phase")
    err, got = [], 0
    for r in rots:
        k = np.searchsorted(sim["t0"][r.channel], r.t0 - 100)
        assert abs(sim["t0"][r.channel][k] - r.t0) <= 40
        a = plane_angles(r.offsets, r.channel)
        d = a - sim["alpha"][r.channel][k]
        err.append(np.abs(d[np.isfinite(d)]))
        got += int(np.isfinite(a).sum())
    err = np.concatenate(err)
    assert err.max() < 1.5 * Q6, err.max()
    total = len(sim["uart"]["pulses"])
    assert got >= 0.95 * total, (got, total)
    assert stats.reasons.get("LH2 block offset disagrees with the rotor phase (mis-decoded bit stream)", 0) > 0
    strays = stats.reasons.get("LH2 second hit of a sensor without channel beside its decoded one (reflection?)", 0)
    assert strays > 0
    # a rotation per channel and rotor zero: the stray hits never split a rotation into two
    assert len(rots) <= sum(len(v) for v in sim["t0"].values()) + 2
    frots, _ = _decode(log, "firmware")
    assert sum(int(np.isfinite(r.offsets).sum()) for r in frots) < 0.7 * total


def test_import_replay_joint_poses_at_the_truth(two_station, tmp_path):
    """import + replay --solve joint with the system config: >= 90 % of the 20 ms windows ok, joint
    positions within 1 mm of the truth (static deck, sigma 4e-5 rad at 3 m), t on the log clock (the
    windows fall inside the simulated log's span)."""
    _, log, yml, sim = two_station
    imp = tmp_path / "imp"
    assert CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(imp), "--system-config",
                                     str(yml)]).exit_code == 0
    r = CliRunner().invoke(main, ["replay", str(imp / "capture.bin"), "--layout", DECK, "--system-config", str(yml),
                                  "--solve", "joint", "--json-lines"])
    assert r.exit_code == 0, r.output[-2000:]
    lines = [json.loads(x) for x in r.output.splitlines() if x.startswith("{")]
    ok = [x for x in lines if x["status"] == "ok" and x["n_stations"] == 2]
    assert len(ok) >= 0.9 * 3.0 / 0.02 * 0.9, len(ok)
    p = np.array([x["translation"] for x in ok])
    t = np.array([x["t"] for x in ok])
    assert np.median(np.linalg.norm(p - truth_position(sim, t), axis=1)) < 1e-3
    t_log = sim["uart"]["events"]["lhUartFrame"][0]
    assert t.min() >= t_log.min() - 0.03 and t.max() <= t_log.max()


def test_import_decode_angles_equal_simulator(session):
    """One station (rate 1): decoded plane angles equal the simulator's to the 6 MHz quantisation,
    every rotation decoded, t on the log clock (24-bit FPGA counter unwrapped: 3 s > 0.7 s wrap)."""
    d, log, alpha, starts, off, _, _ = session
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(d / "imp"), "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["uart_frames"] == alpha.shape[0] * 8
    cap = d / "imp" / "capture.bin"
    sc = read_sidecar(cap)
    assert sc.protocol == "bitcraze-lh2" and sc.n_sensors == 4
    dec = BitcrazeLh2Decoder(4, time_offset_s=sc.protocol_options["time_offset_s"],
                             time_rate=sc.protocol_options["time_rate"])
    sw = dec.feed(cap.read_bytes()) + dec.flush()
    plane0 = [m for m in sw if m.axis == 0]
    plane1 = [m for m in sw if m.axis == 1]
    assert len(plane0) == len(plane1) >= alpha.shape[0] - 1
    got = np.array([[m0.angles, m1.angles] for m0, m1 in zip(plane0, plane1)]).transpose(0, 2, 1)
    want = alpha[: len(got)]
    assert np.nanmax(np.abs(got - want)) <= Q6
    t = np.array([m.t for m in plane0])
    np.testing.assert_allclose(t, starts[: len(t)] + off, atol=1e-4)  # log clock
    assert np.all(np.diff(t) > 0)
    # without the block derivation only the reference pulses would have an angle
    assert np.isfinite(got).mean() > 0.99


def test_replay_good_poses(session):
    """replay --json-lines: >= 95 % of rotations give an ok pose, close to the simulated pose."""
    d, log, alpha, starts, off, rv, tr = session
    imp = d / "imp2"
    assert CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(imp)]).exit_code == 0
    # the only noise is the deck's 6 MHz offset quantisation: q / sqrt(12) = 1.5e-5 rad = 3.1"
    sigma_arcsec = Q6 / np.sqrt(12) / np.radians(1 / 3600)
    r = CliRunner().invoke(main, ["replay", str(imp / "capture.bin"), "--layout", DECK, "--json-lines",
                                  "--sigma-arcsec", f"{sigma_arcsec:.3f}"])
    assert r.exit_code == 0, r.output[-2000:]
    lines = [json.loads(x) for x in r.output.splitlines() if x.startswith("{")]
    ok = [x for x in lines if x["status"] == "ok"]
    assert len(ok) >= 0.95 * alpha.shape[0], (len(ok), len(lines), {x["status"] for x in lines})
    for x in ok:
        assert x["station"] in (0, "0")
        k = int(np.argmin(np.abs(starts + off - x["t"])))
        assert np.linalg.norm(np.subtract(x["translation"], tr[k])) < 0.02


def test_truncated_log_reads_prefix(session, tmp_path):
    d, log, alpha, *_ = session
    data = log.read_bytes()
    cut = tmp_path / "cut"
    cut.write_bytes(data[: len(data) // 2])
    ul = read_cfusdlog(cut)
    assert ul.ended and "truncated" in ul.ended and 0 < len(ul.events["lhUartFrame"]["t"]) < alpha.shape[0] * 8


def test_not_a_log(tmp_path):
    p = tmp_path / "x"
    p.write_bytes(b"hello")
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(p), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "not a Crazyflie microSD log" in r.output


def _system_config(path):
    path.write_text("""type: lighthouse_system_configuration
version: '1'
systemType: 2
geos:
  0:
    origin: [0.0, 0.0, 2.0]
    rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
calibs:
  0:
    uid: 1234
    sweeps:
    - {phase: 0.0, tilt: 0.0, curve: 0.0, gibmag: 0.0, gibphase: 0.0, ogeemag: 0.0, ogeephase: 0.0}
    - {phase: 0.0, tilt: 0.0, curve: 0.0, gibmag: 0.0, gibphase: 0.0, ogeemag: 0.0, ogeephase: 0.0}
""")
    return path


def test_import_with_system_config_and_replay(session, tmp_path):
    """--system-config: its station goes into the sidecar (and replay --system-config takes it too);
    per-station poses carry their station."""
    d, log, alpha, *_ = session
    yml = _system_config(tmp_path / "sys.yaml")
    imp = tmp_path / "imp"
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(imp), "--system-config", str(yml),
                                  "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["stations"] == 1 and len(read_sidecar(imp / "capture.bin").stations) == 1
    r = CliRunner().invoke(main, ["replay", str(imp / "capture.bin"), "--layout", DECK, "--json-lines",
                                  "--system-config", str(yml)])
    assert r.exit_code == 0, r.output[-1500:]
    lines = [json.loads(x) for x in r.output.splitlines() if x.startswith("{")]
    assert lines and all(str(x["station"]) == "0" for x in lines)


def test_replay_without_good_pose_says_why(session, tmp_path):
    """Only sensor 0 logged: no frame can be solved; replay exits 1 naming the most common reason."""
    d, log, alpha, *_ = session
    ul = read_cfusdlog(log)
    ev = ul.events["lhUartFrame"]
    keep = ev["sensor"] == 0
    rows = list(zip(*(ev[k][keep].tolist() for k in ("sensor", "basestation", "offset", "timestampFPGA",
                                                     "timestamp2FPGA"))))
    one = tmp_path / "one"
    write_cfusdlog(one, {"lhUartFrame": (ev["t"][keep], rows)})
    assert CliRunner().invoke(main, ["import", "cfusdlog", str(one), "--out", str(tmp_path / "o")]).exit_code == 0
    r = CliRunner().invoke(main, ["replay", str(tmp_path / "o" / "capture.bin"), "--layout", DECK])
    assert r.exit_code != 0 and "most common reason" in r.output, r.output[-800:]
