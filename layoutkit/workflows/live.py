"""Live-mode orchestration with files: replay a capture, run live from a serial port, compare with
truth / motion capture / camera references, write the validation report. Used by
``layoutkit replay`` / ``layoutkit live`` and by studies.

Each input file is read once and passed on as an object: the capture's sidecar, a Crazyflie log
(:func:`layoutkit.workflows.importers.cfusdlog_replay_source`), the system config
(:func:`layoutkit.io.systemconfig.read_system_config`), the reference files. The run's
configuration is one frozen :class:`~layoutkit.live.session.RunSetup` (a capture's sidecar records
it). ``poses.csv`` is written once, as the run goes, with the firmware's own estimates joined in
(:class:`~layoutkit.live.firmware.FirmwareComparison`).

Memory stays flat for any run length: bytes are decoded as they arrive, frames are solved in
chunks, every pose is written out (JSON lines, ``poses.csv``) and only running statistics and
bounded, decimated series are kept (:mod:`layoutkit.live.stats`) — except when a reference is
compared: its alignment is estimated from the whole run, so the good poses are kept in memory
(72 bytes a pose, :class:`~layoutkit.live.session.PoseStore`) for the comparison at the end.

Why one module of ~650 lines: replay and live are one workflow over the same session, setup,
finish (references, camera, evidence of other runs) and report; split, each half would import the
other's private steps. Every function stays under 120 lines.
"""
from __future__ import annotations

import time
from pathlib import Path

from ..geometry import rotvec_to_matrix
from ..io.sidecar import CaptureSidecar
from ..layout import Layout, load_layout
from ..live.pipeline import LiveConfig
from ..live.session import POSES_EXTRAS, POSES_HEADER, LiveSession, RunSetup, session_for
from ..live.stats import ErrorAccumulator
from ..units import SIGMA_THETA_PAPER

__all__ = [
    "LiveSession",
    "POSES_HEADER",
    "POSES_EXTRAS",
    "RunSetup",
    "open_session",
    "session_from_sidecar",
    "replay_capture",
    "run_live",
    "reference_accuracy",
    "resolve_solve_mode",
    "stations_from_files",
]

_READ_BYTES = 1 << 16


# ----------------------------------------------------------------------------------- helpers

