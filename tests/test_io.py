"""Our file formats (layoutkit/io/): the pose table, stations JSON and the capture sidecar.

Proof kind: round trips against the in-memory arrays that were written (every writer of the pose
table × every reader, agreeing to the printed precision), an explicit unit reference (``rx_deg``
columns vs ``np.radians`` of the same numbers), and the bad-input contract (a degree file fed to
the radians readers fails with a message naming the file, the line and the columns).
"""
from __future__ import annotations

import io
import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.geometry import attitude_error, random_rotations, rotvec_to_matrix
from layoutkit.io.poses import (JOINT, POSE_COLUMNS, PoseTable, PoseWriter, iter_poses, read_poses, read_reference,
                                write_poses)
from layoutkit.io.sidecar import CaptureSidecar, read_sidecar
from layoutkit.io.stations import read_stations, station_from_dict, station_to_dict, write_stations
from layoutkit.layout import save_layout
from layoutkit.lighthouse import Station
from layoutkit.shapes import chen_target

# ------------------------------------------------------------------------------- pose table


def _table(n=40, seed=0, extras=True):
    rng = np.random.default_rng(seed)
    rv = rng.normal(size=(n, 3))
    rv *= (rng.uniform(0.01, 3.1, n) / np.linalg.norm(rv, axis=1))[:, None]  # norms < pi
    ex = {"n_lit": rng.integers(4, 9, n), "adop_deg_per_rad": rng.uniform(10, 20, n)} if extras else {}
    return PoseTable(np.sort(rng.uniform(0, 10, n)), rv, rng.normal(size=(n, 3)) + [0, 0, 2],
                     station=rng.integers(0, 2, n), status=np.zeros(n, int), residual_rms=rng.uniform(0, 1e-4, n),
                     extras=ex)


def _writers(tmp_path):
    """Every writer of the pose table in the code → (path, the in-memory table it wrote)."""
    from layoutkit.live.simulator import simulate_sweeps, write_truth
    from layoutkit.workflows.frames import read_frames, simulate_frames, solution_table, solve_frames, write_frames
    from layoutkit.workflows.live import session_from_sidecar

    out = {}
    tb = _table()
    write_poses(tmp_path / "io.csv", tb)
    out["io.write_poses"] = (tmp_path / "io.csv", tb)

    with PoseWriter(tmp_path / "chunks.csv", tuple(tb.extras)) as w:  # streaming, 3 chunks
        for part in np.array_split(np.arange(len(tb)), 3):
            w.write(tb.take(part))
    out["io.PoseWriter"] = (tmp_path / "chunks.csv", tb)

    lay = chen_target()[1]
    sw = simulate_sweeps(lay, duration=0.3, seed=1)
    write_truth(sw, tmp_path / "TRUTH.csv")
    out["simulator.write_truth"] = (tmp_path / "TRUTH.csv", PoseTable(sw.t, sw.rotvec, sw.translation,
                                                                      station=sw.station))

    lay_path = tmp_path / "layout.json"
    save_layout(lay, lay_path)
    fr = simulate_frames(lay, 12, seed=2, sigma=4e-5, rho=0.8)
    write_frames(fr, tmp_path / "frames.csv")
    from layoutkit.cli import main

    r = CliRunner().invoke(main, ["solve", str(tmp_path / "frames.csv"), "--layout", str(lay_path),
                                  "--out", str(tmp_path / "solve.csv")])
    assert r.exit_code == 0, r.output
    res = solve_frames(read_frames(tmp_path / "frames.csv", lay), lay)
    out["cli solve --out"] = (tmp_path / "solve.csv", solution_table(res))

    from layoutkit.live.simulator import simulate_stream

    chunks, _ = simulate_stream(lay, duration=0.5, seed=4)
    js = io.StringIO()
    s = session_from_sidecar(lay, {"protocol": "layoutkit"}, json_out=js, poses_path=tmp_path / "poses.csv")
    s.feed_bytes(b"".join(c for _, c in chunks))
    s.finish()
    recs = [json.loads(ln) for ln in js.getvalue().splitlines()]
    assert recs
    live = PoseTable([r["t"] for r in recs], [r["rotvec"] for r in recs], [r["translation"] for r in recs],
                     station=[r["station"] for r in recs])
    out["live poses.csv"] = (tmp_path / "poses.csv", live)
    return out


