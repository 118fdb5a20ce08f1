"""The redundancy rule (layoutkit.status ``low_redundancy``): a pose solved from 6 or 7 seen angles
cannot check itself and is not ok; from 8 or more it is judged as before.

Kinds of proof: the reason for the rule shown on the solver's own output — with 6 angles any
noise, and a gross error, is fitted exactly (residual at rounding level, pose moved); with 7 the
standardised residuals of all angles are equal in magnitude (the hat matrix of the independent
Jacobian ``dop.angle_jacobian``), so a faulty angle cannot be located; with 8 (4 sensors, the
Crazyflie deck) they differ and a gross error shows in the residual. The joint solve counts angles over stations.
Real data: the libsurvive LH2 sample's frames with 6-7 seen angles are exactly the new
``low_redundancy`` frames, and their residuals sit far below those of the checked frames.
"""
import numpy as np
import pytest

from layoutkit import status
from layoutkit.dop import angle_jacobian
from layoutkit.geometry import look_at_rotation, transform_points
from layoutkit.joint import solve_joint
from layoutkit.lighthouse import Station, sweep_angles
from layoutkit.pnp import STATUS_LOW_REDUNDANCY, STATUS_OK, solve_pnp
from layoutkit.simulate import simulate_station_angles, stations_looking_at

# five non-coplanar sensors, a few centimetres apart (m)
P5 = np.array([[0.0, 0.0, 0.0], [0.06, 0.0, 0.01], [0.0, 0.05, 0.02], [0.05, 0.05, -0.01], [0.02, -0.03, 0.04]])
R0 = look_at_rotation([0.0, 0.0, 1.0]).T
T0 = np.array([0.1, -0.05, 1.5])


def _frames(F, sigma, rng):
    ang = sweep_angles(transform_points(R0, T0, P5))
    return ang[None] + sigma * rng.standard_normal((F,) + ang.shape)


def _solve(ang, seen):
    """Solve with the true pose as the start (3 sensors have no cold start)."""
    F = ang.shape[0]
    return solve_pnp(P5, ang, seen, initial=(np.tile(R0, (F, 1, 1)), np.tile(T0, (F, 1))), sigma=None)


def _seen(F, sensors, extra_axis=None):
    v = np.zeros((F, 5, 2), bool)
    v[:, sensors] = True
    if extra_axis is not None:
        v[:, extra_axis[0], extra_axis[1]] = True
    return v


def test_six_angles_fit_anything_so_the_pose_is_not_ok(rng):
    """3 sensors (6 angles): noise of 1e-4 rad is fitted to rounding level, and a 2 mrad error in one
    angle moves the pose by millimetres with no residual at all — low_redundancy, pose returned."""
    ang = _frames(20, 1e-4, rng)
    r = _solve(ang, _seen(20, [0, 1, 2]))
    assert (r.status == STATUS_LOW_REDUNDANCY).all() and not r.success.any()
    assert np.all(r.residual_rms < 1e-10)                    # the noise is not seen at all
    bad = ang.copy()
    bad[:, 1, 0] += 2e-3                                     # a gross error in one angle
    rb = _solve(bad, _seen(20, [0, 1, 2]))
    assert np.all(rb.residual_rms < 1e-10)
    assert np.all(np.linalg.norm(rb.translation - r.translation, axis=1) > 1e-3)
    assert (rb.status == STATUS_LOW_REDUNDANCY).all() and np.isfinite(rb.translation).all()


