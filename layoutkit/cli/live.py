"""CLI commands (live): ``layoutkit live`` (serial port → poses, dashboard, record) and
``layoutkit replay`` (capture file → poses, as fast as possible)."""
from __future__ import annotations

import sys

import click

from .options import POSITIVE, Requires, flag_rules
from .options import (camera_options, filter_options, imu_option, smooth_option, length_mm_option, refine_stations_option, json_flag, layout_option, overwrite_option, port_option, protocol_option, report_option,
                      rho_option, sigma_option, solve_mode_option, stations_option, system_config_option,
                      units_option)
from .options import Number

_common_options = [
    layout_option(required=False, help="Layout JSON (sensor positions, m, body frame)."),
    protocol_option(default=None, help="Frame protocol (default: the capture's sidecar, else 'layoutkit')."),
    click.option("--json-lines", is_flag=True,
                 help="Print one JSON object per solved frame (t, rotvec, translation, n_lit, status, adop, pdop, "
                      "residual_rms) instead of the dashboard/summary."),
    click.option("--truth", type=click.Path(exists=True, dir_okay=False), default=None,
                 help="Simulator TRUTH.csv (a pose table; station frame): direct eq. (25) errors."),
    click.option("--reference", type=click.Path(exists=True, dir_okay=False), default=None,
                 help="Motion-capture CSV (t + rx,ry,rz | qx,qy,qz,qw | r11..r33 + tx,ty,tz | x,y,z); clock offset "
                      "and frames estimated from the data."),
    units_option(flag="--reference-units", dest="reference_units", what="the positions in --reference"),
    click.option("--reference-offset", type=float, default=None,
                 help="Known clock offset of --reference in s (reference time = lighthouse time + offset) "
                      "[default: estimated from the data]."),
    click.option("--camera", type=click.Path(exists=True, dir_okay=False), default=None,
                 help="Camera attitude CSV (t + r11..r33 or rx,ry,rz): second, attitude-only reference."),
    report_option(help="Write report.json, poses.csv and PNG plots into this directory."),
    rho_option(),
    sigma_option(),
    click.option("--motion-compensation/--no-motion-compensation", default=None,
                 help="Model the motion across a frame / window with the velocity of the recent poses. "
                      "--solve joint: each station's angles at their own time in the 20 ms window (default on: "
                      "a flying Crazyflie 0.51 vs 2.0 mm RMS, benchmarks/results/joint_crazyflie.json). "
                      "Per-station: each frame's Y sweep moved to its X-sweep time (LH1; default off; for fast "
                      "motion RMS 2.1x -> 1.0x the DOP prediction at 20 deg/s). Costs speed."),
    json_flag(help="Print the run summary as JSON."),
    system_config_option,
    stations_option,
    solve_mode_option,
    length_mm_option("--max-sigma-mm", "max_sigma_position",
                     help="Largest predicted 1-sigma position error (PDOP x sigma, Chen eq. 24) of an 'ok' pose, mm; "
                          "above it a solved pose is 'imprecise'. Default: joint windows with 2+ stations must be "
                          "below the geometric mean of what the best single station and all stations would give "
                          "at that pose (a one-station window of a small deck is not ok); per-station: no limit."),
]


