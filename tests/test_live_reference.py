"""Reference streams (layoutkit.live.reference): CSV formats, interpolation, and recovery of a
known clock offset and known fixed frames from synthetic data (proof by construction)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from layoutkit.geometry import attitude_error, matrix_to_rotvec, random_rotations, rotvec_to_matrix
from layoutkit.io.poses import read_reference
from layoutkit.live.reference import PoseTrack, align_reference, estimate_alignment, estimate_time_offset

DEG = np.pi / 180


def motion(t):
    """Body pose in the lighthouse frame: rotation about varying axes, slow translation."""
    rv = np.column_stack([0.8 * np.sin(0.3 * t + 0.2 * np.sin(0.05 * t)), 0.5 * np.sin(0.17 * t + 1),
                          0.4 * np.cos(0.23 * t)])
    tr = np.column_stack([0.3 * np.sin(0.1 * t), 0.2 * np.cos(0.13 * t), 2 + 0.3 * np.sin(0.07 * t)])
    return rotvec_to_matrix(rv), tr


def mocap_of(t_ref, tau, Rx, tx, Ry, ty):
    """Reference stream sampled at its own times: R_l(t) = Rx R_m(t + tau) Ry (module model)."""
    Rl, tl = motion(t_ref - tau)
    Rm = Rx.T @ Rl @ Ry.T
    tm = (tl - tx) @ Rx - Rm @ ty
    return Rm, tm


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(1)
    t = np.arange(0, 40, 1 / 60)
    Rb, tb = motion(t)
    noise = rotvec_to_matrix(rng.normal(0, 0.1 * DEG / np.sqrt(3), (len(t), 3)))
    L = PoseTrack(t, noise @ Rb, tb + rng.normal(0, 1e-3 / np.sqrt(3), (len(t), 3)))
    Rx, Ry = random_rotations(2, rng)
    tx, ty = np.array([0.5, -1.0, 3.0]), np.array([0.01, 0.02, -0.03])
    tau = 0.337
    tm = np.arange(-1, 42, 1 / 100)  # 100 Hz mocap with its own clock
    Rm, pm = mocap_of(tm, tau, Rx, tx, Ry, ty)
    return L, PoseTrack(tm, Rm, pm), (tau, Rx, tx, Ry, ty)


def test_alignment_recovers_known_offset_and_frames(setup):
    """Known tau (0.337 s), R_x, t_x, R_y, t_y are recovered from noisy lighthouse poses
    (0.1°, 1 mm): tau to 3 ms, rotations to 0.03°, translations to 1 mm."""
    L, M, (tau, Rx, tx, Ry, ty) = setup
    a = align_reference(L, M)
    assert a.success and a.status == "ok"
    assert abs(a.tau - tau) < 3e-3
    assert attitude_error(a.R_x, Rx) < 0.03 * DEG
    assert attitude_error(a.R_y, Ry) < 0.03 * DEG
    assert np.linalg.norm(a.t_x - tx) < 1e-3 and np.linalg.norm(a.t_y - ty) < 1e-3
    # mapped reference reproduces the lighthouse truth at the lighthouse times
    R, t, v = a.apply(M, L.t)
    Rtrue, ttrue = motion(L.t)
    assert v.all()
    assert np.sqrt(np.mean(attitude_error(R, Rtrue) ** 2)) < 0.03 * DEG
    assert np.sqrt(np.mean(np.sum((t - ttrue) ** 2, -1))) < 1e-3


def test_time_offset_by_angular_speed_correlation(setup):
    """The coarse cross-correlation alone lands within 0.1 s of the true offset (the refinement's
    search interval)."""
    L, M, (tau, *_) = setup
    assert abs(estimate_time_offset(L, M) - tau) < 0.1


def test_exact_alignment_without_noise():
    """Noise-free time-matched samples give the transforms to 1e-9 (closed form + linear LSQ)."""
    rng = np.random.default_rng(2)
    t = np.linspace(0, 30, 400)
    Rl, tl = motion(t)
    Rx, Ry = random_rotations(2, rng)
    tx, ty = rng.normal(size=3), rng.normal(size=3) * 0.05
    Rm, tm = mocap_of(t, 0.0, Rx, tx, Ry, ty)
    a = estimate_alignment(Rl, Rm, tl, tm)
    assert attitude_error(a.R_x, Rx) < 1e-9 and attitude_error(a.R_y, Ry) < 1e-9
    np.testing.assert_allclose(a.t_x, tx, atol=1e-9)
    np.testing.assert_allclose(a.t_y, ty, atol=1e-9)


def test_camera_attitude_only_alignment(setup):
    """Rotation-only stream (camera): R_x, R_y recovered, translations None."""
    L, M, (tau, Rx, _, Ry, _) = setup
    cam = PoseTrack(M.t, M.rotation, None)
    a = align_reference(L, cam)
    assert a.success and a.t_x is None
    assert attitude_error(a.R_x, Rx) < 0.03 * DEG and abs(a.tau - tau) < 3e-3


def test_single_axis_rotation_is_degenerate():
    """Rotation about one fixed axis leaves R_x unobservable: a status, not an exception."""
    t = np.linspace(0, 10, 200)
    R = rotvec_to_matrix(np.column_stack([0 * t, 0 * t, 0.5 * t]))
    a = estimate_alignment(R, R)
    assert not a.success and a.status == "degenerate_rotation"


def test_interpolation_is_exact_at_samples_and_geodesic_between():
    """SLERP check: at sample times the stored pose; midway the geodesic midpoint; outside NaN."""
    R = random_rotations(2, np.random.default_rng(3))
    tr = PoseTrack(np.array([0.0, 1.0]), R, np.array([[0, 0, 0], [1.0, 2.0, 3.0]]))
    Ri, ti, v = tr.at(np.array([0.0, 0.5, 1.0, 1.5]))
    np.testing.assert_array_equal(v, [True, True, True, False])
    np.testing.assert_allclose(Ri[[0, 2]], R, atol=1e-12)
    mid = Rotation.from_matrix(R[0]) * Rotation.from_rotvec(0.5 * Rotation.from_matrix(R[0].T @ R[1]).as_rotvec())
    assert attitude_error(Ri[1], mid.as_matrix()) < 1e-12
    np.testing.assert_allclose(ti[1], [0.5, 1.0, 1.5])
    assert np.isnan(ti[3]).all()


@pytest.mark.parametrize("form", ["rotvec", "quat", "matrix"])
def test_csv_formats_and_units_agree(tmp_path, form):
    """The three attitude encodings (scipy conversions) and mm positions read to the same track."""
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(0, 10, 50))
    R = random_rotations(50, rng)
    p = rng.normal(size=(50, 3))
    if form == "rotvec":
        cols, att = "rx,ry,rz", matrix_to_rotvec(R)
    elif form == "quat":
        cols, att = "qx,qy,qz,qw", Rotation.from_matrix(R).as_quat()
    else:
        cols, att = ",".join(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)), R.reshape(50, 9)
    path = tmp_path / "ref.csv"
    np.savetxt(path, np.column_stack([t, att, p * 1e3]), delimiter=",", header="t," + cols + ",x,y,z", comments="")
    tr = PoseTrack.from_reference(read_reference(path, units="mm"))
    np.testing.assert_allclose(tr.t, t)
    assert attitude_error(tr.rotation, R).max() < 1e-9
    np.testing.assert_allclose(tr.translation, p, atol=1e-12)


def test_csv_errors(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("t,a,b\n0,1,2\n1,2,3\n")
    with pytest.raises(ValueError, match=r"expected attitude columns rx,ry,rz or qx,qy,qz,qw or r11..r33 and/or "
                                         r"position columns x,y,z or tx,ty,tz, got header \['t', 'a', 'b'\]$"):
        read_reference(path)
    with pytest.raises(ValueError, match=r"^units: expected one of \['cm', 'in', 'm', 'mm'\], got 'inch'$"):
        read_reference(path, units="inch")
    path.write_text("t,x,y,z\n0,1,2,3\n1,2,3,4\n")
    with pytest.raises(ValueError, match=r"bad.csv: a position-only reference: the alignment needs attitude"):
        PoseTrack.from_reference(read_reference(path))
    with pytest.raises(ValueError, match=r"^PoseTrack: times must be strictly increasing$"):
        PoseTrack(np.array([0.0, 0.0]), np.stack([np.eye(3)] * 2))


def test_clock_offset_of_hours(setup):
    """A mocap clock 2,712.4 s (45 min) away from the lighthouse's (the case that failed with the old
    ±5 s search): the offset and the frames are recovered as for a small offset (construction)."""
    L, _, (_, Rx, tx, Ry, ty) = setup
    tau = 2712.4
    tm = np.arange(tau - 1, tau + 42, 1 / 100)
    Rm, pm = mocap_of(tm, tau, Rx, tx, Ry, ty)
    M = PoseTrack(tm, Rm, pm)
    assert abs(estimate_time_offset(L, M) - tau) < 0.1
    a = align_reference(L, M)
    assert a.success and abs(a.tau - tau) < 3e-3
    assert np.linalg.norm(a.t_x - tx) < 1e-3