def reference_accuracy(poses, reference, *, sigma_theta: float = SIGMA_THETA_PAPER, tau: float | None = None,
                       max_offset: float | None = None, series_capacity: int = 20000, sample=None) -> dict:
    """Accuracy of a run's good poses against a reference stream (Chen eq. 25).

    poses : the run's :class:`~layoutkit.live.session.PoseStore` (every good pose). reference :
    :class:`PoseTrack` in its own frames (motion capture, or a camera attitude stream with
    translation None). The clock offset and the fixed frames are estimated from ``sample`` (a
    decimated :class:`PoseTrack` of good lighthouse poses) by
    :func:`layoutkit.live.reference.align_reference`, then every good pose is compared. Returns a
    dict with ``alignment``, ``errors`` and ``series``.
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
    for t, rotvec, translation, adop, pdop in poses.chunks():
        Rr, tr, v = al.apply(reference, t)
        if not v.any():
            continue
        R = rotvec_to_matrix(rotvec[v])
        p = translation[v]
        tr = p if tr is None else tr[v]  # attitude only: translation error reported as 0
        acc.update(t[v], R, p, Rr[v], tr, adop[v], pdop[v])
    s = acc.summary()
    out["errors"] = None if s is None else s.as_dict()
    out["attitude_only"] = reference.translation is None
    out["series"] = acc.series.array()
    out["message"] = "ok" if s is not None else "no overlap between poses and reference"
    return out


def _track(path, units: str = "m"):
    """A reference file (TRUTH.csv, motion capture, camera attitude) as a
    :class:`~layoutkit.live.reference.PoseTrack` (:func:`layoutkit.io.poses.read_reference`)."""
    from ..io.poses import read_reference
    from ..live.reference import PoseTrack

    return PoseTrack.from_reference(read_reference(path, units))


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


def open_session(setup: RunSetup, *, truth=None, json_out=None, poses_path=None, firmware=None,
                 keep_good: bool = False, imu=None, smooth=None) -> LiveSession:
    """A :class:`LiveSession` for ``setup`` with the file side's sinks: the per-sweep EKF
    (:class:`~layoutkit.workflows.filter.FilterSink`, ``filter_poses.csv`` beside ``poses_path``)
    when ``setup.config.filter`` is set, the firmware's own position estimates joined into the pose
    table (``firmware``: :func:`layoutkit.importers.cfusdlog.firmware_positions`), every good pose
    kept for references (``keep_good``). truth : a PoseTrack (or a TRUTH.csv path). imu : IMU samples
    (:class:`layoutkit.io.imu.ImuSamples`, the sweeps' clock, the layout's frame) for the IMU-aided
    filter (:class:`~layoutkit.workflows.filter.ImuFilterSink`) instead of the lighthouse-only one.
    smooth : a :class:`layoutkit.filter.smoother.SmootherConfig`: that filter's outputs smoothed
    offline (replay only; needs ``imu``)."""
    from ..live.session import calibrated_setup

    tr = _track(truth) if isinstance(truth, (str, Path)) else truth
    if poses_path is not None:  # the report folder, before any sink opens its file in it
        Path(poses_path).parent.mkdir(parents=True, exist_ok=True)
    sink = None
    if setup.config.filter is not None:  # the per-sweep EKF beside the frames
        from ..lighthouse import Station
        from .filter import FilterSink

        fp = None if poses_path is None else Path(poses_path).with_name("filter_poses.csv")
        # the filter sees the sweeps the decoder emits: measured angles with the stations' (or the
        # system config's) calibrations in "model" mode, pre-corrected ones in "undistort" mode
        sts, _, cals = calibrated_setup(setup)
        if not sts and cals and 0 in cals:
            sts = [Station(kind=cals[0].kind, rotor_rpm=3600.0 if cals[0].kind == "lh1" else 3000.0,
                           calibration=cals[0])]
        if imu is not None:
            from .filter import ImuFilterSink

            sink = ImuFilterSink(setup.layout.positions, sts or None, setup.config.filter, imu, tr, json_out, fp,
                                 smooth=smooth)
        else:
            sink = FilterSink(setup.layout.positions, sts or None, setup.config.filter, tr, json_out, fp)
    columns = ()
    if firmware:
        from ..live.firmware import FirmwareComparison

        columns = (FirmwareComparison(firmware),)
    return session_for(setup, truth=tr, json_out=json_out, poses_path=poses_path, sweep_sink=sink, columns=columns,
                       keep_good=keep_good)


def session_from_sidecar(layout, sidecar, *, protocol: str | None = None, options: LiveConfig | None = None,
                         truth=None, json_out=None, poses_path=None) -> LiveSession:
    """:func:`open_session` for the run a capture's sidecar describes (``layout`` a path or
    :class:`Layout`, default: the sidecar's; ``truth`` a TRUTH.csv path or a PoseTrack)."""
    sidecar = CaptureSidecar.from_dict(sidecar)
    setup = RunSetup.from_sidecar(sidecar, _layout_from(layout, sidecar), protocol=protocol, config=options)
    return open_session(setup, truth=truth, json_out=json_out, poses_path=poses_path)


def _finish_run(session: LiveSession, summary: dict, *, reference=None, reference_units="m", camera=None,
                report_dir=None, reference_offset=None, camera_frames=None) -> dict:
    sample = session.pose_track()
    extra_series = {}
    for key, path, units, tau in (("reference", reference, reference_units, reference_offset),
                                  ("camera", camera, "m", None)):
        if path is None:
            continue
        tr = _track(path, units)
        if key == "camera":
            tr = type(tr)(tr.t, tr.rotation, None)
        res = reference_accuracy(session.good_poses, tr, sigma_theta=session.options.sigma_theta, sample=sample,
                                 tau=tau)
        extra_series[key] = res.pop("series", None)
        summary[key] = res
    if camera_frames is not None:
        summary.update(_camera_summary(session, camera_frames, report_dir))
    _mark_other_runs(summary)
    if session.truth_err is not None:
        extra_series["truth"] = session.truth_err.series.array()
    if report_dir is not None:
        from ..live.report import write_report

        summary["report"] = write_report(report_dir, summary, error_series=extra_series,
                                         dop_series=session.dop_series.array())
    return summary


