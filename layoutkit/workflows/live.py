"""Live-mode orchestration with files: replay a capture, run live from a serial port, compare with
truth / motion capture / camera references, write the validation report. Used by
``layoutkit replay`` / ``layoutkit live`` and by studies.

Memory stays flat for any run length: bytes are decoded as they arrive, frames are solved in
chunks, every pose is written out (JSON lines, ``poses.csv``) and only running statistics and
bounded, decimated series are kept (:mod:`layoutkit.live.stats`).
"""
from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..geometry import rotvec_to_matrix
from ..io.poses import POSE_COLUMNS, PoseTable, PoseWriter, iter_poses
from ..io.sidecar import CaptureSidecar
from ..layout import Layout, load_layout
from ..units import RHO_PAPER, SIGMA_THETA_PAPER
from ..live.pipeline import STATUS_NAMES, PipelineConfig, PoseChunk, PosePipeline
from ..live.stats import DecimatedSeries, ErrorAccumulator, StaticGroupTracker

__all__ = [
    "LiveOptions",
    "LiveSession",
    "POSES_HEADER",
    "POSES_EXTRAS",
    "session_from_sidecar",
    "replay_capture",
    "run_live",
    "reference_accuracy",
]

#: Extra columns of ``poses.csv`` after the pose table's fixed ones (:mod:`layoutkit.io.poses`).
POSES_EXTRAS = ("n_lit", "adop_deg_per_rad", "pdop_m_per_rad")
POSES_HEADER = list(POSE_COLUMNS + POSES_EXTRAS)
_READ_BYTES = 1 << 16


@dataclass(frozen=True)
class LiveOptions:
    """Settings shared by replay and live runs.

    sigma_theta : rad and rho : noise model for the predictions (Chen eqs. 19, 24; paper values).
    chunk_frames, chunk_seconds : pipeline chunking (replay: 2048-frame chunks; live runs solve one
        chunk per port read, at most ``chunk_frames``).
    static_window : frames per static-detection window; static_factor : a window is static when its
        spread is within this factor of the predicted precision.
    min_lit : fewest lit sensors for a pose. series_capacity : points kept for plots.
    motion_compensation : move each frame's Y-sweep angles to its X-sweep time with the body
        velocity of the recent poses (``PipelineConfig.motion_compensation``; docs/live.md).
    filter : a :class:`layoutkit.filter.EkfConfig` to also run the per-sweep filter
        (``--filter ekf``; its outputs replace the frame records on ``--json-lines``), or None.
    """

    sigma_theta: float = SIGMA_THETA_PAPER
    rho: float = RHO_PAPER
    chunk_frames: int = 2048
    chunk_seconds: float = float("inf")
    static_window: int = 120
    static_factor: float = 4.0
    min_lit: int = 4
    series_capacity: int = 20000
    motion_compensation: bool = False
    filter: object = None