def _camera_config(camera_device, focal_length_px, principal_point_px, camera_method, aspect_ratio,
                   corner_sigma_px, folder=None, camera_model=None):
    """A :class:`CameraConfig` from the camera flags (None without a camera), with the capture
    folder's ``camera.json`` filling what the flags leave out. ``--camera-model`` (a camera file
    with the lens distortion), else a model recorded in the folder's ``camera.json``, makes the
    camera side undistort (``--focal-length-px`` / ``--principal-point-px`` are then refused)."""
    from pathlib import Path

    from ._common import bad_input, fail

    src = camera_device if camera_device is not None else folder
    if src is None:
        return None
    from ..io.camera import read_camera_meta, read_camera_model
    from ..live.camera import CameraConfig

    with bad_input():
        meta = read_camera_meta(src) if Path(str(src)).is_dir() else None
        model = read_camera_model(camera_model) if camera_model is not None else None
        if model is None and meta is not None and meta.camera_matrix is not None and not focal_length_px:
            model = meta.camera_model()
    if model is not None:
        if camera_model is not None and (focal_length_px or principal_point_px):
            fail("--camera-model: gives the focal length and principal point; leave out --focal-length-px and "
                 "--principal-point-px")
        ar = aspect_ratio if aspect_ratio is not None else (meta.aspect_ratio if meta else None)
        with bad_input():
            return CameraConfig.from_model(model, method=camera_method, aspect_ratio=ar,
                                           corner_sigma_px=corner_sigma_px)
    f = focal_length_px or (meta.focal_length_px if meta else None)
    if f is None:
        if camera_device is None:
            return None
        fail("--focal-length-px: required with --camera-device (no camera.json beside the frames names one)")
    ar = aspect_ratio if aspect_ratio is not None else (meta.aspect_ratio if meta else None)
    with bad_input():
        return CameraConfig(float(f), principal_point_px or (meta.principal_point_px if meta else None),
                            camera_method, ar, corner_sigma_px)


def _print_camera(summary: dict, err: bool) -> None:
    c = summary.get("camera")
    if not isinstance(c, dict) or "frames" not in c:
        return
    lines = [f"camera: {c.get('frames')} frames, {c.get('solved')} solved"
             + (f"  ({', '.join(f'{k} {v}' for k, v in (c.get('by_status') or {}).items() if k != 'ok')})"
                if c.get("by_status") and len(c["by_status"]) > 1 else "")]
    clk = c.get("clock") or {}
    if clk.get("message"):
        lines.append(f"camera clock: {clk['message']}" if clk.get("status") in ("ok", "given", None)
                     else f"camera clock: {clk['status']}: {clk['message']}")
    st = c.get("status")
    head = "lighthouse vs camera: " + ("" if st == "ok" else f"{st}: ")
    if c.get("disagreement_rms_deg") is not None:
        lines.append(f"{head}{c.get('message')} (ratio {c.get('ratio') or float('nan'):.3f}); "
                     f"{c.get('face_on_frames')} face-on frames, {c.get('mirror_branch_frames')} on the mirror branch")
    elif c.get("message"):
        lines.append(f"{head}{c['message']}")
    for ln in lines:
        click.echo(ln, err=err)


def _add(options):
    def deco(f):
        for o in reversed(options):
            f = o(f)
        return f
    return deco


def _options(rho, sigma, live: bool, motion_compensation: bool | None = None, filter_settings=None,
             max_sigma_position: float | None = None):
    from ..live.pipeline import LiveConfig

    kw = dict(sigma_theta=sigma, rho=rho, motion_compensation=motion_compensation, max_sigma_position=max_sigma_position)
    if filter_settings is not None:
        from ..workflows.filter import filter_config

        from ._common import bad_input

        with bad_input("--filter: "):
            kw["filter"] = filter_config(filter_settings, kw["sigma_theta"], kw["rho"])
    return LiveConfig(**kw)


