"""The Crazyflie log's IMU (issue 25, the IMU-aided filter): the imu.csv file, the log's units and
frame, the compiled IMU filter against its numpy reference, and a synthetic log replayed with
``--filter ekf`` with and without the IMU."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from layoutkit.io.imu import IMU_COLUMNS, ImuSamples, read_imu, write_imu
from layoutkit.units import DEG_PER_S, STANDARD_GRAVITY


def test_imu_file_round_trip(tmp_path):
    """Proof kind: round trip. What write_imu writes, read_imu reads back bit for bit."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.009, 0.011, 50))
    s = ImuSamples(t, rng.normal(0, 1, (50, 3)), rng.normal(0, 9, (50, 3)))
    p = write_imu(tmp_path / "imu.csv", s)
    assert p.read_text().splitlines()[0] == ",".join(IMU_COLUMNS)
    r = read_imu(p)
    assert np.array_equal(r.t, s.t) and np.array_equal(r.gyro, s.gyro) and np.array_equal(r.acc, s.acc)
    assert abs(r.rate_hz - 1 / np.median(np.diff(t))) < 1e-9


@pytest.mark.parametrize("text, words", [
    ("t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s,acc_x_m_s2,acc_y_m_s2\n1,0,0,0,0,0\n", ["acc_z_m_s2"]),
    (",".join(IMU_COLUMNS) + "\n1,0,0,x,0,0,9.8\n", ["line 2", "gyro_z_rad_s", "not a number"]),
    (",".join(IMU_COLUMNS) + "\n1,0,0,0,0,0,nan\n", ["line 2", "acc_z_m_s2", "not finite"]),
    (",".join(IMU_COLUMNS) + "\n2,0,0,0,0,0,9.8\n1,0,0,0,0,0,9.8\n", ["t_s", "backwards"]),
    ("", ["empty"]),
])
def test_bad_imu_file_names_file_and_field(tmp_path, text, words):
    p = tmp_path / "imu.csv"
    p.write_text(text)
    with pytest.raises(ValueError) as e:
        read_imu(p)
    assert str(p) in str(e.value)
    for w in words:
        assert w in str(e.value)


@pytest.mark.slow
def test_log_units_and_frame_convention(tmp_path):
    """Proof kind: closed form. A log's fixedFrequency events in deg/s and g (the real files'
    convention) read as rad/s and m/s²: 1 g is 9.80665 m/s², and a constant 90 deg/s about z held for
    1 s integrates (through the compiled IMU filter's propagation) to a quarter turn about the body z
    while a body at rest reading +1 g on z stays where it is."""
    from cf_helpers import write_cfusdlog
    from _cf_imu_sim import IMU_VARS
    from layoutkit.filter import _imu_numba as K
    from layoutkit.importers.cfusdlog import IMU_DELAY_S, imu_samples, read_cfusdlog

    t = 5.0 + np.arange(101) * 0.01
    rows = [(0.0, 0.0, 90.0, 0.0, 0.0, 1.0)] * len(t)
    log = tmp_path / "log00"
    write_cfusdlog(log, {"fixedFrequency": (t, rows)}, types={"fixedFrequency": IMU_VARS})
    s = imu_samples(read_cfusdlog(log))
    assert np.allclose(s.t, t - IMU_DELAY_S, atol=1e-6)
    assert np.allclose(s.acc[:, 2], STANDARD_GRAVITY) and abs(STANDARD_GRAVITY - 9.80665) < 1e-12
    assert np.allclose(s.gyro[:, 2], 90 * DEG_PER_S) and np.allclose(s.gyro[:, 2], np.pi / 2)
    R, p, v, ba, bg = np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    P = np.eye(15) * 1e-6
    g = np.array([0.0, 0.0, -STANDARD_GRAVITY])
    for k in range(len(t) - 1):
        K.propagate(R, p, v, ba, bg, g, P, s.acc[k], s.gyro[k], s.t[k + 1] - s.t[k], 0.01, 1e-4, 1e-6, 1e-8)
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.abs(R - Rz).max() < 1e-9
    assert np.abs(p).max() < 1e-9 and np.abs(v).max() < 1e-9


