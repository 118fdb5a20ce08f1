"""Import workflows: foreign recordings and device files → layoutkit's own files.

Each function reads with a reader of :mod:`layoutkit.importers` and writes with the owners of
our formats (:mod:`layoutkit.io`); all files are written atomically. They return a JSON-able
summary that the CLI prints.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.jsonfile import to_jsonable
from ..io.atomic import atomic_write_text
from ..io.frames import write_frame_table
from ..layout import Layout

__all__ = ["import_vive_config", "import_libsurvive", "import_cfusdlog", "cfusdlog_capture", "cfusdlog_replay_source", "import_reference", "write_layout",
           "write_reference"]


# ---------------------------------------------------------------- writers of our own formats

def write_layout(layout: Layout, path) -> None:
    """Layout JSON, atomically."""
    atomic_write_text(path, json.dumps(to_jsonable(layout.to_dict()), indent=2) + "\n")


def write_reference(path, t, rotvec, translation) -> None:
    """A reference trajectory as a pose table (station ``joint`` = world frame, status 0)."""
    from ..io.poses import JOINT, PoseTable, write_poses

    t = np.asarray(t, float)
    write_poses(path, PoseTable(t, rotvec, translation, station=np.full(len(t), JOINT), status=np.zeros(len(t), int)))


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
    """libsurvive pose quaternions ``(N, 4)`` ``[w, x, y, z]`` → rotation vectors ``(N, 3)`` rad."""
    from ..geometry import matrix_to_rotvec
    from ..rotations import quaternion_to_matrix

    return matrix_to_rotvec(quaternion_to_matrix(np.asarray(q_wxyz, float).reshape(-1, 4), scalar_first=True))


def import_libsurvive(recording, out_dir, *, device: str | None = None, config=None, imu_filter: bool = False,
                      filter_stations=None) -> dict:
    """A libsurvive recording → ``out_dir/<device>/{layout.json, frames.csv, reference*.csv}`` and
    ``out_dir/stations.json``.

    config : the lighthouse configuration JSON; default ``<recording>.json`` when it exists.
    imu_filter : also run the IMU-aided filter on every device with IMU lines
    (:func:`layoutkit.workflows.imu_filter.imu_filter_devices`: ``<device>/imu_filter_poses.csv``),
    through ``filter_stations`` (a stations JSON, e.g. ``calibrate``'s) or the recording's own.
    Returns a summary: per device frames, lit sensors, dropped events by reason; stations; where
    a truncated recording ended.
    """
    from ..importers.libsurvive import device_frames, layout_of, libsurvive_stations, read_lighthouse_config, read_recording

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
    smap = libsurvive_stations(rec, cfg)
    stations, st_info, idx_map, ch_map = smap.stations, smap.info, smap.lh1, smap.lh2
    out.mkdir(parents=True, exist_ok=True)
    summary = {"recording": str(recording), "config": str(cfg_path) if cfg else None, "out": str(out),
               "lines": rec.lines, "line_types": rec.counts, "skipped_lines": rec.skipped,
               "truncated": rec.ended is not None, "ended": rec.ended, "devices": {}}
    if stations:
        from ..io.stations import write_stations

        write_stations(out / "stations.json", stations)
        summary["stations"] = {"file": str(out / "stations.json"), "count": len(stations),
                               "with_pose": sum(i["pose_known"] for i in st_info),
                               "with_calibration": sum(s.calibration is not None for s in stations),
                               "stations": st_info}

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
                write_reference(ddir / name, a[:, 0], _quat_rotvec(a[:, 4:8]), a[:, 1:4])
                info[name.replace(".csv", "")] = {"file": str(ddir / name), "poses": len(a)}
        summary["devices"][dev] = info
    for name, src in rec.external_poses.items():
        if name in devices or device is not None:
            continue
        ddir = out / name
        ddir.mkdir(parents=True, exist_ok=True)
        a = np.asarray(src, float)
        write_reference(ddir / "reference_external.csv", a[:, 0], _quat_rotvec(a[:, 4:8]), a[:, 1:4])
        summary["devices"].setdefault(name, {})["reference_external"] = {
            "file": str(ddir / "reference_external.csv"), "poses": len(a)}
    if imu_filter:
        from .imu_filter import imu_filter_devices

        summary["imu_filter"] = imu_filter_devices(recording, out, [d for d in devices if d in rec.light], rec=rec,
                                                   stations=filter_stations, lighthouse_config=config)
    return summary


# ---------------------------------------------------------------- cfusdlog

def _deck_layout() -> Layout:
    """The Lighthouse deck's 4 sensors (``models/crazyflie_lighthouse_deck.layout.json``; the
    firmware's ``sensorDeckPositions``)."""
    from ..layout import load_layout
    from ..resources import model_path

    return load_layout(model_path("crazyflie_lighthouse_deck.layout.json"))


def deck_bytes(ev: dict, *, sync_every: int = 64) -> tuple[bytes, dict]:
    """``lhUartFrame`` events → the deck's UART byte stream (12-byte frames; a sync frame first and
    every ``sync_every`` frames). Returns the bytes and notes on what was filled in."""
    from ..importers.cfusdlog import no_channel_value
    from ..live.protocols.bitcraze import SYNC_FRAME, DeckPulse, encode_pulse

    need = ("sensor", "basestation", "offset", "timestampFPGA")
    miss = [k for k in need if k not in ev]
    if miss:
        raise ValueError(f"lhUartFrame events lack variable(s) {miss} (have {sorted(k for k in ev if k != 't')})")
    n = len(ev["t"])
    nc = no_channel_value(ev["basestation"], ev["offset"])
    out = [SYNC_FRAME]
    for k in range(n):
        if k and k % sync_every == 0:
            out.append(SYNC_FRAME)
        off24 = int(ev["offset"][k])
        ch = int(ev["basestation"][k])
        out.append(encode_pulse(DeckPulse(int(ev["sensor"][k]) & 3, int(ev["timestampFPGA"][k]) & 0xFFFFFF, 0,
                                          off24 // 4, 0, None if ch == nc or not 0 <= ch < 16 else ch, 0)))
    notes = {"basestation": f"{nc} = no channel found (the deck frame's bit 7; the value past the real channels)"
                            if nc is not None else "every value a channel (none without offsets at the top)",
             "width": "not in the log; 0 (the LH2 angle path does not use it)",
             "beam_word": "not in the log; 0 (not used for angles)",
             "slow_bit": "not in the log; 0 (OOTX calibration data cannot be decoded: give --system-config)",
             "offset": "logged in 24 MHz ticks; written as the deck's 6 MHz field (offset / 4)"}
    return b"".join(out), notes


def cfusdlog_capture(log, ul=None) -> tuple[bytes, "object"]:
    """A Crazyflie microSD log → ``(deck UART bytes, CaptureSidecar)`` in memory, for ``replay LOG``
    without an import step: protocol ``bitcraze-lh2``, the deck layout, the deck-to-log clock offset
    (as :func:`import_cfusdlog`; no stations: give ``--system-config`` or ``--stations``).
    ul : the log already read (:func:`layoutkit.importers.cfusdlog.read_cfusdlog`; default: read
    ``log``). ValueError naming the file when it has no ``lhUartFrame`` events."""
    from ..importers.cfusdlog import read_cfusdlog
    from ..io.sidecar import CaptureSidecar

    log = Path(log)
    ul = read_cfusdlog(log) if ul is None else ul
    if "lhUartFrame" not in ul.events or len(ul.events["lhUartFrame"]["t"]) == 0:
        raise ValueError(f"{log}: no lhUartFrame events (event types: {sorted(ul.events)}); enable the "
                         "lighthouse deck's UART frame event trigger when logging")
    ev = ul.events["lhUartFrame"]
    data, notes = deck_bytes(ev)
    clock = _deck_clock(ul)
    sc = CaptureSidecar(protocol="bitcraze-lh2", protocol_options={"time_offset_s": clock.offset_s,
                                                                   "time_rate": clock.rate},
                        layout=_deck_layout().to_dict(), source="cfusdlog (replayed directly)", n_sensors=4,
                        bytes=len(data), extra={"imported_from": str(log), "log_ended": ul.ended,
                                                "clock": clock.as_dict(),
                                                "import_notes": [f"{k}: {v}" for k, v in notes.items()]})
    return data, sc


def _deck_clock(ul):
    """The deck-to-log clock fit of a log with UART frames (:func:`layoutkit.importers.cfusdlog.fit_deck_clock`),
    its deck time origin the first frame's 24-bit timestamp (as the replayed bytes' decoder)."""
    from ..importers.cfusdlog import fit_deck_clock, uart_frames

    u = uart_frames(ul)
    return fit_deck_clock(u.deck_s, u.t)


def _uart_is_lh1(ul, kind) -> str | None:
    """Why a log's ``lhUartFrame`` events are not written as an LH2 capture (None: they are): an LH1
    system (its sweep events or system config say so), or no frame carries an LH2 channel."""
    from ..importers.cfusdlog import uart_frames

    u = uart_frames(ul)
    if u is None:
        return None
    if kind == "lh1":
        return ("LH1 base stations: lhUartFrame events are not written as a capture (LH1 needs the pulse widths, "
                "which are not logged); the firmware's lhAngle angles are in frames.csv (solve / replay LOG)")
    if not np.any(u.channel >= 0):
        return (f"no lhUartFrame event carries an LH2 channel (every basestation = {u.no_channel}: LH1, or no "
                "channel decoded); no capture written")
    return None


def _found(ul) -> str:
    return ", ".join(f"{k} ({len(v['t'])})" for k, v in sorted(ul.events.items())) or "none"


def _log_kind(ul, ev, stations, system_config) -> str | None:
    """LH1 or LH2 for a log's sweep events: the events' own (estSweepAngle's plane tilt), the system
    config's ``systemType``, the stations' kind, else None."""
    if ev is not None and ev.kind is not None:
        return ev.kind
    if system_config is not None:
        from ..io.systemconfig import read_system_config

        return "lh1" if read_system_config(system_config).system_type == 1 else "lh2"
    kinds = {st.kind for st in stations or ()}
    return kinds.pop() if len(kinds) == 1 else None


def cfusdlog_replay_source(log, *, stations=None, system_config=None, source: str = "auto") -> dict:
    """What ``replay LOG`` solves from a Crazyflie microSD log, in memory.

    source : "uart" (the ``lhUartFrame`` events re-encoded as the deck's bytes, LH2 only:
    :func:`cfusdlog_capture`), "angles" (the firmware's sweep-angle events ``lhAngle`` /
    ``estSweepAngle`` grouped into frames, LH1 and LH2: :func:`layoutkit.live.cf_events.event_frames`)
    or "auto" (uart for a log with UART frames that is not known to be LH1 — the deck's 24 MHz
    clock times each light plane — unless it has fewer than 90 % as many UART frames as angle
    events, i.e. the card dropped UART frames; the angle events otherwise). The base-station type comes from the events, the
    system config's ``systemType`` or the stations.
    Returns ``{"mode", "sidecar", "bytes" | "frames", "stats", "kind", "firmware" (the log's own
    position estimates, :func:`layoutkit.importers.cfusdlog.firmware_positions}), "info"}``, and in
    "uart" mode ``"imu"``: the log's IMU samples on the log clock (the replay's ``t``;
    :func:`layoutkit.importers.cfusdlog.imu_samples`, None when it has none).
    system_config : a path or a loaded :class:`~layoutkit.io.systemconfig.SystemConfig`; the log is
    read once.
    ValueError naming the file and listing the event types found when nothing can be solved.
    """
    from ..importers.cfusdlog import firmware_positions, read_cfusdlog, sweep_events
    from ..io.sidecar import CaptureSidecar

    if source not in ("auto", "uart", "angles"):
        raise ValueError(f"source: expected 'auto', 'uart' or 'angles', got {source!r}")
    log = Path(log)
    ul = read_cfusdlog(log)
    ev = sweep_events(ul)
    uart = "lhUartFrame" in ul.events and len(ul.events["lhUartFrame"]["t"]) > 0
    kind = _log_kind(ul, ev, stations, system_config)
    choice = None
    if source == "auto":
        source = "uart" if uart and kind != "lh1" else "angles"
        n_uart = len(ul.events["lhUartFrame"]["t"]) if uart else 0
        if source == "uart" and ev is not None and kind is not None and n_uart < 0.9 * len(ev.t):
            # one UART frame per sensor and light plane, as one angle event: fewer frames than angles
            # means the card dropped UART frames (its ring buffer overflowed), so the angles are complete
            source = "angles"
            choice = (f"{n_uart} lhUartFrame events < 90 % of {len(ev.t)} {ev.source} events: the UART frames "
                      "were dropped on the card; replaying the angle events")
    fw = firmware_positions(ul)
    info = {"log": str(log), "version": ul.version, "crc_ok": ul.crc_ok, "log_ended": ul.ended,
            "event_types": {k: int(len(v["t"])) for k, v in ul.events.items()},
            "firmware_estimates": {k: {"event": v["event"], "variables": v["variables"], "rows": int(len(v["t"]))}
                                   for k, v in fw.items()}}
    if choice:
        info["source_choice"] = choice
    if source == "uart" or (ev is None and uart):
        if not uart:
            raise ValueError(f"{log}: no lhUartFrame events (found: {_found(ul)})")
        if kind == "lh1":
            raise ValueError(f"{log}: an LH1 system cannot be replayed from lhUartFrame events (the pulse widths "
                             f"that identify LH1 sync pulses are not logged); log lhAngle events (found: {_found(ul)})")
        data, sc = cfusdlog_capture(log, ul)
        info["source"] = "lhUartFrame"
        from ..importers.cfusdlog import imu_samples

        return {"mode": "uart", "bytes": data, "sidecar": sc, "kind": "lh2", "firmware": fw, "info": info,
                "imu": imu_samples(ul)}
    if ev is None:
        raise ValueError(f"{log}: no lighthouse sweep data to solve: found {_found(ul)}; replay needs sweep-angle "
                         "events (lhAngle or estSweepAngle: 'on:lhAngle' in the card's config.txt) or, for LH2, "
                         "lhUartFrame events")
    if kind is None:
        raise ValueError(f"{log}: {ev.source} events do not tell LH1 from LH2 base stations; give --system-config "
                         "(its systemType) or --stations")
    from ..live.cf_events import EventFrameSource, event_frames
    from ..live.frames import DecodeStats

    periods = {k: 60.0 / st.rotor_rpm for k, st in enumerate(stations or ()) if st.kind == kind}
    stats = DecodeStats()
    frames = event_frames(ev, kind, 4, periods=periods, stats=stats)
    if not frames:
        raise ValueError(f"{log}: {len(ev.t)} {ev.source} events gave no frame (found: {_found(ul)})")
    proto = "bitcraze-lh1" if kind == "lh1" else "bitcraze-lh2"
    sc = CaptureSidecar(protocol=proto, layout=_deck_layout().to_dict(), source=f"cfusdlog {ev.source} events",
                        n_sensors=4, extra={"imported_from": str(log), "log_ended": ul.ended})
    info.update(source=ev.source, kind=kind, events=int(len(ev.t)), frames=len(frames))
    return {"mode": "angles", "frames": frames, "source": EventFrameSource(stats), "sidecar": sc, "kind": kind,
            "firmware": fw, "info": info}


def import_cfusdlog(log, out_dir, *, system_config=None) -> dict:
    """A Crazyflie microSD log → ``out_dir/capture.bin`` (the deck's UART bytes re-encoded from the
    ``lhUartFrame`` events) with its sidecar ``capture.bin.json`` (protocol ``bitcraze-lh2``, the
    deck layout, the system config's stations and calibration, the deck-to-log clock offset), and
    ``out_dir/firmware_angles.csv`` (the firmware's own ``lhAngle`` raw and calibrated angles);
    a log with sweep-angle events (``lhAngle`` / ``estSweepAngle``, LH1 or LH2) also gives
    ``frames.csv`` + ``layout.json`` (+ ``stations.json`` with a system config) for ``solve`` and
    ``calibrate``, and the firmware's position estimates ``firmware_<label>.csv``. A log without
    UART frames gives no capture (``capture: null``).

    The replay's ``t`` is the log's event clock: ``t = offset + rate * deck ticks / 24 MHz``, both
    fitted on the frames (:func:`layoutkit.importers.cfusdlog.fit_deck_clock`; ``clock`` in the
    summary and the sidecar).
    """
    from ..importers.cfusdlog import read_cfusdlog, sweep_events
    from ..io.atomic import atomic_write_bytes
    from ..io.sidecar import CaptureSidecar, sidecar_path, write_sidecar
    from ..io.systemconfig import DECK_CLOCK_HZ, read_system_config

    log = Path(log)
    out = Path(out_dir)
    ul = read_cfusdlog(log)
    sweeps = sweep_events(ul)
    has_uart = "lhUartFrame" in ul.events and len(ul.events["lhUartFrame"]["t"]) > 0
    if not has_uart and sweeps is None:
        raise ValueError(f"{log}: no lighthouse sweep data: found {_found(ul)}; log lhAngle or estSweepAngle "
                         "events ('on:lhAngle' in the card's config.txt) or, for LH2, lhUartFrame events")
    cfg = read_system_config(system_config) if system_config else None
    cap = out / "capture.bin"
    if cap.exists() or (out / "frames.csv").exists():
        raise ValueError(f"{out}: holds an import already (capture.bin / frames.csv); imports are never "
                         "overwritten (choose another --out)")
    out.mkdir(parents=True, exist_ok=True)
    summary = {"log": str(log), "version": ul.version, "crc_ok": ul.crc_ok, "ended": ul.ended,
               "event_types": {k: int(len(v["t"])) for k, v in ul.events.items()}}
    summary.update(_import_sweep_events(log, ul, sweeps, out, cfg))
    lh1 = _uart_is_lh1(ul, summary.get("kind"))
    if not has_uart or lh1:
        # an LH1 log's UART frames cannot be decoded (no pulse widths, no channel): never a capture
        notes = [lh1] if lh1 else []
        res = {"uart_frames": int(len(ul.events["lhUartFrame"]["t"])) if has_uart else 0, "capture": None,
               "angle_rows": _firmware_angles(ul, out)[0], "firmware_angles": str(out / "firmware_angles.csv"),
               "notes": notes}
        if has_uart:
            res["clock"] = _deck_clock(ul).as_dict()
        return summary | res
    ev = ul.events["lhUartFrame"]
    data, notes = deck_bytes(ev)
    atomic_write_bytes(cap, data)
    clock = _deck_clock(ul)
    offset = clock.offset_s
    stations = ()
    note_list = [f"{k}: {v}" for k, v in notes.items()]
    if cfg is not None:
        ids = sorted(cfg.stations)
        if ids and ids == list(range(len(ids))):
            stations = tuple(cfg.stations[i] for i in ids)
        elif ids:
            note_list.append(f"system config station ids {ids} are not 0..k-1: stations left out of the sidecar")
    lay = _deck_layout()
    opts = {"time_offset_s": offset, "time_rate": clock.rate}
    if system_config:
        opts["system_config"] = str(Path(system_config).resolve())
    sc = CaptureSidecar(protocol="bitcraze-lh2", protocol_options=opts, stations=stations, layout=lay.to_dict(),
                        source="layoutkit import cfusdlog", n_sensors=4, bytes=len(data),
                        extra={"imported_from": str(log), "clock": clock.as_dict() | {"deck_clock_hz": DECK_CLOCK_HZ},
                               "import_notes": note_list})
    from dataclasses import replace

    imu_note = _write_imu(ul, out)
    if imu_note is not None:
        sc = replace(sc, extra=sc.extra | {"imu": imu_note})
    write_sidecar(cap, sc)
    rows, fa = _firmware_angles(ul, out)
    return summary | {"uart_frames": int(len(ev["t"])), "capture": str(cap), "sidecar": str(sidecar_path(cap)),
                      "firmware_angles": str(fa), "angle_rows": rows, "clock_offset_s": offset,
                      "clock": clock.as_dict(),
                      "stations": len(stations), "notes": note_list, "imu": imu_note}


def _write_imu(ul, out) -> dict | None:
    """The log's IMU samples (:func:`layoutkit.importers.cfusdlog.imu_samples`) → ``out/imu.csv``
    (:mod:`layoutkit.io.imu`; on the log clock = the capture's replay clock); the sidecar's ``imu``
    entry, or None when the log has none."""
    from ..importers.cfusdlog import imu_samples
    from ..io.imu import IMU_FILE, write_imu

    imu = imu_samples(ul)
    if imu is None or len(imu) == 0:
        return None
    write_imu(Path(out) / IMU_FILE, imu)
    return {"file": IMU_FILE, **imu.summary(), "clock": "log clock (the capture's replay t)",
            "units": "t s, gyro rad/s, acc m/s2 (specific force), body frame"}


def _firmware_angles(ul, out) -> tuple[int, Path]:
    """``out/firmware_angles.csv``: the firmware's own ``lhAngle`` raw and calibrated angles."""
    import csv

    from ..io.atomic import atomic_write

    ang = ul.events.get("lhAngle")
    rows = 0
    fa = out / "firmware_angles.csv"
    with atomic_write(fa, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "station", "sensor", "sweep", "angle", "corrected_angle"])
        if ang is not None and len(ang["t"]):
            for k in range(len(ang["t"])):
                w.writerow([repr(float(ang["t"][k])), int(ang.get("basestation", [0] * len(ang["t"]))[k]),
                            int(ang["sensor"][k]), int(ang.get("sweep", [0] * len(ang["t"]))[k]),
                            repr(float(ang["angle"][k])),
                            repr(float(ang["correctedAngle"][k])) if "correctedAngle" in ang else ""])
                rows += 1
    return rows, fa


def _import_sweep_events(log, ul, sweeps, out, cfg) -> dict:
    """The sweep-angle events as a frame table ``out/frames.csv`` (LH1-equivalent measured angles,
    station column; :mod:`layoutkit.io.frames`) with ``out/layout.json`` (the deck) and, with a
    system config, ``out/stations.json``; the log's own position estimates as position-only pose
    tables ``out/firmware_<label>.csv``. Returns the summary's part."""
    from ..importers.cfusdlog import firmware_positions
    from ..io.frames import Frames
    from ..io.poses import JOINT, PoseTable, write_poses

    res = {}
    for label, fw in firmware_positions(ul).items():
        p = out / f"firmware_{label}.csv"
        n = len(fw["t"])
        write_poses(p, PoseTable(fw["t"], np.full((n, 3), np.nan), fw["position"], station=np.full(n, JOINT),
                                 status=np.zeros(n, int)))
        res.setdefault("firmware_estimates", {})[label] = {"file": str(p), "event": fw["event"], "rows": n}
    if sweeps is None:
        return res
    stations = None
    if cfg is not None:
        ids = sorted(cfg.stations)
        stations = [cfg.stations[i] for i in ids] if ids == list(range(len(ids))) else None
    kind = _log_kind(ul, sweeps, stations, cfg)
    if kind is None:
        res["frames_error"] = (f"{log}: {sweeps.source} events do not tell LH1 from LH2 base stations; give "
                               "--system-config to write frames.csv")
        return res
    from ..live.cf_events import event_frames
    from ..live.frames import DecodeStats

    periods = {k: 60.0 / st.rotor_rpm for k, st in enumerate(stations or ()) if st.kind == kind}
    stats = DecodeStats()
    frames = event_frames(sweeps, kind, 4, periods=periods, stats=stats)
    lay = _deck_layout()
    write_layout(lay, out / "layout.json")
    fr = Frames(np.array([f.t for f in frames]), np.array([f.angles for f in frames]).reshape(-1, 4, 2),
                tuple(lay.ids), station=np.array([f.station for f in frames], int))
    write_frame_table(fr, out / "frames.csv")
    res.update(frames_file=str(out / "frames.csv"), frames=len(frames), sweep_events=int(len(sweeps.t)),
               sweep_event_type=sweeps.source, kind=kind, layout=str(out / "layout.json"),
               dropped=dict(stats.reasons))
    if stations:
        from ..io.stations import write_stations

        cals = {k: c.to_calibration(kind) for k, c in cfg.calibs.items()}
        from dataclasses import replace

        sts = [replace(st, calibration=st.calibration or cals.get(k)) for k, st in enumerate(stations)]
        write_stations(out / "stations.json", sts)
        res["stations_file"] = str(out / "stations.json")
    return res


# ---------------------------------------------------------------- motion capture

def import_reference(path, out, *, units: str = "m") -> dict:
    """A motion-capture reference (pose or position only; CSV or .npy) → a pose table ``out``
    (station ``joint`` = the reference's own world frame; position-only rows have an empty
    rotation). Any clock origin is kept as it is: the replay's offset search handles hours."""
    from ..io.poses import JOINT, PoseTable, read_reference, write_poses

    ref = read_reference(path, units)
    n = len(ref.t)
    rv = np.full((n, 3), np.nan) if ref.rotvec is None else ref.rotvec
    pos = np.full((n, 3), np.nan) if ref.translation is None else ref.translation
    write_poses(out, PoseTable(ref.t, rv, pos, station=np.full(n, JOINT), status=np.zeros(n, int)))
    return {"file": str(path), "out": str(out), "rows": n, "dropped_rows": ref.dropped,
            "dropped_lines": list(ref.dropped_lines),
            "position_only": ref.rotvec is None, "attitude_only": ref.translation is None, "t_first": float(ref.t[0]), "t_last": float(ref.t[-1])}
