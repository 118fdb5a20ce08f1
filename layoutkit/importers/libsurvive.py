"""libsurvive recordings (``.rec`` / ``.rec.gz`` text) and their lighthouse configuration JSON.

Format (cntools/libsurvive ``src/survive_recording.c``): one event per line,
``<t> <object> <TYPE> <fields...>`` with ``t`` the host run time in seconds. The lines read here:

- ``<dev> CONFIG <json>``: the device's own configuration; ``lighthouse_config.modelPoints`` /
  ``modelNormals`` give the layout (:mod:`layoutkit.importers.vive`);
- ``<dev> A <sensor> <acode> <timecode> <length> <angle> <lh>`` (LH1 angle): axis = ``acode & 1``
  (0 = the X sweep), ``angle`` in rad, 0 on the lighthouse boresight, ``lh`` the lighthouse index;
- ``<dev> B <channel> <sensor> <timecode> <plane> <angle>`` (LH2 sweep angle), ``plane`` 0/1;
- ``<dev> POSE x y z qw qx qy qz`` and ``<name> EXTERNAL_POSE x y z qw qx qy qz``: object poses
  in the world (libsurvive's solution; an external tracker);
- ``<mode> LH_POSE x y z qw qx qy qz``: a lighthouse pose in the world;
- ``<dev> i <mask> <timecode> ax ay az gx gy gz ...``: raw IMU samples (device counts; scaled by
  :func:`layoutkit.importers.libsurvive_imu.imu_samples`);
- everything else (scaled IMU ``I``, raw light ``C``/``L``/``R``/``W``/``Y``, ``INFO``) is counted
  and skipped.

``timecode`` is the device's 48 MHz counter (32 bits, unwrapped here onto one monotone clock).
The lighthouse configuration ``<recording>.json`` beside the recording (libsurvive's config
file; one ``"key":value`` per line, not strict JSON) holds ``lighthouseN`` objects with ``pose``
``[x, y, z, qw, qx, qy, qz]`` (lighthouse → world), ``mode`` (the LH2 channel) and the factory
calibration ``fcalphase``, ``fcaltilt``, ``fcalcurve``, ``fcalgibpha``, ``fcalgibmag``,
``fcalogeephase``, ``fcalogeemag`` (one value per axis).

Conventions (derived and checked on the shipped samples in docs/real-data.md): libsurvive's
lighthouse frame looks along −z with x to the right and y up; its LH1 angles are
``a_x = -atan(X / -Z)``, ``a_y = atan(Y / -Z)`` (``lighthouse_gen1.py`` ``reproject_axis`` without
calibration). layoutkit's station frame is ``p_st = diag(1, -1, -1) p_lh`` and its angles are
``theta = pi/2 + a`` on both axes. LH2 plane angles (``lighthouse_gen2.py``:
``a_k = atan2(D, X) - asin(tan(t_k) Y / sqrt(X² + D²)) - pi/2``, ``D = -Z``, tilt ``t_0 = +pi/6``,
``t_1 = -pi/6``) are turned into the same two angles per sensor when both planes of one rotation
were seen (:func:`lh2_to_sweep_angles`).
"""
from __future__ import annotations

import json
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.frames import Frames
from ..layout import Layout
from .vive import layout_from_config

__all__ = [
    "TICK_HZ", "LH2_TILT", "LH2_CHANNEL_HZ", "Recording", "DeviceLight", "read_recording", "read_lighthouse_config",
    "libsurvive_to_theta", "lh2_to_sweep_angles", "station_rotation_from_quaternion",
    "device_frames", "FLIP", "libsurvive_stations", "StationMap", "device_sweeps",
]

#: libsurvive's device timecode clock (Vive / Index / Tracker), Hz.
TICK_HZ = 48e6
#: LH2 light-plane tilt in libsurvive's model, rad (plane 0: +pi/6, plane 1: -pi/6).
LH2_TILT = np.pi / 6
#: layoutkit station frame = FLIP @ libsurvive lighthouse frame (x kept, y and z reversed).
FLIP = np.diag([1.0, -1.0, -1.0])
#: LH2 rotor frequency of each channel (libsurvive's ``mode`` 0-15), Hz: the values libsurvive uses
#: (``src/survive_process_gen2.c``, ``freq_per_channel``). Checked on the real recordings: the sweep
#: angle grows at ``2 pi f`` per second of device time (channel 10: 328.2 rad/s measured, 328.17 here).
LH2_CHANNEL_HZ = (50.0521, 50.1567, 50.3673, 50.5796, 50.6864, 50.9014, 51.0096, 51.1182,
                  51.2273, 51.6685, 52.2307, 52.6894, 52.9217, 53.2741, 53.7514, 54.1150)

