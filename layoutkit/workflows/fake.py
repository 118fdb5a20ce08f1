"""What ``layoutkit fake-fpga`` does: simulate a layout in motion and emit a board's exact bytes.

:func:`fake_fpga_stream` builds the byte stream, its truth, the stream's identity
(:class:`layoutkit.io.runtie.StreamTie`) and the capture sidecar (no I/O); :func:`run_fake`
writes the truth file and the bench camera folder (both recording the stream's identity, so a
later ``replay --truth`` can tell whether they belong to a capture) and emits the stream into a
capture file or a pty. Nothing it writes replaces an existing file unless ``overwrite`` (the
capture and the truth; a camera folder is never replaced), and every refusal comes before the
first byte is written. SIGTERM / SIGHUP end it cleanly (:mod:`layoutkit.live.stopping`): the
camera rendering or the emission stops, the capture is closed, the pty link removed, and the
summary says ``stopped_by``. Studies and tests call these instead of the command.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..layout import Layout
from ..units import RHO_PAPER, SIGMA_THETA_PAPER

__all__ = ["FakeStream", "fake_fpga_stream", "run_fake", "render_camera"]


@dataclass(frozen=True)
class FakeStream:
    """chunks : list of ``(t_emit s, bytes)``; sweeps : :class:`layoutkit.live.simulator.SimulatedSweeps`
    (the truth); sidecar : the capture's ``.json`` sidecar (:class:`layoutkit.io.sidecar.CaptureSidecar`,
    recording ``tie`` under ``run``); tie : the byte stream's :class:`layoutkit.io.runtie.StreamTie`."""

    chunks: list
    sweeps: object
    sidecar: object
    tie: object = None


def _check_probability(name: str, p: float) -> None:
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"{name}: expected a probability in [0, 1], got {p}")


def fake_fpga_stream(layout: Layout, *, duration_s: float, seed: int = 0, protocol: str = "layoutkit",
                     motion="tumble", dropout: float = 0.0, frame_loss: float = 0.0, garbage: float = 0.0,
                     sigma: float = SIGMA_THETA_PAPER, rho: float = RHO_PAPER,
                     tumble_rate_deg_s: float | None = None, stations=None) -> FakeStream:
    """The simulated device output for ``layout`` over ``duration_s`` seconds.

    motion : ``"tumble"``, ``"static"``, a trajectory pose table path (:mod:`layoutkit.io.poses`)
    or a :class:`layoutkit.live.simulator.Trajectory`. sigma : sweep-angle noise, rad; rho :
    same-rotor correlation in [0, 1). tumble_rate_deg_s : largest angular rate of the tumble (default
    0.5°/s). stations : optional :class:`layoutkit.lighthouse.Station` list (poses in the world frame,
    kind, calibration; default one LH1 station at the origin): each station with a calibration emits
    its forward model's distorted angles (``measure(p, calibration)``), one without exactly the ideal
    ones; the sidecar records the stations used, calibration included. ValueError (naming the option)
    for bad input.
    """
    from ..io.runtie import stream_tie
    from ..io.sidecar import CaptureSidecar
    from ..live.protocols import protocol_entry
    from ..live.simulator import load_trajectory, simulate_stream

    if not duration_s > 0:
        raise ValueError(f"--duration: expected > 0 s, got {duration_s}")
    for name, p in (("--dropout", dropout), ("--frame-loss", frame_loss), ("--garbage", garbage)):
        _check_probability(name, p)
    motion_name = motion if isinstance(motion, str) and motion in ("tumble", "static") else "csv"
    if isinstance(motion, (str, Path)) and motion_name == "csv":
        if not Path(motion).is_file():
            raise ValueError(f"--motion: expected tumble, static or a trajectory CSV file, got {str(motion)!r}")
        motion = load_trajectory(motion)
    if tumble_rate_deg_s is not None:
        if motion_name != "tumble":
            raise ValueError("--tumble-rate-deg-s: only with --motion tumble")
        import numpy as np

        from ..live.simulator import tumble_trajectory

        motion = tumble_trajectory(layout, duration_s, np.random.default_rng(seed),
                                   max_rate=np.deg2rad(tumble_rate_deg_s),
                                   station=stations[0] if stations else None)
    chunks, sw = simulate_stream(layout, duration=duration_s, seed=seed, protocol=protocol, motion=motion,
                                 dropout=dropout, frame_loss=frame_loss, garbage=garbage, sigma=sigma, rho=rho,
                                 stations=stations or None)
    sidecar = CaptureSidecar(
        source="fake-fpga", protocol=protocol, protocol_options=protocol_entry(protocol).options(sw.stations, layout.n),
        n_sensors=layout.n, layout=layout.to_dict(), stations=tuple(sw.stations), port={"url": None, "baudrate": None},
        simulator={"seed": seed, "duration_s": duration_s, "motion": motion_name, "tumble_rate_deg_s": tumble_rate_deg_s,
                   **sw.info})
    tie = stream_tie((c for _, c in chunks), seed=seed)
    return FakeStream(chunks, sw, sidecar.updated(run=tie.to_dict()), tie)