def _mark_other_runs(summary: dict) -> None:
    """A comparison with a file of another run (``summary["evidence"]``, a live run) says so in its
    own status: ``other_run``, never ``ok``."""
    for ev in summary.get("evidence") or ():
        if ev.get("status") != "other_run":
            continue
        key = {"--truth": "truth", "--reference": "reference", "--camera": "camera", "--camera-device": "camera",
               "the capture's camera folder": "camera"}.get(ev["option"])
        if isinstance(summary.get(key), dict):
            summary[key] = {**summary[key], "status": "other_run",
                            "message": ev["message"] + (f"; {summary[key]['message']}" if summary[key].get("message")
                                                        else "")}


def _camera_summary(session: LiveSession, camera_frames, report_dir) -> dict:
    """The lighthouse vs camera cross-check of a run (``camera``, and ``camera_report`` with plots)."""
    from ..live.camera_report import write_camera_plots
    from ..live.crosscheck import camera_crosscheck

    frames, info = camera_frames
    a = session.pose_sample.array()
    cc = camera_crosscheck(a[:, 0], rotvec_to_matrix(a[:, 1:4]), a[:, 7], session.options.sigma_theta,
                           frames.arrays(), truth=info.get("truth"), camera_counts=frames.counts(),
                           clock=info.get("clock"), alignment=info.get("alignment"),
                           corner_sigma_px=info.get("corner_sigma_px"))
    cam = dict(cc.summary)
    cam.update({k: v for k, v in info.items() if k not in ("truth", "clock", "alignment")})
    out = {"camera": cam}
    if report_dir is not None and cc.series:
        out["camera_report"] = write_camera_plots(report_dir, cc)
    return out


def stations_from_files(stations_path=None, system_config=None):
    """Stations given on the command line: a stations JSON (:mod:`layoutkit.io.stations`), else the
    stations of a Crazyflie system config (a path or a loaded
    :class:`~layoutkit.io.systemconfig.SystemConfig`; base-station ids 0..k-1), else None."""
    if stations_path:
        from ..io.stations import read_stations

        return list(read_stations(stations_path))
    if system_config is not None:
        from ..io.systemconfig import read_system_config

        return read_system_config(system_config).station_list()
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


def _replay_setup(capture: Path, layout, *, protocol, options, stations, system_config, solve, cfusdlog_source,
                  tied=None):
    """Every input of a replay read once: ``(RunSetup, the cfusdlog source dict or None, evidence, the
    capture's sidecar)``.
    tied : ``{option: path}`` of the files given beside the capture, checked against it
    (:func:`layoutkit.io.runtie.check_ties`: a file of another run is a ValueError)."""
    from dataclasses import replace

    from ..io.sidecar import read_sidecar
    from ..io.systemconfig import read_system_config

    cfg = None if system_config is None else read_system_config(system_config)
    given = stations_from_files(stations, cfg) if (stations is not None or cfg is not None) else None
    sidecar = read_sidecar(capture)
    from ..io.runtie import check_ties

    # before any work: another run's file is refused (the camera folder found beside it: flagged)
    evidence = check_ties(capture, sidecar, tied or {}, soft=("the capture's camera folder",))
    usd = None
    if not sidecar.protocol and _is_cfusdlog(capture):
        from .importers import cfusdlog_replay_source

        usd = cfusdlog_replay_source(capture, stations=given, system_config=cfg, source=cfusdlog_source)
        sidecar = usd["sidecar"]
    setup = RunSetup.from_sidecar(sidecar, _layout_from(layout, sidecar), protocol=protocol, config=options,
                                  stations=given, system_config=cfg)
    return replace(setup, config=resolve_solve_mode(solve, setup.stations, setup.config)), usd, evidence, sidecar


def _decode_all(setup: RunSetup, capture: Path, usd):
    """The first pass of a refining replay: every sweep of the capture decoded into memory and paired
    into frames (a log's sweep-angle frames as they are). Returns ``(sweeps or None, frames, decoder)``."""
    import io

    from ..live.pipeline import PosePipeline
    from ..live.session import calibrated_setup, make_decoder

    if usd is not None and usd["mode"] == "angles":
        return None, list(usd["frames"]), usd["source"]
    sts, opts, _ = calibrated_setup(setup)
    dec = make_decoder(setup.protocol, setup.layout.n, sts or None, opts)
    pairer = PosePipeline(setup.layout.positions, setup.config, sts or None).pairer
    sweeps = []
    data = usd.get("bytes") if usd is not None else None
    with (io.BytesIO(data) if data is not None else open(capture, "rb")) as rd:
        while True:
            block = rd.read(_READ_BYTES)
            if not block:
                break
            sweeps.extend(dec.feed(block))
    sweeps.extend(dec.flush())
    frames = [f for f in (pairer.push(m) for m in sweeps) if f is not None]
    return sweeps, frames, dec