def _readers():
    """Every reader of the pose table → function(path) → (t, R (N,3,3), translation) of the finite rows."""
    from layoutkit.envelope import Envelope
    from layoutkit.live.reference import PoseTrack
    from layoutkit.live.simulator import load_trajectory

    def read_pose_csv(p):
        return PoseTrack.from_reference(read_reference(p))

    def io_read(p):
        tb = read_poses(p)
        return tb.t, rotvec_to_matrix(tb.rotvec), tb.translation

    def io_iter(p):
        tb = PoseTable.concatenate(iter_poses(p, chunk_rows=7))
        return tb.t, rotvec_to_matrix(tb.rotvec), tb.translation

    def trajectory(p):
        tr = load_trajectory(p)
        return tr.times, rotvec_to_matrix(tr.rotvecs), tr.translations

    def envelope(p):
        R, t = Envelope.from_dict({"count": 0, "attitude": {"kind": "trajectory", "file": str(p)}}).poses()
        return None, R, t

    def reference(p):
        tr = read_pose_csv(p)
        return tr.t, tr.rotation, tr.translation

    return {"io.read_poses": io_read, "io.iter_poses": io_iter, "simulator.load_trajectory": trajectory,
            "envelope trajectory": envelope, "io.read_reference": reference}


def test_every_writer_read_by_every_reader_agrees(tmp_path):
    """Round trip: each writer's file, read by each reader, gives back the poses the writer had in
    memory (rotation to 1e-9 rad, translation to 1e-9 m, times to 1e-9 s; the solve output is
    compared with a second, in-memory solve of the same frames), in the fixed column order."""
    writers, readers = _writers(tmp_path), _readers()
    assert len(writers) == 5 and len(readers) == 5
    for wname, (path, table) in writers.items():
        header = path.read_text().splitlines()[0].split(",")
        assert tuple(header[:len(POSE_COLUMNS)]) == POSE_COLUMNS, wname
        got = read_poses(path)
        np.testing.assert_array_equal(got.station, table.station, err_msg=wname)
        np.testing.assert_array_equal(got.status, table.status, err_msg=wname)
        fin = table.ok
        order = np.argsort(table.t[fin], kind="stable")
        t_ref = table.t[fin][order]
        R_ref, tr_ref = rotvec_to_matrix(table.rotvec[fin][order]), table.translation[fin][order]
        for rname, read in readers.items():
            if rname == "envelope trajectory" and not np.all(table.ok):
                with pytest.raises(ValueError, match="non-finite"):
                    read(path)
                continue
            t, R, tr = read(path)
            if rname == "io.read_reference":  # drops repeated times (two sweeps per frame)
                keep = np.concatenate([[True], np.diff(t_ref) > 0])
                t_r, R_r, tr_r = t_ref[keep], R_ref[keep], tr_ref[keep]
            elif rname == "envelope trajectory":
                t_r, R_r, tr_r = None, rotvec_to_matrix(table.rotvec), table.translation
            else:
                t_r, R_r, tr_r = t_ref, R_ref, tr_ref
                if rname.startswith("io."):  # these keep every row, failed solves included
                    t_r, R_r, tr_r = table.t, rotvec_to_matrix(table.rotvec), table.translation
            assert len(R) == len(R_r), (wname, rname)
            ok = np.all(np.isfinite(tr_r), -1)
            np.testing.assert_array_equal(np.isfinite(tr).all(-1), ok, err_msg=f"{wname} / {rname}")
            assert attitude_error(R[ok], R_r[ok]).max() < 1e-9, (wname, rname)
            np.testing.assert_allclose(tr[ok], tr_r[ok], atol=1e-9, err_msg=f"{wname} / {rname}")
            if t is not None:
                np.testing.assert_allclose(t, t_r, atol=1e-9, err_msg=f"{wname} / {rname}")


DEG_ROWS = [(0.1 * k, 10.0 * k, -5.0, 2.0, 0.1 * k, 0.0, 2.0) for k in range(6)]