def test_seven_angles_detect_but_cannot_locate(rng):
    """3 sensors + one axis of a fourth (7 angles): low_redundancy. The one residual degree of freedom
    makes every angle's standardised residual |e_i| / sqrt(1 - h_ii) equal (hat matrix of the
    independent Jacobian at the solution), whichever angle carries the error."""
    ang = _frames(5, 1e-4, rng)
    ang[:, 0, 1] += 1e-3
    seen = _seen(5, [0, 1, 2], extra_axis=(3, 0))
    r = _solve(ang, seen)
    assert (r.status == STATUS_LOW_REDUNDANCY).all()
    for f in range(5):
        p = transform_points(r.rotation[f], r.translation[f], P5)
        J = angle_jacobian(p, p - r.translation[f])[seen[f]]            # (7, 6)
        e = (ang[f] - sweep_angles(p))[seen[f]]
        H = J @ np.linalg.solve(J.T @ J, J.T)
        w = np.abs(e) / np.sqrt(1.0 - np.diag(H))
        assert np.ptp(w) < 1e-2 * w.max() and w.max() > 1e-5    # all equal (to the LM tolerance), not zero
    # contrast: with 8 angles (both axes of the fourth sensor) the residual space is 2-D and the
    # standardised residuals differ — the least count at which locating the faulty angle is possible
    # at all (whether it succeeds depends on the geometry; here three angles are close)
    seen8 = _seen(5, [0, 1, 2, 3])
    r8 = _solve(ang, seen8)
    p = transform_points(r8.rotation[0], r8.translation[0], P5)
    J = angle_jacobian(p, p - r8.translation[0])[seen8[0]]
    e = (ang[0] - sweep_angles(p))[seen8[0]]
    w = np.abs(e) / np.sqrt(1.0 - np.diag(J @ np.linalg.solve(J.T @ J, J.T)))
    assert np.ptp(w) > 0.5 * w.max() and np.argmax(w) == 1    # angle (sensor 0, y), the second seen


def test_eight_angles_are_checked(rng):
    """4 sensors on both axes (8 angles, the Crazyflie deck's count): ok as before; a gross error now
    leaves a residual far above the noise. The same 4 sensors with one angle missing: low_redundancy."""
    ang = _frames(20, 1e-5, rng)
    r = _solve(ang, _seen(20, [0, 1, 2, 3]))
    assert (r.status == STATUS_OK).all()
    bad = ang.copy()
    bad[:, 1, 0] += 2e-3
    rb = _solve(bad, _seen(20, [0, 1, 2, 3]))
    assert np.all(rb.residual_rms > 50 * np.median(r.residual_rms))
    v = _seen(20, [0, 1, 2, 3])
    v[:, 3, 1] = False
    assert (_solve(ang, v).status == STATUS_LOW_REDUNDANCY).all()
    cold = solve_pnp(P5, ang, _seen(20, [0, 1, 2, 3]))        # the cold start agrees
    assert (cold.status == STATUS_OK).all()


def test_joint_counts_angles_over_all_stations(rng):
    """Joint solve: 3 sensors seen by each of two stations (12 angles) is ok; the same window with one
    station alone (6 angles) is low_redundancy; 3 sensors at one station + 1 at the other (8) is ok."""
    sts = stations_looking_at([[-1.5, -1.0, 2.0], [1.5, -1.2, 2.0]], (0, 0, 0), kind="lh1")
    F = 10
    R = np.tile(np.eye(3), (F, 1, 1))
    t = np.zeros((F, 3))
    a = simulate_station_angles(P5, R, t, sts, sigma=1e-5, rho=0.0, rng=rng)   # (F, 2, 5, 2)
    ini = (R, t + 1e-3)
    cases = {((0, 1, 2), (0, 1, 2)): STATUS_OK, ((0, 1, 2), ()): STATUS_LOW_REDUNDANCY,
             ((0, 1, 2), (4,)): STATUS_OK}
    for (s0, s1), want in cases.items():
        vis = np.zeros((F, 2, 5), bool)
        vis[:, 0, list(s0)] = True
        vis[:, 1, list(s1)] = True
        r = solve_joint(P5, a, vis, stations=sts, initial=ini)
        assert (r.status == want).all(), (s0, s1, r.message)
        assert np.all(np.linalg.norm(r.translation, axis=1) < 1e-2)         # the pose itself is sane


def test_status_table_and_message():
    assert status.NAMES[status.LOW_REDUNDANCY] == "low_redundancy"
    assert status.MIN_ANGLES + status.MIN_REDUNDANCY == 8
    st = np.array([STATUS_OK, STATUS_LOW_REDUNDANCY, STATUS_LOW_REDUNDANCY])
    assert status.summarize(st) == "1 ok, 2 low_redundancy"


