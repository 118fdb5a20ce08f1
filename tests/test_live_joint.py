"""Joint multi-station solving in ``replay`` / ``live`` (issue 11): streaming windows, the CLI
contract ``replay CAPTURE --system-config YAML --solve joint --json-lines``, the calibrated forward
model on the Bitcraze bytes, and the firmware's crossing-beam method as a yardstick.

Data: a simulated Crazyflie Lighthouse deck ~3 m from two LH2 stations with factory-size
calibrations, written as the deck's real UART bytes with a cflib system-config YAML
(tests/_cf_joint_sim.py)."""
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main

from _cf_joint_sim import crossing_beam, decoded_windows, flying_motion, scenario, truth_position, write_capture


def _lines(out):
    return [json.loads(x) for x in out.splitlines() if x.startswith("{")]


@pytest.fixture(scope="module")
def static(tmp_path_factory):
    sc = scenario(1, duration=8.0)
    cap, yml = write_capture(sc, tmp_path_factory.mktemp("static"))
    return sc, cap, yml


def test_windower_equals_batch_window_rule():
    """Proof kind: reference implementation. The streaming windower (reorder buffer + incremental
    rule) gives exactly the windows of the batch rule :func:`layoutkit.joint.group_windows` on the
    time-sorted frames, whatever the arrival order within the reorder span."""
    from layoutkit.joint import group_windows
    from layoutkit.live.joint_stream import JointWindower
    from layoutkit.live.pipeline import AngleFrame

    rng = np.random.default_rng(3)
    S, R = 3, 400
    t = np.sort(rng.uniform(0, 4.0, R))
    st = rng.integers(0, S, R)
    frames = [AngleFrame(float(t[k]), int(st[k]), np.full((4, 2), float(k))) for k in range(R)]
    arrival = np.argsort(t + rng.uniform(0, 0.008, R))       # up to 8 ms late: inside the 20 ms buffer
    win = JointWindower(S)
    got = []
    for k in arrival:
        got += win.push(frames[k])
    got += win.flush()
    rows, tw = group_windows(t, st, S)
    assert len(got) == len(rows)
    mine = np.array([[-1 if f is None else int(f.angles[0, 0]) for f in w.frames] for w in got])
    np.testing.assert_array_equal(mine, rows)
    np.testing.assert_allclose([w.t for w in got], tw, rtol=0, atol=1e-12)
    assert np.all(np.diff([w.t for w in got]) >= 0)               # emitted in time order


def test_crossing_beam_matches_firmware_ray_and_closed_form():
    """Proof kind: closed form + the firmware's formula re-typed. (1) Our ray from LH1-equivalent
    angles is the firmware's ``lighthouseGeometryGetRay`` (cross product of the two sweep planes'
    normals in the Bitcraze station frame x_bc = z, y_bc = x, z_bc = y, firmware angles
    a = pi/2 - theta). (2) Noise-free angles of two stations give the sensors' true positions (the
    rays intersect), averaged into the deck centre. (3) The midpoint of two skew lines equals a
    brute-force minimisation of the distance between points on them."""
    from scipy.optimize import minimize

    from layoutkit.geometry import rotvec_to_matrix
    from layoutkit.joint import crossing_beam_positions, ray_midpoints
    from layoutkit.lighthouse import angles_to_ray, sweep_angles
    from layoutkit.simulate import stations_looking_at

    rng = np.random.default_rng(0)
    th = rng.uniform(np.pi / 2 - 0.6, np.pi / 2 + 0.6, (50, 2))
    ours = angles_to_ray(th)
    aH, aV = np.pi / 2 - th[:, 0], np.pi / 2 - th[:, 1]
    a = np.stack([np.sin(aH), -np.cos(aH), np.zeros_like(aH)], -1)     # firmware: normal to the X plane
    b = np.stack([-np.sin(aV), np.zeros_like(aV), np.cos(aV)], -1)     # normal to the Y plane
    fw = np.cross(b, a)
    fw /= np.linalg.norm(fw, axis=-1, keepdims=True)
    ours_bc = np.stack([ours[:, 2], ours[:, 0], ours[:, 1]], -1)
    ours_bc /= np.linalg.norm(ours_bc, axis=-1, keepdims=True)
    np.testing.assert_allclose(ours_bc, fw, atol=1e-12)

    P = np.array([[-0.015, 0.0075, 0], [-0.015, -0.0075, 0], [0.015, 0.0075, 0], [0.015, -0.0075, 0]])
    stations = stations_looking_at([[-1.6, -1.8, 2.4], [1.9, -1.4, 2.3]], [0, 0, 0.5])
    R, c = rotvec_to_matrix([0.1, -0.2, 0.7]), np.array([0.05, -0.02, 0.48])
    pw = P @ R.T + c
    theta = np.stack([sweep_angles((pw - s.translation) @ s.rotation) for s in stations], 0)
    pos, k, gap = crossing_beam_positions(theta, stations)
    assert k == 4 and gap < 1e-12
    np.testing.assert_allclose(pos, pw.mean(0), atol=1e-12)

    o = rng.normal(size=(2, 3))
    d = rng.normal(size=(2, 3))
    mid, g = ray_midpoints(o, d)
    f = lambda x: np.sum((o[0] + x[0] * d[0] - o[1] - x[1] * d[1]) ** 2)  # noqa: E731
    x = minimize(f, [0.0, 0.0], tol=1e-14).x
    p0, p1 = o[0] + x[0] * d[0], o[1] + x[1] * d[1]
    np.testing.assert_allclose(mid, 0.5 * (p0 + p1), atol=1e-6)
    assert abs(g - np.linalg.norm(p0 - p1)) < 1e-6


