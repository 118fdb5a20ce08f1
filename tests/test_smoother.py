"""The offline smoother of the IMU-aided filter (``replay --filter ekf --smooth``,
:mod:`layoutkit.filter.smoother`): the compiled RTS pass against the batch solution of a linear
case (closed form), the fixed-lag smoother by blocks against the full-interval one, and on a
simulated hand-moved deck with one-station gaps (our own synthetic sweeps and IMU samples): the
smoothed error against the smoothed covariance over Monte-Carlo runs (NEES), the smoothed error
below the filtered one, the causal filter untouched by the recorder."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from layoutkit.filter.smoother import SmootherConfig, rts_smooth


def _linear_case(rng, K=7):
    """A linear-Gaussian chain in the error-state layout (rotation block uncoupled and unmeasured,
    R = I throughout): prior, transitions F_k, noise Q_k, measurements z_k = H x_k + v (of p and ba)."""
    n = 15
    lin = np.r_[0:6, 9:15]
    F = np.zeros((K, n, n))
    Q = np.zeros((K, n, n))
    for k in range(K):
        A = np.eye(12) + 0.2 * rng.normal(size=(12, 12))
        F[k] = np.eye(n)
        F[k][np.ix_(lin, lin)] = A
        B = rng.normal(size=(12, 12)) * 0.1
        Q[k][np.ix_(lin, lin)] = B @ B.T + 0.01 * np.eye(12)
        Q[k][6:9, 6:9] = 0.01 * np.eye(3)
    H = np.zeros((4, n))
    H[0:3, 0:3] = np.eye(3)
    H[3, 9] = 1.0
    Rm = 0.05 * np.eye(4)
    P0 = np.eye(n)
    m0 = np.zeros(n)
    x = rng.multivariate_normal(m0, P0)
    z = []
    for k in range(K):
        if k:
            x = F[k] @ x + rng.multivariate_normal(np.zeros(n), Q[k] + 1e-12 * np.eye(n))
        z.append(H @ x + rng.multivariate_normal(np.zeros(4), Rm))
    return F, Q, H, Rm, m0, P0, np.array(z)


@pytest.mark.slow
def test_rts_equals_the_batch_solution_on_a_linear_case():
    """Proof kind: closed form. On a linear-Gaussian chain the compiled backward pass (fed with a
    textbook Kalman filter's filtered / predicted states) gives the batch posterior: the mean and
    marginal covariances of the whole trajectory given every measurement (normal equations)."""
    rng = np.random.default_rng(3)
    F, Q, H, Rm, m0, P0, z = _linear_case(rng)
    K, n = len(z), 15
    xf, Pf, xp, Pp = np.zeros((K, n)), np.zeros((K, n, n)), np.zeros((K, n)), np.zeros((K, n, n))
    x, P = m0.copy(), P0.copy()
    for k in range(K):
        if k:
            x, P = F[k] @ x, F[k] @ P @ F[k].T + Q[k]
        xp[k], Pp[k] = x, P
        S = H @ P @ H.T + Rm
        G = P @ H.T @ np.linalg.inv(S)
        x, P = x + G @ (z[k] - H @ x), (np.eye(n) - G @ H) @ P
        xf[k], Pf[k] = x, 0.5 * (P + P.T)
    lin = np.r_[0:6, 9:15]
    I3 = np.broadcast_to(np.eye(3), (K, 3, 3))
    Rs, xs, Ps = rts_smooth(I3, xf[:, lin], Pf, I3, xp[:, lin], Pp, F)
    # batch: information matrix of the stacked trajectory
    N = K * n
    A = np.zeros((N, N))
    b = np.zeros(N)
    P0i = np.linalg.inv(P0)
    A[:n, :n] += P0i
    b[:n] += P0i @ m0
    Ri = np.linalg.inv(Rm)
    for k in range(K):
        s = slice(k * n, (k + 1) * n)
        A[s, s] += H.T @ Ri @ H
        b[s] += H.T @ Ri @ z[k]
        if k:
            r = slice((k - 1) * n, k * n)
            Qi = np.linalg.inv(Q[k])
            M = np.hstack([-F[k], np.eye(n)])          # x_k - F x_{k-1} ~ N(0, Q)
            idx = np.r_[(k - 1) * n:k * n, k * n:(k + 1) * n]
            A[np.ix_(idx, idx)] += M.T @ Qi @ M
            del r
    Ai = np.linalg.inv(A)
    mean = Ai @ b
    for k in range(K):
        s = slice(k * n, (k + 1) * n)
        assert np.allclose(xs[k], mean[s][lin], atol=1e-9)
        assert np.allclose(Ps[k], Ai[s, s], atol=1e-9)
        assert np.allclose(Rs[k], np.eye(3), atol=1e-12)


# ---------------------------------------------------------------------------------------- simulation
SIGMA = 1e-4          # rad, the sweeps' angle noise (= the filter's sigma_theta)
RATE = 100.0          # Hz, IMU samples
GAPS = ((1.6, 2.1), (2.7, 3.1))   # s after the start: station 1 unseen (one-station stretches)


def _simulate(rng, duration=3.6):
    """Sweeps of two LH2 stations (LH2 cycle, both planes, every sensor lit, angles at each sweep's
    mean hit time + N(0, SIGMA)), and IMU samples (the motion's rate and specific force + white
    noise of the filter's own densities: per sample density / sqrt(dt)) of a hand-moved deck;
    station 1's sweeps removed in GAPS."""
    from _cf_imu_sim import hand_motion
    from _cf_joint_sim import STATION_POS, TARGET
    from layoutkit.filter.consistency import Sweep
    from layoutkit.filter.imu import ImuFilterConfig
    from layoutkit.geometry import matrix_to_rotvec
    from layoutkit.layout import load_layout
    from layoutkit.lighthouse import hit_offset, measure_jacobian
    from layoutkit.simulate import stations_looking_at
    from layoutkit.units import STANDARD_GRAVITY

    lay = load_layout("models/crazyflie_lighthouse_deck.layout.json")
    stations = stations_looking_at(STATION_POS, TARGET, kind="lh2")
    motion = hand_motion(0.0, rest_s=0.3)
    fc = ImuFilterConfig()
    dt = 1.0 / RATE
    tau = np.arange(-0.2, duration + 0.1, dt)
    h = 1e-3
    Rm, cm = motion(tau - h)
    R0, c0 = motion(tau)
    Rp, cp = motion(tau + h)
    w = matrix_to_rotvec(np.swapaxes(Rm, -1, -2) @ Rp) / (2 * h)
    a = (cp - 2 * c0 + cm) / h ** 2
    f = np.einsum("kji,kj->ki", R0, a - np.array([0.0, 0.0, -STANDARD_GRAVITY]))
    gyro = w + rng.normal(0, fc.gyro_noise / np.sqrt(dt), w.shape)
    acc = f + rng.normal(0, fc.acc_noise / np.sqrt(dt), f.shape)
    sweeps = []
    for s, st in enumerate(stations):
        period = (1.0 / 50.0) * (1.0 + 0.01 * s)
        for t in np.arange(0.013 * s, duration, period):
            if s == 1 and any(a0 <= t < a1 for a0, a1 in GAPS):
                continue
            for axis in (0, 1):
                th = t + hit_offset(st, "lh2", 0.0, axis)
                for _ in range(2):
                    R, c = motion(th)
                    ps = (lay.positions @ R[0].T + c[0] - st.translation) @ st.rotation
                    ang = measure_jacobian(ps[None], None, "lh2", jacobian=False)[0][0, :, axis]
                    th = t + hit_offset(st, "lh2", float(np.mean(ang)), axis)
                sweeps.append(Sweep(float(t), s, axis, ang + rng.normal(0, SIGMA, ang.shape), "lh2"))
    sweeps.sort(key=lambda m: m.t)
    return lay, stations, motion, (tau, gyro, acc), sweeps


def _run(sim, lag_s=0.5):
    """The causal outputs and the smoothed ones of the same sweeps."""
    from layoutkit.filter import EkfConfig
    from layoutkit.filter.imu_tracker import ImuSweepTracker, ImuTrackerConfig
    from layoutkit.filter.smoother import SmoothedImuTracker

    lay, stations, motion, (tau, gyro, acc), sweeps = sim
    cfg = EkfConfig(sigma_theta=SIGMA)
    ic = ImuTrackerConfig(gravity_from_start=False)
    trk = ImuSweepTracker(lay.positions, stations, cfg, tau, gyro, acc, ic)
    sm = SmoothedImuTracker(trk, SmootherConfig(lag_s=lag_s))
    causal, smoothed = [], []
    for m in sweeps:
        smoothed += sm.push(m)
        if sm.last_causal is not None:
            causal.append(sm.last_causal)
    smoothed += sm.finish()
    return causal, smoothed, sm


def _errors(outs, motion):
    from layoutkit.filter.consistency import nees, pose_error
    from layoutkit.geometry import matrix_to_rotvec

    t = np.array([o.t for o in outs])
    R, c = motion(t)
    e = pose_error(np.array([o.rotvec for o in outs]), np.array([o.translation for o in outs]),
                   matrix_to_rotvec(R), c)
    return t, e, nees(e, np.array([o.pose_cov for o in outs]))


@pytest.mark.slow
def test_smoothed_estimate_is_consistent_and_better_than_the_filtered_one():
    """Proof kind: Monte-Carlo vs predicted covariance, simulator truth. Over independent runs of a
    simulated hand-moved deck (sweep and IMU noise of the filter's own model, station 1 unseen for
    0.5 s and 0.4 s), at fixed times inside and outside the one-station gaps the smoothed 6-dof pose
    error against the smoothed covariance has a mean NEES within the chi² band of its degrees of
    freedom; the smoothed position error is well below the filtered one (most in the gaps); the
    causal outputs are those of the tracker without the smoother (byte for byte)."""
    from layoutkit.filter import EkfConfig
    from layoutkit.filter.imu_tracker import ImuSweepTracker, ImuTrackerConfig

    runs = 12
    probe = np.array([1.2, 1.7, 1.85, 2.0, 2.4, 2.8, 2.95, 3.3])       # s; 1.7-2.0, 2.8-2.95 in gaps
    nees_s, nees_f, e_s, e_f = [], [], [], []
    for r in range(runs):
        sim = _simulate(np.random.default_rng(100 + r))
        causal, smoothed, sm = _run(sim)
        if r == 0:  # the recorder does not touch the causal filter
            lay, stations, motion, (tau, gyro, acc), sweeps = sim
            trk = ImuSweepTracker(lay.positions, stations, EkfConfig(sigma_theta=SIGMA), tau, gyro, acc,
                                  ImuTrackerConfig(gravity_from_start=False))
            plain = [o for o in (trk.push(m) for m in sweeps) if o is not None]
            assert len(plain) == len(causal)
            assert all(a.t == b.t and a.status == b.status and np.array_equal(a.translation, b.translation)
                       and np.array_equal(a.state_cov, b.state_cov) for a, b in zip(plain, causal))
        sw = [o for o in smoothed if o.smoothed and o.event != "gap"]
        assert len(sw) == len(causal) - sm.counters.passthrough  # one smoothed output per sweep output
        ts, es, ns = _errors(sw, sim[2])
        tf, ef, nf = _errors([o for o in causal if o.t >= sw[0].t], sim[2])
        for tp in probe:
            i, j = np.argmin(np.abs(ts - tp)), np.argmin(np.abs(tf - tp))
            nees_s.append(ns[i])
            nees_f.append(nf[j])
            e_s.append(np.linalg.norm(es[i, 3:]))
            e_f.append(np.linalg.norm(ef[j, 3:]))
    nees_s, e_s, e_f = np.array(nees_s).reshape(runs, -1), np.array(e_s).reshape(runs, -1), np.array(e_f).reshape(runs, -1)
    lo, hi = chi2.ppf([0.005, 0.995], 6 * runs) / runs
    mean_per_probe = nees_s.mean(0)
    print("smoothed mean NEES per probe", mean_per_probe.round(2), "band", round(lo, 2), round(hi, 2),
          "filtered", np.array(nees_f).reshape(runs, -1).mean(0).round(2))
    print("RMS position error mm smoothed", (np.sqrt((e_s ** 2).mean(0)) * 1e3).round(3),
          "filtered", (np.sqrt((e_f ** 2).mean(0)) * 1e3).round(3))
    assert lo <= nees_s.mean() <= hi
    assert np.sum((mean_per_probe < lo) | (mean_per_probe > hi)) <= 1
    assert np.sqrt(np.mean(e_s ** 2)) < 0.8 * np.sqrt(np.mean(e_f ** 2))
    gap = (probe > 1.6) & (probe < 2.1) | (probe > 2.7) & (probe < 3.1)
    assert np.sqrt(np.mean(e_s[:, gap] ** 2)) < 0.7 * np.sqrt(np.mean(e_f[:, gap] ** 2))


@pytest.mark.slow
def test_fixed_lag_blocks_match_the_full_interval_smoother():
    """Proof kind: same computation, two deliveries. The fixed-lag smoother by blocks with a lag
    longer than the one-station gaps (0.6 s: several blocks) gives every output within a small
    fraction of its 1-sigma of the full-interval RTS smoother (one block: a lag longer than the run),
    with the same statuses; the buffer stays bounded by the lag. (Measured: 0.03 sigma at most,
    sigma within 0.13 %; with a 0.3 s lag, shorter than the gaps, 0.37 sigma.)"""
    sim = _simulate(np.random.default_rng(7))
    _, short, sm_short = _run(sim, lag_s=0.6)
    _, full, sm_full = _run(sim, lag_s=100.0)
    assert sm_short.counters.blocks >= 3 and sm_full.counters.blocks == 0
    assert len(short) == len(full)
    # ~210 sweeps per second (two stations' LH2 planes) + gap poses: 2 lags' worth of steps
    assert sm_short.counters.max_buffer < 2 * 0.6 * 220
    d_pos = np.array([np.linalg.norm(a.translation - b.translation) for a, b in zip(short, full)])
    sig = np.array([np.linalg.norm(b.cov_pos_m) for b in full])
    d_sig = np.array([np.abs(a.cov_pos_m - b.cov_pos_m).max() / b.cov_pos_m.max() for a, b in zip(short, full)])
    assert all(a.t == b.t and a.status == b.status for a, b in zip(short, full))
    assert np.max(d_pos / sig) < 0.05, np.max(d_pos / sig)
    assert np.max(d_sig) < 0.01, np.max(d_sig)


def test_smoothed_json_line_is_json_dumps_of_the_record():
    """Proof kind: independent implementation. The fast JSON line of a smoothed output is
    ``json.dumps`` of its record (which carries ``"smoothed": true``); a causal one has no such key."""
    import json

    from layoutkit.filter.jsonline import json_line
    from layoutkit.filter.tracker import FilterOutput

    rng = np.random.default_rng(2)
    A = rng.normal(size=(12, 12))
    q = np.array([0.1, -0.2, 0.3, 0.9])
    q /= np.linalg.norm(q)
    for smoothed, station, event in ((True, 1, ""), (True, -1, "gap"), (False, 0, "")):
        o = FilterOutput(12.5, station, station, "ok", q, rng.normal(size=3), A @ A.T, 4, 0, False, 3.2, 4, False,
                         event, smoothed=smoothed)
        assert json_line(o) == json.dumps(o.record())
        assert ("smoothed" in json.loads(json_line(o))) == smoothed


@pytest.mark.slow
def test_a_chain_that_ends_lost_is_smoothed_up_to_its_last_ok_output():
    """Proof kind: simulator truth, structure. Station 1's angles 0.02 rad off for 0.3 s make the
    filter lose itself (a soft restart): the outputs stay one per causal output and in time order,
    the chain ending lost is emitted smoothed up to its last causal ok output and as the causal filter
    gave it after that (none of those ok), a later chain is smoothed again; the smoothed ok
    outputs before the fault are within a few millimetres of the simulated motion."""
    from layoutkit.filter.consistency import Sweep

    lay, stations, motion, imu, sweeps = _simulate(np.random.default_rng(5))
    bad = [Sweep(m.t, m.station, m.axis, m.angles + (0.02 if m.station == 1 and 2.3 <= m.t < 2.6 else 0.0),
                 m.kind) for m in sweeps]
    causal, out, sm = _run((lay, stations, motion, imu, bad), lag_s=0.6)
    c = sm.counters
    assert c.segments >= 2 and c.unsmoothed_tail > 0 and c.gap_poses == 0
    assert len(out) == len(causal)
    t = np.array([o.t for o in out])
    assert np.all(np.diff(t) >= 0)
    k_lost = next(k for k, o in enumerate(causal) if o.status == "lost")
    k_ok = max(k for k in range(k_lost) if causal[k].status == "ok")
    assert all(out[k].smoothed for k in range(k_ok + 1))
    tail = out[k_ok + 1:k_lost + 1]
    assert tail and all(not o.smoothed and o.status != "ok" for o in tail)
    assert all(a is b for a, b in zip(tail, causal[k_ok + 1:k_lost + 1]))  # the causal outputs themselves
    # the chain of the soft restart has no ok output (the faulty station's axis refused: not confirmed) and
    # ends lost too: emitted as the causal filter gave it; the chain after the fault is smoothed again
    assert any(o.smoothed and o.status == "ok" for o in out[k_lost + 1:])
    before = [o for o in out if o.status == "ok" and o.t < 2.3]
    _, e, _ = _errors(before, motion)
    assert np.max(np.linalg.norm(e[:, 3:], axis=1)) < 6e-3


def test_recorded_transition_is_the_propagation_jacobian():
    """Proof kind: independent implementation + finite differences. The compiled transition the
    recorder accumulates (``_imu_numba.transition``) is the ``F`` of the numpy reference
    :class:`layoutkit.filter.imu.ImuEskf`'s propagation (``F P Fᵀ + Q`` = its covariance, to 1e-12), and
    the derivative of the nominal propagation to the first order in dt that the filter's ``F`` keeps: an
    error-state perturbation injected before two steps comes out as ``F₂ F₁ δx`` (central differences)
    up to the dt² terms it leaves out (0.5 R [f]x dt², ...): the gap shrinks 4x when dt halves."""
    from layoutkit.filter import _imu_numba as K
    from layoutkit.filter.imu import ImuEskf, ImuFilterConfig
    from layoutkit.geometry import matrix_to_rotvec, rotvec_to_matrix

    rng = np.random.default_rng(4)
    cfg = ImuFilterConfig()
    g = np.array([0.0, 0.0, -9.80665])
    R0 = rotvec_to_matrix(np.array([0.3, -0.2, 0.9]))
    p0, v0 = np.array([0.1, 0.2, 0.5]), np.array([0.4, -0.3, 0.2])
    ba0, bg0 = np.array([0.05, -0.02, 0.03]), np.array([0.01, 0.02, -0.01])
    samples = [(np.array([0.5, -1.2, 10.3]), np.array([0.8, -0.4, 1.5]), 0.01),
               (np.array([-0.7, 0.4, 9.1]), np.array([-0.2, 0.9, 0.3]), 0.007)]

    def start(dx=np.zeros(15)):
        e = ImuEskf(R0 @ rotvec_to_matrix(dx[6:9]), p0 + dx[0:3], g, cfg, v=v0 + dx[3:6])
        e.ba, e.bg = ba0 + dx[9:12], bg0 + dx[12:15]
        return e

    # one step: F P F^T + Q is the reference's covariance
    A = rng.normal(size=(15, 15))
    e = start()
    e.P = A @ A.T
    P0 = e.P.copy()
    F1 = np.eye(15)
    f, w, dt = samples[0]
    K.transition(np.ascontiguousarray(e.R), e.ba, e.bg, f, w, dt, F1)
    e.propagate(f, w, dt)
    Q = np.diag(np.repeat([0.0, cfg.acc_noise ** 2 * dt, cfg.gyro_noise ** 2 * dt, cfg.acc_bias_walk ** 2 * dt,
                           cfg.gyro_bias_walk ** 2 * dt], 3))
    assert np.allclose(F1 @ P0 @ F1.T + Q, e.P, rtol=1e-12, atol=1e-12)

    def gap(scale):
        steps = [(f, w, dt * scale) for f, w, dt in samples]
        x = start()
        Fc = np.eye(15)
        for f, w, dt in steps:
            K.transition(np.ascontiguousarray(x.R), x.ba, x.bg, f, w, dt, Fc)
            x.propagate(f, w, dt)

        def run(dx):
            y = start(dx)
            for f, w, dt in steps:
                y.propagate(f, w, dt)
            return np.concatenate([y.p - x.p, y.v - x.v, matrix_to_rotvec(x.R.T @ y.R), y.ba - x.ba, y.bg - x.bg])
        h = 1e-6
        J = np.column_stack([(run(h * np.eye(15)[i]) - run(-h * np.eye(15)[i])) / (2 * h) for i in range(15)])
        return np.abs(Fc - J).max()
    g1, g2 = gap(1.0), gap(0.5)
    assert g1 < 10.5 * 0.017 ** 2, g1           # |f| dt² over the two steps
    assert 3.0 < g1 / g2 < 5.0, (g1, g2)


@pytest.mark.slow
def test_a_faulty_station_pulling_a_soft_restart_is_never_ok():
    """Proof kind: simulator truth. Station 1's angles 0.02 rad off for 0.3 s: the filter's soft
    restart let them in and the state settled ~13 cm off, where they agree with station 0 (the bias
    moves the deck along station 0's range) and with one axis of station 1, the other axis refused
    every time; it was reported ok there for 0.22 s. A (re)start is confirmed only once every station
    axis that sent sweeps since has had one accepted: no ok output of the causal filter or of the
    smoother is more than 2 cm off, and both are ok again after the fault."""
    from layoutkit.filter.consistency import Sweep

    lay, stations, motion, imu, sweeps = _simulate(np.random.default_rng(5))
    bad = [Sweep(m.t, m.station, m.axis, m.angles + (0.02 if m.station == 1 and 2.3 <= m.t < 2.6 else 0.0),
                 m.kind) for m in sweeps]
    causal, out, _ = _run((lay, stations, motion, imu, bad), lag_s=0.6)
    for outs in (causal, out):
        ok = [o for o in outs if o.status == "ok"]
        t, e, _ = _errors(ok, motion)
        err = np.linalg.norm(e[:, 3:], axis=1)
        assert err.max() < 0.02, (t[err.argmax()], err.max())
        assert (t > 3.2).sum() > 50  # tracking ok again after the fault