def test_libsurvive_lh2_sample_low_redundancy_frames(libsurvive_dir, tmp_path):
    """Real LH2 tracker (the sample's first 4 s; ``solve --solve per-station``, each station through
    its calibration): the frames that come out low_redundancy are exactly the solved frames with 6-7
    seen angles (12 of the 300 that were all 'ok' before the rule), and their residuals are at
    rounding level while the checked frames show the device's real ~3e-5 rad: nothing was checked."""
    import json

    from click.testing import CliRunner

    from layoutkit.cli import main
    from layoutkit.io.frames import read_frame_table
    from layoutkit.io.poses import read_poses

    rec = libsurvive_dir / "lh2_test_cal_first4s.rec.gz"
    r = CliRunner().invoke(main, ["import", "libsurvive", str(rec), "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    d = tmp_path / "T20"
    r = CliRunner().invoke(main, ["solve", str(d / "frames.csv"), "--layout", str(d / "layout.json"), "--stations",
                                  str(tmp_path / "stations.json"), "--solve", "per-station", "--json",
                                  "--out", str(tmp_path / "poses.csv")])
    assert r.exit_code == 0, r.output
    counts = json.loads(r.stdout)["status_counts"]
    n_ang = np.isfinite(read_frame_table(d / "frames.csv").angles).sum((1, 2))
    poses = read_poses(tmp_path / "poses.csv")
    assert len(poses.t) == len(n_ang)
    low = poses.status == STATUS_LOW_REDUNDANCY
    ok = poses.status == STATUS_OK
    assert counts[str(STATUS_LOW_REDUNDANCY)] == low.sum() == 12 and ok.sum() == 288
    assert np.all((n_ang[low] >= 6) & (n_ang[low] <= 7)) and not np.any(ok & (n_ang < 8))
    assert np.all(poses.residual_rms[low] < 1e-9) and np.median(poses.residual_rms[ok]) > 1e-5


def test_live_pipeline_reports_low_redundancy_not_solver_failed():
    """Replay/live path: with ``min_lit=3`` a 3-sensor frame tracked from the previous pose is solved but
    reported ``low_redundancy`` (counted by name, its record says so), never ``ok`` or ``solver_failed``."""
    from layoutkit.live.frames import SweepMeasurement
    from layoutkit.live.pipeline import LiveConfig, PosePipeline
    from layoutkit.shapes import chen_target
    from layoutkit.visibility import facing_mask

    lay = chen_target()[1]
    F = 20
    t = np.arange(F) / 60.0
    R = np.tile(np.diag([1.0, -1.0, -1.0]), (F, 1, 1))                  # top face towards the station
    tr = np.column_stack([0.1 + 0.001 * t, 0.05 + 0 * t, 2.0 + 0 * t])
    lit = facing_mask(lay.positions, lay.normals, R, tr)
    ang = sweep_angles(np.einsum("fij,nj->fni", R, lay.positions) + tr[:, None])
    ang = np.where(lit[..., None], ang, np.nan)
    keep3 = np.flatnonzero(lit[0])[:3]
    ang[10:, np.setdiff1d(np.arange(lay.n), keep3)] = np.nan           # the last 10 frames: 3 sensors
    sw = []
    for k in range(F):
        sw.append(SweepMeasurement(t[k], 0, 0, ang[k, :, 0], 2 * k))
        sw.append(SweepMeasurement(t[k] + 1 / 120, 0, 1, ang[k, :, 1], 2 * k + 1))
    pipe = PosePipeline(lay.positions, LiveConfig(n_sensors=lay.n, min_lit=3))
    # two chunks: the second (3 sensors) starts from the first's last pose
    chunks = pipe.feed(sw[:20]) + pipe.flush() + pipe.feed(sw[20:]) + pipe.flush(end_of_stream=True)
    st = np.concatenate([c.status for c in chunks])
    assert (st[:10] == STATUS_OK).all() and (st[10:] == STATUS_LOW_REDUNDANCY).all()
    assert pipe.counters.by_status.get("low_redundancy") == 10
    recs = [r for c in chunks for r in c.records()]
    assert sum(r["status"] == "low_redundancy" for r in recs) == 10