def _refined(setup: RunSetup, frames, report_dir, fit_calibration: bool = False):
    """``(setup with the stations refined from the frames when that helps, the refinement's report)``
    (:func:`layoutkit.live.refine.refine_stations`; ``frames`` one capture's or a list of several);
    ``stations_refined.json`` in the report folder."""
    from dataclasses import replace

    from ..live.refine import refine_stations
    from ..live.session import calibrated_setup

    sts, _, _ = calibrated_setup(setup)
    c = setup.config
    ref = refine_stations(frames, setup.layout.positions, sts, sigma=c.sigma_theta, window_s=c.window_s,
                          fit_calibration=fit_calibration)
    rep = dict(ref.report, applied=ref.applied, status=ref.status)
    if not ref.applied:
        return setup, rep
    if report_dir is not None:
        from ..io.stations import write_stations

        Path(report_dir).mkdir(parents=True, exist_ok=True)
        write_stations(Path(report_dir) / "stations_refined.json", list(ref.stations))
        rep["file"] = str(Path(report_dir) / "stations_refined.json")
    return replace(setup, stations=tuple(ref.stations)), rep


def _feed_capture(s: LiveSession, capture: Path, usd, on_progress) -> None:
    """Decode and solve the whole capture (the raw bytes in blocks: memory stays flat whatever its
    length), or the frames of a Crazyflie log's sweep-angle events."""
    import io

    data = usd.get("bytes") if usd is not None else None
    if usd is not None and usd["mode"] == "angles":
        s.decoder = usd["source"]
        frames = usd["frames"]
        for k in range(0, len(frames), 4096):
            s.feed_frames(frames[k:k + 4096])
            if on_progress is not None:
                on_progress(s)
        data = b""
    with (io.BytesIO(data) if data is not None else open(capture, "rb")) as rd:
        while True:
            block = rd.read(_READ_BYTES)
            if not block:
                break
            s.feed_bytes(block)
            if on_progress is not None:
                on_progress(s)


