"""Protocol decoders: layoutkit frame protocol and the Bitcraze Lighthouse deck stream (LH1, LH2).

Proof kinds: byte-exact comparison with frames packed by hand from the documented byte table
(docs/protocol.md), closed-form timing → angle formulas (Chen eq. 1; Bitcraze firmware formulas
re-implemented here from the pulse list), round trips under arbitrary chunking (hypothesis),
counter/sequence arithmetic, and the firmware calibration model inverted in closed loop.
"""
from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from layoutkit.lighthouse import lh2_sweep_angles, points_in_station, ticks_to_angles
from layoutkit.live.protocols import PROTOCOLS, get_protocol
from layoutkit.live.protocols import bitcraze as bc
from layoutkit.io.systemconfig import read_system_config
from layoutkit.live.protocols.layoutkit import NO_HIT, encode_sweep, encode_sweeps, frame_size


def _frames(K=40, n=6, seed=0, sync0=123456):
    rng = np.random.default_rng(seed)
    hits = rng.integers(0, 416_000, (K, n))
    hits[rng.random((K, n)) < 0.3] = -1
    sync = sync0 + np.arange(K) * 416_667
    axis = np.arange(K) % 2
    return hits, sync, axis, encode_sweeps(0, axis, np.arange(K), sync, hits)


def _decode(name, data, chunk=4096, **kw):
    dec = get_protocol(name)(**kw)
    out = []
    for i in range(0, len(data), chunk):
        out += dec.feed(data[i:i + chunk])
    return out + dec.flush(), dec


# ------------------------------------------------------------------------------- registry
def test_registry_names_and_unknown_message():
    """The registry holds the three documented names; an unknown name lists them."""
    assert set(PROTOCOLS) == {"layoutkit", "bitcraze-lh1", "bitcraze-lh2"}
    with pytest.raises(ValueError, match=r"^protocol: expected one of \['bitcraze-lh1', 'bitcraze-lh2', "
                                         r"'layoutkit'\], got 'nmea'$"):
        get_protocol("nmea")


# --------------------------------------------------------------------------- layoutkit
def test_encoder_matches_byte_table():
    """encode_sweep equals a frame packed by hand from the docs/protocol.md byte table + zlib CRC-32."""
    hits = [5, NO_HIT, 70000]
    body = (b"\xd7\x4b" + bytes([1, 3 | (1 << 4)]) + struct.pack("<H", 513) + bytes([3])
            + struct.pack("<I", 0xFFFFFFF0) + struct.pack("<3I", *hits))
    ref = body + struct.pack("<I", zlib.crc32(body))
    assert encode_sweep(3, 1, 513, 0xFFFFFFF0, hits) == ref
    assert len(ref) == frame_size(3) == 11 + 12 + 4
    K_hits, sync, axis, frames = _frames(K=5, n=3)
    for k in range(5):
        assert frames[k] == encode_sweep(0, axis[k], k, sync[k], K_hits[k])


def test_layoutkit_decode_angles_and_time():
    """Angles = omega * ticks / clock (Chen eq. 1, lighthouse.ticks_to_angles), NaN for no hit;
    t = sync counter / clock; stats count every frame as good."""
    hits, sync, axis, frames = _frames()
    out, dec = _decode("layoutkit", b"".join(frames), n_sensors=6)
    assert len(out) == len(frames) == dec.stats.good
    A = np.array([m.angles for m in out])
    want = np.where(hits < 0, np.nan, ticks_to_angles(hits))
    np.testing.assert_allclose(A, want, rtol=0, atol=1e-15)
    np.testing.assert_allclose([m.t for m in out], sync / 50e6, rtol=0, atol=1e-12)
    assert [m.axis for m in out] == list(axis) and [m.seq for m in out] == list(range(len(frames)))
    assert all(m.kind == "lh1" and m.station == 0 for m in out)
    assert dec.stats.bad == dec.stats.dropped == dec.stats.skipped_bytes == 0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 200), min_size=1, max_size=60))
def test_layoutkit_arbitrary_chunking(cuts):
    """Any chunking of the byte stream gives the same sweeps as one feed (incremental decoding)."""
    hits, sync, axis, frames = _frames(K=12, n=4, seed=3)
    data = b"".join(frames)
    dec = get_protocol("layoutkit")(n_sensors=4)
    out, pos = [], 0
    for c in cuts:
        out += dec.feed(data[pos:pos + c])
        pos += c
    out += dec.feed(data[pos:])
    assert [m.seq for m in out] == list(range(12))
    np.testing.assert_array_equal(np.isnan([m.angles for m in out]), hits < 0)