def _print_summary(summary: dict, as_json: bool, err: bool = False) -> None:
    from ..io.jsonfile import to_jsonable

    if as_json:
        import json

        s = {k: v for k, v in summary.items()}
        click.echo(json.dumps(to_jsonable(s), indent=2), err=err)
        return
    d = summary.get("decode") or {}
    lines = [
        f"frames {summary['frames']}  good {summary['good']}  bad {summary['bad']}  "
        f"too few lit {summary['too_few_lit']}  unpaired sweeps {summary['unpaired_sweeps']}",
        f"decoder: good {d.get('good', 0)}  bad {d.get('bad', 0)}  dropped {d.get('dropped', 0)}  "
        f"resyncs {d.get('resyncs', 0)}  skipped bytes {d.get('skipped_bytes', 0)}",
        f"stream {summary['stream_time_s']:.2f} s in {summary['wall_s']:.2f} s wall"
        + (f"  ({summary['speed_x_realtime']:.0f}x real time, {summary['frames_per_s']:.0f} frames/s)"
           if summary.get("speed_x_realtime") else ""),
    ]
    j = summary.get("joint")
    if j:
        per = ", ".join(f"{k} station(s): {v}" for k, v in (j.get("windows_by_stations") or {}).items())
        lines.append(f"joint: {j['poses']} windows ({per}), {j['good']} ok; window {j['window_s'] * 1e3:.0f} ms; "
                     f"poses in the stations' world frame")
    sr = summary.get("station_refinement")
    if sr:
        lines.append(f"stations ({'refined' if sr.get('applied') else 'as given'}): {sr.get('message')}")
    g = summary.get("static_groups") or []
    if g:
        lines.append(f"static groups: {len(g)}")
    for name in ("truth",):
        e = summary.get(name)
        if e:
            lines.append(f"error vs {name}: RMS {e['rms_rot_deg']:.4f} deg / {e['rms_trans_m'] * 1e3:.3f} mm "
                         f"(predicted {e['predicted_rot_deg']:.4f} deg / {e['predicted_trans_m'] * 1e3:.3f} mm, "
                         f"ratio {e['ratio_rot']:.3f} / {e['ratio_trans']:.3f}); max {e['max_rot_deg']:.3f} deg / "
                         f"{e['max_trans_m'] * 1e3:.2f} mm over {e['n']} frames")
    for name in ("reference", "camera"):
        r = summary.get(name)
        if r and not (name == "camera" and "frames" in r):  # the live camera stream: _print_camera
            e = r.get("errors")
            a = r.get("alignment") or {}
            if e:
                lines.append(f"error vs {name}: RMS {e['rms_rot_deg']:.4f} deg / {e['rms_trans_m'] * 1e3:.3f} mm, "
                             f"max {e['max_rot_deg']:.3f} deg / {e['max_trans_m'] * 1e3:.2f} mm "
                             f"(clock offset {a.get('tau_s', float('nan')):.4f} s)")
                if a.get("message") not in (None, "ok"):
                    lines.append(f"  note: {a['message']}")
            else:
                lines.append(f"{name}: {r.get('message')}")
    f = summary.get("filter")
    if f:
        c = f["counters"]
        lines.append(f"filter: {c['sweeps']} sweeps, ok {f['share_ok'] * 100:.1f} %, inits {c['inits']}, lost "
                     f"{c['losts']}, angles used {c['angles_used']} / rejected {c['angles_rejected']}, sweeps "
                     f"rejected {c['sweeps_rejected']}" + (f", {f['sweeps_per_s']:.0f} sweeps/s" if f.get("sweeps_per_s")
                                                           else ""))
        imu = f.get("imu")
        if imu:
            h = imu["health"]
            lines.append(f"filter IMU: {imu['samples']} samples at {imu['rate_hz']:.1f} Hz, gravity from "
                         f"{imu['gravity'].get('from')}; mean NIS per dof {h['mean_nis_per_dof'] or float('nan'):.2f}, "
                         f"sweeps rejected by the gate {h['sweeps_rejected_by_gate']}, restarts {h['restarts']}")
        elif summary.get("imu") and not summary["imu"].get("used"):
            lines.append(f"filter IMU: not used ({summary['imu'].get('why')})")
        sm = f.get("smoother")
        if sm:
            lines.append(f"filter smoothed (--smooth, lag {sm['lag_s']:g} s): {sm['outputs']} outputs ({sm['gap_poses']} "
                         f"gap poses), ok {sm['share_ok'] * 100:.1f} %, chains {sm['segments']}, largest buffer "
                         f"{sm['max_buffer']} steps")
        e = f.get("truth")
        if e:
            lines.append(f"filter error vs truth: RMS {e['rms_rot_deg']:.4f} deg / {e['rms_pos_m'] * 1e3:.3f} mm "
                         f"(own covariance {e['cov_rms_rot_deg']:.4f} deg / {e['cov_rms_pos_m'] * 1e3:.3f} mm, "
                         f"ratio {e['ratio_to_cov_rot']:.3f} / {e['ratio_to_cov_pos']:.3f}; mean NEES "
                         f"{e['mean_nees_6dof']:.2f} of 6)")
            if e.get("frame_dop_predicted_rot_deg") is not None:
                lines.append(f"  frame by frame: RMS {e['frame_by_frame_rms_rot_deg']:.4f} deg / "
                             f"{e['frame_by_frame_rms_pos_m'] * 1e3:.3f} mm, DOP prediction "
                             f"{e['frame_dop_predicted_rot_deg']:.4f} deg / {e['frame_dop_predicted_pos_m'] * 1e3:.3f} mm")
    for ev in summary.get("evidence") or ():  # files given beside the capture: whose run they are
        if ev.get("status") == "other_run":
            lines.append(f"warning: {ev['message']}")
        elif ev.get("status") != "tied":
            lines.append(f"note: {ev['message']}")
    rep = summary.get("report")
    if rep:
        lines.append(f"report: {rep.get('json')}")
    for ln in lines:
        click.echo(ln, err=err)