def replay_capture(capture, layout=None, *, protocol: str | None = None, options: LiveConfig | None = None,
                   truth=None, reference=None, reference_units: str = "m", reference_offset: float | None = None,
                   camera=None, json_out=None, report_dir=None, on_progress=None, camera_device=None,
                   camera_config=None, stations=None, system_config=None, solve: str | None = None,
                   cfusdlog_source: str = "auto", refine_stations: bool = False, refine_from=(),
                   refine_calibration: bool = False, imu: bool | None = None, smooth=None) -> dict:
    """Decode and solve a capture file as fast as possible; returns the run summary dict.

    capture : path (with its ``.json`` sidecar when present: protocol, stations, layout).
    layout : path or :class:`Layout` (default: from the sidecar). truth : TRUTH.csv (station frame,
    no alignment); reference : motion-capture CSV; camera : camera attitude CSV (both aligned in
    time and frame from the data; ``reference_offset`` s fixes the clock offset instead). json_out :
    stream for ``--json-lines``. report_dir : write ``report.json``, plots and ``poses.csv`` there.
    camera_device : a camera capture folder (``fake-fpga --camera-out`` or a live session's
    ``CAPTURE.camera/``) solved with ``camera_config`` (:class:`layoutkit.live.camera.CameraConfig`)
    and compared with the poses (:func:`layoutkit.live.crosscheck.camera_crosscheck`); default:
    ``CAPTURE.camera/`` when it exists and a config is given. stations : a stations JSON path
    replacing the sidecar's stations; system_config : a Crazyflie system config YAML (path or
    loaded :class:`~layoutkit.io.systemconfig.SystemConfig`: calibration for the Bitcraze
    decoders, and the stations when no stations file is given). solve : "joint", "per-station" or
    None (joint when two or more stations with known poses are given; :func:`resolve_solve_mode`).
    A Crazyflie microSD log (cfusdlog, detected from its header) is replayed directly
    (:func:`layoutkit.workflows.importers.cfusdlog_replay_source`, ``cfusdlog_source``): its
    ``lhUartFrame`` events turned into the deck's bytes in memory (LH2), or its sweep-angle events
    (``lhAngle`` / ``estSweepAngle``, LH1 and LH2) grouped into frames. The log's own position
    estimates (crossing beam, state estimate) are compared with the joint poses
    (``summary["firmware_vs_ours"]``, columns ``firmware_*`` in ``poses.csv``). refine_stations :
    estimate the stations from the capture first (:func:`layoutkit.live.refine.refine_stations`:
    slow windows seen by every station, bundle-adjusted) and solve with them when they explain the
    angles better (``summary["station_refinement"]``; ``stations_refined.json`` in the report
    folder); the capture is decoded once, into memory. refine_from : more captures of the same
    station set-up whose slow windows join the refinement (a deck at rest in several places fixes
    the stations; a capture in constant motion has no slow window of its own); refine_calibration :
    also the observable calibration terms. imu : with ``--filter ekf``, run the IMU-aided filter on
    the capture's IMU samples (a Crazyflie log's own, or the ``imu.csv`` its import wrote beside the
    capture: :func:`capture_imu`); None (default) = when the capture has them, False = never (the
    lighthouse-only filter), True = required (ValueError without them). ``summary["imu"]`` says
    whether it was used and why not.
    """
    capture = Path(capture)
    if not capture.is_file():
        raise ValueError(f"{capture}: no such capture file")
    beside = camera_folder_for(capture) if camera_device is None and camera_config is not None else None
    setup, usd, evidence, sidecar = _replay_setup(
        capture, layout, protocol=protocol, options=options, stations=stations, system_config=system_config,
        solve=solve, cfusdlog_source=cfusdlog_source,
        tied={"--truth": truth, "--reference": reference, "--camera": camera,
              "--camera-device": camera_device if camera_device is None or Path(camera_device).is_dir() else None,
              "the capture's camera folder": beside if beside is not None and beside.is_dir() else None})
    firmware = (usd or {}).get("firmware") if setup.config.solve == "joint" else None
    poses = None if report_dir is None else Path(report_dir) / "poses.csv"
    decoded = refinement = None
    if refine_stations:
        if len(setup.stations) < 2:
            raise ValueError("--refine-stations: needs two or more stations with known poses (--system-config "
                             "with geos, or --stations)")
        decoded = _decode_all(setup, capture, usd)
        sets = [decoded[1]]
        for extra in refine_from or ():
            extra = Path(extra)
            if not extra.is_file():
                raise ValueError(f"{extra}: no such capture file (--refine-from)")
            x_setup, x_usd, _, _ = _replay_setup(extra, setup.layout, protocol=None, options=setup.config,
                                              stations=stations, system_config=setup.system_config, solve=solve,
                                              cfusdlog_source=cfusdlog_source)
            sets.append(_decode_all(x_setup, extra, x_usd)[1])
        setup, refinement = _refined(setup, sets, report_dir, refine_calibration)
        if refine_from:
            refinement["refined_from"] = [str(capture)] + [str(x) for x in refine_from]
    imu_samples, imu_note = _imu_for(capture, usd, sidecar, setup, imu)
    smooth = _smoother_config(smooth, setup, imu_samples, imu_note)
    s = open_session(setup, truth=truth, json_out=json_out, poses_path=poses, firmware=firmware,
                     keep_good=reference is not None or camera is not None, imu=imu_samples, smooth=smooth)
    if decoded is None:
        _feed_capture(s, capture, usd, on_progress)
    else:
        sweeps, frames, s.decoder = decoded
        if sweeps is not None:
            s.feed_sweeps(sweeps)
        else:
            s.feed_frames(frames)
    summary = s.finish()
    if refinement is not None:
        summary["station_refinement"] = refinement
    summary["capture"] = str(capture)
    summary["protocol"] = setup.protocol
    summary["evidence"] = evidence
    if setup.config.filter is not None:
        summary["imu"] = imu_note
    if usd is not None:
        summary["cfusdlog"] = usd["info"]
        if firmware:  # the firmware's own estimates beside ours (same clock, same world frame)
            summary["firmware_vs_ours"] = s.column_summaries[0]
    cam = _camera_from_folder(capture, camera_device, camera_config)
    return _finish_run(s, summary, reference=reference, reference_units=reference_units, camera=camera,
                       report_dir=report_dir, reference_offset=reference_offset, camera_frames=cam)