def test_replay_joint_follows_joint_dop_in_world_frame(static, tmp_path):
    """Proof kind: Monte-Carlo vs predicted covariance. ``replay --system-config --solve joint
    --json-lines`` on the deck's bytes: every line is a joint pose (``station == "joint"``), in the
    stations' world frame (compared with the world truth), and the position RMS over ~400 static
    windows equals the joint DOP prediction ``pdop * sigma_eff`` (each station's calibrated
    forward-model Jacobian, rho = 0: the simulated noise is independent; sigma_eff includes the
    deck's 6 MHz quantisation) within 15 %. ``poses.csv`` and ``report.json`` count the joint poses."""
    sc, cap, yml = static
    rep = tmp_path / "rep"
    r = CliRunner().invoke(main, ["replay", str(cap), "--system-config", str(yml), "--solve", "joint",
                                  "--json-lines", "--rho", "0", "--report", str(rep)])
    assert r.exit_code == 0, r.output[-2000:]
    L = _lines(r.output)
    assert L and all(x["station"] == "joint" for x in L)
    two = [x for x in L if x["status"] == "ok" and x["n_stations"] == 2]
    assert len(two) >= 0.95 * len(L) and len(two) > 350
    t = np.array([x["t"] for x in two])
    p = np.array([x["translation"] for x in two])
    rms = np.sqrt(np.mean(np.sum((p - truth_position(sc, t)) ** 2, 1)))
    pred = np.sqrt(np.mean(np.square([x["pdop"] for x in two]))) * sc["sigma_eff"]
    assert abs(rms / pred - 1) < 0.15, (rms, pred)
    from layoutkit.io.poses import JOINT, read_poses

    tab = read_poses(rep / "poses.csv")
    assert np.all(tab.station == JOINT) and int(np.sum(tab.ok)) == sum(x["status"] == "ok" for x in L)
    summ = json.loads((rep / "report.json").read_text())
    s = summ.get("summary", summ)
    assert s["solve"] == "joint" and s["good"] == int(np.sum(tab.ok))
    assert sum(s["joint"]["windows_by_stations"].values()) == s["frames"] == len(tab)


def test_replay_per_station_keeps_per_station_lines(static):
    """Proof kind: the planar-ambiguity test on the same bytes. ``--solve per-station`` keeps one
    pose per station frame (``station`` 0 or 1, world frame from the system config's geometry, each
    station through its calibrated forward model, started from the fast PnP on the inverted
    angles): the 3 x 1.5 cm planar deck at 3 m from ONE station has two poses that fit equally well
    at this noise, so almost every frame is honestly ``ambiguous`` — while the joint solve of the
    same windows is ``ok`` (two stations break the two-fold ambiguity)."""
    sc, cap, yml = static
    r = CliRunner().invoke(main, ["replay", str(cap), "--system-config", str(yml), "--solve", "per-station",
                                  "--json-lines", "--rho", "0"])
    assert r.exit_code == 1, r.output[-2000:]            # no good pose: exit 1 with the reason
    assert "most common reason" in r.output
    L = _lines(r.output)
    assert {x["station"] for x in L} == {0, 1}
    assert sum(x["status"] == "ambiguous" for x in L) >= 0.9 * len(L)
    # the poses it does print (the better-fitting of the two) are at the one-station precision,
    # not biased: median distance to the world truth within the one-station DOP scale (~1 cm)
    e = np.linalg.norm(np.array([x["translation"] for x in L]) - truth_position(sc, [x["t"] for x in L]), axis=1)
    assert np.median(e) < 0.02
    r = CliRunner().invoke(main, ["replay", str(cap), "--system-config", str(yml), "--json-lines"])
    J = _lines(r.output)
    assert 1.9 * len(J) <= len(L) <= 2.1 * len(J) and sum(x["status"] == "ok" for x in J) >= 0.95 * len(J)