def check_new_outputs(*, out=None, truth_path=None, camera_folder=None, overwrite: bool = False) -> None:
    """Refuse (``FileExistsError`` naming the option and file) before anything is written: an
    existing capture ``out`` or truth file unless ``overwrite``; a camera folder that already
    holds a camera capture always (frames are never replaced)."""
    if out is not None and not overwrite:
        from ..live.capture import check_new_capture

        check_new_capture(out)
    if truth_path is not None:
        p = Path(truth_path)
        if p.is_dir():
            raise FileExistsError(f"--truth {p}: is a folder, not a file")
        if p.exists() and not overwrite:
            raise FileExistsError(f"--truth {p}: a file of {p.stat().st_size:,} bytes is already there (another "
                                  "run's truth?); a truth file is never replaced silently: choose a new name, or "
                                  "pass --overwrite to replace it")
    if camera_folder is not None:
        from ..io.camera import INDEX_NAME

        idx = Path(camera_folder) / INDEX_NAME
        if idx.exists():
            raise FileExistsError(f"--camera-out {camera_folder}: a camera capture is already there ({idx}); frames "
                                  "are never replaced: choose another folder")


class Stopped(Exception):
    """Raised inside a step when a stop signal arrived (caught by :func:`run_fake`)."""


def run_fake(layout: Layout, *, out=None, link=None, truth_path=None, realtime: bool | None = None,
             speed: float = 1.0, wait_reader_s: float | None = None, overwrite: bool = False, on_ready=None,
             camera: dict | None = None, on_camera=None, **stream_kw) -> dict:
    """Simulate (:func:`fake_fpga_stream` with ``stream_kw``), write the truth, emit the bytes.

    out : capture file (+ ``.idx`` and ``.json`` sidecar); None: a pseudo-terminal, whose path is
    given to ``on_ready(path)`` (``link``: a symlink kept pointing at it), waited on by a reader
    at most ``wait_reader_s`` s (None: for ever). truth_path : TRUTH.csv, a pose table (s, rad, m;
    one row per sweep) ended by the stream's tie line (:mod:`layoutkit.io.runtie`). An existing
    ``out`` or ``truth_path`` is refused unless ``overwrite``, an existing camera folder always —
    before anything is written (:func:`check_new_outputs`). Returns the emit summary with
    ``sweeps``, ``frames_sent``, ``truth``, ``protocol``, ``stream_id`` and ``stopped_by`` (the
    name of the signal that ended the run early, else None). Raises ValueError (bad input),
    FileExistsError (an output is there), TimeoutError / :class:`layoutkit.live.simulator.ReaderGone`
    (pty reader) and OSError.
    camera : render the bench camera's view of the same trajectory first (:func:`render_camera`
    keywords: ``folder``, ``focal_length_px``, ``fps``, ``size``, ``clock_offset_s``, ``clock_drift``);
    ``on_camera(summary)`` is told when it is written (before streaming starts).
    """
    from ..live.simulator import run_fake_fpga, write_truth
    from ..live.stopping import stop_on_signals

    check_new_outputs(out=out, truth_path=truth_path, camera_folder=None if camera is None else camera["folder"],
                      overwrite=overwrite)
    with stop_on_signals(interrupt=True) as stop:
        st = fake_fpga_stream(layout, **stream_kw)
        if truth_path:
            write_truth(st.sweeps, truth_path, st.tie)
        base = {"sweeps": int(len(st.sweeps.t)), "truth": None if truth_path is None else str(truth_path),
                "protocol": st.sidecar.protocol, "stream_id": st.tie.stream_id}
        cam = None
        if camera is not None:

            def check_stop(k, n):  # noqa: ARG001 - on_frame signature
                if stop.requested:
                    raise Stopped

            try:
                check_stop(0, 0)
                cam = render_camera(st.sweeps, seed=stream_kw.get("seed", 0), duration_s=stream_kw["duration_s"],
                                    run=st.tie.to_dict(), on_frame=check_stop, **camera)
            except Stopped:
                from ..io.camera import read_camera_index

                folder = Path(camera["folder"])
                n = len(read_camera_index(folder)) if (folder / "index.csv").exists() else 0
                return {**base, "path": None if out is None else str(out), "bytes": 0, "chunks": len(st.chunks),
                        "chunks_sent": 0, "frames_sent": 0, "wall_s": None, "stopped_by": stop.name,
                        "camera": {"folder": str(folder), "frames": n, "incomplete": True}}
            if on_camera is not None:
                on_camera(cam)
        if stop.requested:  # before the first byte: no capture, no pty
            return {**base, "path": None if out is None else str(out), "bytes": 0, "chunks": len(st.chunks),
                    "chunks_sent": 0, "frames_sent": 0, "wall_s": None, "stopped_by": stop.name, "camera": cam}
        summary = run_fake_fpga(st.chunks, out=out, realtime=realtime, link=link, on_ready=on_ready, speed=speed,
                                sidecar=st.sidecar, wait_reader=wait_reader_s, overwrite=overwrite, stop=stop)
    summary.update(base, camera=cam,
                   frames_sent=summary["chunks_sent"] if summary["stopped_by"] else int(st.sweeps.emitted.sum()))
    return summary