@click.command("replay", short_help="Decode and solve a recorded capture as fast as possible.")
@click.argument("capture", type=click.Path(dir_okay=False))
@_add(_common_options)
@refine_stations_option
@filter_options
@imu_option
@smooth_option
@camera_options
def replay_cmd(capture, layout_path, protocol, json_lines, truth, reference, reference_units, reference_offset, camera,
               report_dir, rho, sigma, motion_compensation, as_json, system_config, stations_path, filter_settings,
               camera_device, focal_length_px, principal_point_px, camera_method, aspect_ratio, corner_sigma_px,
               camera_model, solve_mode, max_sigma_position, refine_stations, refine_from, refine_calibration, imu,
               smooth):
    """Decode and solve a recorded CAPTURE as fast as possible.

    Protocol, stations (and layout) come from the capture's sidecar JSON (<CAPTURE>.json) when
    present. Poses are body poses in the station frame (m, rad), or in the stations' world frame
    when station poses are known; t is the device time base of the simulator's TRUTH.csv.
    --solve joint (the default with two or more known stations): one pose per 20 ms window from
    all stations' angles, "station": "joint" (docs/live.md "Joint solving"). A Crazyflie microSD
    log (cfusdlog) is replayed directly. With --camera-device DIR (or a CAPTURE.camera/ folder beside the
    capture) the camera frames are solved too and compared with the poses (summary "camera").
    """
    from ..workflows.live import camera_folder_for, replay_capture
    from ._common import fail

    opts = _options(rho, sigma, live=False, motion_compensation=motion_compensation,
                    filter_settings=filter_settings, max_sigma_position=max_sigma_position)
    beside = camera_folder_for(capture)
    cam_cfg = _camera_config(camera_device, focal_length_px, principal_point_px, camera_method, aspect_ratio,
                             corner_sigma_px, folder=beside if beside.is_dir() else None, camera_model=camera_model)
    try:
        summary = replay_capture(capture, layout_path, protocol=protocol, options=opts, truth=truth,
                                 reference=reference, reference_units=reference_units,
                                 reference_offset=reference_offset, camera=camera,
                                 json_out=sys.stdout if json_lines else None, report_dir=report_dir,
                                 camera_device=camera_device, camera_config=cam_cfg, stations=stations_path,
                                 system_config=system_config, solve=solve_mode,
                                 refine_stations=refine_stations or bool(refine_from), refine_from=refine_from,
                                 refine_calibration=refine_calibration, imu=imu, smooth=smooth)
    except BrokenPipeError:  # the reader of --json-lines went away (e.g. `| head`): stop quietly
        _quiet_exit()
    except (ValueError, FileNotFoundError, OSError) as exc:
        fail(str(exc))
    _print_run(summary, as_json, json_lines)
    dec = summary.get("decode") or {}
    if not dec.get("good"):  # nothing decodable: not a capture, or another protocol
        n_in = dec.get("bytes_in", 0)
        reasons = dec.get("reasons") or {}
        why = f"; most common reason: {max(reasons, key=reasons.get)}" if reasons else ""
        fail(f"{capture}: empty capture (0 bytes)" if not n_in else
             f"{capture}: no valid {summary.get('protocol')} frame in {n_in} byte(s); not a capture file, "
             "or recorded with another --protocol?" + why)
    if not summary.get("good"):  # frames decoded but no good pose: say why, exit 1
        fail(f"{capture}: no good pose in {summary.get('frames', 0)} frame(s); most common reason: "
             f"{_most_common_reason(summary)}", code=1)