def test_counter_wrap_and_lh2_kind():
    """The u32 sync counter wraps (85.9 s at 50 MHz): t keeps increasing by the true interval.
    LH2 frames: alpha = omega * ticks / clock - pi at 3000 rpm."""
    sync = (2**32 - 2 * 416_667 + np.arange(6) * 416_667)  # crosses the wrap
    frames = encode_sweeps(2, np.arange(6) % 2, np.arange(6), sync, np.full((6, 2), 1000), "lh2")
    out, dec = _decode("layoutkit", b"".join(frames), n_sensors=2)
    np.testing.assert_allclose(np.diff([m.t for m in out]), 416_667 / 50e6, atol=1e-12)
    assert out[0].t == pytest.approx(sync[0] / 50e6)
    assert all(m.kind == "lh2" and m.station == 2 for m in out)
    np.testing.assert_allclose(out[0].angles, 1000 * 2 * np.pi * 50 / 50e6 - np.pi, atol=1e-15)


def test_sequence_gaps_and_device_reset():
    """Frames missing from the stream count as dropped (sequence gaps, also across the u16 wrap);
    a repeated frame is reported once; a restart at seq 0 counts as a reset and keeps t monotone."""
    K = 30
    seq = (65530 + np.arange(K)) % 65536
    sync = 1000 + np.arange(K) * 416_667
    frames = encode_sweeps(0, 0, seq, sync, np.zeros((K, 1)))
    keep = [k for k in range(K) if k not in (3, 4, 9, 20)]
    reset = encode_sweeps(0, 0, [0, 1], [500, 500 + 416_667], np.zeros((2, 1)))
    repeat = [frames[keep[-1]]]  # the last frame sent twice: reported once
    out, dec = _decode("layoutkit", b"".join([frames[k] for k in keep] + repeat + reset), n_sensors=1)
    assert dec.stats.dropped == 4 and dec.stats.resets == 1 and dec.stats.good == len(keep) + 2
    assert dec.stats.bad == 1
    assert np.all(np.diff([m.t for m in out]) > 0)


def test_garbage_bitflips_and_wrong_sensor_count():
    """Garbage between frames, a corrupted frame and a frame of another sensor count: all the
    intact frames decode, the corrupted one is not reported, the counters say what happened."""
    hits, sync, axis, frames = _frames(K=10, n=6)
    bad = bytearray(frames[4])
    bad[20] ^= 0x10
    other = encode_sweep(0, 0, 99, 0, [1, 2, 3])
    junk = b"\xd7\x4b\x01\x00\x00\x00\xff" + bytes(range(40))  # a false magic with n=0 inside
    data = frames[0] + junk + b"".join(frames[1:4]) + bytes(bad) + frames[5] + other + b"".join(frames[6:])
    out, dec = _decode("layoutkit", data, chunk=7, n_sensors=6)
    assert [m.seq for m in out] == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    assert dec.stats.dropped == 1 and dec.stats.bad >= 3 and dec.stats.errors == 0
    assert dec.stats.skipped_bytes == len(junk) + len(bad) + len(other)


def test_decoder_never_raises_on_junk():
    """Random bytes, empty input and non-bytes never raise and never yield a sweep."""
    rng = np.random.default_rng(7)
    for name in PROTOCOLS:
        dec = get_protocol(name)(n_sensors=4)
        assert dec.feed(b"") == [] and dec.feed(None) == []
        for _ in range(20):
            assert dec.feed(rng.integers(0, 256, 500, dtype=np.uint8).tobytes()) == []
        dec.flush()
        assert dec.stats.errors == 0


def test_constructor_messages():
    with pytest.raises(ValueError, match=r"^n_sensors: expected 1-255, got 0$"):
        get_protocol("layoutkit")(n_sensors=0)
    with pytest.raises(ValueError, match=r"^n_sensors: the Lighthouse deck has 1-4 sensors, got 5$"):
        get_protocol("bitcraze-lh2")(n_sensors=5)
    with pytest.raises(ValueError, match=r"^station: expected 0-15, got 16$"):
        encode_sweep(16, 0, 0, 0, [1])


