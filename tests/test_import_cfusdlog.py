"""cfusdlog round trip: a simulated Crazyflie LH2 session, written as a real-format microSD log
with the real deck's habit of one sync offset per block → `layoutkit import cfusdlog` → decode and
`layoutkit replay`. Proof kinds: the simulator's exact plane angles (to the deck's 6 MHz
quantisation) and poses; the firmware's block-offset derivation (without it only ~1 pulse in 4
has an angle)."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.importers.cfusdlog import read_cfusdlog
from layoutkit.io.sidecar import read_sidecar
from layoutkit.layout import load_layout
from layoutkit.live.protocols.bitcraze import LH2_CYCLE_PERIODS, BitcrazeLh2Decoder

from cf_helpers import simulate_deck_session, write_cfusdlog

DECK = "models/crazyflie_lighthouse_deck.layout.json"


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


def test_reader_round_trip(session):
    """The log reads back: header types, CRC, every event, times in s on the log clock."""
    d, log, alpha, starts, off, _, _ = session
    ul = read_cfusdlog(log)
    assert ul.version == 2 and ul.crc_ok and ul.ended is None
    ev = ul.events["lhUartFrame"]
    assert len(ev["t"]) == alpha.shape[0] * 8
    assert np.sum(ev["offset"] > 0) == alpha.shape[0] * 2  # one offset per block
    assert ev["t"].min() > off


def test_import_decode_angles_equal_simulator(session):
    """Decoded plane angles equal the simulator's to the 6 MHz quantisation, every rotation decoded,
    t on the log's clock (24-bit FPGA counter unwrapped: 3 s > 0.7 s wrap)."""
    d, log, alpha, starts, off, _, _ = session
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(d / "imp"), "--json"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.output)
    assert s["uart_frames"] == alpha.shape[0] * 8 and s["angle_rows"] == alpha.shape[0] * 8
    cap = d / "imp" / "capture.bin"
    sc = read_sidecar(cap)
    assert sc.protocol == "bitcraze-lh2" and sc.n_sensors == 4
    dec = BitcrazeLh2Decoder(4, time_offset_s=sc.protocol_options["time_offset_s"])
    sw = dec.feed(cap.read_bytes()) + dec.flush()
    plane0 = [m for m in sw if m.axis == 0]
    plane1 = [m for m in sw if m.axis == 1]
    assert len(plane0) == len(plane1) >= alpha.shape[0] - 1
    q = 2 * np.pi * 4 / LH2_CYCLE_PERIODS[0]  # one 6 MHz tick of the rotor
    got = np.array([[m0.angles, m1.angles] for m0, m1 in zip(plane0, plane1)]).transpose(0, 2, 1)
    want = alpha[: len(got)]
    assert np.nanmax(np.abs(got - want)) <= q
    t = np.array([m.t for m in plane0])
    np.testing.assert_allclose(t, starts[: len(t)] + off, atol=3e-4)  # log clock (events logged <0.2 ms late)
    assert np.all(np.diff(t) > 0)
    # without the block derivation only the reference pulses would have an angle
    assert np.isfinite(got).mean() > 0.99


def test_replay_good_poses(session):
    """replay --json-lines: >= 95 % of rotations give an ok pose, close to the simulated pose."""
    d, log, alpha, starts, off, rv, tr = session
    imp = d / "imp2"
    assert CliRunner().invoke(main, ["import", "cfusdlog", str(log), "--out", str(imp)]).exit_code == 0
    # the only noise is the deck's 6 MHz offset quantisation: q / sqrt(12) = 1.5e-5 rad = 3.1"
    sigma_arcsec = 2 * np.pi * 4 / LH2_CYCLE_PERIODS[0] / np.sqrt(12) / np.radians(1 / 3600)
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
    assert json.loads(r.output)["stations"] == 1 and len(read_sidecar(imp / "capture.bin").stations) == 1
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