@pytest.mark.slow
def test_compiled_filter_matches_numpy_reference():
    """Proof kind: independent implementation. The compiled propagation and sweep update equal
    :class:`layoutkit.filter.imu.ImuEskf` (numpy, Solà 2017) on the same inputs."""
    from _cf_joint_sim import STATION_POS, TARGET
    from layoutkit.filter import _imu_numba as K
    from layoutkit.filter.imu import ImuEskf, ImuFilterConfig
    from layoutkit.layout import load_layout
    from layoutkit.lighthouse import measure_jacobian
    from layoutkit.simulate import stations_looking_at

    rng = np.random.default_rng(5)
    lay = load_layout("models/crazyflie_lighthouse_deck.layout.json")
    st = stations_looking_at(STATION_POS, TARGET, kind="lh2")[0]
    cfg = ImuFilterConfig(sigma_theta=1e-4, gate_p=1e-12)
    from layoutkit.geometry import rotvec_to_matrix

    R0 = rotvec_to_matrix(np.array([0.1, -0.2, 0.5]))
    ref = ImuEskf(R0, TARGET, np.array([0.0, 0.0, -9.80665]), cfg, v=np.array([0.2, -0.1, 0.05]))
    ref.ba, ref.bg = np.array([0.01, -0.02, 0.03]), np.array([1e-3, 2e-3, -1e-3])
    ref.P = ref.P + 1e-6 * np.eye(15)
    S = [x.copy() for x in (ref.R, ref.p, ref.v, ref.ba, ref.bg, ref.P)]
    f, w = np.array([0.3, -0.2, 9.9]), np.array([0.4, -0.3, 1.1])
    ref.propagate(f, w, 0.01)
    K.propagate(*S[:5], ref.g, S[5], f, w, 0.01, cfg.acc_noise ** 2, cfg.gyro_noise ** 2, cfg.acc_bias_walk ** 2,
                cfg.gyro_bias_walk ** 2)
    for a, b in zip(S, (ref.R, ref.p, ref.v, ref.ba, ref.bg, ref.P)):
        assert np.allclose(a, b, rtol=1e-10, atol=1e-14)
    # a sweep from a pose 2 mm / 5 mrad off the filter's
    Rt = ref.R @ rotvec_to_matrix(np.array([0.005, 0.0, -0.003]))
    pt = ref.p + np.array([0.002, -0.001, 0.001])
    ps = (lay.positions @ Rt.T + pt - st.translation) @ st.rotation
    z = measure_jacobian(ps, None, "lh2", jacobian=False)[0][:, 1] + rng.normal(0, 1e-4, 4)
    r = ref.update(st, 1, z, lay.positions)
    out = np.zeros(6)
    qm = np.full(5, 1e9)
    K.update(*S[:5], S[5], lay.positions, np.arange(4), z, np.ascontiguousarray(st.rotation),
             np.ascontiguousarray(st.translation), True, 1, np.zeros(7), False, 1e-8, 1e9, qm, out)
    assert r["accepted"] and out[0] == 1.0 and abs(out[1] - r["nis"]) < 1e-8 * max(1.0, r["nis"])
    for a, b in zip(S, (ref.R, ref.p, ref.v, ref.ba, ref.bg, ref.P)):
        assert np.allclose(a, b, rtol=1e-7, atol=1e-12)


@pytest.fixture(scope="module")
def imu_log(tmp_path_factory):
    """A 5 s two-station log with IMU events and the same log without them (same pulses)."""
    import yaml

    from _cf_joint_sim import STATION_POS, TARGET, factory_calibrations
    from _cf_imu_sim import IMU_VARS, hand_motion, imu_events, plane_angles
    from cf_helpers import LOG_RATE, simulate_lh2_log, write_cfusdlog
    from layoutkit.io.systemconfig import system_config_dict
    from layoutkit.layout import load_layout
    from layoutkit.simulate import stations_looking_at

    rng = np.random.default_rng(11)
    lay = load_layout("models/crazyflie_lighthouse_deck.layout.json")
    cals = factory_calibrations(rng)
    cal = [cals[k].to_calibration("lh2") for k in range(2)]
    stations = stations_looking_at(STATION_POS, TARGET, kind="lh2", calibrations=cal)
    off = 10.78
    t_start = off + LOG_RATE * 2_000_000 / 24e6
    motion = hand_motion(t_start)
    alpha, t0 = plane_angles(motion, stations, cal, lay.positions, off, LOG_RATE, 5.0, rng)
    sim = simulate_lh2_log(alpha, t0, rng=rng, mode="kalman", log_offset_s=off, log_rate=LOG_RATE)
    tev, rows, truth_imu = imu_events(motion, t_start - 0.05, t_start + 5.0)
    folder = tmp_path_factory.mktemp("imu_log")
    with_imu, without = folder / "log00", folder / "log01"
    types = dict(sim["types"]) | {"fixedFrequency": IMU_VARS}
    write_cfusdlog(with_imu, dict(sim["events"]) | {"fixedFrequency": (tev, rows)}, types=types)
    write_cfusdlog(without, sim["events"], types=sim["types"])
    yml = folder / "sys.yaml"
    yml.write_text(yaml.safe_dump(system_config_dict({k: s for k, s in enumerate(stations)}, cals)))
    return {"with": with_imu, "without": without, "yaml": yml, "motion": motion, "layout": lay,
            "folder": folder}