# ------------------------------------------------------------------------------ Bitcraze
def test_deck_frame_layout_and_validity():
    """encode_pulse packs the public 12-byte layout; parse_frame inverts it; the padding rule
    ((b5 | b8) & 0xFE) == 0 rejects misaligned frames; 12 × 0xFF is the sync frame."""
    p = bc.DeckPulse(sensor=2, timestamp=0xABCDEF, width=0x1234, offset=0x1ABCD, beam_word=0x10001,
                     channel=5, slow_bit=1)
    b = bc.encode_pulse(p)
    assert b == bytes([2 | 4 | (5 << 3), 0x34, 0x12, 0xCD, 0xAB, 0x01, 0x01, 0x00, 0x01, 0xEF, 0xCD, 0xAB])
    assert bc.parse_frame(b) == p
    assert bc.parse_frame(bc.SYNC_FRAME) is None
    assert bc.parse_frame(bc.encode_pulse(bc.DeckPulse(0, 1, 2))).channel is None
    with pytest.raises(ValueError, match="padding bits set"):
        bc.parse_frame(b[1:] + b[:1])


def _lh1_reference(pulses, n):
    """Firmware LH1 formula applied directly to the encoded pulses: per active sync, sweep pulse
    delta, P = time between syncs of the same station and axis, a = (delta - P/4) 2pi/P."""
    syncs = []  # first pulse of each sync event (pulses of all sensors within 10 ticks)
    for p in pulses:
        if 1000 < p.width < 3250 and (not syncs or p.timestamp - syncs[-1].timestamp > 10):
            syncs.append(p)
    last, out = {}, {}
    st_prev = None
    for k, s in enumerate(syncs):
        station = 1 if st_prev is not None and 7500 < s.timestamp - st_prev < 12500 else 0
        st_prev = s.timestamp
        code = (s.width - 1375) // 250
        prev = last.get((station, code & 1))
        last[(station, code & 1)] = s.timestamp
        if code & 4 or prev is None:
            continue
        P = s.timestamp - prev
        a = np.full(n, np.nan)
        for p in pulses:  # sweep pulses less than one frame (200000 ticks) after the active sync
            if p.width < 512 and 0 < p.timestamp - s.timestamp < 200000:
                a[p.sensor] = (p.timestamp - s.timestamp - P / 4) * 2 * np.pi / P
        out[s.timestamp] = (station, code & 1, np.pi / 2 - a)
    return out


@pytest.mark.parametrize("stations", [1, 2])
def test_bitcraze_lh1_stream_matches_firmware_formula(stations):
    """An LH1 deck stream built from the public spec decodes to the firmware's formula applied to
    the pulse timestamps exactly, and to the generating angles within the 24 MHz tick (1.57e-5 rad)
    plus the 0-3 tick sensor skew of the sync pulses."""
    rng = np.random.default_rng(11)
    F, n = 48, 4
    theta = np.deg2rad(rng.uniform(50, 130, (F, 1))) + rng.uniform(-0.01, 0.01, (F, n))
    theta[5, 1] = np.nan
    data, sync, pulses = bc.lh1_deck_stream(theta, stations=stations, jitter=np.random.default_rng(1))
    out, dec = _decode("bitcraze-lh1", data, chunk=29, n_sensors=n)
    ref = _lh1_reference(pulses, n)
    got = {round(m.t * bc.DECK_CLOCK_HZ): m for m in out}
    assert set(got) == set(ref) and len(out) >= F - 2 * stations
    for ts, (station, axis, angles) in ref.items():
        m = got[ts]
        assert (m.station, m.axis, m.kind) == (station, axis, "lh1")
        np.testing.assert_allclose(m.angles, angles, atol=1e-12)
    by_sync = {int(s): f for f, s in enumerate(sync)}
    for m in out:
        f = by_sync[min(by_sync, key=lambda s: abs(s - m.t * 24e6))]
        np.testing.assert_allclose(m.angles, theta[f], atol=4 * 2 * np.pi / 400000)  # tick + 0-3 tick skew
    assert dec.stats.bad == 0 and dec.stats.errors == 0