@dataclass
class LiveSession:
    """Decoder + pipeline + sinks for one run. Feed bytes, get pose chunks; ``finish`` summarises.

    layout : the sensor layout; decoder : a protocol decoder (``feed``, ``flush``, ``stats``);
    stations : station set-up (poses in station 0's frame when None or a single station);
    truth : optional :class:`layoutkit.live.reference.PoseTrack` in the pipeline's frame (TRUTH.csv);
    json_out : text stream receiving one JSON object per solved frame; poses_path : CSV of all poses.
    """

    layout: Layout
    decoder: object
    options: LiveOptions = field(default_factory=LiveOptions)
    stations: list | None = None
    truth: object = None
    json_out: object = None
    poses_path: Path | None = None

    def __post_init__(self):
        rpm = self.stations[0].rotor_rpm if self.stations else 3600.0
        o = self.options
        self.config = PipelineConfig(n_sensors=self.layout.n, min_lit=o.min_lit, chunk_frames=o.chunk_frames,
                                     chunk_seconds=o.chunk_seconds, rotor_rpm=rpm, sigma_theta=o.sigma_theta,
                                     rho=o.rho, motion_compensation=o.motion_compensation)
        multi = self.stations is not None and len(self.stations) > 1
        self.pipeline = PosePipeline(self.layout.positions, self.config, self.stations if multi else None)
        self.static = StaticGroupTracker(o.sigma_theta, o.static_window, o.static_factor)
        self.truth_err = ErrorAccumulator(o.sigma_theta, o.series_capacity) if self.truth is not None else None
        # decimated good poses (t, rotvec, translation) for reference alignment, and DOP series for plots
        self.pose_sample = DecimatedSeries(7, o.series_capacity)
        self.dop_series = DecimatedSeries(4, o.series_capacity)  # t, adop, pdop, n_lit
        self._poses = None
        if self.poses_path is not None:
            self.poses_path = Path(self.poses_path)
            self.poses_path.parent.mkdir(parents=True, exist_ok=True)
            self._poses = PoseWriter(self.poses_path, POSES_EXTRAS)
        self.wall_start = time.monotonic()
        self.t_first = None
        self.t_last = None
        self.last = None  # last good pose record (for the dashboard)
        self.lit_sum = 0
        self.frames_in_rate = []  # (wall time, frames) samples over the last few seconds
        self.finished = None
        self.filter = None
        if o.filter is not None:
            from .filter import FilterSink

            self.filter = FilterSink(self.layout.positions, self.stations, o.filter, self.truth, self.json_out)

    # -- feeding ----------------------------------------------------------------------------
    def feed_bytes(self, data: bytes) -> list[PoseChunk]:
        """Decode ``data`` and solve whatever frames complete a chunk (and filter every sweep)."""
        return self._consume(self.pipeline.feed(self._filtered(self.decoder.feed(data))))

    def _filtered(self, sweeps):
        if self.filter is None:
            return sweeps
        sweeps = list(sweeps)
        self.filter.feed(sweeps)
        return sweeps

    def flush_pending(self) -> list[PoseChunk]:
        """Solve the frames waiting in the current chunk now (live: when the port is quiet)."""
        return self._consume(self.pipeline.flush())

    def _consume(self, chunks: list[PoseChunk]) -> list[PoseChunk]:
        for ch in chunks:
            self._sink(ch)
        return chunks

    def _sink(self, ch: PoseChunk) -> None:
        if not len(ch):
            return
        if self.t_first is None:
            self.t_first = float(ch.t[0])
        self.t_last = float(ch.t[-1])
        now = time.monotonic()
        self.frames_in_rate.append((now, len(ch)))
        while self.frames_in_rate and now - self.frames_in_rate[0][0] > 2.0:
            self.frames_in_rate.pop(0)
        self.lit_sum += int(ch.n_lit.sum())
        if self.json_out is not None and self.filter is None:
            self.json_out.write("".join(json.dumps(r) + "\n" for r in ch.records()))
            self.json_out.flush()
        if self._poses is not None:
            self._poses.write(PoseTable(ch.t, ch.rotvec, ch.translation, ch.station, ch.status, ch.residual_rms, {
                "n_lit": ch.n_lit, "adop_deg_per_rad": np.where(np.isfinite(ch.adop), ch.adop, np.nan),
                "pdop_m_per_rad": np.where(np.isfinite(ch.pdop), ch.pdop, np.nan)}))
        g = ch.good
        self.dop_series.extend(np.column_stack([ch.t, np.where(g, ch.adop, np.nan),
                                                np.where(g, ch.pdop, np.nan), ch.n_lit]))
        if not g.any():
            return
        t, R, tr, a, p = ch.t[g], ch.rotation[g], ch.translation[g], ch.adop[g], ch.pdop[g]
        self.pose_sample.extend(np.column_stack([t, ch.rotvec[g], tr]))
        self.static.update(t, R, tr, a, p)
        if self.truth_err is not None:
            Rr, trr, v = self.truth.at(t)
            if v.any():
                self.truth_err.update(t[v], R[v], tr[v], Rr[v], trr[v], a[v], p[v])
        j = np.flatnonzero(g)[-1]
        self.last = {"t": float(ch.t[j]), "rotvec": ch.rotvec[j], "translation": ch.translation[j],
                     "n_lit": int(ch.n_lit[j]), "adop": float(ch.adop[j]), "pdop": float(ch.pdop[j]),
                     "residual_rms": float(ch.residual_rms[j])}

    # -- reporting --------------------------------------------------------------------------
    def rate(self) -> float:
        """Solved frames per wall second over the last ~2 s."""
        if len(self.frames_in_rate) < 2:
            return 0.0
        dt = self.frames_in_rate[-1][0] - self.frames_in_rate[0][0]
        n = sum(k for _, k in self.frames_in_rate[1:])
        return n / dt if dt > 0 else 0.0

    def snapshot(self, source_state: dict | None = None) -> dict:
        """Plain dict of the current state (dashboard)."""
        c = self.pipeline.counters
        grp = self.static.current()
        return {
            "wall_s": time.monotonic() - self.wall_start,
            "rate_fps": self.rate(),
            "frames": c.frames, "good": c.good, "bad": c.bad, "too_few_lit": c.too_few_lit,
            "unpaired_sweeps": c.unpaired_sweeps,
            "decode": self.decoder.stats.as_dict(),
            "last": self.last,
            "mean_lit": self.lit_sum / c.frames if c.frames else 0.0,
            "sigma_theta": self.options.sigma_theta,
            "static_group": None if grp is None else grp.as_dict(),
            "static_groups": len(self.static.groups),
            "truth": None if self.truth_err is None or self.truth_err.n == 0 else self.truth_err.summary().as_dict(),
            "source": source_state,
        }

    def finish(self) -> dict:
        """End of stream: decode and solve what is left, close files, return the run summary."""
        if self.finished is not None:
            return self.finished
        self._consume(self.pipeline.feed(self._filtered(self.decoder.flush())))
        self._consume(self.pipeline.flush(end_of_stream=True))
        groups = self.static.finish()
        if self._poses is not None:
            self._poses.close()
        wall = time.monotonic() - self.wall_start
        c = self.pipeline.counters
        span = (self.t_last - self.t_first) if self.t_first is not None else 0.0
        self.finished = {
            "frames": c.frames, "good": c.good, "bad": c.bad, "too_few_lit": c.too_few_lit,
            "unpaired_sweeps": c.unpaired_sweeps, "decode": self.decoder.stats.as_dict(),
            "stream_time_s": span, "wall_s": wall,
            "speed_x_realtime": span / wall if wall > 0 else None,
            "frames_per_s": c.frames / wall if wall > 0 else None,
            "mean_lit": self.lit_sum / c.frames if c.frames else 0.0,
            "sigma_theta_rad": self.options.sigma_theta, "rho": self.options.rho,
            "static_groups": [g.as_dict() for g in groups],
            "truth": None if self.truth_err is None or self.truth_err.n == 0 else self.truth_err.summary().as_dict(),
            "status_names": STATUS_NAMES,
        }
        if self.filter is not None:
            self.finished["filter"] = self.filter.summary(self.finished["truth"])
        return self.finished

    def pose_track(self):
        """The decimated good poses as a :class:`PoseTrack` (for reference alignment), or None."""
        from ..live.reference import PoseTrack

        a = self.pose_sample.array()
        if len(a) < 3:
            return None
        a = a[np.concatenate([[True], np.diff(a[:, 0]) > 0])]
        return PoseTrack(a[:, 0], rotvec_to_matrix(a[:, 1:4]), a[:, 4:7])