def _replay(log, yml, imu=None):
    from layoutkit.filter import EkfConfig
    from layoutkit.live.pipeline import LiveConfig
    from layoutkit.workflows.live import replay_capture

    cfg = LiveConfig()
    from dataclasses import replace

    cfg = replace(cfg, filter=EkfConfig(sigma_theta=cfg.sigma_theta, rho=cfg.rho))
    out = io.StringIO()
    s = replay_capture(log, "models/crazyflie_lighthouse_deck.layout.json", system_config=yml, solve="joint",
                       options=cfg, json_out=out, imu=imu)
    return s, out.getvalue()


@pytest.mark.slow
def test_replay_with_imu_tracks_the_simulated_truth(imu_log):
    """Proof kind: simulator truth. The synthetic log (real conventions: deck pulses, clock rate,
    fixedFrequency deg/s and g, the IMU's 5 ms stamp lag) replayed with --filter ekf uses its IMU; the
    filter's ok poses lie within a millimetre of the simulated motion, their errors match the
    filter's own 1-sigma, the lines keep the lighthouse-only filter's keys, and the summary says
    the IMU was used (gravity from the accelerometer at the resting start)."""
    s, text = _replay(imu_log["with"], imu_log["yaml"])
    assert s["imu"]["used"] and s["filter"]["imu"]["samples"] > 450
    h = s["filter"]["imu"]["health"]
    assert h["restarts"] == 0 and h["share_rejected"] < 0.05
    assert s["filter"]["imu"]["gravity"]["from"].startswith("accelerometer at rest")
    lines = [json.loads(x) for x in text.splitlines() if x.startswith("{")]
    keys = {"t", "station", "status", "rotvec", "translation", "cov_pos_m", "cov_rot_deg", "used", "nis", "event"}
    assert keys <= set(lines[0])
    ok = [x for x in lines if x["status"] == "ok"]
    assert len(ok) > 0.8 * len(lines)
    t = np.array([x["t"] for x in ok])
    p = np.array([x["translation"] for x in ok])
    R, c = imu_log["motion"](t)
    e = np.linalg.norm(p - c, axis=1)
    moving = t > t.min() + 1.0
    # measured: median 0.15 mm, p99 0.39 mm (the lighthouse-only filter on the same log: 0.42 / 1.31)
    assert np.median(e) < 0.4e-3 and np.percentile(e, 99) < 1e-3, (np.median(e), np.percentile(e, 99))
    assert np.median(e[moving]) < 0.5e-3
    # the covariance is honest here (the simulation's noise is the model's): error / root-trace sigma
    sig = np.array([np.linalg.norm(x["cov_pos_m"]) for x in ok])
    assert 0.5 < np.sqrt(np.mean((e / sig) ** 2)) < 2.0


@pytest.mark.slow
def test_no_imu_gives_the_lighthouse_only_filter(imu_log):
    """Proof kind: same computation, two deliveries. ``--no-imu`` on the log with IMU events gives the
    JSON lines, byte for byte, of the same log without them (today's lighthouse-only filter); the
    default on the log without IMU events says why the IMU was not used."""
    s1, a = _replay(imu_log["with"], imu_log["yaml"], imu=False)
    s2, b = _replay(imu_log["without"], imu_log["yaml"])
    assert a == b and len(a) > 1000
    assert s1["imu"] == {"used": False, "why": "--no-imu"}
    assert not s2["imu"]["used"] and "no IMU events" in s2["imu"]["why"]
    assert "imu" not in s2["filter"]
    with pytest.raises(ValueError, match="--imu: no IMU samples"):
        _replay(imu_log["without"], imu_log["yaml"], imu=True)