def test_bitcraze_lh2_stream_matches_firmware_formula():
    """An LH2 deck stream (channel 6, some pulses without channel) decodes to the firmware formula
    a0 = 4 off 2pi/P - pi + pi/3, a1 = 4 off 2pi/P - pi - pi/3, within half a 6 MHz step of truth."""
    rng = np.random.default_rng(12)
    R, n = 40, 4
    alpha = rng.uniform(-0.7, 0.7, (R, 1, 2)) + rng.uniform(-0.01, 0.01, (R, n, 2))
    alpha[7, 2, 1] = np.nan
    data, starts, pulses = bc.lh2_deck_stream(alpha, channel=6, drop_channel_every=3)
    out, dec = _decode("bitcraze-lh2", data, chunk=5, n_sensors=n)
    P = bc.LH2_CYCLE_PERIODS[6]
    assert len(out) == 2 * R and dec.stats.good == 2 * R
    ref = np.full((R, n, 2), np.nan)
    by_t0 = {int(s): r for r, s in enumerate(starts)}
    for p in pulses:
        r = by_t0[p.timestamp - 4 * p.offset]
        plane = 0 if 4 * p.offset < P / 2 else 1  # plane 0 sweeps the first half turn here (|a| < 0.72)
        shift = np.pi / 3 if plane == 0 else -np.pi / 3
        ref[r, p.sensor, plane] = 4 * p.offset * 2 * np.pi / P - np.pi + shift
    A = np.array([m.angles for m in out]).reshape(R, 2, n).transpose(0, 2, 1)
    np.testing.assert_allclose(A, ref, atol=1e-12)
    np.testing.assert_allclose(A, alpha, atol=0.5 * 4 * 2 * np.pi / P + 1e-12)
    assert all(m.station == 6 and m.kind == "lh2" for m in out)
    np.testing.assert_allclose([m.t for m in out[::2]], starts / 24e6, atol=1e-12)


def _calib(seed):
    rng = np.random.default_rng(seed)
    sw = [bc.SweepCalibration(phase=rng.uniform(-0.03, 0.03), tilt=rng.uniform(-0.05, 0.05),
                              curve=rng.uniform(-0.01, 0.01), gibmag=rng.uniform(-0.005, 0.005),
                              gibphase=rng.uniform(-3, 3)) for _ in range(2)]
    return bc.StationCalibration(tuple(sw), 42)


def test_calibration_model_and_inverse():
    """The firmware models at zero calibration are the identity; the inverse recovers ideal
    angles from distorted ones to 1e-9 rad (closed loop); phase alone shifts by -phase."""
    rng = np.random.default_rng(3)
    a = rng.uniform(-0.8, 0.8, (200, 2))
    zero = bc.StationCalibration()
    np.testing.assert_allclose(bc.lh1_model(a[:, 0], a[:, 1], zero), a, atol=1e-12)
    np.testing.assert_allclose(bc.lh2_model(a[:, 0], a[:, 1], zero), a, atol=1e-12)
    ph = bc.StationCalibration((bc.SweepCalibration(phase=0.01), bc.SweepCalibration(phase=-0.02)))
    np.testing.assert_allclose(bc.lh1_model(a[:, 0], a[:, 1], ph), a - [0.01, -0.02], atol=1e-12)
    cal = _calib(4)
    np.testing.assert_allclose(bc.calibrate_lh1(bc.lh1_model(a[:, 0], a[:, 1], cal), cal), a, atol=1e-9)
    np.testing.assert_allclose(bc.calibrate_lh2(bc.lh2_model(a[:, 0], a[:, 1], cal), cal), a, atol=1e-9)