_CAL_KEYS = ("fcalphase", "fcaltilt", "fcalcurve", "fcalgibpha", "fcalgibmag", "fcalogeephase", "fcalogeemag")
# a sweep of one station and axis lasts well under one 8.33 ms LH1 slot
_SWEEP_GAP_S = 0.004
# X and the following Y sweep of one LH1 station start one slot (8.33 ms) apart
_LH1_PAIR_S = 0.0125


def _float(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        return float.fromhex(s)  # SURVIVE_HEX_FLOATS recordings


@dataclass
class DeviceLight:
    """Light events of one device, in file order (lists while reading, arrays after)."""

    t: list = field(default_factory=list)          # host time, s
    timecode: list = field(default_factory=list)   # raw 32-bit device timecode
    sensor: list = field(default_factory=list)
    station: list = field(default_factory=list)    # LH1: lighthouse index; LH2: channel
    axis: list = field(default_factory=list)       # LH1: acode & 1; LH2: plane
    angle: list = field(default_factory=list)      # libsurvive angle, rad
    gen: list = field(default_factory=list)        # 1 or 2


@dataclass
class Recording:
    """What :func:`read_recording` found.

    configs : device name → CONFIG dict; light : device name → :class:`DeviceLight`;
    poses : object name → list of ``(t, x, y, z, qw, qx, qy, qz)`` (POSE lines);
    external_poses : the same for EXTERNAL_POSE; lh_poses : the line's object (LH1: lighthouse
    index, LH2: channel) → last ``(x, y, z, qw, qx, qy, qz)``; lh_serials : the same → the serial
    some recordings write after the pose; imu : device → list of ``[t, timecode, ax, ay, az, gx, gy,
    gz]`` (raw ``i`` lines: device counts, 48 MHz timecode);
    lines : lines read; counts : line type → count; skipped : reason → count;
    ended : None if the file ended cleanly, else a message saying where and why it ended.
    """

    path: str
    configs: dict = field(default_factory=dict)
    light: dict = field(default_factory=dict)
    poses: dict = field(default_factory=dict)
    external_poses: dict = field(default_factory=dict)
    lh_poses: dict = field(default_factory=dict)
    lh_serials: dict = field(default_factory=dict)
    imu: dict = field(default_factory=dict)
    lines: int = 0
    counts: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    ended: str | None = None
    last_t: float = float("nan")


def _chunks(path: Path, rec: Recording):
    """Decompressed bytes of a plain or gzip file, streamed; a truncated or corrupt gzip stream
    yields everything that could be decompressed and records why it ended in ``rec.ended``."""
    with open(path, "rb") as fh:
        gz = fh.read(2) == b"\x1f\x8b"
        fh.seek(0)
        if not gz:
            while True:
                b = fh.read(1 << 20)
                if not b:
                    return
                yield b
        d = zlib.decompressobj(wbits=31)
        while True:
            raw = fh.read(1 << 18)
            if not raw:
                if not d.eof:
                    tail = d.flush()
                    if tail:
                        yield tail
                    rec.ended = "the compressed stream ends early (truncated .gz)"
                return
            while raw:
                try:
                    out = d.decompress(raw)
                except zlib.error as exc:
                    rec.ended = f"corrupt gzip data ({exc})"
                    return
                if out:
                    yield out
                if not d.eof:
                    break
                raw = d.unused_data  # a next gzip member may follow
                d = zlib.decompressobj(wbits=31)
                if not raw:
                    raw = fh.read(1 << 18)
                    if not raw:
                        return
                if raw[:2] != b"\x1f\x8b":
                    if raw.strip(b"\x00"):
                        rec.ended = "trailing bytes after the gzip stream"
                    return


def _lines(path: Path, rec: Recording):
    """Text lines of a (possibly gzip-compressed, possibly truncated) recording.

    A truncated or corrupt stream ends after the last complete line; ``rec.ended`` then says where
    (line count, decompressed byte offset, last time stamp) and why.
    """
    pos = 0
    n = 0
    pending = b""
    try:
        for chunk in _chunks(path, rec):
            data = pending + chunk
            parts = data.split(b"\n")
            pending = parts.pop()
            for p in parts:
                pos += len(p) + 1
                n += 1
                yield p.decode("utf-8", "replace")
        if pending.strip() and rec.ended is None:
            n += 1  # a last line without its newline, in a stream that ended cleanly
            yield pending.decode("utf-8", "replace")
        if rec.ended is not None:
            rec.ended = (f"{path}: {rec.ended}; imported the {n} complete line(s) before decompressed byte "
                         f"{pos} (last time stamp {rec.last_t:.6f} s)"
                         + (f"; dropped a partial last line of {len(pending)} bytes" if pending else ""))
    finally:
        rec.lines = n


def read_recording(path) -> Recording:
    """Parse a libsurvive recording (``ValueError`` naming the file if it is not one)."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such recording")
    rec = Recording(str(path))
    counts = rec.counts
    skipped = rec.skipped
    for line in _lines(path, rec):
        parts = line.split()
        if len(parts) < 3:
            if parts:
                skipped["short line"] = skipped.get("short line", 0) + 1
            continue
        try:
            t = _float(parts[0])
        except ValueError:
            skipped["no time stamp"] = skipped.get("no time stamp", 0) + 1
            continue
        obj, typ = parts[1], parts[2]
        counts[typ] = counts.get(typ, 0) + 1
        rec.last_t = t
        try:
            if typ == "A" and len(parts) >= 9:
                d = rec.light.setdefault(obj, DeviceLight())
                d.t.append(t); d.sensor.append(int(parts[3])); d.axis.append(int(parts[4]) & 1)
                d.timecode.append(int(parts[5])); d.angle.append(_float(parts[7]))
                d.station.append(int(parts[8])); d.gen.append(1)
            elif typ == "B" and len(parts) >= 8:
                d = rec.light.setdefault(obj, DeviceLight())
                d.t.append(t); d.station.append(int(parts[3])); d.sensor.append(int(parts[4]))
                d.timecode.append(int(parts[5])); d.axis.append(int(parts[6])); d.angle.append(_float(parts[7]))
                d.gen.append(2)
            elif typ == "CONFIG":
                text = line.split(" CONFIG ", 1)[1] if " CONFIG " in line else ""
                try:
                    rec.configs[obj] = json.loads(text)
                except json.JSONDecodeError as exc:
                    skipped[f"{obj} CONFIG not valid JSON ({exc.msg})"] = 1
            elif typ in ("POSE", "EXTERNAL_POSE") and len(parts) >= 10:
                target = rec.poses if typ == "POSE" else rec.external_poses
                target.setdefault(obj, []).append([t] + [_float(x) for x in parts[3:10]])
            elif typ == "i" and len(parts) >= 11:
                # raw IMU: <mask> <timecode> ax ay az gx gy gz [mx my mz] [id] (device counts)
                rec.imu.setdefault(obj, []).append([t, float(int(parts[4]))] + [_float(x) for x in parts[5:11]])
            elif typ == "LH_POSE" and len(parts) >= 10:
                rec.lh_poses[int(obj)] = [_float(x) for x in parts[3:10]]
                if len(parts) >= 11:                  # newer recordings end the line with the serial
                    rec.lh_serials[int(obj)] = parts[10]
        except ValueError:
            skipped[f"malformed {typ} line"] = skipped.get(f"malformed {typ} line", 0) + 1
    if rec.lines == 0:
        raise ValueError(f"{path}: empty, or not a libsurvive recording")
    if not rec.light and not rec.configs and not rec.poses:
        raise ValueError(f"{path}: no libsurvive CONFIG, A, B or POSE lines in {rec.lines} line(s); "
                         "not a libsurvive recording?")
    return rec


_KV = re.compile(r'^\s*"([^"]+)"\s*:\s*(.*?)\s*,?\s*$')


def read_lighthouse_config(path) -> dict:
    """libsurvive's config JSON (``<recording>.json``) → ``{index: {pose, mode, calibration, id}}``.

    The file is libsurvive's own dialect (``"key":value`` lines, objects without commas between
    them); it is made strict by inserting the missing commas. ``ValueError`` naming the file on
    content it cannot read.
    """
    path = Path(path)
    text = path.read_text(errors="replace")
    body = text.strip()
    if not body.startswith("{"):
        body = "{" + body + "}"
    # commas between a value/object end and the next key
    body = re.sub(r'("|\]|\}|\d)\s*\n(\s*")', r"\1,\n\2", body)
    try:
        d = json.loads(body)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: cannot read libsurvive config ({exc})") from None
    out = {}
    for key, v in d.items():
        m = re.fullmatch(r"lighthouse(\d+)", key)
        if not m or not isinstance(v, dict):
            continue
        idx = int(m.group(1))
        try:
            pose = [float(x) for x in v.get("pose", [])]
            cal = {k[4:]: [float(x) for x in v[k]] for k in _CAL_KEYS if k in v}
        except (TypeError, ValueError):
            raise ValueError(f"{path}: {key}: pose / fcal* values must be numbers") from None
        if pose and len(pose) != 7:
            raise ValueError(f"{path}: {key}.pose: expected 7 numbers (x y z qw qx qy qz), got {len(pose)}")
        out[idx] = {"pose": pose or None, "mode": int(v["mode"]) if "mode" in v else None,
                    "id": str(v.get("id", "")), "calibration": cal,
                    "position_set": str(v.get("PositionSet", "1")) == "1"}
    return out


def station_rotation_from_quaternion(q) -> np.ndarray:
    """Station → world rotation of a libsurvive lighthouse pose quaternion ``(qw, qx, qy, qz)``.

    libsurvive: ``p_world = R(q) p_lh + pos``; layoutkit: ``p_st = FLIP p_lh``, so
    ``p_world = (R(q) FLIP) p_st + pos`` (``FLIP`` has det +1: a proper rotation, 180° about x).
    """
    from ..rotations import quaternion_to_matrix

    return quaternion_to_matrix(np.asarray(q, float)[:4], scalar_first=True) @ FLIP


def libsurvive_to_theta(angle) -> np.ndarray:
    """LH1 libsurvive angle (rad, 0 on boresight) → layoutkit sweep angle ``pi/2 + a`` (rad)."""
    return np.pi / 2 + np.asarray(angle, float)


def lh2_to_sweep_angles(a0, a1) -> np.ndarray:
    """LH2 plane angles of libsurvive (plane 0 tilt +pi/6, plane 1 −pi/6, rad) → ``(…, 2)``
    layoutkit ``[theta_x, theta_y]`` of the same direction (uncalibrated model).

    With ``u_k = a_k + pi/2 = B ∓ s``, ``B = atan2(D, X)`` and ``s = asin(tan(pi/6) Y / r)``:
    ``B = (u0 + u1) / 2``, ``s = (u1 - u0) / 2``; the direction has ``X = r cos B``, ``D = r sin B``,
    ``Y = r sin(s) / tan(pi/6)``; in the station frame ``x = X, y = -Y, z = D``, so
    ``theta_x = B`` and ``theta_y = atan2(tan(pi/6) sin B, -sin s)``.
    """
    u0 = np.asarray(a0, float) + np.pi / 2
    u1 = np.asarray(a1, float) + np.pi / 2
    B = 0.5 * (u0 + u1)
    s = 0.5 * (u1 - u0)
    return np.stack([B, np.arctan2(np.tan(LH2_TILT) * np.sin(B), -np.sin(s))], -1)


def _unwrap32(tc: np.ndarray) -> np.ndarray:
    """32-bit timecodes in file order → monotone-ish int64 (differences taken mod 2**32, signed)."""
    tc = np.asarray(tc, np.int64)
    if tc.size == 0:
        return tc
    d = np.diff(tc) % (1 << 32)
    d = np.where(d >= (1 << 31), d - (1 << 32), d)
    return np.concatenate([[tc[0]], tc[0] + np.cumsum(d)])


def _sweeps(order, tc, st, ax, sensor, gap):
    """Split events (indices ``order`` in file order) into sweeps: runs of one station and axis,
    broken at a gap > ``gap`` ticks or a repeated sensor. Returns a list of index arrays."""
    out = []
    cur = []
    key = None
    seen = set()
    for i in order:
        k = (st[i], ax[i])
        if cur and (k != key or abs(tc[i] - tc[cur[-1]]) > gap or sensor[i] in seen):
            out.append(cur)
            cur, seen = [], set()
        if not cur:
            key = k
        cur.append(i)
        seen.add(sensor[i])
    if cur:
        out.append(cur)
    return out


def device_frames(d: DeviceLight, layout_n: int, station_of) -> tuple[Frames, dict]:
    """Frames of one device's light events.

    station_of : maps an LH1 lighthouse index or an LH2 channel to the station index of the
    stations JSON. One frame = the sweeps of one station close in time: LH1, an X sweep and the
    following Y sweep (< 12.5 ms later); LH2, both planes of one rotation (the plane that leads
    within a rotation is found from the data). A missing axis stays empty (NaN).
    Returns the frames (``t`` on the device clock mapped to the host time of the recording) and
    counts of what was dropped, by reason.
    """
    tc = _unwrap32(np.asarray(d.timecode, np.int64))
    host = np.asarray(d.t, float)
    sensor = np.asarray(d.sensor, int)
    st = np.asarray(d.station, int)
    ax = np.asarray(d.axis, int)
    ang = np.asarray(d.angle, float)
    gen = np.asarray(d.gen, int)
    dropped = {}

    def drop(reason, k=1):
        if k:
            dropped[reason] = dropped.get(reason, 0) + int(k)

    # device clock → host seconds: one offset, the median (host batching only delays lines)
    t_of = (tc - tc[0]) / TICK_HZ if tc.size else tc
    off = float(np.median(host - t_of)) if tc.size else 0.0
    in_layout = (sensor >= 0) & (sensor < layout_n)
    ang_ok = np.isfinite(ang) & (np.abs(ang) < np.pi / 2)
    drop("sensor index not in the device's layout", np.sum(~in_layout))
    drop("angle not finite or |angle| >= pi/2", np.sum(in_layout & ~ang_ok))
    good = in_layout & ang_ok
    rows = []  # (t, station, {sensor: [thx, thy]})
    gap = _SWEEP_GAP_S * TICK_HZ
    for g in (1, 2):
        idx = np.flatnonzero(good & (gen == g))
        if idx.size == 0:
            continue
        for ch in np.unique(st[idx]):
            sub = idx[st[idx] == ch]
            sw = _sweeps(sub, tc, st, ax, sensor, gap)
            starts = np.array([tc[s[0]] for s in sw], float)
            axes = np.array([ax[s[0]] for s in sw])
            if g == 1:
                lead, pair_gap = 0, _LH1_PAIR_S * TICK_HZ
            else:
                # the plane that leads within a rotation: the shorter median gap to the other plane
                dt = np.diff(starts)
                chg = axes[:-1] != axes[1:]
                g01 = dt[chg & (axes[:-1] == 0)]
                g10 = dt[chg & (axes[:-1] == 1)]
                m01 = np.median(g01) if g01.size else np.inf
                m10 = np.median(g10) if g10.size else np.inf
                lead = 0 if m01 <= m10 else 1
                period = np.median(dt[axes[:-1] == axes[1:]]) if np.any(axes[:-1] == axes[1:]) else 0.02 * TICK_HZ
                if not np.isfinite(period) or period <= 0:
                    period = 0.02 * TICK_HZ
                pair_gap = 0.75 * period
            k = 0
            while k < len(sw):
                group = [sw[k]]
                if axes[k] == lead and k + 1 < len(sw) and axes[k + 1] != lead and starts[k + 1] - starts[k] < pair_gap:
                    group.append(sw[k + 1])
                    k += 2
                else:
                    k += 1
                vals = {}
                for s in group:
                    for i in s:
                        vals.setdefault(sensor[i], [np.nan, np.nan])[ax[i]] = ang[i]
                first = min(tc[s[0]] for s in group)
                t = (first - tc[0]) / TICK_HZ + off
                if g == 1:
                    th = {s_: [libsurvive_to_theta(a) if np.isfinite(a) else np.nan for a in v] for s_, v in vals.items()}
                else:
                    th = {}
                    for s_, v in vals.items():
                        if np.isfinite(v[0]) and np.isfinite(v[1]):
                            th[s_] = list(lh2_to_sweep_angles(v[0], v[1]))
                        else:
                            drop("LH2 sensor seen on one plane only (both are needed for its two angles)")
                rows.append((t, station_of(g, int(ch)), th))
    rows.sort(key=lambda r: r[0])
    F = len(rows)
    A = np.full((F, layout_n, 2), np.nan)
    for f, (_, _, th) in enumerate(rows):
        for s_, v in th.items():
            A[f, s_] = v
    t = np.array([r[0] for r in rows], float)
    station = np.array([r[1] for r in rows], int)
    keep = np.isfinite(A).any((1, 2))
    drop("frames with no usable angle", int(np.sum(~keep)))
    return Frames(t[keep], A[keep], tuple(str(i) for i in range(layout_n)), station=station[keep]), dropped


def layout_of(rec: Recording, device: str) -> Layout:
    """The device's layout from its CONFIG line (``ValueError`` if the recording has none)."""
    if device not in rec.configs:
        raise ValueError(f"{rec.path}: no CONFIG line for device {device!r} (devices with configs: "
                         f"{sorted(rec.configs)})")
    lay = layout_from_config(rec.configs[device], source=f"{rec.path} {device} CONFIG")
    meta = dict(lay.metadata)
    meta["source"] = {"format": "libsurvive", "file": rec.path, "device": device}
    return Layout(lay.positions, lay.normals, lay.ids, meta)


