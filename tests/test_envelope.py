"""Operating envelopes: TOML validation with exact messages, the sampled poses obey the declared
sets (range, cone, attitude cone), sampling distributions match closed forms (Archimedes' cap area,
Haar angle law via a KS test), trajectories read back exactly."""
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from layoutkit.envelope import Envelope, load_envelope, sample_cone_directions, sample_cone_rotations
from layoutkit.geometry import attitude_error, rotvec_to_matrix

MODELS = Path(__file__).resolve().parent.parent / "models"


def test_chen_example_poses_respect_the_envelope():
    env = load_envelope(MODELS / "chen_envelope.toml")
    R, t = env.poses()
    assert R.shape == (env.count, 3, 3) and t.shape == (env.count, 3)
    r = np.linalg.norm(t, axis=1)
    assert r.min() >= 1.0 and r.max() <= 3.0
    assert np.degrees(np.arccos(t[:, 2] / r)).max() <= 30.0 + 1e-9
    err = np.degrees(attitude_error(R, rotvec_to_matrix(np.radians([180.0, 0, 0]))))
    assert err.max() <= 45.0 + 1e-9
    np.testing.assert_allclose(np.einsum("pij,pkj->pik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    R2, t2 = load_envelope(MODELS / "chen_envelope.toml").poses()
    np.testing.assert_array_equal(t, t2)  # seeded
    assert not np.allclose(Envelope.from_dict({**env.to_dict(), "seed": 1}).poses()[1], t)


def test_cap_directions_are_area_uniform(rng):
    """Archimedes: the fraction of a cap of half-angle h above cos(h2) is (1-cos h2)/(1-cos h)."""
    h, h2, n = np.radians(50), np.radians(30), 40000
    d = sample_cone_directions(n, h, rng)
    frac = np.mean(d[:, 2] >= np.cos(h2))
    p = (1 - np.cos(h2)) / (1 - np.cos(h))
    assert abs(frac - p) < 4 * np.sqrt(p * (1 - p) / n)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)


@pytest.mark.parametrize("half_deg", [20.0, 90.0, 180.0])
def test_cone_rotation_angles_follow_haar_law(rng, half_deg):
    """KS test of the geodesic angle against the Haar CDF (a - sin a) / (h - sin h)."""
    h = np.radians(half_deg)
    nom = rotvec_to_matrix(np.array([0.3, -1.0, 0.5]))
    R = sample_cone_rotations(4000, nom, h, rng)
    a = attitude_error(R, nom)
    assert a.max() <= h + 1e-9
    p = stats.kstest(a, lambda x: (x - np.sin(x)) / (h - np.sin(h))).pvalue
    assert p > 1e-3


def test_two_station_example_and_look_at():
    env = load_envelope(MODELS / "docking_two_stations.toml")
    assert [s.id for s in env.stations] == ["L", "R"] and [s.kind for s in env.stations] == ["lh2", "lh2"]
    for s in env.stations:  # boresight (station z axis in the world) points at look_at_m
        want = np.array([0.0, 0.0, 6.0]) - s.translation
        np.testing.assert_allclose(s.rotation[:, 2], want / np.linalg.norm(want), atol=1e-12)
    R, t = env.poses()
    ref = env.stations[0]
    r = np.linalg.norm(t - ref.translation, axis=1)
    assert r.min() >= 3.0 and r.max() <= 8.0


def test_unknown_keys_are_rejected_with_exact_messages(tmp_path):
    p = tmp_path / "e.toml"
    p.write_text('count = 10\nrnage_m = [1, 2]\n')
    with pytest.raises(ValueError) as e:
        load_envelope(p)
    assert str(e.value) == (f"{p}: envelope: unknown key(s) ['rnage_m']; allowed: ['attitude', 'boresight_cone_deg', "
                            "'count', 'description', 'name', 'range_m', 'reference_station', 'seed', 'station']")
    p.write_text('[attitude]\nkind = "uniform"\nhalf_angle_deg = 10\n')
    with pytest.raises(ValueError) as e:
        load_envelope(p)
    assert str(e.value) == f"{p}: attitude (kind = 'uniform'): unknown key(s) ['half_angle_deg']; allowed: ['kind']"
    p.write_text('[[station]]\nid = "A"\nfov = 120\n')
    with pytest.raises(ValueError) as e:
        load_envelope(p)
    assert str(e.value).startswith(f"{p}: station 0: unknown key(s) ['fov']; allowed: ['clock_hz', 'fov_deg', 'id'")


@pytest.mark.parametrize("text,msg", [
    ("range_m = [3, 1]", "range_m: expected [min, max] with 0 < min <= max, got [3, 1]"),
    ("count = -5", "count: expected a positive integer, got -5"),
    ('[attitude]\nkind = "gaussian"', "attitude.kind: expected one of ['uniform', 'cone', 'trajectory'], got 'gaussian'"),
    ('[[station]]\nposition_m = [0, 0]', "station 0.position_m: expected 3 finite numbers, got [0, 0]"),
    ('[[station]]\nkind = "lh3"', "station 0: Station.kind: expected 'lh1' or 'lh2', got 'lh3'"),
    ("count = ", None),
])
def test_bad_values_name_the_field(tmp_path, text, msg):
    p = tmp_path / "e.toml"
    p.write_text(text + "\n")
    with pytest.raises(ValueError) as e:
        load_envelope(p)
    if msg is None:
        assert str(e.value).startswith(f"{p}: not valid TOML (")
    else:
        assert str(e.value) == f"{p}: {msg}"


def test_trajectory_csv_gives_the_poses_exactly(tmp_path):
    """A trajectory is a pose table (io/poses.py): degrees only when the columns say so (rx_deg)."""
    rows = [(0.1 * k, 10.0 * k, -5.0, 2.0, 0.1 * k, 0.0, 2.0 + 0.01 * k) for k in range(11)]
    (tmp_path / "traj.csv").write_text("t,rx_deg,ry_deg,rz_deg,tx,ty,tz\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    p = tmp_path / "e.toml"
    p.write_text('count = 6\n[attitude]\nkind = "trajectory"\nfile = "traj.csv"\n')
    R, t = load_envelope(p).poses()
    sel = np.array(rows)[::2]
    np.testing.assert_allclose(t, sel[:, 4:7])
    np.testing.assert_allclose(R, rotvec_to_matrix(np.radians(sel[:, 1:4])))
    (tmp_path / "traj.csv").write_text("time,rx,ry,rz,tx,ty,tz\n0,0,0,0,0,0,1\n")
    with pytest.raises(ValueError) as e:
        load_envelope(p)
    assert str(e.value).startswith(f"{p}: {tmp_path / 'traj.csv'}: not a pose table: missing column(s) t ")
    # the same degrees under the radians header: rejected, not read 57x too large
    (tmp_path / "traj.csv").write_text("t,rx,ry,rz,tx,ty,tz\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    with pytest.raises(ValueError, match=r"traj.csv: line 2: columns rx,ry,rz: rotation vector norm .* > pi .*degrees"):
        load_envelope(p)


def test_default_station_is_at_the_origin_and_round_trip():
    env = Envelope.from_dict({"count": 5, "seed": 3})
    assert len(env.stations) == 1 and np.allclose(env.stations[0].rotation, np.eye(3))
    back = Envelope.from_dict(env.to_dict())
    for a, b in zip(env.poses(), back.poses()):
        np.testing.assert_array_equal(a, b)