def _most_common_reason(summary: dict) -> str:
    """The most common reason a run produced no good pose, from the run and decode counters."""
    cands = {"at most 3 sensors lit per frame (too few)": summary.get("too_few_lit") or 0,
             "sweeps without their partner (unpaired)": summary.get("unpaired_sweeps") or 0,
             "frames solved with a status other than ok": summary.get("bad") or 0}
    for k, v in ((summary.get("decode") or {}).get("reasons") or {}).items():
        cands[k] = v
    best = max(cands, key=cands.get)
    return best if cands[best] else "no frame was formed from the decoded sweeps"


def _stations_arg(stations_path, system_config):
    """The system config read once (or None) and the stations of a live run: a stations JSON, else
    the system config's stations, else None."""
    from ..io.systemconfig import read_system_config
    from ..workflows.live import stations_from_files

    cfg = None if system_config is None else read_system_config(system_config)
    return cfg, stations_from_files(stations_path, cfg)


def _print_run(summary: dict, as_json: bool, json_lines: bool) -> None:
    """The run's summary (JSON or text; on stderr when stdout carries --json-lines) and, in text,
    the camera cross-check."""
    _print_summary(summary, as_json, err=json_lines)
    if not as_json:
        _print_camera(summary, err=json_lines)


def _quiet_exit():
    import os

    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
    sys.exit(0)


@click.command("live", short_help="Solve poses live from a serial port, with a dashboard.")
@port_option
@click.option("--record", type=click.Path(dir_okay=False), default=None,
              help="New capture file: raw bytes are written as received, before decoding (+ .idx, .json "
                   "sidecar). An existing capture is never overwritten: the run is refused (exit 2) unless "
                   "--overwrite.")
@overwrite_option(what="an existing --record capture (and its .idx/.json)")
@click.option("--duration", type=POSITIVE, default=None, help="Stop after this many seconds (wall clock) [default: Ctrl-C].")
@click.option("--idle-timeout", type=POSITIVE, default=None,
              help="Stop when no byte arrived for this many seconds after the first byte.")
@click.option("--port-timeout", "port_timeout", type=Number(0.0, min_open=True, allow_inf=True, what="seconds"),
              default=10.0, show_default=True,
              help="Give up (exit 2) when the port has not opened within this many seconds: a mistyped or absent "
                   "device ('inf': wait). Once it has opened, an unplugged port is waited for as long as the run lasts.")