def render_camera(sweeps, *, folder, duration_s: float, seed: int = 0, focal_length_px: float | None = None,
                  fps: float = 30.0, size=(640, 480), clock_offset_s: float = 0.37, clock_drift: float = 50e-6,
                  run: dict | None = None, on_frame=None) -> dict:
    """Render the bench camera stream (:mod:`layoutkit.live.camera_sim`) for simulated ``sweeps``
    into the camera capture folder ``folder`` (refused if one is there). run : the serial
    stream's tie (recorded in ``camera.json``); on_frame(k, n) : after each frame. Returns its summary."""
    import numpy as np

    from ..live.camera_sim import bench_camera_for, render_camera_stream
    from ..live.simulator import Trajectory

    traj = Trajectory(sweeps.t, sweeps.rotvec, sweeps.translation)
    R0, t0 = traj(np.array([sweeps.t[0]]))
    cam = bench_camera_for(R0[0], t0[0], focal_length_px=focal_length_px, width=int(size[0]), height=int(size[1]),
                           fps=fps, rng=np.random.default_rng(seed), clock_offset_s=clock_offset_s,
                           clock_drift=clock_drift)
    return render_camera_stream(cam, traj, duration_s, folder, seed=seed, t_start=float(sweeps.t[0]), run=run,
                                on_frame=on_frame)