def capture_imu(capture, usd=None, sidecar=None):
    """The IMU samples of a capture (:class:`layoutkit.io.imu.ImuSamples`, on its replay clock) and
    where they come from: a Crazyflie log replayed directly carries its own (``usd["imu"]``,
    :func:`layoutkit.importers.cfusdlog.imu_samples`); an imported capture names its ``imu.csv`` in
    its sidecar (``imu.file``, beside the capture; ``sidecar``: the one already read, else it is read
    here). ``(None, why)`` when there are none."""
    from ..io.imu import read_imu
    from ..io.sidecar import read_sidecar

    if usd is not None:
        imu = usd.get("imu")
        if imu is None or len(imu) == 0:
            return None, "the log has no IMU events (gyro.x/y/z, acc.x/y/z)"
        return imu, "the log's own events"
    capture = Path(capture)
    entry = ((sidecar if sidecar is not None else read_sidecar(capture)).extra or {}).get("imu")
    if not isinstance(entry, dict) or not entry.get("file"):
        return None, "the capture's sidecar names no IMU file"
    path = capture.parent / entry["file"]
    if not path.is_file():
        return None, f"{path}: the IMU file the sidecar names is missing"
    return read_imu(path), str(path)


def _smoother_config(smooth, setup, imu_samples, imu_note):
    """The :class:`~layoutkit.filter.smoother.SmootherConfig` of :func:`replay_capture`'s ``smooth``
    (None / False: none; True: the defaults; a config as it is); ValueError when there is no IMU-aided
    filter to smooth."""
    if smooth is None or smooth is False:
        return None
    if setup.config.filter is None:
        raise ValueError("--smooth: smooths the filter's outputs; add --filter ekf")
    if imu_samples is None:
        why = (imu_note or {}).get("why") or "the capture has no IMU samples"
        raise ValueError(f"--smooth: smooths the IMU-aided filter, which does not run here ({why})")
    from ..filter.smoother import SmootherConfig

    return SmootherConfig() if smooth is True else smooth