def _csv(path, header, rows):
    path.write_text(header + "\n" + "\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return path


def test_degrees_file_fed_to_the_radians_readers_is_rejected(tmp_path):
    """The factor-57 bug: a trajectory in degrees under the radians header is an error that names
    the file, the line and the columns, from every reader; the same numbers under ``rx_deg``
    columns read as np.radians of them (independent conversion)."""
    from layoutkit.envelope import Envelope
    from layoutkit.live.reference import PoseTrack
    from layoutkit.live.simulator import load_trajectory

    def read_pose_csv(p):
        return PoseTrack.from_reference(read_reference(p))

    bad = _csv(tmp_path / "deg.csv", "t,rx,ry,rz,tx,ty,tz", DEG_ROWS)
    want = (rf"^{bad}: line 2: columns rx,ry,rz: rotation vector norm 5.385 > pi — pose tables hold the rotation "
            r"vector in radians; this looks like degrees. Convert to radians, or name the columns rx_deg,ry_deg,rz_deg$")
    for read in (read_poses, load_trajectory, read_pose_csv,
                 lambda p: Envelope.from_dict({"count": 0, "attitude": {"kind": "trajectory", "file": str(p)}}).poses()):
        with pytest.raises(ValueError, match=want):
            read(bad)
    # a reference (mocap) file with x,y,z positions goes through the same check
    mocap = _csv(tmp_path / "mocap.csv", "t,rx,ry,rz,x,y,z", DEG_ROWS)
    with pytest.raises(ValueError, match=rf"^{mocap}: line 2: columns rx,ry,rz: rotation vector norm 5.385 > pi"):
        read_pose_csv(mocap)
    good = _csv(tmp_path / "tagged.csv", "t,rx_deg,ry_deg,rz_deg,tx_mm,ty_mm,tz_mm",
                [(r[0], *r[1:4], *(1e3 * np.array(r[4:]))) for r in DEG_ROWS])
    tb = read_poses(good)
    np.testing.assert_allclose(tb.rotvec, np.radians(np.array(DEG_ROWS)[:, 1:4]), rtol=1e-15)
    np.testing.assert_allclose(tb.translation, np.array(DEG_ROWS)[:, 4:], rtol=1e-12)
    traj = load_trajectory(good)
    np.testing.assert_allclose(traj.rotvecs, tb.rotvec)
    assert attitude_error(read_pose_csv(good).rotation, rotvec_to_matrix(tb.rotvec)).max() < 1e-12


@pytest.mark.parametrize("header, message", [
    ("t,rx_grad,ry_grad,rz_grad,tx,ty,tz", "column 'rx_grad': unknown angle unit 'grad' (expected rx, rx_rad or rx_deg)"),
    ("t,rx,ry,rz,tx_ft,ty,tz", "column 'tx_ft': unknown length unit 'ft'"),
    ("t,rx_deg,ry,rz,tx,ty,tz", "rotation columns rx_deg, ry, rz mix units"),
    ("time,rx,ry,rz,tx,ty,tz", "not a pose table: missing column(s) t (expected t,station,status,"),
    ("t,rx,ry,rz,rx_deg,ty,tz,tx", "column 'rx' appears twice (as 'rx' and 'rx_deg')"),
])
def test_bad_pose_headers_name_the_file_and_column(tmp_path, header, message):
    p = _csv(tmp_path / "p.csv", header, [(0,) * 7 if header.count(",") == 6 else (0,) * 8])
    with pytest.raises(ValueError) as e:
        read_poses(p)
    assert str(e.value).startswith(f"{p}: {message}")


def test_bad_pose_cells_name_line_and_column(tmp_path):
    p = _csv(tmp_path / "p.csv", ",".join(POSE_COLUMNS), [(0, 0, 0, 0, 0, 0, 0, 0, 1, 0), (1, "x", 0, 0, 0, 0, 0, 0, 1, 0)])
    with pytest.raises(ValueError, match=rf"^{p}: line 3: column station: expected an index or 'joint' \('x'\)$"):
        read_poses(p)
    p = _csv(tmp_path / "q.csv", ",".join(POSE_COLUMNS), [(0, 0, 0, 0, 0, 0, 0, 0, "abc", 0)])
    with pytest.raises(ValueError, match=rf"^{p}: line 2: column tz: not a number \('abc'\)$"):
        read_poses(p)
    p = _csv(tmp_path / "r.csv", ",".join(POSE_COLUMNS), [(0, "joint", 0, 0, 0, 0, 0, 0, 1, "")])
    tb = read_poses(p)
    assert tb.station[0] == JOINT and np.isnan(tb.residual_rms[0])
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'none.csv'}: no such pose table$"):
        read_poses(tmp_path / "none.csv")