@dataclass(frozen=True)
class StationMap:
    """The stations of a recording and how its light events find them.

    stations : :class:`~layoutkit.lighthouse.Station` list (the frame table's ``station`` column
    indexes it); info : one dict per station for the import summary; lh1 : LH1 lighthouse index →
    station index; lh2 : LH2 channel → station index.
    """

    stations: list
    info: list
    lh1: dict
    lh2: dict


def libsurvive_stations(rec: Recording, cfg: dict) -> StationMap:
    """Stations of a recording: poses from the lighthouse config (``.json``) or ``LH_POSE`` lines,
    factory calibration from its ``fcal*`` values (libsurvive convention,
    :func:`layoutkit.lighthouse.calibration_from_libsurvive`).

    Ids are unique and stable: ``LH<N>`` for the config's ``lighthouse<N>`` (libsurvive's own
    lighthouse index, the order of the calibration file) or an LH1 index / LH_POSE line the config
    does not name, ``ch<c>`` for an LH2 channel the config does not name. libsurvive's own id (the
    lighthouse serial; not unique: ``nan_crash_windows`` writes 2147483647 for all three) is kept as
    ``source_id``. LH2 stations get the rotor speed of their channel (:data:`LH2_CHANNEL_HZ`).
    Stations without a known pose get the identity pose and ``pose_known: false`` in the info.
    """
    from ..lighthouse import Station, calibration_from_libsurvive

    gens = {g for d in rec.light.values() for g in set(d.gen)}
    kind = "lh2" if gens == {2} else "lh1"
    channels = sorted({c for d in rec.light.values() for c, g in zip(d.station, d.gen) if g == 2})
    lh1_idx = sorted({c for d in rec.light.values() for c, g in zip(d.station, d.gen) if g == 1})
    by_mode = {v["mode"]: k for k, v in cfg.items() if v.get("mode") is not None}
    keys = sorted(set(cfg) | set(lh1_idx) | {by_mode[c] for c in channels if c in by_mode})
    keys += [("ch", c) for c in channels if c not in by_mode]  # channels the config does not name
    index = {k: i for i, k in enumerate(keys)}
    idx_map = {i: index[i] for i in lh1_idx}
    ch_map = {c: index[by_mode[c]] if c in by_mode else index[("ch", c)] for c in channels}
    stations, info = [], []
    for k in keys:
        c = cfg.get(k, {}) if not isinstance(k, tuple) else {}
        mode = c.get("mode") if not isinstance(k, tuple) else k[1]
        pose = c.get("pose") if c.get("position_set", True) else None
        source = "libsurvive config json" if pose is not None else None
        line_key = mode if kind == "lh2" else k
        lhp = rec.lh_poses.get(line_key)
        if lhp is not None:
            pose, source = lhp, "LH_POSE line"
        kw = {}
        if pose is not None:
            kw = {"rotation": station_rotation_from_quaternion(pose[3:]), "translation": np.asarray(pose[:3], float)}
        cal = c.get("calibration")
        if kind == "lh2":
            hz = LH2_CHANNEL_HZ[mode] if mode is not None and 0 <= mode < len(LH2_CHANNEL_HZ) else 50.0
            kw["rotor_rpm"] = 60.0 * hz
        src = c.get("id") or rec.lh_serials.get(line_key)
        sid = f"ch{k[1]}" if isinstance(k, tuple) else f"LH{k}"
        st = Station(id=sid, kind=kind, calibration=calibration_from_libsurvive(cal, kind) if cal else None,
                     source_id=str(src) if src else None, **kw)
        stations.append(st)
        info.append({"index": index[k], "id": st.id, "source_id": st.source_id, "kind": kind,
                     "pose_known": pose is not None, "pose_source": source, "libsurvive_pose": pose,
                     "channel": mode if kind == "lh2" else None, "rotor_hz": st.rotor_rpm / 60.0,
                     "calibration_fcal": cal or None})
    return StationMap(stations, info, idx_map, ch_map)


