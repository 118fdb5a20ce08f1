"""A live or replay run in memory: decoder set-up, pose pipeline and sinks (JSON lines, the
poses table, static-group precision, truth errors, decimated series for the report).

:class:`LiveSession` takes bytes and gives :class:`~layoutkit.live.posechunk.PoseChunk` s; it is
configured by ONE :class:`~layoutkit.live.pipeline.LiveConfig`. :func:`make_decoder` builds the
registered decoder from the station set-up (:data:`layoutkit.live.protocols.PROTOCOLS`), and
:func:`session_for` a whole session from a :class:`RunSetup` (the run's frozen configuration; a
capture's sidecar records it). What a command does with files
(reading captures, ports, reference files, writing reports) is :mod:`layoutkit.workflows.live`.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..geometry import rotvec_to_matrix
from ..io.poses import POSE_COLUMNS, PoseTable, PoseWriter
from ..io.sidecar import CaptureSidecar
from ..layout import Layout
from .pipeline import LiveConfig, PosePipeline
from .posechunk import STATUS_NAMES, PoseChunk
from .stats import DecimatedSeries, ErrorAccumulator, StaticGroupTracker

__all__ = ["LiveSession", "POSES_EXTRAS", "POSES_HEADER", "PoseStore", "RunSetup", "config_record", "make_decoder",
           "session_for", "calibrated_setup"]

#: Extra columns of ``poses.csv`` after the pose table's fixed ones (:mod:`layoutkit.io.poses`).
POSES_EXTRAS = ("n_lit", "adop_deg_per_rad", "pdop_m_per_rad")
POSES_HEADER = list(POSE_COLUMNS + POSES_EXTRAS)


@dataclass
class LiveSession:
    """Decoder + pipeline + sinks for one run. Feed bytes, get pose chunks; ``finish`` summarises.

    layout : the sensor layout; decoder : a protocol decoder (``feed``, ``flush``, ``stats``;
    :func:`make_decoder`); options : the run's :class:`LiveConfig` (sensor count and rotor speed
    are filled in from ``layout`` and ``stations``); stations : station set-up (poses in station
    0's frame when None or a single station); truth : optional
    :class:`layoutkit.live.reference.PoseTrack` in the pipeline's frame (TRUTH.csv); json_out :
    text stream receiving one JSON object per solved frame; poses_path : pose table of all frames
    (:mod:`layoutkit.io.poses`, extras :data:`POSES_EXTRAS`; appears complete at :meth:`finish`);
    sweep_sink : optional per-sweep consumer (``feed(sweeps)``, ``summary(truth_summary)``; the EKF's
    :class:`layoutkit.workflows.filter.FilterSink` when ``options.filter`` is set): it sees every
    decoded sweep, its outputs replace the frame records on ``json_out`` and its summary goes
    under ``"filter"``. calibrations : optional dict station index -> Calibration for stations
    without a known pose (per-station solving through the forward model, ``options.calibration ==
    "model"``); stations' own calibrations are used too. columns : column joiners (``names``,
    ``join(chunk) -> {name: (F,)}``, ``summary()``; e.g. :class:`layoutkit.live.firmware.FirmwareComparison`):
    their columns are written into the pose table beside the pose, their summaries go under
    :attr:`column_summaries`. keep_good : keep every good pose in memory (:class:`PoseStore`,
    72 bytes a pose) for a comparison after the run (references aligned from the whole run).
    """

    layout: Layout
    decoder: object
    options: LiveConfig = field(default_factory=LiveConfig)
    stations: list | None = None
    truth: object = None
    json_out: object = None
    poses_path: Path | None = None
    sweep_sink: object = None
    calibrations: dict | None = None
    columns: tuple = ()
    keep_good: bool = False

    def __post_init__(self):
        self.options = o = self.options.resolved(self.layout.n, self.stations)
        self.config = o  # the pipeline runs on the same config
        multi = self.stations is not None and (len(self.stations) > 1 or o.solve == "joint")
        cals = None
        if o.calibration == "model":
            cals = dict(self.calibrations or {})
            for k, st in enumerate(self.stations or ()):
                if st.calibration is not None:
                    cals.setdefault(k, st.calibration)
            cals = cals or None
        self.pipeline = PosePipeline(self.layout.positions, self.config, self.stations if multi else None,
                                     calibrations=cals)
        self.static = StaticGroupTracker(o.sigma_theta, o.static_window, o.static_factor)
        self.truth_err = ErrorAccumulator(o.sigma_theta, o.series_capacity) if self.truth is not None else None
        # decimated good poses (t, rotvec, translation) for reference alignment, and DOP series for plots
        self.pose_sample = DecimatedSeries(8, o.series_capacity)  # t, rotvec, translation, adop
        self.dop_series = DecimatedSeries(4, o.series_capacity)  # t, adop, pdop, n_lit
        self._poses = None
        if self.poses_path is not None:
            self.poses_path = Path(self.poses_path)
            self.poses_path.parent.mkdir(parents=True, exist_ok=True)
            self._poses = PoseWriter(self.poses_path, POSES_EXTRAS + tuple(n for c in self.columns for n in c.names))
        self.good_poses = PoseStore() if self.keep_good else None
        self.wall_start = time.monotonic()
        self.t_first = None
        self.t_last = None
        self.last = None  # last good pose record (for the dashboard)
        self.lit_sum = 0
        self.frames_in_rate = []  # (wall time, frames) samples over the last few seconds
        self.finished = None
        self.filter = self.sweep_sink

    # -- feeding ----------------------------------------------------------------------------
    def feed_bytes(self, data: bytes) -> list[PoseChunk]:
        """Decode ``data`` and solve whatever frames complete a chunk (and filter every sweep)."""
        return self._consume(self.pipeline.feed(self._filtered(self.decoder.feed(data))))

    def feed_sweeps(self, sweeps) -> list[PoseChunk]:
        """Solve already decoded sweeps (a capture decoded before, e.g. by a refining replay's first
        pass) exactly as :meth:`feed_bytes` would after decoding them."""
        return self._consume(self.pipeline.feed(self._filtered(sweeps)))

    def feed_frames(self, frames) -> list[PoseChunk]:
        """Solve already paired frames (:meth:`PosePipeline.feed_frames`; the per-sweep filter, which
        needs sweeps, does not see them)."""
        return self._consume(self.pipeline.feed_frames(frames))

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
        joined = {}
        for c in self.columns:
            joined.update(c.join(ch))
        if self._poses is not None:
            self._poses.write(PoseTable(ch.t, ch.rotvec, ch.translation, ch.station, ch.status, ch.residual_rms, {
                "n_lit": ch.n_lit, "adop_deg_per_rad": np.where(np.isfinite(ch.adop), ch.adop, np.nan),
                "pdop_m_per_rad": np.where(np.isfinite(ch.pdop), ch.pdop, np.nan), **joined}))
        g = ch.good
        self.dop_series.extend(np.column_stack([ch.t, np.where(g, ch.adop, np.nan),
                                                np.where(g, ch.pdop, np.nan), ch.n_lit]))
        if not g.any():
            return
        t, R, tr, a, p = ch.t[g], ch.rotation[g], ch.translation[g], ch.adop[g], ch.pdop[g]
        if self.good_poses is not None:
            self.good_poses.append(t, ch.rotvec[g], tr, a, p)
        self.pose_sample.extend(np.column_stack([t, ch.rotvec[g], tr, a]))
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
            "max_sigma_position_m": self.options.max_sigma_position if self.options.max_sigma_position is not None
            else ("auto: per window, the geometric mean of the best single station's and all stations' predicted "
                  "1-sigma position at that pose" if self.options.solve == "joint" and len(self.stations or ()) >= 2
                  else None),
            "static_groups": [g.as_dict() for g in groups],
            "truth": None if self.truth_err is None or self.truth_err.n == 0 else self.truth_err.summary().as_dict(),
            "status_names": STATUS_NAMES,
            "by_status": dict(c.by_status),
            "solve": self.options.solve,
            "calibration": {"mode": self.options.calibration,
                            "stations_with_calibration": sorted(self.pipeline.calibrations or {})
                            if self.options.solve == "per-station" else
                            [k for k, st in enumerate(self.stations or ()) if st.calibration is not None]},
        }
        if self.options.solve == "joint":
            self.finished["joint"] = {
                "poses": c.frames, "good": c.good, "window_s": self.options.window_s,
                "windows_by_stations": {str(k): v for k, v in sorted(c.windows_by_stations.items())},
                "frames_of_unknown_station": c.unknown_station_frames, "late_frames": c.late_frames,
                "stations": len(self.stations or ()),
                "motion_compensation": bool(self.options.motion_compensation),
                "frame": "world (the stations' common frame)"}
        if self.filter is not None:
            self.finished["filter"] = self.filter.summary(self.finished["truth"])
        return self.finished

    @property
    def column_summaries(self) -> list:
        """The column joiners' summaries (after :meth:`finish`)."""
        return [c.summary() for c in self.columns]

    def pose_track(self):
        """The decimated good poses as a :class:`PoseTrack` (for reference alignment), or None."""
        from ..live.reference import PoseTrack

        a = self.pose_sample.array()
        if len(a) < 3:
            return None
        a = a[np.concatenate([[True], np.diff(a[:, 0]) > 0])]
        return PoseTrack(a[:, 0], rotvec_to_matrix(a[:, 1:4]), a[:, 4:7])


