"""Import workflows: foreign recordings and device files → layoutkit's own files.

Each function reads with a reader of :mod:`layoutkit.importers` and writes with the owners of
our formats (:mod:`layoutkit.io`); all files are written atomically. They return a JSON-able
summary that the CLI prints.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .._json import to_jsonable
from ..io.atomic import atomic_write_text
from ..io.frames import write_frame_table
from ..layout import Layout

__all__ = ["import_vive_config", "import_libsurvive", "write_stations_json", "write_pose_table",
           "STATIONS_FORMAT"]

STATIONS_FORMAT = "layoutkit-stations"


# ---------------------------------------------------------------- writers of our own formats
# (thin: they go through layoutkit.io as soon as io/stations.py and io/poses.py exist)

def write_layout(layout: Layout, path) -> None:
    """Layout JSON, atomically."""
    atomic_write_text(path, json.dumps(to_jsonable(layout.to_dict()), indent=2) + "\n")


def write_stations_json(path, stations: list[dict]) -> None:
    """Stations JSON: ``{"format": "layoutkit-stations", "version": 1, "stations": [...]}``, each
    station ``{"index", "id", "kind", "rotation" (3×3, station → world), "translation" (m),
    "calibration": {...}, ...}`` with ``p_world = rotation @ p_station + translation``."""
    try:
        from ..io import stations as _st  # the owner, once it exists
        if hasattr(_st, "write_stations"):
            return _st.write_stations(path, stations)
    except ImportError:
        pass
    doc = {"format": STATIONS_FORMAT, "version": 1, "stations": stations}
    atomic_write_text(path, json.dumps(to_jsonable(doc), indent=2) + "\n")


def write_pose_table(path, t, station, status, rotvec, translation, residual_rms, extra: dict | None = None) -> None:
    """THE POSE TABLE (CSV): ``t, station, status, rx, ry, rz, tx, ty, tz, residual_rms`` (s, station
    index as text or ``joint``, status code 0 = ok, rotation vector rad, m, rad), then ``extra``
    columns."""
    import csv

    from ..io.atomic import atomic_write

    t = np.asarray(t, float)
    F = len(t)
    rv = np.asarray(rotvec, float).reshape(F, 3)
    tr = np.asarray(translation, float).reshape(F, 3)
    res = np.asarray(residual_rms, float).reshape(F)
    st = np.asarray(status).reshape(F)
    sta = [str(s) for s in (station if station is not None else ["0"] * F)]
    extra = extra or {}
    cols = ["t", "station", "status", "rx", "ry", "rz", "tx", "ty", "tz", "residual_rms"] + list(extra)

    def f(x):
        return "" if not np.isfinite(x) else repr(float(x))

    with atomic_write(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for k in range(F):
            row = [repr(float(t[k])), sta[k], str(int(st[k]))] + [f(x) for x in rv[k]] + [f(x) for x in tr[k]] + [f(res[k])]
            row += [v[k] if isinstance(v[k], str) else f(v[k]) for v in extra.values()]
            w.writerow(row)


# ---------------------------------------------------------------- vive-config

def import_vive_config(path, out) -> dict:
    """Vive / Index device calibration JSON → layout JSON ``out``."""
    from ..importers.vive import read_vive_config

    lay = read_vive_config(path)
    write_layout(lay, out)
    return {"out": str(out), "sensors": lay.n,
            **{k: lay.metadata[k] for k in ("device_class", "model_number") if k in lay.metadata}}


# ---------------------------------------------------------------- libsurvive

def _quat_rotvec(q_wxyz) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q = np.asarray(q_wxyz, float).reshape(-1, 4)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_rotvec()


def _libsurvive_stations(rec, cfg: dict) -> tuple[list[dict], dict, dict]:
    """Stations of a recording: from the ``.json`` lighthouse config, then ``LH_POSE`` lines.

    Returns the station dicts (index order), the LH1 lighthouse-index → station map and the LH2
    channel → station map.
    """
    from ..importers.libsurvive import station_rotation_from_quaternion

    gens = {g for d in rec.light.values() for g in set(d.gen)}
    kind = "lh2" if gens == {2} else "lh1"
    channels = sorted({c for d in rec.light.values() for c, g in zip(d.station, d.gen) if g == 2})
    lh1_idx = sorted({c for d in rec.light.values() for c, g in zip(d.station, d.gen) if g == 1})
    by_mode = {v["mode"]: k for k, v in cfg.items() if v.get("mode") is not None}
    ch_map = {}
    for ch in channels:
        if ch in by_mode:
            ch_map[ch] = by_mode[ch]
    nxt = max(list(cfg) + list(ch_map.values()) + lh1_idx + [-1]) + 1
    for ch in channels:  # channels the config does not name: new stations in order
        if ch not in ch_map:
            ch_map[ch] = nxt
            nxt += 1
    idx_map = {i: i for i in lh1_idx}
    used = sorted(set(idx_map.values()) | set(ch_map.values()) | set(cfg))
    stations = []
    for s in used:
        c = cfg.get(s, {})
        d = {"index": s, "id": c.get("id") or str(s), "kind": kind}
        mode = c.get("mode")
        chans = [ch for ch, v in ch_map.items() if v == s]
        if kind == "lh2":
            d["channel"] = chans[0] if chans else mode
        pose = c.get("pose")
        lhp = rec.lh_poses.get(mode if kind == "lh2" else s) if rec.lh_poses else None
        source = None
        if pose is not None and c.get("position_set", True):
            source = "libsurvive config json"
        if lhp is not None:
            pose, source = lhp, "LH_POSE line"
        if pose is not None:
            d["rotation"] = station_rotation_from_quaternion(pose[3:]).tolist()
            d["translation"] = [float(x) for x in pose[:3]]
            d["pose_source"] = source
            d["libsurvive_pose"] = [float(x) for x in pose]
        cal = c.get("calibration")
        if cal:
            d["calibration"] = {"model": "libsurvive-gen1" if kind == "lh1" else "libsurvive-gen2",
                                "axis_order": ["x", "y"] if kind == "lh1" else ["plane0", "plane1"], **cal}
        stations.append(d)
    return stations, idx_map, ch_map


def import_libsurvive(recording, out_dir, *, device: str | None = None, config=None) -> dict:
    """A libsurvive recording → ``out_dir/<device>/{layout.json, frames.csv, reference*.csv}`` and
    ``out_dir/stations.json``.

    config : the lighthouse configuration JSON; default ``<recording>.json`` when it exists.
    Returns a summary: per device frames, lit sensors, dropped events by reason; stations; where
    a truncated recording ended.
    """
    from ..importers.libsurvive import device_frames, layout_of, read_lighthouse_config, read_recording

    recording = Path(recording)
    out = Path(out_dir)
    rec = read_recording(recording)
    cfg_path = Path(config) if config else Path(str(recording) + ".json")
    cfg = read_lighthouse_config(cfg_path) if cfg_path.exists() else {}
    if config and not cfg_path.exists():
        raise ValueError(f"{cfg_path}: no such libsurvive config file")
    devices = sorted(set(rec.light) | set(rec.configs) | set(rec.poses))
    if device is not None:
        if device not in devices:
            raise ValueError(f"{recording}: no device {device!r}; the recording has {devices}")
        devices = [device]
    stations, idx_map, ch_map = _libsurvive_stations(rec, cfg)
    out.mkdir(parents=True, exist_ok=True)
    summary = {"recording": str(recording), "config": str(cfg_path) if cfg else None, "out": str(out),
               "lines": rec.lines, "line_types": rec.counts, "skipped_lines": rec.skipped,
               "truncated": rec.ended is not None, "ended": rec.ended, "devices": {}}
    if stations:
        write_stations_json(out / "stations.json", stations)
        summary["stations"] = {"file": str(out / "stations.json"), "count": len(stations),
                               "with_pose": sum("rotation" in s for s in stations),
                               "with_calibration": sum("calibration" in s for s in stations)}

    def station_of(gen, ch):
        return idx_map.get(ch, ch) if gen == 1 else ch_map.get(ch, ch)

    for dev in devices:
        ddir = out / dev
        info = {}
        lay = None
        if dev in rec.configs:
            try:
                lay = layout_of(rec, dev)
            except ValueError as exc:
                info["layout_error"] = str(exc)
        if lay is not None or dev in rec.poses:
            ddir.mkdir(parents=True, exist_ok=True)
        if lay is not None:
            write_layout(lay, ddir / "layout.json")
            info.update(layout=str(ddir / "layout.json"), sensors=lay.n)
            if dev in rec.light:
                fr, dropped = device_frames(rec.light[dev], lay.n, station_of)
                write_frame_table(fr, ddir / "frames.csv")
                seen = ~np.isnan(fr.angles)
                lit = seen.any(-1).sum(1)
                info.update(frames_file=str(ddir / "frames.csv"), frames=fr.n_frames,
                            frames_per_station={str(s): int(c) for s, c in zip(*np.unique(fr.stations(), return_counts=True))},
                            angles=int(seen.sum()), one_axis_sensors=int(np.sum(seen.any(-1) & ~seen.all(-1))),
                            lit_min=int(lit.min()) if lit.size else 0, lit_median=float(np.median(lit)) if lit.size else 0.0,
                            frames_with_4_lit=int(np.sum(seen.all(-1).sum(1) >= 4)),
                            light_events=len(rec.light[dev].t), dropped=dropped)
        elif dev in rec.light:
            info["frames_error"] = f"no CONFIG line for {dev}: its light events need the device layout"
        for name, src in (("reference.csv", rec.poses.get(dev)), ("reference_external.csv", rec.external_poses.get(dev))):
            if src:
                a = np.asarray(src, float)
                write_pose_table(ddir / name, a[:, 0], ["joint"] * len(a), np.zeros(len(a), int),
                                 _quat_rotvec(a[:, 4:8]), a[:, 1:4], np.full(len(a), np.nan))
                info[name.replace(".csv", "")] = {"file": str(ddir / name), "poses": len(a)}
        summary["devices"][dev] = info
    for name, src in rec.external_poses.items():
        if name in devices or device is not None:
            continue
        ddir = out / name
        ddir.mkdir(parents=True, exist_ok=True)
        a = np.asarray(src, float)
        write_pose_table(ddir / "reference_external.csv", a[:, 0], ["joint"] * len(a), np.zeros(len(a), int),
                         _quat_rotvec(a[:, 4:8]), a[:, 1:4], np.full(len(a), np.nan))
        summary["devices"].setdefault(name, {})["reference_external"] = {
            "file": str(ddir / "reference_external.csv"), "poses": len(a)}
    return summary