@click.option("--baudrate", type=click.IntRange(min=1), default=None, help="Baud rate [default: 921600].")
@click.option("--no-dashboard", is_flag=True, help="No rich dashboard (print the summary at the end only).")
@_add(_common_options)
@filter_options
@camera_options
@flag_rules(Requires("--overwrite", "--record", "only a --record capture can be replaced"))
def live_cmd(port, record, overwrite, duration, idle_timeout, port_timeout, baudrate, no_dashboard, layout_path, protocol, json_lines,
             truth, reference, reference_units, reference_offset, camera, report_dir, rho, sigma, motion_compensation,
             as_json, system_config, stations_path, filter_settings, camera_device, focal_length_px, principal_point_px,
             camera_method, aspect_ratio, corner_sigma_px, camera_model, solve_mode, max_sigma_position):
    """Solve poses live from a serial port (reconnects after unplug), with a dashboard.

    Ctrl-C, SIGTERM and SIGHUP end the run cleanly: reading stops, everything received is in the
    capture (fsynced), pending frames are solved, the report and summary are written. Exit status:
    0 (duration / idle timeout / Ctrl-C), 143 after SIGTERM, 129 after SIGHUP, 2 when the capture
    could not be written (disk full: the capture keeps what was written, the report is still made)
    or when the port never opened within --port-timeout (no empty capture is left behind).
    Without a dashboard the waiting state is printed to stderr while the port is not connected.
    A reconnect reads only the device first opened (same path and device identity), else refuses.
    With --camera-device the camera stream runs beside the serial stream (own threads; frames kept
    raw in RECORD.camera/ before solving) and the dashboard shows their disagreement.
    """
    from ..workflows.live import run_live
    from ._common import call_or_fail, fail

    if layout_path is None:
        fail("--layout is required for live runs")
    if duration is not None and not duration > 0:
        fail(f"--duration: expected a positive number of seconds, got {duration}")
    opts = _options(rho, sigma, live=True, motion_compensation=motion_compensation,
                    filter_settings=filter_settings, max_sigma_position=max_sigma_position)
    cfg, stations = call_or_fail(_stations_arg, stations_path, system_config)
    kw = dict(protocol=protocol or "layoutkit", options=opts, record=record, duration=duration, truth=truth,
              reference=reference, reference_units=reference_units, reference_offset=reference_offset, camera=camera,
              json_out=sys.stdout if json_lines else None, report_dir=report_dir, baudrate=baudrate,
              idle_timeout=idle_timeout, overwrite=overwrite, port_timeout=None if port_timeout == float("inf") else port_timeout, camera_device=camera_device,
              stations=stations, system_config=cfg, solve=solve_mode,
              camera_config=_camera_config(camera_device, focal_length_px, principal_point_px, camera_method,
                                           aspect_ratio, corner_sigma_px, camera_model=camera_model))
    try:
        if json_lines or no_dashboard or not sys.stderr.isatty():
            summary = run_live(port, layout_path, on_status=lambda m: click.echo(m, err=True), **kw)
        else:
            from ..live.dashboard import Dashboard

            with Dashboard() as dash:
                summary = run_live(port, layout_path, on_update=dash.update, **kw)
    except BrokenPipeError:  # the reader of --json-lines went away (e.g. `| head`): stop quietly
        _quiet_exit()
    except (ValueError, FileNotFoundError, OSError) as exc:
        fail(str(exc))
    _print_run(summary, as_json, json_lines)
    src = summary.get("source") or {}
    if summary.get("capture_error"):  # disk full: the capture holds a valid prefix, the report was written
        fail(f"{summary['capture_error']} (the capture keeps the {summary.get('capture_bytes') or 0} bytes "
             "written before; reading stopped)")
    if src.get("refusals") and not json_lines:
        click.echo(f"warning: {src.get('refusals')} reconnect(s) refused: {src.get('last_refusal')}", err=True)
    stopped = summary.get("stopped_by")
    if stopped in ("SIGTERM", "SIGHUP"):
        import signal

        click.echo(f"stopped by {stopped}: " + ", ".join(
            (["capture closed (fsynced)"] if summary.get("capture") else [])
            + (["report written"] if summary.get("report") else []) + ["summary printed"]), err=True)
        sys.exit(128 + int(getattr(signal, stopped)))
    if not src.get("connects"):  # the port never opened: say so rather than a silent empty run
        within = (f" within {summary['port_timeout_s']:g} s (--port-timeout)" if summary.get("port_timeout_s") else "")
        fail(f"{port}: the port never opened{within} ({src.get('last_error') or 'no such device'}); nothing was "
             "received" + (f", no capture kept at {record}" if record and not summary.get("capture") else ""))


commands: list = [live_cmd, replay_cmd]
