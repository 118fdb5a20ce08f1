"""Hardware simulator: angles from the true poses, noise statistics, lit sets, motion bounds,
time base shared with the decoder, and the fake-fpga CLI.

Proof kinds: recomputation from TRUTH.csv with the core measurement model (independent path),
Monte-Carlo statistics against the model's sigma/rho, finite differences of the trajectory,
and decoding the simulator's bytes with the protocol decoder.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.geometry import rotvec_to_matrix, transform_points
from layoutkit.layout import load_layout
from layoutkit.lighthouse import in_field_of_view, sweep_angles
from layoutkit.live.capture import CaptureReader, read_sidecar
from layoutkit.live.protocols import get_protocol
from layoutkit.live.simulator import (TRUTH_HEADER, Trajectory, load_trajectory, simulate_stream,
                                      simulate_sweeps, write_truth)

LAYOUT = "tests/data/chen_layout.json"


@pytest.fixture(scope="module")
def layout():
    return load_layout(LAYOUT)


def test_angles_come_from_truth_pose_at_sweep_time(layout, tmp_path):
    """Noise-free simulated angles equal sweep_angles of the layout moved by the TRUTH.csv pose of
    the same row (pose at the sweep's sync time), axis by axis."""
    sw = simulate_sweeps(layout, duration=2.0, seed=1, sigma=0.0)
    write_truth(sw, tmp_path / "T.csv")
    tr = load_trajectory(tmp_path / "T.csv")
    np.testing.assert_allclose(tr.times, sw.t, atol=1e-9)
    p = transform_points(rotvec_to_matrix(tr.rotvecs), tr.translations, layout.positions)
    ref = np.take_along_axis(sweep_angles(p), sw.axis[:, None, None], -1)[..., 0]
    np.testing.assert_allclose(sw.angles_true, np.where(sw.lit, ref, np.nan), atol=1e-9)
    tick = 2 * np.pi * 60 / 50e6  # the wire carries whole 50 MHz ticks
    np.testing.assert_allclose(sw.measured_angles(), np.where(sw.lit, ref, np.nan), atol=tick / 2 + 1e-12)
    assert (tmp_path / "T.csv").read_text().splitlines()[0] == TRUTH_HEADER


def test_noise_sigma_rho_and_quantisation(layout):
    """Measured − true angles: std = sqrt(sigma² + tick²/12) and the correlation of two sensors'
    errors in the same sweep = rho (Chen eq. 19), Monte-Carlo over 30 s of sweeps."""
    sigma, rho = 4.014e-5, 0.8717
    sw = simulate_sweeps(layout, duration=30.0, seed=2, motion="static", sigma=sigma, rho=rho)
    e = sw.measured_angles() - sw.angles_true
    tick = 2 * np.pi * 60 / 50e6
    assert np.nanstd(e) == pytest.approx(np.sqrt(sigma**2 + tick**2 / 12), rel=0.03)
    both = np.isfinite(e).sum(0)
    i, j = np.argsort(both)[-2:]
    m = np.isfinite(e[:, i]) & np.isfinite(e[:, j])
    r = np.corrcoef(e[m, i], e[m, j])[0, 1]
    assert r == pytest.approx(rho * sigma**2 / (sigma**2 + tick**2 / 12), abs=0.02)


def test_lit_set_rule_and_minimum(layout):
    """Lit = facing the station (normal within 60° of the direction to it) and in the FOV,
    recomputed independently; the default tumble keeps at least 4 lit."""
    sw = simulate_sweeps(layout, duration=20.0, seed=3, sigma=0.0)
    R = rotvec_to_matrix(sw.rotvec)
    p = transform_points(R, sw.translation, layout.positions)
    n = np.einsum("kij,nj->kni", R, layout.normals)
    cosang = np.einsum("kni,kni->kn", n, -p) / np.linalg.norm(p, axis=-1)
    want = (cosang >= np.cos(np.deg2rad(60))) & in_field_of_view(p)
    np.testing.assert_array_equal(sw.lit, want)
    assert sw.lit.sum(1).min() >= 4


def test_tumble_is_slow_and_in_range(layout):
    """Finite differences of the truth: angular rate <= 0.5°/s, speed <= 1 mm/s, range 1.5-3 m,
    so the 8.3 ms between an X and a Y sweep moves the target far below the angle noise."""
    for seed in range(3):
        sw = simulate_sweeps(layout, duration=120.0, seed=seed, sigma=0.0)
        R = rotvec_to_matrix(sw.rotvec)
        dt = np.diff(sw.t)
        rel = np.einsum("kji,kjl->kil", R[:-1], R[1:])
        ang = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
        assert np.max(ang / dt) <= np.deg2rad(0.5) * 1.01
        assert np.max(np.linalg.norm(np.diff(sw.translation, axis=0), axis=1) / dt) <= 1e-3 * 1.01
        d = np.linalg.norm(sw.translation, axis=1)
        assert 1.5 <= d.min() and d.max() <= 3.0


def test_stream_time_base_dropouts_and_garbage(layout):
    """Decoding the simulator's bytes: t equals the truth time of every sent sweep exactly,
    lost frames appear as 'dropped', garbage never hides a frame, angles are the quantised ones."""
    chunks, sw = simulate_stream(layout, duration=10.0, seed=4, frame_loss=0.05, dropout=0.1, garbage=0.2)
    dec = get_protocol("layoutkit")(n_sensors=layout.n)
    out = []
    for _, b in chunks:
        out += dec.feed(b)
    sent = np.flatnonzero(sw.emitted)
    assert len(out) == len(sent) and dec.stats.errors == 0
    np.testing.assert_allclose([m.t for m in out], sw.t[sent], atol=1e-9)
    np.testing.assert_allclose(np.array([m.angles for m in out]), sw.measured_angles()[sent], atol=1e-12)
    lost_between = int(np.sum(np.diff(sent) - 1))
    assert dec.stats.dropped == lost_between
    hit = np.isfinite(sw.measured_angles())
    assert np.mean(hit[sw.lit]) == pytest.approx(0.9, abs=0.02)
    assert dec.stats.skipped_bytes > 0 and [t for t, _ in chunks] == sorted(t for t, _ in chunks)


def test_trajectory_motion_roundtrip(layout, tmp_path):
    """A trajectory CSV drives the simulator: its truth reproduces the CSV poses (interpolated)."""
    t = np.array([0.0, 1.0, 2.0])
    rv = np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0.01, 0]])
    tr = np.array([[0, 0, 2.0], [0.001, 0, 2.0], [0.002, 0, 2.001]])
    path = tmp_path / "traj.csv"
    np.savetxt(path, np.column_stack([t, rv, tr]), delimiter=",", header="t,rx,ry,rz,tx,ty,tz", comments="")
    traj = load_trajectory(path)
    sw = simulate_sweeps(layout, duration=2.0, seed=0, motion=traj, sigma=0.0)
    k = np.argmin(np.abs(sw.t - 1.0))
    R, tt = Trajectory(t, rv, tr)(sw.t[k:k + 1])
    np.testing.assert_allclose(sw.translation[k], tt[0], atol=1e-12)
    np.testing.assert_allclose(sw.translation[k], [0.001 * sw.t[k], 0, 2.0], atol=2e-6)
    with pytest.raises(ValueError, match=r"bad.csv: not a pose table: missing column\(s\) t, rx, ry, rz, tx, ty, tz"):
        bad = tmp_path / "bad.csv"
        bad.write_text("a,b\n1,2\n")
        load_trajectory(bad)