def _device_time(d: DeviceLight, extra_timecodes=()):
    """The device clock of :func:`device_frames` (light timecodes unwrapped, one median offset onto the
    host clock) and the same mapping for ``extra_timecodes`` (e.g. the IMU's, unwrapped together with
    the light events in host-time order). Returns ``(light_t, extra_t)`` s."""
    tl = np.asarray(d.timecode, np.int64)
    hl = np.asarray(d.t, float)
    te = np.asarray([x[1] for x in extra_timecodes], np.int64) if len(extra_timecodes) else np.zeros(0, np.int64)
    he = np.asarray([x[0] for x in extra_timecodes], float) if len(extra_timecodes) else np.zeros(0)
    tc = np.concatenate([tl, te])
    host = np.concatenate([hl, he])
    order = np.argsort(host, kind="stable")
    un = np.empty_like(tc)
    un[order] = _unwrap32(tc[order])
    ul, ue = un[: tl.size], un[tl.size:]
    t0 = _unwrap32(tl)[0] if tl.size else 0
    shift = ul[0] - t0 if tl.size else 0                    # joint unwrap vs device_frames' own
    sl = (ul - shift - t0) / TICK_HZ
    off = float(np.median(hl - sl)) if tl.size else 0.0
    return sl + off, (ue - shift - t0) / TICK_HZ + off