def _yaml(tmp_path, system_type, cal, R, origin):
    import yaml

    sweeps = [{k: float(getattr(s, k)) for k in bc.SweepCalibration.__dataclass_fields__} for s in cal.sweeps]
    doc = {"type": "lighthouse_system_configuration", "version": "1", "systemType": system_type,
           "geos": {0: {"origin": [float(v) for v in origin], "rotation": np.asarray(R).tolist()}},
           "calibs": {0: {"sweeps": sweeps, "uid": cal.uid}}}
    path = tmp_path / "lh.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_system_config_geometry_matches_bitcraze_model(tmp_path):
    """Geometry from the YAML: Bitcraze's model angle atan2(y,x) + asin(z tan t / r) of a world
    point in the Bitcraze station frame (R^T (p - origin)) equals lh2_sweep_angles of the same
    point in the layoutkit station frame of the loaded Station."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("zyx", [20, -30, 5], degrees=True).as_matrix()
    origin = np.array([-2.0, 0.3, 2.3])
    cfg = read_system_config(_yaml(tmp_path, 2, _calib(1), R, origin))
    station = cfg.stations[0]
    assert station.kind == "lh2" and cfg.calibs[0].uid == 42
    rng = np.random.default_rng(0)
    world = origin + R @ np.array([2.0, 0, 0]) + rng.uniform(-0.5, 0.5, (20, 3))
    pb = (world - origin) @ R  # Bitcraze station frame
    r = np.hypot(pb[:, 0], pb[:, 1])
    ref = np.stack([np.arctan2(pb[:, 1], pb[:, 0]) + np.arcsin(pb[:, 2] * np.tan(t) / r)
                    for t in (-np.pi / 6, np.pi / 6)], -1)
    np.testing.assert_allclose(lh2_sweep_angles(points_in_station(station, world)), ref, atol=1e-12)


def test_decoders_apply_yaml_calibration(tmp_path):
    """Streams distorted with the firmware model decode to the undistorted angles when the
    system-configuration YAML is given (LH1 and LH2)."""
    cal = _calib(9)
    rng = np.random.default_rng(5)
    alpha = rng.uniform(-0.6, 0.6, (20, 1, 2)) + rng.uniform(-0.01, 0.01, (20, 4, 2))
    data, _, _ = bc.lh2_deck_stream(alpha, channel=0, calib=cal)
    path = _yaml(tmp_path, 2, cal, np.eye(3), [0, 0, 0])
    out, _ = _decode("bitcraze-lh2", data, n_sensors=4, system_config=path)
    A = np.array([m.angles for m in out]).reshape(20, 2, 4).transpose(0, 2, 1)
    np.testing.assert_allclose(A, alpha, atol=6e-5)
    raw, _ = _decode("bitcraze-lh2", data, n_sensors=4)
    assert np.abs(np.array([m.angles for m in raw]).reshape(20, 2, 4).transpose(0, 2, 1) - alpha).max() > 1e-3
    theta = np.deg2rad(rng.uniform(60, 120, (30, 1))) + rng.uniform(-0.01, 0.01, (30, 4))
    data1, sync, _ = bc.lh1_deck_stream(theta, calib={0: cal})
    out1, dec1 = _decode("bitcraze-lh1", data1, n_sensors=4, system_config=_yaml(tmp_path, 1, cal, np.eye(3), [0, 0, 0]))
    f_of = {int(s): f for f, s in enumerate(sync)}
    for m in out1:
        np.testing.assert_allclose(m.angles, theta[f_of[round(m.t * 24e6)]], atol=3e-5)
    assert len(out1) >= 26


def test_system_config_messages(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("type: something\n")
    with pytest.raises(ValueError, match=r"expected 'type: lighthouse_system_configuration'$"):
        read_system_config(p)
    with pytest.raises(ValueError, match=r"no such system configuration file$"):
        read_system_config(tmp_path / "missing.yaml")


def test_bitcraze_resync_after_garbage():
    """Bytes lost mid-stream: the decoder flags the misaligned frame, waits for the next sync
    frame (12 × 0xFF) and decodes everything after it."""
    rng = np.random.default_rng(2)
    alpha = rng.uniform(-0.6, 0.6, (30, 1, 2)) + rng.uniform(-0.01, 0.01, (30, 4, 2))
    data, starts, _ = bc.lh2_deck_stream(alpha, channel=1, sync_every=10)
    cut = 12 * 30 + 5  # drop 5 bytes inside the 4th rotation (before the 2nd sync frame)
    damaged = data[:cut] + data[cut + 5:]
    out, dec = _decode("bitcraze-lh2", damaged, chunk=17, n_sensors=4)
    assert dec.stats.bad >= 1 and dec.stats.resyncs >= 1 and dec.stats.errors == 0
    t0s = np.round(np.array([m.t for m in out[::2]]) * 24e6).astype(int)
    assert set(starts[10:].tolist()) <= set(t0s.tolist())  # everything after the next sync frame
    assert set(t0s.tolist()) <= set(starts.tolist())  # nothing invented


def _stream_for(name):
    rng = np.random.default_rng(21)
    if name == "layoutkit":
        return b"".join(_frames(K=20, n=4)[3])
    if name == "bitcraze-lh1":
        theta = np.deg2rad(rng.uniform(60, 120, (30, 1))) + rng.uniform(-0.01, 0.01, (30, 4))
        return bc.lh1_deck_stream(theta, stations=2)[0]
    alpha = rng.uniform(-0.6, 0.6, (15, 1, 2)) + rng.uniform(-0.01, 0.01, (15, 4, 2))
    return bc.lh2_deck_stream(alpha, channel=4)[0]


@pytest.mark.parametrize("name", sorted(PROTOCOLS))
def test_every_protocol_is_incremental(name):
    """Byte-by-byte feeding gives exactly the sweeps of one big feed (every registered decoder)."""
    data = _stream_for(name)
    whole, _ = _decode(name, data, chunk=len(data), n_sensors=4)
    single, _ = _decode(name, data, chunk=1, n_sensors=4)
    assert len(whole) == len(single) > 10
    for a, b in zip(whole, single):
        assert (a.t, a.station, a.axis, a.seq, a.kind) == (b.t, b.station, b.axis, b.seq, b.kind)
        np.testing.assert_array_equal(a.angles, b.angles)
