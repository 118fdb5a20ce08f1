"""`layoutkit import reference`: position-only (t,x,y,z) and pose references, CSV and .npy, any
clock origin → a pose table (round trip exact; construction)."""
import numpy as np
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.io.poses import read_poses


def test_position_only_csv_and_npy(tmp_path):
    t = 2712.0 + np.arange(50) / 100.0  # a mocap clock 45 min from anything else
    p = np.column_stack([np.sin(t), np.cos(t), 0.1 * (t - t[0])])  # metres: a mocap volume is a room
    csvf = tmp_path / "mocap.csv"
    csvf.write_text("t,x,y,z\n" + "\n".join(",".join(repr(float(v)) for v in row) for row in np.column_stack([t, p * 1e3])))
    out = tmp_path / "ref.csv"
    r = CliRunner().invoke(main, ["import", "reference", str(csvf), "--out", str(out), "--units", "mm", "--json"])
    assert r.exit_code == 0, r.output
    tb = read_poses(out)
    np.testing.assert_allclose(tb.t, t)
    np.testing.assert_allclose(tb.translation, p, atol=1e-12)
    assert np.isnan(tb.rotvec).all()
    npy = tmp_path / "mocap.npy"
    np.save(npy, np.column_stack([t, p]))
    r = CliRunner().invoke(main, ["import", "reference", str(npy), "--out", str(tmp_path / "ref2.csv")])
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(read_poses(tmp_path / "ref2.csv").translation, p, atol=1e-12)


def test_pose_csv_and_errors(tmp_path):
    f = tmp_path / "m.csv"
    f.write_text("t,qx,qy,qz,qw,x,y,z\n0,0,0,0,1,1,2,3\n1,0,0,0.7071067811865476,0.7071067811865476,1,2,3\n")
    r = CliRunner().invoke(main, ["import", "reference", str(f), "--out", str(tmp_path / "o.csv")])
    assert r.exit_code == 0, r.output
    tb = read_poses(tmp_path / "o.csv")
    np.testing.assert_allclose(tb.rotvec[1], [0, 0, np.pi / 2], atol=1e-12)
    f.write_text("time,x,y,z\n0,1,2,3\n")
    r = CliRunner().invoke(main, ["import", "reference", str(f), "--out", str(tmp_path / "o2.csv")])
    assert r.exit_code == 2 and "no 't' column" in r.output