def device_sweeps(d: DeviceLight, layout_n: int, station_of):
    """Every sweep of one device as its own measurement, for a filter that updates per sweep.

    Returns a dict of arrays over sweeps ``t`` (s, the device clock of :func:`device_frames`: the mean
    hit time of the sweep), ``station`` (index, via ``station_of(gen, lh)``), ``axis`` (LH1 0 = x
    sweep, 1 = y; LH2 the plane) and ``angles (K, n)`` rad in the station's convention (LH1 ``theta
    = pi/2 + a``, LH2 light-plane ``alpha = -a``; NaN = not hit), and ``kind`` per sweep (1 or 2).
    """
    t_all, _ = _device_time(d)
    sensor = np.asarray(d.sensor, int)
    st = np.asarray(d.station, int)
    ax = np.asarray(d.axis, int)
    ang = np.asarray(d.angle, float)
    gen = np.asarray(d.gen, int)
    tc = _unwrap32(np.asarray(d.timecode, np.int64))
    good = (sensor >= 0) & (sensor < layout_n) & np.isfinite(ang) & (np.abs(ang) < np.pi / 2)
    out_t, out_s, out_a, out_k, out_g = [], [], [], [], []
    for g in (1, 2):
        idx = np.flatnonzero(good & (gen == g))
        for ch in np.unique(st[idx]):
            sub = idx[st[idx] == ch]
            for sw in _sweeps(sub, tc, st, ax, sensor, _SWEEP_GAP_S * TICK_HZ):
                row = np.full(layout_n, np.nan)
                a = ang[sw]
                row[sensor[sw]] = np.pi / 2 + a if g == 1 else -a
                out_t.append(float(np.mean(t_all[sw])))
                out_s.append(station_of(g, int(ch)))
                out_k.append(int(ax[sw[0]]))
                out_a.append(row)
                out_g.append(g)
    order = np.argsort(out_t, kind="stable")
    A = np.array(out_a, float).reshape(-1, layout_n)
    return {"t": np.asarray(out_t)[order], "station": np.asarray(out_s, int)[order],
            "axis": np.asarray(out_k, int)[order], "angles": A[order], "gen": np.asarray(out_g, int)[order]}
