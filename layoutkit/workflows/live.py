"""Live-mode orchestration with files: replay a capture, run live from a serial port, compare with
truth / motion capture / camera references, write the validation report. Used by
``layoutkit replay`` / ``layoutkit live`` and by studies.

Memory stays flat for any run length: bytes are decoded as they arrive, frames are solved in
chunks, every pose is written out (JSON lines, ``poses.csv``) and only running statistics and
bounded, decimated series are kept (:mod:`layoutkit.live.stats`).
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

from ..geometry import rotvec_to_matrix
from ..io.poses import iter_poses
from ..io.sidecar import CaptureSidecar
from ..layout import Layout, load_layout
from ..live.pipeline import LiveConfig
from ..live.session import POSES_EXTRAS, POSES_HEADER, LiveSession, make_decoder, session_for  # noqa: F401
from ..live.stats import ErrorAccumulator
from ..units import SIGMA_THETA_PAPER

__all__ = [
    "LiveConfig",
    "LiveOptions",
    "LiveSession",
    "POSES_HEADER",
    "POSES_EXTRAS",
    "session_from_sidecar",
    "replay_capture",
    "run_live",
    "reference_accuracy",
    "resolve_solve_mode",
]

_READ_BYTES = 1 << 16


#: Old name of :class:`layoutkit.live.pipeline.LiveConfig` (the one live/replay config).
LiveOptions = LiveConfig


# ----------------------------------------------------------------------------------- helpers

def reference_accuracy(poses_csv, reference, *, sigma_theta: float = SIGMA_THETA_PAPER, tau: float | None = None,
                       max_offset: float | None = None, series_capacity: int = 20000, sample=None) -> dict:
    """Accuracy of the poses in ``poses_csv`` against a reference stream (Chen eq. 25).

    reference : :class:`PoseTrack` in its own frames (motion capture, or a camera attitude stream
    with translation None). The clock offset and the fixed frames are estimated from ``sample``
    (a decimated :class:`PoseTrack` of good lighthouse poses) by
    :func:`layoutkit.live.reference.align_reference`, then every good pose is compared in a
    streaming pass over the CSV. Returns a dict with ``alignment``, ``errors`` and ``series``.
    """
    from ..live.reference import align_reference

    if sample is None:
        return {"alignment": None, "errors": None, "message": "no good poses"}
    al = align_reference(sample, reference, tau=tau, max_offset=max_offset)
    out = {"alignment": al.as_dict(), "errors": None, "series": None}
    if not al.success:
        out["message"] = al.message
        return out
    acc = ErrorAccumulator(sigma_theta, series_capacity)
    for tb in iter_poses(poses_csv):  # streaming pass, columns by name
        tb = tb.take(tb.ok)
        if not len(tb):
            continue
        Rr, tr, v = al.apply(reference, tb.t)
        if not v.any():
            continue
        R = rotvec_to_matrix(tb.rotvec[v])
        t = tb.translation[v]
        if tr is None:  # attitude only: translation error reported as 0
            tr = t
        else:
            tr = tr[v]
        acc.update(tb.t[v], R, t, Rr[v], tr, tb.extras["adop_deg_per_rad"][v], tb.extras["pdop_m_per_rad"][v])
    s = acc.summary()
    out["errors"] = None if s is None else s.as_dict()
    out["attitude_only"] = reference.translation is None
    out["series"] = acc.series.array()
    out["message"] = "ok" if s is not None else "no overlap between poses and reference"
    return out


def _layout_from(layout, sidecar: CaptureSidecar) -> Layout:
    if isinstance(layout, Layout):
        return layout
    if layout is not None:
        return load_layout(layout)
    lay = sidecar.layout
    if isinstance(lay, dict) and "sensors" in lay:
        return Layout.from_dict(lay)
    if isinstance(lay, str) and Path(lay).is_file():
        return load_layout(lay)
    raise ValueError("no layout: pass --layout (the capture's sidecar names none that can be loaded)")


def _protocol_from(sidecar: CaptureSidecar, protocol: str | None):
    return (protocol or sidecar.protocol or "layoutkit"), dict(sidecar.protocol_options)


def session_from_sidecar(layout, sidecar, *, protocol: str | None = None, options: LiveConfig | None = None,
                         truth=None, json_out=None, poses_path=None) -> LiveSession:
    """:func:`layoutkit.live.session.session_for` with files resolved: ``layout`` a path or
    :class:`Layout` (default: the sidecar's), ``truth`` a TRUTH.csv path or a PoseTrack.

    sidecar : :class:`~layoutkit.io.sidecar.CaptureSidecar` or its dict.
    """
    from ..live.reference import read_pose_csv

    sidecar = CaptureSidecar.from_dict(sidecar)
    lay = _layout_from(layout, sidecar)
    tr = read_pose_csv(truth) if isinstance(truth, (str, Path)) else truth
    sink = None
    if options is not None and options.filter is not None:  # the per-sweep EKF beside the frames
        from .filter import FilterSink

        from ..live.session import calibrated_setup

        fp = None if poses_path is None else Path(poses_path).with_name("filter_poses.csv")
        # the filter sees the sweeps the decoder emits: measured angles with the stations' (or the
        # system config's) calibrations in "model" mode, pre-corrected ones in "undistort" mode
        sts, _, cals = calibrated_setup(list(sidecar.stations), sidecar.protocol_options, options.calibration)
        if not sts and cals and 0 in cals:
            from ..lighthouse import Station

            sts = [Station(kind=cals[0].kind, rotor_rpm=3600.0 if cals[0].kind == "lh1" else 3000.0,
                           calibration=cals[0])]
        sink = FilterSink(lay.positions, sts or None, options.filter, tr, json_out, fp)
    return session_for(lay, sidecar, protocol=protocol, options=options, truth=tr, json_out=json_out,
                       poses_path=poses_path, sweep_sink=sink)


def _finish_run(session: LiveSession, summary: dict, *, reference=None, reference_units="m", camera=None,
                report_dir=None, reference_offset=None, camera_frames=None) -> dict:
    from ..live.reference import read_pose_csv

    sample = session.pose_track()
    extra_series = {}
    for key, path, units, tau in (("reference", reference, reference_units, reference_offset),
                                  ("camera", camera, "m", None)):
        if path is None:
            continue
        tr = read_pose_csv(path, units=units)
        if key == "camera":
            tr = type(tr)(tr.t, tr.rotation, None)
        res = reference_accuracy(session.poses_path, tr, sigma_theta=session.options.sigma_theta, sample=sample,
                                 tau=tau)
        extra_series[key] = res.pop("series", None)
        summary[key] = res
    if camera_frames is not None:
        from ..live.crosscheck import camera_crosscheck
        from ..live.camera_report import write_camera_plots

        frames, info = camera_frames
        a = session.pose_sample.array()
        cc = camera_crosscheck(a[:, 0], rotvec_to_matrix(a[:, 1:4]), a[:, 7], session.options.sigma_theta,
                               frames.arrays(), truth=info.get("truth"), camera_counts=frames.counts(),
                               clock=info.get("clock"), alignment=info.get("alignment"),
                               corner_sigma_px=info.get("corner_sigma_px"))
        cam = dict(cc.summary)
        cam.update({k: v for k, v in info.items() if k not in ("truth", "clock", "alignment")})
        summary["camera"] = cam
        if report_dir is not None and cc.series:
            summary.setdefault("camera_report", write_camera_plots(report_dir, cc))
    if session.truth_err is not None:
        extra_series["truth"] = session.truth_err.series.array()
    if report_dir is not None:
        from ..live.report import write_report

        summary["report"] = write_report(report_dir, summary, error_series=extra_series,
                                         dop_series=session.dop_series.array())
    return summary


def stations_from_files(stations_path=None, system_config=None):
    """Stations given on the command line: a stations JSON (:mod:`layoutkit.io.stations`), else the
    stations of a Crazyflie system config (base-station ids 0..k-1), else None."""
    if stations_path:
        from ..io.stations import read_stations

        return list(read_stations(stations_path))
    if system_config:
        from ..io.systemconfig import read_system_config

        cfg = read_system_config(system_config)
        ids = sorted(cfg.stations)
        if ids != list(range(len(ids))):
            raise ValueError(f"{system_config}: base-station ids {ids} are not 0..k-1; give --stations")
        return [cfg.stations[i] for i in ids] or None
    return None


def resolve_solve_mode(solve: str | None, stations, options: LiveConfig | None) -> LiveConfig:
    """``options`` with ``solve`` resolved: None → "joint" when two or more stations with known poses
    are given, else "per-station"; "joint" without any station pose → ValueError (the CLI's one
    ``error:`` line)."""
    from dataclasses import replace

    options = options or LiveConfig()
    n = len(stations or ())
    if solve is None:
        solve = "joint" if n >= 2 else "per-station"
    if solve == "joint" and n == 0:
        raise ValueError("--solve joint: no station poses known (give --stations FILE, --system-config YAML with "
                         "geos, or a capture whose sidecar lists its stations)")
    return replace(options, solve=solve)


def replay_capture(capture, layout=None, *, protocol: str | None = None, options: LiveConfig | None = None,
                   truth=None, reference=None, reference_units: str = "m", reference_offset: float | None = None,
                   camera=None, json_out=None, report_dir=None, on_progress=None, camera_device=None,
                   camera_config=None, stations=None, system_config=None, solve: str | None = None,
                   cfusdlog_source: str = "auto") -> dict:
    """Decode and solve a capture file as fast as possible; returns the run summary dict.

    capture : path (with its ``.json`` sidecar when present: protocol, stations, layout).
    layout : path or :class:`Layout` (default: from the sidecar). truth : TRUTH.csv (station frame,
    no alignment); reference : motion-capture CSV; camera : camera attitude CSV (both aligned in
    time and frame from the data; ``reference_offset`` s fixes the clock offset instead). json_out : stream for ``--json-lines``. report_dir : write
    ``report.json``, plots and ``poses.csv`` there. camera_device : a camera capture folder
    (``fake-fpga --camera-out`` or a live session's ``CAPTURE.camera/``) solved with
    ``camera_config`` (:class:`layoutkit.live.camera.CameraConfig`) and compared with the poses
    (:func:`layoutkit.live.crosscheck.camera_crosscheck`); default: ``CAPTURE.camera/`` when it exists
    and a config is given. stations : a stations JSON path replacing the sidecar's stations;
    system_config : a Crazyflie system config YAML (calibration for the Bitcraze decoders, and the
    stations when no stations file is given). solve : "joint", "per-station" or None (joint when
    two or more stations with known poses are given; :func:`resolve_solve_mode`).
    A Crazyflie microSD log (cfusdlog, detected from its header) is replayed directly
    (:func:`layoutkit.workflows.importers.cfusdlog_replay_source`, ``cfusdlog_source``): its
    ``lhUartFrame`` events turned into the deck's bytes in memory (LH2), or its sweep-angle events
    (``lhAngle`` / ``estSweepAngle``, LH1 and LH2) grouped into frames. The log's own position
    estimates (crossing beam, state estimate) are compared with the joint poses
    (``summary["firmware_vs_ours"]``, columns ``firmware_*`` in ``poses.csv``).
    """
    from ..io.sidecar import read_sidecar

    capture = Path(capture)
    if not capture.is_file():
        raise ValueError(f"{capture}: no such capture file")
    sidecar = read_sidecar(capture)
    data_override = usd = None
    if not sidecar.protocol and _is_cfusdlog(capture):
        from .importers import cfusdlog_replay_source

        usd = cfusdlog_replay_source(capture, stations=stations_from_files(stations, system_config),
                                     system_config=system_config, source=cfusdlog_source)
        sidecar = usd["sidecar"]
        data_override = usd.get("bytes")
    if stations is not None or system_config is not None:
        st = stations_from_files(stations, system_config)
        opts = dict(sidecar.protocol_options)
        if system_config is not None:
            opts["system_config"] = str(system_config)
        sidecar = sidecar.updated(stations=tuple(st) if st else sidecar.stations, protocol_options=opts)
    options = resolve_solve_mode(solve, sidecar.stations, options)
    with tempfile.TemporaryDirectory() as tmp:
        poses = None
        firmware = (usd or {}).get("firmware") if options.solve == "joint" else None
        if report_dir is not None:
            poses = Path(report_dir) / "poses.csv"
        elif reference is not None or camera is not None or firmware:
            poses = Path(tmp) / "poses.csv"
        s = session_from_sidecar(layout, sidecar, protocol=protocol, options=options, truth=truth,
                                 json_out=json_out, poses_path=poses)
        if usd is not None and usd["mode"] == "angles":
            s.decoder = usd["source"]
            frames = usd["frames"]
            for k in range(0, len(frames), 4096):
                s.feed_frames(frames[k:k + 4096])
                if on_progress is not None:
                    on_progress(s)
            data_override = b""
        # the raw bytes in blocks (the timing index is not needed as fast as possible: memory stays
        # flat whatever the capture's length)
        import io

        with (io.BytesIO(data_override) if data_override is not None else open(capture, "rb")) as rd:
            while True:
                data = rd.read(_READ_BYTES)
                if not data:
                    break
                s.feed_bytes(data)
                if on_progress is not None:
                    on_progress(s)
        summary = s.finish()
        summary["capture"] = str(capture)
        summary["protocol"] = _protocol_from(sidecar, protocol)[0]
        if usd is not None:
            summary["cfusdlog"] = usd["info"]
            if firmware:
                from .importers import firmware_comparison

                # the firmware's own estimates beside ours (same clock, same world frame)
                summary["firmware_vs_ours"] = firmware_comparison(poses, firmware)
        cam = _camera_from_folder(capture, camera_device, camera_config)
        return _finish_run(s, summary, reference=reference, reference_units=reference_units, camera=camera,
                           report_dir=report_dir, reference_offset=reference_offset, camera_frames=cam)


def _is_cfusdlog(path) -> bool:
    """A Crazyflie microSD log: magic 0xBC, then version 1 or 2 (little-endian u16)."""
    with open(path, "rb") as fh:
        head = fh.read(3)
    return len(head) == 3 and head[0] == 0xBC and int.from_bytes(head[1:3], "little") in (1, 2)


def camera_folder_for(capture) -> Path:
    """Where a live session keeps the camera frames of capture ``capture``: ``CAPTURE.camera/``."""
    capture = Path(capture)
    return capture.with_name(capture.name + ".camera")


def _camera_from_folder(capture, camera_device, camera_config):
    """Solve a camera capture folder for replay: ``(CameraFrames, info)`` or None."""
    from ..io.camera import read_camera_meta
    from ..live.camera import process_camera_folder

    folder = Path(camera_device) if camera_device is not None else camera_folder_for(capture)
    if camera_config is None or not folder.is_dir():
        if camera_device is not None and not folder.is_dir():
            raise ValueError(f"{folder}: no camera capture folder")
        return None
    meta = read_camera_meta(folder)
    frames, info = process_camera_folder(folder, camera_config)
    info.update(truth=meta.truth, source=meta.source, clock_kind=meta.clock)
    return frames, info


def run_live(port: str, layout, *, protocol: str = "layoutkit", options: LiveConfig | None = None,
             record=None, duration: float | None = None, truth=None, reference=None, reference_units: str = "m",
             reference_offset: float | None = None, camera=None, json_out=None, report_dir=None, baudrate: int | None = None, stations=None,
             on_update=None, update_interval: float = 0.25, idle_timeout: float | None = None,
             overwrite: bool = False, on_status=None, status_interval: float = 10.0, camera_device=None,
             camera_config=None, system_config=None, solve: str | None = None) -> dict:
    """Read a serial port (reconnecting), record the raw bytes before decoding, solve live.

    port : pyserial URL or device/pty path. record : capture path (raw bytes + index + sidecar);
    an existing capture is refused (:class:`layoutkit.live.capture.CaptureExists`) unless
    ``overwrite``. duration : stop after this many wall seconds (None: until Ctrl-C / SIGTERM /
    SIGHUP). idle_timeout : stop when no byte arrived for this many seconds after the first byte
    (None: never). on_update(snapshot) is called every ``update_interval`` s (dashboard).
    on_status(text) (no dashboard) is told once, then every ``status_interval`` s, while the port
    is not connected and why (never a silent wait). camera_device + camera_config : a camera stream
    beside the serial one (:class:`layoutkit.live.camera.CameraReader`: own threads, host-clock
    stamps, frames kept raw in ``RECORD.camera/`` before they are solved); a camera that stops,
    stalls or sends corrupt frames never stops the serial side; the summary's ``camera`` object
    compares both streams (the same computation as ``replay``).

    Ctrl-C, SIGTERM and SIGHUP end the run cleanly: reading stops, the capture is fsynced and
    closed with everything received, the pending frames are solved and the report is written;
    ``summary["stopped_by"]`` names the signal. A capture write that fails (disk full) stops the
    run the same way: the capture keeps the valid prefix, the report is still written (it can be
    on another disk) and ``summary["capture_error"]`` says ``<capture>: <reason>``.
    """
    from ..live.capture import CaptureWriter
    from ..live.sources import DEFAULT_BAUDRATE, ReconnectingSerial
    from ..live.stopping import stop_on_signals

    options = resolve_solve_mode(solve, stations, options)
    lay = _layout_from(layout, CaptureSidecar())
    baudrate = baudrate or DEFAULT_BAUDRATE
    settings = {"url": port, "baudrate": baudrate, "timeout": 0.05, "reconnect": True}
    sidecar = CaptureSidecar(protocol=protocol, layout=lay.to_dict(), port=settings, stations=tuple(stations or ()),
                             source="live",
                             protocol_options={"system_config": str(system_config)} if system_config else {})
    # the capture first: an existing one is refused before the port is touched
    writer = CaptureWriter(record, sidecar, overwrite=overwrite) if record is not None else None
    with tempfile.TemporaryDirectory() as tmp, stop_on_signals() as stop:
        try:
            src = ReconnectingSerial(port, baudrate=baudrate, timeout=0.05)
            poses = Path(report_dir) / "poses.csv" if report_dir is not None else (
                Path(tmp) / "poses.csv" if (reference is not None or camera is not None) else None)
            s = session_from_sidecar(lay, CaptureSidecar(stations=sidecar.stations, protocol_options=sidecar.protocol_options),
                                     protocol=protocol, options=options,
                                     truth=truth, json_out=json_out, poses_path=poses)
        except BaseException:
            if writer is not None:
                writer.close()
            raise
        cam_reader = cam_live = None
        if camera_device is not None and camera_config is not None:
            from ..live.camera import CameraReader, LiveCrossCheck

            try:
                cam_reader = CameraReader(camera_device, camera_config,
                                          camera_folder_for(record) if record is not None else None).start()
            except (OSError, ValueError):
                src.close()
                if writer is not None:
                    writer.close()
                raise
            cam_live = LiveCrossCheck(options.sigma_theta)
        t_start = time.monotonic()
        t_end = None if duration is None else t_start + duration
        last_update = 0.0
        last_byte = None
        last_status = None
        interrupted = False
        capture_error = None
        try:
            while (t_end is None or time.monotonic() < t_end) and not stop.requested:
                data = src.read(_READ_BYTES)
                now = time.monotonic()
                if data:
                    if writer is not None:
                        try:
                            writer.write(data)  # raw bytes are kept before any decoding
                        except OSError as exc:  # disk full: keep the prefix, stop, still report
                            capture_error = f"{exc.filename}: {exc.strerror or exc}"
                            break
                    s.feed_bytes(data)
                    s.flush_pending()  # one chunk per read: low latency, large chunks after a backlog
                    last_byte = now
                elif idle_timeout is not None and last_byte is not None and now - last_byte > idle_timeout:
                    break
                if on_status is not None and not src.connected and (
                        last_status is None or now - last_status >= status_interval):
                    st = src.state
                    what = "refusing the device now at the path" if st.get("refusals") and st.get("connects") else (
                        "disconnected" if st.get("connects") else "not connected yet")
                    on_status(f"waiting for {port}: {what} ({st.get('last_error') or 'no such device'}); "
                              f"{now - t_start:.0f} s so far, retrying (every <= {src.backoff_max:g} s); "
                              + ("Ctrl-C or SIGTERM ends the run" if t_end is None else
                                 f"the run ends in {t_end - now:.0f} s"))
                    last_status = now
                elif src.connected:
                    last_status = None
                if on_update is not None and now - last_update >= update_interval:
                    snap = s.snapshot(src.state)
                    if cam_reader is not None:
                        snap["camera"] = {**cam_live.update(s.pose_sample.array(), cam_reader.processor.frames),
                                          "error": cam_reader.error}
                    on_update(snap)
                    last_update = now
        except KeyboardInterrupt:
            interrupted = True
        finally:
            src.close()
            if cam_reader is not None:
                cam_reader.stop()
            if writer is not None:
                writer.close(decode=s.decoder.stats.as_dict(),
                             **({"stopped_by": stop.name} if stop.requested else {}))
        summary = s.finish()
        cam_frames = None
        if cam_reader is not None:
            info = {k: v for k, v in cam_reader.stats().items() if k not in ("processed", "solved", "by_status")}
            cam_frames = (cam_reader.processor.frames, info)
        stopped_by = stop.name or ("SIGINT" if interrupted else None)
        summary.update(port=port, protocol=protocol, interrupted=interrupted or stop.requested, source=src.state,
                       capture=None if record is None else str(record), stopped_by=stopped_by,
                       capture_error=capture_error,
                       capture_bytes=None if writer is None else writer.bytes_written)
        out = _finish_run(s, summary, reference=reference, reference_units=reference_units, camera=camera,
                          report_dir=report_dir, reference_offset=reference_offset, camera_frames=cam_frames)
        if on_update is not None:
            on_update(s.snapshot(src.state))
        return out