@pytest.mark.slow
def test_import_writes_imu_csv_and_replay_of_the_capture_uses_it(imu_log, tmp_path, monkeypatch):
    """Proof kind: round trip. ``import cfusdlog`` writes imu.csv beside capture.bin (named in the
    sidecar; SI units, the capture's clock) and ``replay CAPTURE --filter ekf`` uses it exactly as
    ``replay LOG`` uses the log's own events, reading the capture's sidecar once (the IMU entry comes
    from the sidecar the replay's set-up read)."""
    from click.testing import CliRunner

    from layoutkit.cli import main
    from layoutkit.importers.cfusdlog import imu_samples, read_cfusdlog

    out = tmp_path / "imp"
    r = CliRunner().invoke(main, ["import", "cfusdlog", str(imu_log["with"]), "--out", str(out), "--system-config",
                                  str(imu_log["yaml"]), "--json"])
    assert r.exit_code == 0, r.output[-2000:]
    side = json.loads((out / "capture.bin.json").read_text())
    assert side["imu"]["file"] == "imu.csv" and side["imu"]["samples"] > 450
    got = read_imu(out / "imu.csv")
    want = imu_samples(read_cfusdlog(imu_log["with"]))
    assert np.allclose(got.t, want.t, atol=0) and np.allclose(got.gyro, want.gyro) and np.allclose(got.acc, want.acc)
    import layoutkit.io.sidecar as sidecar_io

    reads = []
    real = sidecar_io.read_sidecar
    monkeypatch.setattr(sidecar_io, "read_sidecar", lambda path, *a, **k: reads.append(path) or real(path, *a, **k))
    s, _ = _replay(out / "capture.bin", imu_log["yaml"])
    assert s["imu"]["used"] and s["imu"]["from"].endswith("imu.csv")
    assert len(reads) == 1, reads


def test_rest_flags_follow_the_imu():
    """Proof kind: constructed input. The IMU's rest test (zero-velocity updates) is true once a
    window of samples at the Crazyflie's resting noise (gyro 0.003 rad/s, accelerometer 0.012 m/s²)
    is full, and false while the body turns at 0.2 rad/s or is shaken by ±0.5 m/s² at 3 Hz."""
    from layoutkit.filter.imu_tracker import rest_flags

    rng = np.random.default_rng(2)
    t = np.arange(300) * 0.01
    gyro = rng.normal(0, 0.003, (300, 3))
    acc = np.array([0.0, 0.0, STANDARD_GRAVITY]) + rng.normal(0, 0.012, (300, 3))
    gyro[100:150, 2] += 0.2
    acc[200:230, 0] += 0.5 * np.sin(2 * np.pi * 3 * t[200:230])
    r = rest_flags(t, gyro, acc, 0.2, 0.02, 0.05)
    assert not r[:18].any() and r[20:100].all()
    assert not r[100:168].any() and r[170:201].all()
    assert not r[203:248].any() and r[250:].all()


@pytest.mark.slow
def test_replay_smooth_through_the_cli(imu_log):
    """Proof kind: simulator truth, same computation two deliveries. ``replay LOG --filter ekf --smooth``
    (the CLI) on the synthetic log: every line once the IMU filter started is marked smoothed (poses
    in the sweeps' order, gap poses with ``"event": "gap"``), the smoothed ok poses are closer to the
    simulated motion than the causal ones of ``--filter ekf`` on the same log, with as many or more ok
    lines; without the flag the lines are those of the API's causal replay; ``--smooth`` with
    ``--no-imu`` says it needs the IMU-aided filter."""
    from click.testing import CliRunner

    from layoutkit.cli import main

    base = ["replay", str(imu_log["with"]), "--layout", "models/crazyflie_lighthouse_deck.layout.json",
            "--system-config", str(imu_log["yaml"]), "--solve", "joint", "--filter", "ekf", "--json-lines"]
    r0 = CliRunner().invoke(main, base)
    r1 = CliRunner().invoke(main, base + ["--smooth"])
    assert r0.exit_code == 0 and r1.exit_code == 0, r1.output[-2000:]
    _, api = _replay(imu_log["with"], imu_log["yaml"])
    causal = [json.loads(x) for x in r0.output.splitlines() if x.startswith("{")]
    assert [json.loads(x) for x in api.splitlines() if x.startswith("{")] == causal
    sm = [json.loads(x) for x in r1.output.splitlines() if x.startswith("{")]
    first = next(i for i, x in enumerate(sm) if x.get("smoothed"))
    assert all(x.get("smoothed") is True for x in sm[first:])
    sweeps = [x for x in sm if x["event"] != "gap"]
    assert [x["t"] for x in sweeps] == [x["t"] for x in causal]
    err = {}
    for name, lines in (("causal", causal), ("smoothed", sm[first:])):
        ok = [x for x in lines if x["status"] == "ok"]
        t = np.array([x["t"] for x in ok])
        _, c = imu_log["motion"](t)
        err[name] = (len(ok), float(np.sqrt(np.mean(np.sum((np.array([x["translation"] for x in ok]) - c) ** 2, 1)))))
    assert err["smoothed"][0] >= err["causal"][0] and err["smoothed"][1] < err["causal"][1], err
    r2 = CliRunner().invoke(main, base + ["--smooth", "--no-imu"])
    assert r2.exit_code != 0 and "--smooth" in r2.output and "IMU-aided" in r2.output, r2.output[-500:]