def test_joint_without_station_poses_is_one_error_line(static):
    """Bad input: ``--solve joint`` with no station pose (a sidecar without stations, no
    --stations / --system-config) → one ``error:`` line, exit 2."""
    _, cap, _ = static
    r = CliRunner().invoke(main, ["replay", str(cap), "--solve", "joint", "--json-lines"])
    assert r.exit_code == 2
    errs = [x for x in r.output.splitlines() if x.startswith("error:")]
    assert len(errs) == 1 and "--solve joint" in errs[0] and "Traceback" not in r.output


def test_joint_at_least_as_steady_and_accurate_as_crossing_beam(static, tmp_path):
    """Proof kind: comparison with the firmware's method on the same decoded bytes and windows.
    Static deck: the joint solve's jitter (RMS distance from the mean) is at most the crossing
    beam's (both ~0.1 mm here; the joint fit is the least-squares pose, the crossing beam a
    per-sensor average). A flight at ~0.5 m/s: the joint solve with ``--motion-compensation`` (each
    light plane at its own time in the window) is at least as accurate vs the truth as the
    crossing beam (the crossing beam mixes the stations' and planes' times)."""
    sc, cap, yml = static
    r = CliRunner().invoke(main, ["replay", str(cap), "--system-config", str(yml), "--json-lines"])
    assert r.exit_code == 0, r.output[-1500:]
    two = [x for x in _lines(r.output) if x["status"] == "ok" and x["n_stations"] == 2]
    pj = np.array([x["translation"] for x in two])
    tc, pc = crossing_beam(sc, decoded_windows(sc))
    jit = lambda p: np.sqrt(np.mean(np.sum((p - p.mean(0)) ** 2, 1)))  # noqa: E731
    assert len(pc) > 350 and jit(pj) <= jit(pc), (jit(pj), jit(pc))

    fl = scenario(2, duration=4.0, motion=flying_motion(0.5))
    cap2, yml2 = write_capture(fl, tmp_path / "fly")
    r = CliRunner().invoke(main, ["replay", str(cap2), "--system-config", str(yml2), "--json-lines",
                                  "--motion-compensation"])
    assert r.exit_code == 0, r.output[-1500:]
    two = [x for x in _lines(r.output) if x["status"] == "ok" and x["n_stations"] == 2]
    tj, pj = np.array([x["t"] for x in two]), np.array([x["translation"] for x in two])
    tc, pc = crossing_beam(fl, decoded_windows(fl))
    rms = lambda t, p: np.sqrt(np.mean(np.sum((p - truth_position(fl, t)) ** 2, 1)))  # noqa: E731
    assert len(two) > 0.9 * len(pc) and rms(tj, pj) <= rms(tc, pc), (rms(tj, pj), rms(tc, pc))


def test_calibrated_model_beats_ignoring_calibration(static):
    """Proof kind: world truth with and without the model. The same bytes solved with the stations'
    poses but no calibration (a stations file without calibration, ``--stations``) are biased by
    the factory-size calibration (mm at 3 m), the calibrated joint solve is not."""
    from layoutkit.io.stations import write_stations
    from layoutkit.lighthouse import Station

    sc, cap, yml = static
    plain = cap.parent / "plain_stations.json"
    write_stations(plain, [Station(id=s.id, rotation=s.rotation, translation=s.translation, kind="lh2",
                                   rotor_rpm=s.rotor_rpm) for s in sc["stations"]])
    out = {}
    for name, args in (("model", ["--system-config", str(yml)]), ("plain", ["--stations", str(plain)])):
        r = CliRunner().invoke(main, ["replay", str(cap), *args, "--solve", "joint", "--json-lines"])
        L = [x for x in _lines(r.output) if x["n_stations"] == 2 and x["translation"][0] == x["translation"][0]]
        p = np.array([x["translation"] for x in L])
        out[name] = np.linalg.norm(p.mean(0) - truth_position(sc, [L[0]["t"]])[0])
    assert out["model"] < 2e-5 and out["plain"] > 20 * out["model"], out