class PoseStore:
    """Every good pose of a run, in memory (append-only chunks): ``t (N,)`` s, ``rotvec (N, 3)``
    rad, ``translation (N, 3)`` m, ``adop (N,)`` deg/rad, ``pdop (N,)`` m/rad — 72 bytes a pose."""

    def __init__(self):
        self._chunks = []

    def append(self, t, rotvec, translation, adop, pdop) -> None:
        self._chunks.append(np.column_stack([t, rotvec, translation, adop, pdop]))

    def __len__(self) -> int:
        return sum(len(c) for c in self._chunks)

    def chunks(self):
        """Yield ``(t, rotvec, translation, adop, pdop)`` per stored chunk, in time order of arrival."""
        for c in self._chunks:
            yield c[:, 0], c[:, 1:4], c[:, 4:7], c[:, 7], c[:, 8]


def make_decoder(protocol: str, n_sensors: int, stations=None, options: dict | None = None):
    """The registered decoder ``protocol`` for ``n_sensors``: options from the stations (rotor,
    clock; :meth:`~layoutkit.live.protocols.ProtocolEntry.make_decoder`) overridden by ``options``."""
    from .protocols import protocol_entry

    return protocol_entry(protocol).make_decoder(n_sensors, stations, options)


@dataclass(frozen=True)
class RunSetup:
    """The configuration of one live / replay run: what its bytes are decoded and solved with.

    Frozen and resolved once (files read once, objects passed on): built from the command's
    arguments (``live``) or from a capture's sidecar and the arguments (``replay``,
    :meth:`from_sidecar`). A capture records it (:meth:`sidecar`); the sidecar is a record, not
    the configuration.

    layout : the :class:`Layout`. protocol : a registered protocol name
    (:data:`layoutkit.live.protocols.PROTOCOLS`). protocol_options : decoder options as recorded
    (JSON values: clock offset, ...). stations : tuple of :class:`~layoutkit.lighthouse.Station`
    (world poses; empty = unknown). system_config : the Crazyflie system configuration
    (:class:`layoutkit.io.systemconfig.SystemConfig`, read once) whose calibrations the run uses,
    or None. config : the run's :class:`LiveConfig`.
    """

    layout: Layout
    protocol: str = "layoutkit"
    protocol_options: dict = field(default_factory=dict)
    stations: tuple = ()
    system_config: object = None
    config: LiveConfig = field(default_factory=LiveConfig)

    def __post_init__(self):
        opts = dict(self.protocol_options or {})
        opts.pop("system_config", None)  # the loaded object is the run's; the path is a record
        object.__setattr__(self, "protocol_options", opts)
        object.__setattr__(self, "stations", tuple(self.stations or ()))

    @classmethod
    def from_sidecar(cls, sidecar, layout: Layout, *, protocol: str | None = None, config: LiveConfig | None = None,
                     stations=None, system_config=None) -> "RunSetup":
        """The run a capture's sidecar describes, with the command's overrides: ``protocol``,
        ``stations`` (replace the sidecar's when given), ``system_config`` (a loaded
        :class:`~layoutkit.io.systemconfig.SystemConfig`; default: the file the sidecar names, read
        here once)."""
        sc = CaptureSidecar.from_dict(sidecar or {})
        cfg = system_config
        if cfg is None and sc.protocol_options.get("system_config"):
            from ..io.systemconfig import read_system_config

            cfg = read_system_config(sc.protocol_options["system_config"])
        return cls(layout, protocol or sc.protocol or "layoutkit", sc.protocol_options,
                   tuple(stations) if stations else sc.stations, cfg, config or LiveConfig())

    def sidecar(self, **fields) -> CaptureSidecar:
        """The capture sidecar that records this run (``fields``: port, source, ... of
        :class:`~layoutkit.io.sidecar.CaptureSidecar`); the settings go under ``live_config``."""
        opts = dict(self.protocol_options)
        if self.system_config is not None and getattr(self.system_config, "source", None):
            opts["system_config"] = self.system_config.source
        extra = dict(fields.pop("extra", {}) or {})
        extra.setdefault("live_config", config_record(self.config))
        return CaptureSidecar(protocol=self.protocol, protocol_options=opts, stations=self.stations,
                              layout=self.layout.to_dict(), extra=extra, **fields)