def test_fake_fpga_cli_writes_capture_sidecar_truth(tmp_path):
    """`layoutkit fake-fpga --out` writes the capture (+ index + sidecar with layout, stations,
    protocol) and TRUTH.csv; the capture decodes to one sweep per truth row."""
    from layoutkit.cli import main

    cap, truth = tmp_path / "c.lkcap", tmp_path / "T.csv"
    res = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--truth", str(truth),
                                    "--duration", "3", "--seed", "7", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    side = read_sidecar(cap)
    assert side["protocol"] == "layoutkit" and side["protocol_options"]["n_sensors"] == 12
    assert len(side["layout"]["sensors"]) == 12 and len(side["stations"]) == 1 and "start_time_utc" in side
    rows = np.loadtxt(truth, delimiter=",", skiprows=1)
    dec = get_protocol("layoutkit")(n_sensors=12)
    with CaptureReader(cap) as r:
        out = dec.feed(r.read(1 << 20))
    assert len(out) == len(rows) == summary["frames_sent"]
    np.testing.assert_allclose([m.t for m in out], rows[:, 0], atol=1e-9)
    bad = CliRunner().invoke(main, ["fake-fpga", "--layout", LAYOUT, "--out", str(cap), "--dropout", "2"])
    assert bad.exit_code == 2 and bad.output.startswith("error: Invalid value for '--dropout': 2.0 is not in the range") \
        and "(a probability in [0, 1])" in bad.output


def test_simulator_bitcraze_lh1_stream(layout):
    """protocol="bitcraze-lh1": the deck stream of a 4-sensor layout decodes (firmware method) to the
    simulated angles within half a 24 MHz tick, at the truth times; only the first sweep of each
    axis is lost (no rotor period measured yet). More than 4 sensors: a clear error."""
    four = layout.subset([0, 1, 2, 3])
    chunks, sw = simulate_stream(four, duration=3.0, seed=2, protocol="bitcraze-lh1", frame_loss=0.05)
    dec = get_protocol("bitcraze-lh1")(n_sensors=4)
    out = [m for _, b in chunks for m in dec.feed(b)] + dec.flush()
    assert len(out) == len(sw.t) - 2 and dec.stats.bad == 0
    t = np.array([m.t for m in out])
    k = np.searchsorted(sw.t, t - 1e-6)
    np.testing.assert_allclose(t, sw.t[k], atol=1e-8)
    want = np.where(sw.emitted[:, None], sw.measured_angles(), np.nan)[k]
    got = np.array([m.angles for m in out])
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, atol=np.pi / 400000 + 1e-12)
    with pytest.raises(ValueError, match=r"^protocol bitcraze-lh1: the Lighthouse deck has at most 4 sensors, "
                                         r"the layout has 12$"):
        simulate_stream(layout, duration=1.0, protocol="bitcraze-lh1")


def test_pty_simulator_stops_when_its_reader_is_gone(monkeypatch):
    """A reader that opens the port, reads nothing and closes it: once the pty buffer is full
    and nobody has the port open, the simulator stops with ReaderGone instead of waiting forever."""
    import os
    import threading
    import time

    from layoutkit.live import simulator
    from layoutkit.live.simulator import ReaderGone, run_fake_fpga

    monkeypatch.setattr(simulator, "READER_GONE_S", 0.3)
    chunks = [(0.0, bytes(4096))] * 200  # 800 KiB: more than a pty buffers
    box = {}

    def reader(path):
        def go():
            fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
            time.sleep(0.3)
            os.close(fd)
        threading.Thread(target=go, daemon=True).start()

    t0 = time.monotonic()
    try:
        run_fake_fpga(chunks, realtime=False, on_ready=reader, wait_reader=5)
    except ReaderGone as exc:
        box["msg"] = str(exc)
    assert "closed the port" in box.get("msg", "")
    assert time.monotonic() - t0 < 10