def test_replay_reads_a_cfusdlog_directly(tmp_path):
    """Proof kind: simulator truth. A Crazyflie microSD log given to ``replay`` as is (detected from
    its header, no import step) decodes like its imported capture: ok per-station poses near the
    simulated ones."""
    from layoutkit.layout import load_layout

    from cf_helpers import simulate_deck_session, write_cfusdlog

    lay = load_layout("models/crazyflie_lighthouse_deck.layout.json")
    k = np.arange(60)
    tr = np.column_stack([0.2 * np.sin(k / 40), 0.1 * np.cos(k / 50), 0.8 + 0.1 * np.sin(k / 70)])
    rv = np.column_stack([np.pi + 0.6 + 0.1 * np.sin(k / 30), 0.1 * np.cos(k / 45), 0.3 * np.sin(k / 60)])
    events, alpha, starts, off = simulate_deck_session(lay.positions, rv, tr)
    log = tmp_path / "log00"
    write_cfusdlog(log, events)
    r = CliRunner().invoke(main, ["replay", str(log), "--json-lines"])
    assert r.exit_code == 0, r.output[-1500:]
    ok = [x for x in _lines(r.output) if x["status"] == "ok"]
    assert len(ok) >= 0.9 * len(k)
    for x in ok:
        j = int(np.argmin(np.abs(starts + off - x["t"])))
        assert np.linalg.norm(np.subtract(x["translation"], tr[j])) < 0.02


def test_live_joint_from_a_pty_equals_replay(tmp_path):
    """Proof kind: same computation, two deliveries. The deck's bytes served over a real pty
    (``run_fake_fpga``, 600-byte pieces at 4x real time) to ``layoutkit live --solve joint``: the
    streaming windows (solved after every port read, the open window kept for the next read) give
    the same joint poses as ``replay`` on the same bytes (same window times and statuses, poses to
    1e-9). ``live --solve joint`` without station poses is one ``error:`` line, exit 2."""
    import threading

    from layoutkit.live.simulator import run_fake_fpga

    sc = scenario(4, duration=3.0)
    cap, yml = write_capture(sc, tmp_path / "c")
    r = CliRunner().invoke(main, ["replay", str(cap), "--system-config", str(yml), "--json-lines"])
    assert r.exit_code == 0, r.output[-1500:]
    want = _lines(r.output)
    data = sc["bytes"]
    chunks = [(k / 600 * 0.005, data[k:k + 600]) for k in range(0, len(data), 600)]
    ready, box = threading.Event(), {}

    def on_ready(path):
        box["path"] = path
        ready.set()

    th = threading.Thread(target=run_fake_fpga, args=(chunks,), kwargs=dict(on_ready=on_ready, realtime=True, speed=4.0),
                          daemon=True)
    th.start()
    assert ready.wait(5)
    r = CliRunner().invoke(main, ["live", "--port", box["path"], "--layout", str(sc_layout_path(tmp_path, sc)),
                                  "--protocol", "bitcraze-lh2", "--system-config", str(yml), "--solve", "joint",
                                  "--json-lines", "--idle-timeout", "1.5", "--duration", "30"])
    th.join(10)
    assert r.exit_code == 0, r.output[-1500:]
    got = _lines(r.output)
    assert len(got) == len(want) > 100 and all(x["station"] == "joint" for x in got)
    assert [x["status"] for x in got] == [x["status"] for x in want]
    np.testing.assert_allclose([x["t"] for x in got], [x["t"] for x in want], rtol=0, atol=1e-12)
    np.testing.assert_allclose([x["translation"] for x in got], [x["translation"] for x in want], rtol=0, atol=1e-9)
    r = CliRunner().invoke(main, ["live", "--port", "loop://", "--layout", str(sc_layout_path(tmp_path, sc)),
                                  "--solve", "joint", "--duration", "1"])
    assert r.exit_code == 2 and sum(x.startswith("error:") for x in r.output.splitlines()) == 1, r.output


def sc_layout_path(tmp_path, sc):
    p = tmp_path / "deck.layout.json"
    if not p.exists():
        p.write_text(json.dumps(sc["layout"].to_dict()))
    return p