def config_record(config: LiveConfig) -> dict:
    """A :class:`LiveConfig` as plain JSON values (what a capture records of its run)."""
    from dataclasses import asdict, fields as dc_fields, is_dataclass

    out = {}
    for f in dc_fields(config):
        v = getattr(config, f.name)
        out[f.name] = asdict(v) if is_dataclass(v) else v
    return out


def session_for(setup: RunSetup, *, truth=None, json_out=None, poses_path=None, sweep_sink=None, columns=(),
                keep_good: bool = False) -> LiveSession:
    """A :class:`LiveSession` for a :class:`RunSetup`: the stations and decoder options of its
    calibration mode (:func:`calibrated_setup`), the registered decoder. truth : a
    :class:`~layoutkit.live.reference.PoseTrack` or None; ``sweep_sink``, ``columns``,
    ``keep_good`` as :class:`LiveSession`."""
    stations, dec_options, cals = calibrated_setup(setup)
    dec = make_decoder(setup.protocol, setup.layout.n, stations or None, dec_options)
    return LiveSession(setup.layout, dec, setup.config, stations or None, truth, json_out, poses_path, sweep_sink,
                       calibrations=cals, columns=tuple(columns), keep_good=keep_good)


def calibrated_setup(setup: RunSetup):
    """Stations and decoder options of a run for its calibration mode (:class:`LiveConfig`
    ``calibration``); no file is read (the system config is the setup's object).

    "model": the system config gives its calibrations to the stations of the same index that have
    none, and the decoder is told not to pre-correct (``calibrate=False``: it emits the measured
    angles, the solvers fit them through :func:`layoutkit.lighthouse.measure`). "undistort": the
    stations lose their calibrations and the decoder corrects the angles with the system config's
    (the Bitcraze decoders' firmware-style inverse; the ``layoutkit`` protocol then solves
    uncalibrated). Returns ``(stations (list), decoder options, calibrations)`` with
    ``calibrations`` a dict station index -> :class:`~layoutkit.lighthouse.Calibration` (also for
    stations without a known pose: the per-station solve needs no pose) or None.
    """
    stations = list(setup.stations)
    opts = dict(setup.protocol_options)
    cfg = setup.system_config
    if cfg is not None:
        opts["system_config"] = cfg  # the decoders take the loaded object
    if setup.config.calibration == "undistort":
        return [replace(st, calibration=None) for st in stations], opts, None
    cals = {k: st.calibration for k, st in enumerate(stations) if st.calibration is not None}
    if cfg is not None:
        kind = "lh1" if cfg.system_type == 1 else "lh2"
        for sid, cal in cfg.calibs.items():
            if sid < len(stations):
                if stations[sid].calibration is None and stations[sid].kind == kind:
                    stations[sid] = replace(stations[sid], calibration=cal.to_calibration(kind))
                    cals[sid] = stations[sid].calibration
            else:
                cals.setdefault(sid, cal.to_calibration(kind))
        opts["calibrate"] = False
    return stations, opts, (cals or None)