def _imu_for(capture, usd, sidecar, setup, want):
    """(samples or None, summary note) for :func:`replay_capture`'s ``imu`` option."""
    if setup.config.filter is None:
        return None, None
    if want is False:
        return None, {"used": False, "why": "--no-imu"}
    imu, where = capture_imu(capture, usd, sidecar)
    if imu is None:
        if want:
            raise ValueError(f"{capture}: --imu: no IMU samples ({where})")
        return None, {"used": False, "why": where}
    if len(setup.stations) < 2:
        if want:
            raise ValueError(f"{capture}: --imu: the IMU-aided filter starts from two stations' joint solve; "
                             f"{len(setup.stations)} station(s) with known poses (--system-config or --stations)")
        return None, {"used": False, "why": "fewer than two stations with known poses"}
    return imu, {"used": True, "from": where, **imu.summary()}


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
             reference_offset: float | None = None, camera=None, json_out=None, report_dir=None,
             baudrate: int | None = None, stations=None, on_update=None, update_interval: float = 0.25,
             idle_timeout: float | None = None, overwrite: bool = False, on_status=None, status_interval: float = 10.0,
             camera_device=None, camera_config=None, system_config=None, solve: str | None = None,
             port_timeout: float | None = None) -> dict:
    """Read a serial port (reconnecting), record the raw bytes before decoding, solve live.

    port : pyserial URL or device/pty path. record : capture path (raw bytes + index + sidecar);
    an existing capture is refused (:class:`layoutkit.live.capture.CaptureExists`) unless
    ``overwrite``. duration : stop after this many wall seconds (None: until Ctrl-C / SIGTERM /
    SIGHUP). idle_timeout : stop when no byte arrived for this many seconds after the first byte
    (None: never). on_update(snapshot) is called every ``update_interval`` s (dashboard).
    on_status(text) (no dashboard) is told once, then every ``status_interval`` s, while the port
    is not connected and why (never a silent wait). port_timeout : give up when the port has not
    opened once within this many seconds (None: wait; after the first connection a replug is
    waited for as long as the run lasts): ``summary["port_timeout_s"]`` is then set, and a capture
    that received nothing is removed (an empty file would block the retry). camera_device + camera_config : a camera stream
    beside the serial one (:class:`layoutkit.live.camera.CameraReader`: own threads, host-clock
    stamps, frames kept raw in ``RECORD.camera/`` before they are solved); a camera that stops,
    stalls or sends corrupt frames never stops the serial side; the summary's ``camera`` object
    compares both streams (the same computation as ``replay``). system_config : a Crazyflie
    system config (path or loaded :class:`~layoutkit.io.systemconfig.SystemConfig`): its
    calibrations; the capture records its path.

    Ctrl-C, SIGTERM and SIGHUP end the run cleanly: reading stops, the capture is fsynced and
    closed with everything received, the pending frames are solved and the report is written;
    ``summary["stopped_by"]`` names the signal. A capture write that fails (disk full) stops the
    run the same way: the capture keeps the valid prefix, the report is still written (it can be
    on another disk) and ``summary["capture_error"]`` says ``<capture>: <reason>``.
    """
    from ..io.systemconfig import read_system_config
    from ..live.capture import CaptureWriter
    from ..live.sources import DEFAULT_BAUDRATE, ReconnectingSerial
    from ..live.stopping import stop_on_signals

    setup = RunSetup(_layout_from(layout, CaptureSidecar()), protocol, {}, tuple(stations or ()),
                     None if system_config is None else read_system_config(system_config),
                     resolve_solve_mode(solve, stations, options))
    baudrate = baudrate or DEFAULT_BAUDRATE
    settings = {"url": port, "baudrate": baudrate, "timeout": 0.05, "reconnect": True}
    # the capture first: an existing one is refused before the port is touched
    writer = CaptureWriter(record, setup.sidecar(port=settings, source="live"), overwrite=overwrite) \
        if record is not None else None
    with stop_on_signals(interrupt=True) as stop:  # Ctrl-C is a flag too: no frame lost mid-solve
        try:
            src = ReconnectingSerial(port, baudrate=baudrate, timeout=0.05)
            s = open_session(setup, truth=truth, json_out=json_out,
                             poses_path=Path(report_dir) / "poses.csv" if report_dir is not None else None,
                             keep_good=reference is not None or camera is not None)
            cam_reader = _start_camera(camera_device, camera_config, record, src)
        except BaseException:
            if writer is not None:
                writer.close()
            raise
        loop = _LiveLoop(src, s, writer, stop, port, cam_reader, on_update, update_interval, on_status,
                         status_interval, idle_timeout, port_timeout)
        try:
            loop.run(duration)
        finally:
            src.close()
            if cam_reader is not None:
                cam_reader.stop()
            if writer is not None:
                writer.close(decode=s.decoder.stats.as_dict(),
                             **({"stopped_by": stop.name} if stop.requested else {}))
                if not src.connects and not writer.bytes_written and cam_reader is None:
                    _remove_capture(record)  # nothing received: an empty capture would only block the retry
                    record = None
        summary = s.finish()
        cam_frames = None
        if cam_reader is not None:
            info = {k: v for k, v in cam_reader.stats().items() if k not in ("processed", "solved", "by_status")}
            cam_frames = (cam_reader.processor.frames, info)
        summary.update(port=port, protocol=protocol, interrupted=loop.interrupted or stop.requested, source=src.state,
                       capture=None if record is None else str(record),
                       stopped_by=stop.name or ("SIGINT" if loop.interrupted else None),
                       capture_error=loop.capture_error,
                       capture_bytes=None if writer is None else writer.bytes_written,
                       port_timeout_s=port_timeout if loop.port_gave_up else None)
        from ..io.runtie import check_ties_head  # files of another run: said, never silently compared

        summary["evidence"] = check_ties_head(loop.head, port, {
            "--truth": truth, "--reference": reference, "--camera": camera,
            "--camera-device": camera_device if camera_device is not None and Path(str(camera_device)).is_dir() else None})
        out = _finish_run(s, summary, reference=reference, reference_units=reference_units, camera=camera,
                          report_dir=report_dir, reference_offset=reference_offset, camera_frames=cam_frames)
        if on_update is not None:
            on_update(s.snapshot(src.state))
        return out