# ----------------------------------------------------------------------------------- helpers

def reference_accuracy(poses_csv, reference, *, sigma_theta: float = SIGMA_THETA_PAPER, tau: float | None = None,
                       max_offset: float = 5.0, series_capacity: int = 20000, sample=None) -> dict:
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


def make_decoder(protocol: str, n_sensors: int, stations=None, options: dict | None = None):
    """The registered decoder ``protocol`` for ``n_sensors``: options from the stations (rotor,
    clock; :meth:`~layoutkit.live.protocols.ProtocolEntry.make_decoder`) overridden by ``options``."""
    from ..live.protocols import protocol_entry

    return protocol_entry(protocol).make_decoder(n_sensors, stations, options)


def session_from_sidecar(layout, sidecar, *, protocol: str | None = None, options: LiveOptions | None = None,
                         truth=None, json_out=None, poses_path=None) -> LiveSession:
    """A :class:`LiveSession` configured from a capture sidecar (protocol, stations) and overrides.

    sidecar : :class:`~layoutkit.io.sidecar.CaptureSidecar` or its dict.
    """
    from ..live.reference import read_pose_csv

    sidecar = CaptureSidecar.from_dict(sidecar)
    lay = _layout_from(layout, sidecar)
    name, popts = _protocol_from(sidecar, protocol)
    stations = list(sidecar.stations) or None
    dec = make_decoder(name, lay.n, stations, popts)
    tr = read_pose_csv(truth) if isinstance(truth, (str, Path)) else truth
    return LiveSession(lay, dec, options or LiveOptions(), stations, tr, json_out, poses_path)


def _finish_run(session: LiveSession, summary: dict, *, reference=None, reference_units="m", camera=None,
                report_dir=None, reference_offset=None) -> dict:
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
    if session.truth_err is not None:
        extra_series["truth"] = session.truth_err.series.array()
    if report_dir is not None:
        from ..live.report import write_report

        summary["report"] = write_report(report_dir, summary, error_series=extra_series,
                                         dop_series=session.dop_series.array())
    return summary