def test_failed_writer_leaves_no_file(tmp_path):
    """Atomic: an exception inside the writer leaves neither the target nor a temporary file."""
    with pytest.raises(RuntimeError):
        with PoseWriter(tmp_path / "p.csv") as w:
            w.write(_table(extras=False))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------- stations, sidecar

def _stations():
    from layoutkit.lighthouse import CALIBRATION_PARAMS, calibration_from_dict

    rng = np.random.default_rng(5)
    cal = {"convention": "layoutkit", "kind": "lh2", "gib_argument": "ideal"}
    cal.update({name: list(rng.uniform(-1e-3, 1e-3, 2)) for name in CALIBRATION_PARAMS})
    return [Station(), Station(id="B", rotation=random_rotations(1, rng)[0], translation=[1.0, 0.2, -0.3],
                               kind="lh2", rotor_rpm=3000.0, fov_deg=110.0, calibration=calibration_from_dict(cal))]


def test_stations_round_trip_with_calibration(tmp_path):
    """Stations → JSON file → stations: every field back exactly, the calibration dict unchanged;
    unknown keys are rejected naming the station."""
    st = _stations()
    write_stations(tmp_path / "s.json", st)
    back = read_stations(tmp_path / "s.json")
    for a, b in zip(st, back, strict=True):
        assert station_to_dict(a) == station_to_dict(b)
        np.testing.assert_array_equal(a.rotation, b.rotation)
    np.testing.assert_array_equal(back[1].calibration.params, st[1].calibration.params)
    assert back[0].calibration is None and back[1].calibration.kind == "lh2"
    with pytest.raises(ValueError, match=r"^station: unknown key\(s\) 'colour' \(expected id, kind"):
        station_from_dict({"colour": "red"})
    (tmp_path / "bad.json").write_text('{"stations": [{"id": "A"}, {"kind": "lh3"}]}')
    with pytest.raises(ValueError, match=r"bad.json: stations\[1\]: Station.kind: expected 'lh1' or 'lh2', got 'lh3'$"):
        read_stations(tmp_path / "bad.json")


def test_capture_sidecar_round_trip(tmp_path):
    """CaptureWriter writes the sidecar dataclass; read_sidecar gives it back (stations with their
    calibration, protocol options, keys unknown to this version kept); the legacy nested protocol
    form reads the same."""
    from layoutkit.live.capture import CaptureWriter

    sc = CaptureSidecar(protocol="layoutkit", protocol_options={"n_sensors": 7}, stations=tuple(_stations()),
                        layout={"units": "m", "sensors": []}, port={"url": "loop://", "baudrate": 115200},
                        source="test", extra={"operator": "ada"})
    with CaptureWriter(tmp_path / "c.lkcap", sc) as w:
        w.write(b"abc", 0.0)
    back = read_sidecar(tmp_path / "c.lkcap")
    assert back.protocol == "layoutkit" and back.protocol_options == {"n_sensors": 7}
    assert back.bytes == 3 and back.start_time_utc and back.end_time_utc
    assert [station_to_dict(s) for s in back.stations] == [station_to_dict(s) for s in sc.stations]
    assert back.extra["operator"] == "ada" and back.layout == sc.layout and back.port == sc.port
    legacy = CaptureSidecar.from_dict({"protocol": {"name": "bitcraze-lh1", "options": {"x": 1}}})
    assert legacy.protocol == "bitcraze-lh1" and legacy.protocol_options == {"x": 1}
    (tmp_path / "d.lkcap.json").write_text('{"stations": [{"rotation": 3}]}')
    with pytest.raises(ValueError, match=r"d.lkcap.json.stations\[0\]: Station.rotation: expected shape \(3, 3\)"):
        read_sidecar(tmp_path / "d.lkcap")
    assert read_sidecar(tmp_path / "none.lkcap") == CaptureSidecar()