def _remove_capture(record) -> None:
    """Remove the capture ``record`` (+ .idx/.json) of a run that received no byte."""
    from ..io.sidecar import sidecar_path
    from ..live.capture import index_path

    for p in (Path(record), index_path(record), sidecar_path(record)):
        p.unlink(missing_ok=True)


def _start_camera(camera_device, camera_config, record, src):
    """The camera stream beside the serial one (:class:`layoutkit.live.camera.CameraReader`), or None."""
    if camera_device is None or camera_config is None:
        return None
    from ..live.camera import CameraReader

    try:
        return CameraReader(camera_device, camera_config,
                            camera_folder_for(record) if record is not None else None).start()
    except (OSError, ValueError):
        src.close()
        raise


class _LiveLoop:
    """The read loop of :func:`run_live`: port → capture (raw bytes first) → session, the dashboard
    updates and the waiting-state messages; ends on duration, idle timeout, a signal, Ctrl-C
    (``interrupted``) or a failed capture write (``capture_error``)."""

    def __init__(self, src, session, writer, stop, port, cam_reader, on_update, update_interval, on_status,
                 status_interval, idle_timeout, port_timeout=None):
        self.src, self.s, self.writer, self.stop, self.port = src, session, writer, stop, port
        self.cam_reader = cam_reader
        self.cam_live = None
        if cam_reader is not None:
            from ..live.camera import LiveCrossCheck

            self.cam_live = LiveCrossCheck(session.options.sigma_theta)
        self.on_update, self.update_interval = on_update, update_interval
        self.on_status, self.status_interval = on_status, status_interval
        self.idle_timeout = idle_timeout
        self.port_timeout = port_timeout
        self.port_gave_up = False
        from ..io.runtie import HeadHash

        self.head = HeadHash()  # the stream's first bytes: which run a truth or camera file belongs to
        self.interrupted = False
        self.capture_error = None

    def run(self, duration) -> None:
        src, s = self.src, self.s
        t_start = time.monotonic()
        t_end = None if duration is None else t_start + duration
        last_update, last_byte, last_status = 0.0, None, None
        try:
            while (t_end is None or time.monotonic() < t_end) and not self.stop.requested:
                data = src.read(_READ_BYTES)
                now = time.monotonic()
                if data:
                    if self.writer is not None:
                        try:
                            self.writer.write(data)  # raw bytes are kept before any decoding
                        except OSError as exc:  # disk full: keep the prefix, stop, still report
                            self.capture_error = f"{exc.filename}: {exc.strerror or exc}"
                            break
                    self.head.update(data)
                    s.feed_bytes(data)
                    s.flush_pending()  # one chunk per read: low latency, large chunks after a backlog
                    last_byte = now
                elif self.idle_timeout is not None and last_byte is not None and now - last_byte > self.idle_timeout:
                    break
                elif self.port_timeout is not None and not src.connects and now - t_start > self.port_timeout:
                    self.port_gave_up = True  # never opened: a mistyped or absent device
                    break
                if self.on_status is not None and not src.connected and (
                        last_status is None or now - last_status >= self.status_interval):
                    self.on_status(self._waiting(now - t_start, None if t_end is None else t_end - now))
                    last_status = now
                elif src.connected:
                    last_status = None
                if self.on_update is not None and now - last_update >= self.update_interval:
                    snap = s.snapshot(src.state)
                    if self.cam_reader is not None:
                        snap["camera"] = {**self.cam_live.update(s.pose_sample.array(), self.cam_reader.processor.frames),
                                          "error": self.cam_reader.error}
                    self.on_update(snap)
                    last_update = now
        except KeyboardInterrupt:
            self.interrupted = True

    def _waiting(self, elapsed: float, remaining: float | None) -> str:
        st = self.src.state
        what = "refusing the device now at the path" if st.get("refusals") and st.get("connects") else (
            "disconnected" if st.get("connects") else "not connected yet")
        if not st.get("connects") and self.port_timeout is not None:
            remaining = self.port_timeout - elapsed if remaining is None else min(remaining, self.port_timeout - elapsed)
        return (f"waiting for {self.port}: {what} ({st.get('last_error') or 'no such device'}); "
                f"{elapsed:.0f} s so far, retrying (every <= {self.src.backoff_max:g} s); "
                + ("Ctrl-C or SIGTERM ends the run" if remaining is None else f"the run ends in {max(remaining, 0):.0f} s"))