def replay_capture(capture, layout=None, *, protocol: str | None = None, options: LiveOptions | None = None,
                   truth=None, reference=None, reference_units: str = "m", reference_offset: float | None = None,
                   camera=None, json_out=None, report_dir=None, on_progress=None) -> dict:
    """Decode and solve a capture file as fast as possible; returns the run summary dict.

    capture : path (with its ``.json`` sidecar when present: protocol, stations, layout).
    layout : path or :class:`Layout` (default: from the sidecar). truth : TRUTH.csv (station frame,
    no alignment); reference : motion-capture CSV; camera : camera attitude CSV (both aligned in
    time and frame from the data; ``reference_offset`` s fixes the clock offset instead). json_out : stream for ``--json-lines``. report_dir : write
    ``report.json``, plots and ``poses.csv`` there.
    """
    from ..io.sidecar import read_sidecar

    capture = Path(capture)
    if not capture.is_file():
        raise ValueError(f"{capture}: no such capture file")
    sidecar = read_sidecar(capture)
    with tempfile.TemporaryDirectory() as tmp:
        poses = None
        if report_dir is not None:
            poses = Path(report_dir) / "poses.csv"
        elif reference is not None or camera is not None:
            poses = Path(tmp) / "poses.csv"
        s = session_from_sidecar(layout, sidecar, protocol=protocol, options=options, truth=truth,
                                 json_out=json_out, poses_path=poses)
        # the raw bytes in blocks (the timing index is not needed as fast as possible: memory stays
        # flat whatever the capture's length)
        with open(capture, "rb") as rd:
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
        return _finish_run(s, summary, reference=reference, reference_units=reference_units, camera=camera,
                           report_dir=report_dir, reference_offset=reference_offset)


def run_live(port: str, layout, *, protocol: str = "layoutkit", options: LiveOptions | None = None,
             record=None, duration: float | None = None, truth=None, reference=None, reference_units: str = "m",
             reference_offset: float | None = None, camera=None, json_out=None, report_dir=None, baudrate: int | None = None, stations=None,
             on_update=None, update_interval: float = 0.25, idle_timeout: float | None = None,
             overwrite: bool = False, on_status=None, status_interval: float = 10.0) -> dict:
    """Read a serial port (reconnecting), record the raw bytes before decoding, solve live.

    port : pyserial URL or device/pty path. record : capture path (raw bytes + index + sidecar);
    an existing capture is refused (:class:`layoutkit.live.capture.CaptureExists`) unless
    ``overwrite``. duration : stop after this many wall seconds (None: until Ctrl-C / SIGTERM /
    SIGHUP). idle_timeout : stop when no byte arrived for this many seconds after the first byte
    (None: never). on_update(snapshot) is called every ``update_interval`` s (dashboard).
    on_status(text) (no dashboard) is told once, then every ``status_interval`` s, while the port
    is not connected and why (never a silent wait).

    Ctrl-C, SIGTERM and SIGHUP end the run cleanly: reading stops, the capture is fsynced and
    closed with everything received, the pending frames are solved and the report is written;
    ``summary["stopped_by"]`` names the signal. A capture write that fails (disk full) stops the
    run the same way: the capture keeps the valid prefix, the report is still written (it can be
    on another disk) and ``summary["capture_error"]`` says ``<capture>: <reason>``.
    """
    from ..live.capture import CaptureWriter
    from ..live.sources import DEFAULT_BAUDRATE, ReconnectingSerial
    from ..live.stopping import stop_on_signals

    options = options or LiveOptions(chunk_frames=1024)
    lay = _layout_from(layout, CaptureSidecar())
    baudrate = baudrate or DEFAULT_BAUDRATE
    settings = {"url": port, "baudrate": baudrate, "timeout": 0.05, "reconnect": True}
    sidecar = CaptureSidecar(protocol=protocol, layout=lay.to_dict(), port=settings, stations=tuple(stations or ()),
                             source="live")
    # the capture first: an existing one is refused before the port is touched
    writer = CaptureWriter(record, sidecar, overwrite=overwrite) if record is not None else None
    with tempfile.TemporaryDirectory() as tmp, stop_on_signals() as stop:
        try:
            src = ReconnectingSerial(port, baudrate=baudrate, timeout=0.05)
            poses = Path(report_dir) / "poses.csv" if report_dir is not None else (
                Path(tmp) / "poses.csv" if (reference is not None or camera is not None) else None)
            s = session_from_sidecar(lay, CaptureSidecar(stations=sidecar.stations), protocol=protocol, options=options,
                                     truth=truth, json_out=json_out, poses_path=poses)
        except BaseException:
            if writer is not None:
                writer.close()
            raise
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
                    on_update(s.snapshot(src.state))
                    last_update = now
        except KeyboardInterrupt:
            interrupted = True
        finally:
            src.close()
            if writer is not None:
                writer.close(decode=s.decoder.stats.as_dict(),
                             **({"stopped_by": stop.name} if stop.requested else {}))
        summary = s.finish()
        stopped_by = stop.name or ("SIGINT" if interrupted else None)
        summary.update(port=port, protocol=protocol, interrupted=interrupted or stop.requested, source=src.state,
                       capture=None if record is None else str(record), stopped_by=stopped_by,
                       capture_error=capture_error,
                       capture_bytes=None if writer is None else writer.bytes_written)
        out = _finish_run(s, summary, reference=reference, reference_units=reference_units, camera=camera,
                          report_dir=report_dir, reference_offset=reference_offset)
        if on_update is not None:
            on_update(s.snapshot(src.state))
        return out
