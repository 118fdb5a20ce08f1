"""Live pose pipeline: decoded sweeps → paired angle frames → batched PnP → timestamped poses + DOP.

Why one module of ~630 lines: the stages below (pairing, batching, the chunk solve with its
motion compensation) pass per-station state to each other and to the one config class
:class:`LiveConfig`; they are read as one data flow. The continuity gate and the velocity estimate
are in :mod:`layoutkit.live.continuity`, the result type in :mod:`layoutkit.live.posechunk`, the
joint windows in :mod:`layoutkit.live.joint_stream`.

Data flow (design §3–§5, issue #5 part 4)::

    SweepMeasurement ─▶ SweepPairer ─▶ AngleFrame ─▶ FrameBatcher ─▶ solve_chunk ─▶ PoseChunk
     (one rotor sweep)  (X then Y of     (t, station,   (≤ chunk_frames or       (PnP + DOP,
                         one station)     angles (n,2))  ≤ chunk_seconds)          arrays over F)

Everything downstream of the pairer works on chunks of ``F`` frames with arrays ``(F, ...)`` so
that a live run keeps latency low (small chunks: ``chunk_seconds`` of frame time, or an explicit
:meth:`PosePipeline.flush` after every port read as ``layoutkit live`` does) and a replay is fast
(large chunks, ``chunk_frames``); no stage keeps more than one chunk in memory.

Frame time. A frame's ``t`` is the sync time of its X sweep (axis 0), in the decoder's time base
(seconds since the capture started, device clock) — the definition of the simulator's TRUTH.csv
(``docs/live-io.md``). Poses are in the station frame of a single station or, when the set-up
gives station poses, in the common world frame (design §2). The Y sweep comes 8.33 ms later; with
``LiveConfig.motion_compensation`` its angles are first moved to ``t`` with the body velocity
of the recent poses (``docs/live.md`` "Motion compensation"), otherwise the pose blends both times.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .. import status as _status
from .._validate import as_array
from ..geometry import matrix_to_rotvec
from ..lighthouse import LH1_ROTOR_RPM, Station, to_sweep_angles
from ..units import RHO_PAPER, SIGMA_THETA_PAPER
from .continuity import continuity_gate, motion_history, recent_velocity
from .frames import SweepMeasurement
from .joint_stream import JointWindower, solve_windows
from .posechunk import STATUS_NAMES, PoseChunk, empty_pose_arrays

__all__ = [
    "LiveConfig",
    "AngleFrame",
    "SweepPairer",
    "FrameBatcher",
    "motion_corrected_angles",
    "solve_chunk",
    "PosePipeline",
]

LH2_ROTOR_HZ_MIN = 48.0  # slowest LH2 channel (design §3: ~50–54 Hz)
#: ``LiveConfig.solve`` values (the CLI's ``--solve`` choices, :data:`layoutkit.cli.options.SOLVE_MODES`).
SOLVE_MODES = ("joint", "per-station")
#: ``LiveConfig.calibration`` values.
CALIBRATION_MODES = ("model", "undistort")


@dataclass(frozen=True)
class LiveConfig:
    """The ONE settings class of a live/replay run: pose pipeline and session sinks.

    n_sensors : sensors in the layout (length of ``SweepMeasurement.angles``); None = taken from
        the layout when the pipeline starts (:meth:`resolved`).
    min_lit : fewest sensors lit on both axes for a pose (PnP needs 4).
    chunk_frames, chunk_seconds : a chunk is solved when it holds ``chunk_frames`` frames or spans
        ``chunk_seconds`` of frame time, whichever comes first. Replay feeds large blocks and gets
        full chunks; a live session also solves what one port read completed
        (:meth:`layoutkit.live.session.LiveSession.flush_pending`), so its chunks stay small.
    rotor_rpm : LH1 rotor speed; an X sweep pairs with the next Y sweep of the same station
        within one rotor period (60 / rotor_rpm s; LH2: one revolution at >= 48 Hz). None = the
        first station's (:meth:`resolved`), :data:`~layoutkit.lighthouse.LH1_ROTOR_RPM` without stations.
    sigma_theta : rad, angle noise for predictions (Chen eq. 24); rho : same-rotor correlation (eq. 19).
    max_residual_sigma : a solved pose whose RMS angle residual exceeds this many sigma_theta is
        reported ``high_residual`` (never as good).
    max_rate_deg_s, max_speed_m_s, gate_sigma, reacquire_s : continuity gate. A pose further from
        the last good pose of its station than ``max_rate · dt + gate_sigma · predicted sigma``
        (attitude, and likewise position) is reported ``jump``: with 4-5 lit sensors a
        wrong PnP basin can fit the angles as well as the right one. After ``reacquire_s``
        without a good pose the next pose is accepted as is, and ``reacquire_frames`` consecutive
        jumped poses that agree with each other become the new track.
    motion_compensation : per-station: correct each frame's Y-sweep angles to its X-sweep time with
        the body velocity of the recent good poses (see :func:`solve_chunk`, ``docs/live.md`` "Motion
        compensation"; LH1 frames only); joint: model every station's and axis' angles at their own
        time in the window (:func:`layoutkit.live.joint_stream.solve_windows`). None (default) = on
        for ``solve="joint"`` (a flying deck's stations are measured up to 20 ms apart:
        benchmarks/results/joint_crazyflie.json), off per-station (a stream whose X and Y angles
        come from one pose, the static frame model of ``tests/test_live_pipeline.py``, is made
        worse by it); :meth:`resolved` fills it in.
    motion_window, motion_window_s : the velocity is the least-squares slope over the last
        ``motion_window`` good poses of the station (at least 3) within ``motion_window_s`` s of the
        frame, with no jump between consecutive ones; otherwise (first frames, after a gap, jump or
        re-acquisition) the frame is not corrected.
    motion_passes : correct-and-re-solve passes (the first estimates the velocity from uncorrected
        poses, the next ones from corrected ones).
    static_window : frames per static-detection window; static_factor : a window is static when
        its spread is within this factor of the predicted precision (Chen eq. 23 vs 24).
    series_capacity : points kept for plots (decimated series).
    filter : a :class:`layoutkit.filter.EkfConfig` to also run the per-sweep filter
        (``--filter ekf``; its outputs replace the frame records on ``--json-lines``), or None.
    solve : "per-station" (one pose per station frame, station or world frame) or "joint" (one
        world pose per window from every station's frame, :mod:`layoutkit.live.joint_stream`;
        needs station poses). The commands pick the default (joint when several stations are known).
    window_s : the joint window rule's span (s, :data:`layoutkit.joint.WINDOW_S`).
    max_sigma_position : m, the largest predicted 1-sigma position error (``PDOP · sigma_theta``,
        Chen eq. 24 with the run's sigma/rho, at the solved pose and lit set) of an ``ok`` pose; a
        solved pose above it is ``imprecise``. None (default): joint solving with two or more
        stations takes, per window, the geometric mean of what the best single station and all
        stations together would give at that pose with every sensor lit — so a one-station window of
        a small deck (range from a 3 cm baseline) is not ok, while a window that also has a few
        angles of a second station is (:func:`layoutkit.live.joint_stream.auto_sigma_limit`);
        per-station solving has no limit then.
    calibration : how a station calibration enters — "model": the decoder's measured (distorted)
        angles are fitted through the station's forward model :func:`layoutkit.lighthouse.measure`
        (joint, and per-station through :func:`layoutkit.pnp.solve_pnp` ``calibration=``);
        "undistort": the decoder pre-corrects the angles (firmware style, Bitcraze decoders with a
        system config) and the ideal model is fitted (the behaviour before the forward model).
    """

    n_sensors: int | None = None
    min_lit: int = 4
    chunk_frames: int = 1024
    chunk_seconds: float = float("inf")
    rotor_rpm: float | None = None
    sigma_theta: float = SIGMA_THETA_PAPER
    rho: float = RHO_PAPER
    max_residual_sigma: float = 8.0
    max_rate_deg_s: float = 360.0
    max_speed_m_s: float = 5.0
    gate_sigma: float = 6.0
    reacquire_s: float = 0.5
    reacquire_frames: int = 5
    motion_compensation: bool | None = None
    motion_window: int = 8
    motion_window_s: float = 0.25
    motion_passes: int = 2
    static_window: int = 120
    static_factor: float = 4.0
    series_capacity: int = 20000
    filter: object = None
    solve: str = "per-station"
    window_s: float = 0.020
    calibration: str = "model"
    max_sigma_position: float | None = None

    def __post_init__(self):
        if self.solve not in SOLVE_MODES:
            raise ValueError(f"solve: expected one of {SOLVE_MODES}, got {self.solve!r}")
        if self.calibration not in CALIBRATION_MODES:
            raise ValueError(f"calibration: expected one of {CALIBRATION_MODES}, got {self.calibration!r}")
        if self.max_sigma_position is not None and not self.max_sigma_position > 0:
            raise ValueError(f"max_sigma_position: expected > 0 m, got {self.max_sigma_position}")
        if not self.window_s > 0:
            raise ValueError(f"window_s: expected > 0 s, got {self.window_s}")
        if self.n_sensors is not None and self.n_sensors < 1:
            raise ValueError(f"n_sensors: expected >= 1, got {self.n_sensors}")
        if self.min_lit < 3:
            raise ValueError(f"min_lit: expected >= 3, got {self.min_lit}")
        if self.chunk_frames < 1:
            raise ValueError(f"chunk_frames: expected >= 1, got {self.chunk_frames}")
        if self.motion_passes < 1:
            raise ValueError(f"motion_passes: expected >= 1, got {self.motion_passes}")
        if self.motion_window < 3:
            raise ValueError(f"motion_window: expected >= 3, got {self.motion_window}")
        if self.rotor_rpm is not None and not self.rotor_rpm > 0:
            raise ValueError(f"rotor_rpm: expected > 0, got {self.rotor_rpm}")

    def resolved(self, n_sensors: int, stations=None) -> "LiveConfig":
        """This config with ``n_sensors`` and ``rotor_rpm`` filled in from the layout and stations.

        ValueError when ``n_sensors`` was set and differs from the layout's.
        """
        if self.n_sensors is not None and self.n_sensors != n_sensors:
            raise ValueError(f"points_body: expected shape ({self.n_sensors}, 3), got ({n_sensors}, 3)")
        rpm = self.rotor_rpm
        if rpm is None:
            rpm = float(stations[0].rotor_rpm) if stations else LH1_ROTOR_RPM
        mc = (self.solve == "joint") if self.motion_compensation is None else bool(self.motion_compensation)
        return replace(self, n_sensors=int(n_sensors), rotor_rpm=rpm, motion_compensation=mc)


@dataclass(frozen=True)
class AngleFrame:
    """One pose frame: both sweep angles of every sensor from one station.

    t : s, sync time of the X sweep; station : index; angles : (n, 2) rad [theta_x, theta_y]
    (LH1-equivalent, LH2 planes converted with the nominal tilt), NaN where a sensor was not hit
    on that axis; seq : X sweep's sequence number or None;
    dt_y : s, sync time of the Y sweep minus ``t`` (LH1; NaN for LH2 and when unknown).
    kind : the station kind of the sweeps ("lh1"/"lh2"); raw : (n, 2) rad, the decoder's angles in
    that kind's own convention (LH1 sweep angles, LH2 light-plane angles; as measured, i.e.
    distorted when the decoder does not pre-correct) — what a calibrated forward model takes.
    None = same as ``angles``. t_axes : (2,) s, when each axis was measured: LH1 the X and Y sync
    times; LH2 each light plane's crossing of the sensors, ``t + (mean alpha_k + pi -/+ pi/3) / 2 pi
    * period`` from the rotor zero ``t`` (None = both at ``t``).
    """

    t: float
    station: int
    angles: np.ndarray
    seq: int | None = None
    dt_y: float = float("nan")
    kind: str = "lh1"
    raw: np.ndarray | None = None
    t_axes: tuple | None = None

    @property
    def t_measured(self) -> float:
        """Mean measurement time of the two axes (s)."""
        return float(self.t) if self.t_axes is None else 0.5 * float(self.t_axes[0] + self.t_axes[1])


class SweepPairer:
    """Pairs the X (axis 0) and following Y (axis 1) sweep of each station into an :class:`AngleFrame`.

    A Y sweep pairs with the pending X sweep of its station when it arrives within one rotor
    period after it.
    Everything else — an X sweep replaced by a newer X, a Y with no pending X, a pair too far
    apart — is dropped and counted in ``unpaired``. State: one pending sweep per station.
    """

    def __init__(self, n_sensors: int, rotor_rpm: float = LH1_ROTOR_RPM, lh2_periods: dict | None = None):
        self.n_sensors = int(n_sensors)
        self.max_gap = {"lh1": 60.0 / rotor_rpm, "lh2": 1.0 / LH2_ROTOR_HZ_MIN}
        self.lh2_periods = dict(lh2_periods or {})   # station -> rotor period (s), default 1/50 s
        self._pending: dict[int, SweepMeasurement] = {}
        self.paired = 0
        self.unpaired = 0
        self.wrong_size = 0

    def push(self, m: SweepMeasurement) -> AngleFrame | None:
        """Add one sweep; return the completed frame or None."""
        ang = np.asarray(m.angles, dtype=float)
        if ang.shape != (self.n_sensors,):
            self.wrong_size += 1
            return None
        if m.axis == 0:
            if m.station in self._pending:
                self.unpaired += 1
            self._pending[m.station] = m
            return None
        x = self._pending.pop(m.station, None)
        if x is None:
            self.unpaired += 1
            return None
        gap = m.t - x.t
        if not (0.0 <= gap <= self.max_gap.get(m.kind, self.max_gap["lh1"])) or m.kind != x.kind:
            self.unpaired += 2  # both sweeps are lost
            return None
        raw = np.empty((self.n_sensors, 2))  # np.stack([x.angles, ang], -1) without its per-call overhead
        raw[:, 0] = x.angles
        raw[:, 1] = ang
        angles = to_sweep_angles(raw, m.kind)
        self.paired += 1
        if m.kind == "lh2":
            per = self.lh2_periods.get(int(m.station), 0.02)
            cnt = np.isfinite(raw).sum(0)   # a plane may be all NaN (one-plane rotations): no nanmean warning
            mean = np.where(cnt > 0, np.where(np.isfinite(raw), raw, 0.0).sum(0) / np.maximum(cnt, 1), 0.0)
            t_axes = (float(x.t + (mean[0] + np.pi - np.pi / 3) / (2 * np.pi) * per),
                      float(m.t + (mean[1] + np.pi + np.pi / 3) / (2 * np.pi) * per))
        else:
            t_axes = (float(x.t), float(m.t))
        return AngleFrame(t=float(x.t), station=int(m.station), angles=angles, seq=x.seq,
                          dt_y=float(gap) if m.kind == "lh1" else float("nan"), kind=m.kind,
                          raw=raw if m.kind == "lh2" else None, t_axes=t_axes)

    def flush(self) -> None:
        """End of stream: a still pending X sweep is unpaired."""
        self.unpaired += len(self._pending)
        self._pending.clear()


class FrameBatcher:
    """Collects :class:`AngleFrame` into chunks of at most ``chunk_frames`` frames spanning at most
    ``chunk_seconds`` of frame time. ``push`` returns a finished chunk (list of frames) or None."""

    def __init__(self, chunk_frames: int = 256, chunk_seconds: float = 0.05):
        self.chunk_frames = int(chunk_frames)
        self.chunk_seconds = float(chunk_seconds)
        self._frames: list[AngleFrame] = []

    def push(self, frame: AngleFrame) -> list[AngleFrame] | None:
        self._frames.append(frame)
        if (len(self._frames) >= self.chunk_frames
                or frame.t - self._frames[0].t >= self.chunk_seconds):
            return self.flush()
        return None

    def flush(self) -> list[AngleFrame] | None:
        if not self._frames:
            return None
        out, self._frames = self._frames, []
        return out


def _solver():
    from ..pnp import solve_pnp  # the core solver (layoutkit/pnp.py)

    return solve_pnp



def solve_chunk(points_body, frames: list[AngleFrame], config: LiveConfig,
                initial: dict | None = None, stations: "list[Station] | None" = None,
                calibrations: dict | None = None) -> PoseChunk:
    """Solve the poses of a chunk of frames (batched PnP, then batched DOP).

    points_body : (n, 3) m, sensor positions (body frame).
    frames : F frames; their stations may differ — each station's frames are solved in its own
        frame with ``layoutkit.pnp.solve_pnp``, started from ``initial[station] = (R, t)`` when given
        (the previous pose), and mapped to the world frame when ``stations`` are given.
    initial : dict station -> (R (3, 3), t (3,), time s); updated in place with the last good pose
        (also the reference of the continuity gate, see :class:`LiveConfig`), and with the
        recent poses per pass under ``("motion", station)`` when ``config.motion_compensation``:
        then the Y angles of every frame with a velocity estimate are moved to its X time and the
        frame is solved again (:func:`_compensate_motion`).
    calibrations : optional dict station index -> :class:`~layoutkit.lighthouse.Calibration`: that
        station's frames are fitted through its forward model from their ``raw`` (measured) angles
        (``solve_pnp(..., calibration=)``, cold start per frame; no Y-sweep motion correction) and
        their DOP comes from the model's Jacobian.
    Returns a :class:`PoseChunk`; failures are statuses, never exceptions.
    """
    P = as_array(points_body, "points_body", (None, 3))
    n = P.shape[0]
    F = len(frames)
    t = np.fromiter((f.t for f in frames), float, F)
    st = np.fromiter((f.station for f in frames), int, F)
    dty = np.fromiter((f.dt_y for f in frames), float, F)
    ang = np.stack([f.angles for f in frames]) if F else np.zeros((0, n, 2))
    lit = np.all(np.isfinite(ang), axis=-1)
    n_lit = lit.sum(-1)
    R, tr, res, status, adop, pdop = empty_pose_arrays(F)
    enough = n_lit >= config.min_lit
    solve_pnp = _solver()
    initial = {} if initial is None else initial
    calibrations = calibrations or {}
    for s in np.unique(st[enough]):
        idx = np.flatnonzero(enough & (st == s))
        a = np.where(lit[idx, :, None], ang[idx], np.pi / 2)  # placeholders never enter the fit
        init = initial.get(int(s))
        kw = {}
        cal = calibrations.get(int(s))
        if cal is not None and all(frames[i].kind == cal.kind for i in idx):
            # through the forward model: the measured angles in the station's own convention
            raw = np.stack([frames[i].angles if frames[i].raw is None else frames[i].raw for i in idx])
            kw["calibration"] = cal
            kw["raw"] = np.where(lit[idx, :, None], raw, 0.0)
        if init is not None and 0 <= t[idx[0]] - init[2] <= config.reacquire_s:
            kw["initial"] = (np.broadcast_to(init[0], (len(idx), 3, 3)),
                             np.broadcast_to(init[1], (len(idx), 3)))
        Rs, ts, ok, rr, ad, pd, stat = _solve_frames(solve_pnp, P, a, lit[idx], kw, config)
        if config.motion_compensation and "calibration" not in kw:
            (Rs, ts, ok, rr, ad, pd, stat), initial[("motion", int(s))] = _compensate_motion(
                solve_pnp, P, t[idx], dty[idx], a, lit[idx], (Rs, ts, ok, rr, ad, pd, stat), init,
                initial.get(("jump", int(s))), initial.get(("motion", int(s))), config)
        if config.max_sigma_position is not None:  # the user's precision limit (Chen eq. 24)
            stat = np.where((stat == _status.OK) & (pd * config.sigma_theta > config.max_sigma_position),
                            _status.IMPRECISE, stat)
        stat, cand = continuity_gate(t[idx], Rs, ts, stat, ad, pd, init, initial.get(("jump", int(s))), config)
        initial[("jump", int(s))] = cand
        if stations is not None:
            S = stations[int(s)]
            Rs = np.einsum("ij,fjk->fik", S.rotation, Rs)
            ts = ts @ S.rotation.T + S.translation
        R[idx], tr[idx], res[idx], status[idx] = Rs, ts, rr, stat
        adop[idx] = np.where(ok, ad, np.inf)
        pdop[idx] = np.where(ok, pd, np.inf)
        good = np.flatnonzero(stat == _status.OK)
        if good.size:
            j = idx[good[-1]]
            Rl, tl = R[j], tr[j]
            if stations is not None:  # keep the start in the station's own frame
                Rl, tl = S.rotation.T @ Rl, S.rotation.T @ (tl - S.translation)
            initial[int(s)] = (Rl.copy(), tl.copy(), float(t[j]))
    has = np.isfinite(R[:, 0, 0])
    rv = np.full((F, 3), np.nan)
    if has.any():
        rv[has] = matrix_to_rotvec(R[has])
    return PoseChunk(t=t, station=st, n_lit=n_lit, rotation=R, translation=tr, rotvec=rv,
                     status=status, residual_rms=res, adop=adop, pdop=pdop, lit=lit, sigma_theta=config.sigma_theta)


def _solve_frames(solve_pnp, P, a, lit, kw, config: LiveConfig, dop=None):
    """PnP + DOP + residual status of one station's frames: a (F, n, 2) rad, lit (F, n).

    dop : None, or ``(adop (F,), pdop (F,))`` to reuse instead of computing them (a re-solve
    whose pose moved by a fraction of a degree: the geometry, and so the DOP, is the same).
    Returns writable arrays ``(R (F, 3, 3), t (F, 3), ok (F,), residual_rms (F,) rad, adop (F,),
    pdop (F,), status (F,))`` (status before the continuity gate).
    kw ``calibration`` + ``raw`` (F, n, 2) (measured angles, the station's own convention): the fast
    PnP runs on the angles inverted through the calibration (its start, its planar-ambiguity test)
    and its pose is refined by :func:`layoutkit.joint.solve_joint` through the forward model — the
    residuals and the pose are the forward model's, an ambiguous frame stays ambiguous.
    """
    kw = dict(kw)
    cal, raw = kw.pop("calibration", None), kw.pop("raw", None)
    if cal is not None:
        a = np.where(lit[..., None], to_sweep_angles(np.where(lit[..., None], raw, np.nan), cal.kind, cal), np.pi / 2)
    sol = solve_pnp(P, a, lit, sigma=config.sigma_theta, rho=config.rho, **kw)
    ok = np.array(sol.success, bool)
    Rs, ts = np.array(sol.rotation, float), np.array(sol.translation, float)
    rr = np.array(sol.residual_rms, float)
    status0 = np.asarray(sol.status)
    if cal is not None:
        from ..joint import solve_joint

        go = np.flatnonzero(np.all(np.isfinite(Rs), (1, 2)) & np.all(np.isfinite(ts), 1))
        if go.size:
            ref = solve_joint(P, raw[go][:, None], lit[go][:, None],
                              stations=[Station(kind=cal.kind, calibration=cal)], initial=(Rs[go], ts[go]))
            took = np.isfinite(np.asarray(ref.rotation)[:, 0, 0])
            k = go[took]
            Rs[k], ts[k], rr[k] = np.asarray(ref.rotation)[took], np.asarray(ref.translation)[took], \
                np.asarray(ref.residual_rms)[took]
            st_ref = np.asarray(ref.status)[took]
            status0 = status0.copy()
            status0[k] = np.where(status0[k] == _status.AMBIGUOUS, _status.AMBIGUOUS, st_ref)
            ok = status0 == _status.OK
            bad = go[~took]
            ok[bad] = False
        sol = type(sol)(Rs, ts, ok, status0, rr, sol.iterations)
    if dop is not None:
        ad, pd = np.array(dop[0]), np.array(dop[1])
    else:
        ad, pd = _dop(P, Rs, ts, ok, lit, config, cal)
    st0 = np.asarray(sol.status)  # ambiguous and low-redundancy poses keep their names (layoutkit.status)
    failed = np.where(np.isin(st0, (_status.AMBIGUOUS, _status.LOW_REDUNDANCY)), st0, _status.SOLVER_FAILED)
    stat = np.where(~ok, failed,
                    np.where(rr > config.max_residual_sigma * config.sigma_theta, _status.HIGH_RESIDUAL, _status.OK))
    return Rs, ts, ok, rr, ad, pd, stat


def _dop(P, R, t, ok, lit, config: LiveConfig, calibration=None):
    """ADOP (F,) deg/rad and PDOP (F,) m/rad at poses R (F, 3, 3), t (F, 3) (placeholder where not ok);
    with a ``calibration`` through that station model's Jacobian (station frame)."""
    from ..dop import pose_dop

    st = None if calibration is None else [Station(kind=calibration.kind, calibration=calibration)]
    d = pose_dop(P, np.where(ok[:, None, None], R, np.eye(3)), np.where(ok[:, None], t, [0, 0, 1.0]),
                 rho=config.rho, visible=lit if st is None else lit[:, None], stations=st)
    return np.array(d.adop, float), np.array(d.pdop, float)


def _compensate_motion(solve_pnp, P, t, dt_y, angles, lit, first, last, cand, history, config: LiveConfig):
    """Motion-compensated poses of one station's frames (see :class:`LiveConfig`).

    t (F,) s, dt_y (F,) s (Y sync − X sync; NaN = no correction), angles (F, n, 2) rad, lit (F, n);
    first = the uncorrected solution (arrays as from :func:`_solve_frames`); last, cand: the
    continuity gate's state; history: None or, per pass, the station's previous poses of that pass
    (:func:`~layoutkit.live.continuity.motion_history`).
    Pass i (``motion_passes`` of them): velocity of every frame from the pass-i poses that the gate
    accepts (:func:`~layoutkit.live.continuity.recent_velocity`, after the pass-i history), Y angles moved to the X time
    (:func:`motion_corrected_angles` at the pass-i pose), PnP started from the pass-i pose → the
    pass-(i+1) poses. Pass 1 uses uncorrected poses, whose X/Y-blend bias shifts with the geometry
    (~1 % of the rate); pass 2 re-estimates from corrected ones. Each pass's velocity comes from
    poses of that same pass only, so the result does not depend on chunking.
    Frames without a velocity, or whose re-solve fails, keep the previous pass's solution.
    Returns ``(arrays of first, updated; new history)``.
    """
    cur = tuple(np.array(x) for x in first)
    new_history = []
    moved = np.zeros(t.size, bool)
    for i in range(config.motion_passes):
        Rs, ts, ok, _, ad, pd, stat = cur
        gated, _ = continuity_gate(t, Rs, ts, stat, ad, pd, last, cand, config)
        h = None if history is None else history[i]
        w, v = recent_velocity(t, Rs, ts, gated == _status.OK, ad, pd, h, config)
        new_history.append(motion_history(h, t, Rs, ts, gated == _status.OK, ad, pd, config.motion_window))
        fix = np.flatnonzero(ok & np.isfinite(w[:, 0]) & np.isfinite(dt_y))
        if fix.size == 0:
            continue
        a2 = motion_corrected_angles(P, Rs[fix], ts[fix], w[fix], v[fix], dt_y[fix], angles[fix])
        out = _solve_frames(solve_pnp, P, a2, lit[fix], {"initial": (Rs[fix], ts[fix])}, config,
                            dop=(ad[fix], pd[fix]))
        nxt = tuple(x.copy() for x in cur)
        for arr, new in zip(nxt, out):
            arr[fix[out[2]]] = new[out[2]]
        cur = nxt
        moved[fix[out[2]]] = True
    if moved.any():  # the reported DOP is at the final pose
        Rs, ts, ok, _, ad, pd, _ = cur
        k = np.flatnonzero(moved)
        ad[k], pd[k] = _dop(P, Rs[k], ts[k], ok[k], lit[k], config)
    return cur, new_history


def motion_corrected_angles(points_body, rotation, translation, omega, velocity, dt, angles) -> np.ndarray:
    """Y-sweep angles moved from the Y sweep's time to the X sweep's time (constant velocity).

    points_body : (n, 3) m; rotation (F, 3, 3), translation (F, 3) m: the pose at the X time
    (station frame, ``p = R p_body + t``); omega (F, 3) rad/s, velocity (F, 3) m/s: body velocity,
    ``R(t_x + dt) = exp([omega dt]x) R``, ``t(t_x + dt) = t + velocity dt`` (the left perturbation of
    design §5, both in the station frame); dt (F,) s = Y sync time − X sync time;
    angles (F, n, 2) rad ``[theta_x, theta_y]`` (theta_x is returned unchanged).
    Returns (F, n, 2) rad with ``theta_y + theta_y(pose at t_x) - theta_y(pose at t_x + dt)``, both
    predicted with :func:`layoutkit.lighthouse.sweep_angles` — to first order the
    ``- (d theta_y / d psi) psi``, ``psi = (omega dt, velocity dt)``, of
    :func:`layoutkit.dop.angle_jacobian`, without the linearisation. An error ``e`` of the given
    pose changes the correction by ``O(|e| |psi|)`` only.
    """
    from ..geometry import rotvec_to_matrix
    from ..lighthouse import sweep_angles

    dt = np.asarray(dt, float)[:, None]
    p = np.asarray(points_body, float)
    lever = np.einsum("fij,nj->fni", rotation, p)
    moved = np.einsum("fij,fnj->fni", rotvec_to_matrix(omega * dt), lever) + (translation + velocity * dt)[:, None]
    out = np.array(angles, float)
    out[..., 1] += sweep_angles(lever + translation[:, None, :])[..., 1] - sweep_angles(moved)[..., 1]
    return out


@dataclass
class PipelineCounters:
    """Running counters of the pipeline (frames, not sweeps)."""

    frames: int = 0
    good: int = 0
    bad: int = 0
    too_few_lit: int = 0
    unpaired_sweeps: int = 0
    by_status: dict = field(default_factory=dict)          # status name -> poses
    windows_by_stations: dict = field(default_factory=dict)  # joint: stations in the window -> windows
    unknown_station_frames: int = 0                         # joint: frames of a station not in the set-up
    late_frames: int = 0                                     # joint: frames older than one already windowed

    def as_dict(self) -> dict:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.__dict__.items()}


@dataclass
class PosePipeline:
    """Stateful glue: sweeps in, :class:`PoseChunk` out (one pending chunk, one pose per station).

    Usage::

        pipe = PosePipeline(layout.positions, LiveConfig())
        for chunk in pipe.feed(decoder.feed(data)): ...
        for chunk in pipe.flush(): ...
    """

    points_body: np.ndarray
    config: LiveConfig
    stations: "list[Station] | None" = None
    counters: PipelineCounters = field(default_factory=PipelineCounters)
    calibrations: dict | None = None

    def __post_init__(self):
        self.points_body = as_array(self.points_body, "points_body", (None, 3))
        self.config = self.config.resolved(self.points_body.shape[0], self.stations)
        lh2 = {k: 60.0 / st.rotor_rpm for k, st in enumerate(self.stations or ()) if st.kind == "lh2"}
        self.pairer = SweepPairer(self.config.n_sensors, self.config.rotor_rpm, lh2)
        self.batcher = FrameBatcher(self.config.chunk_frames, self.config.chunk_seconds)
        self.previous: dict = {}
        self.windower = None
        if self.config.solve == "joint":
            if not self.stations:
                raise ValueError("solve 'joint': station poses are required (a stations file, the capture's "
                                 "sidecar stations or a system config's geometry)")
            self.windower = JointWindower(len(self.stations), self.config.window_s)
            self.window_batcher = FrameBatcher(self.config.chunk_frames, self.config.chunk_seconds)

    def feed(self, sweeps) -> list[PoseChunk]:
        """Add decoded sweeps; return the chunks completed by them (possibly none)."""
        out = []
        for m in sweeps:
            fr = self.pairer.push(m)
            if fr is not None:
                out += self.feed_frames((fr,))
        self.counters.unpaired_sweeps = self.pairer.unpaired
        return out

    def feed_frames(self, frames) -> list[PoseChunk]:
        """Add already paired :class:`AngleFrame` s (a source that gives whole frames, e.g. a
        Crazyflie log's sweep-angle events, :mod:`layoutkit.live.cf_events`); return the chunks
        completed by them."""
        out = []
        for fr in frames:
            if self.windower is not None:
                for w in self.windower.push(fr):
                    batch = self.window_batcher.push(w)
                    if batch is not None:
                        out.append(self._solve(batch))
                continue
            batch = self.batcher.push(fr)
            if batch is not None:
                out.append(self._solve(batch))
        return out

    def flush(self, end_of_stream: bool = False) -> list[PoseChunk]:
        """Solve the pending frames now (live: on a timer; end of stream: ``end_of_stream=True``).

        Joint: the windows closed so far are solved; an open window (and frames in the reorder
        buffer) wait for the next frames unless ``end_of_stream``."""
        if end_of_stream:
            self.pairer.flush()
            self.counters.unpaired_sweeps = self.pairer.unpaired
        if self.windower is not None:
            out = []
            for w in (self.windower.flush() if end_of_stream else []):
                batch = self.window_batcher.push(w)
                if batch is not None:
                    out.append(self._solve(batch))
            batch = self.window_batcher.flush()
            self.counters.unknown_station_frames = self.windower.unknown_station
            self.counters.late_frames = self.windower.late
            return out + ([] if batch is None else [self._solve(batch)])
        batch = self.batcher.flush()
        return [] if batch is None else [self._solve(batch)]

    def _solve(self, frames) -> PoseChunk:
        if self.windower is not None:
            ch = solve_windows(self.points_body, frames, self.config, self.stations, self.previous)
        else:
            ch = solve_chunk(self.points_body, frames, self.config, self.previous, self.stations, self.calibrations)
        c = self.counters
        if self.windower is not None:
            c.unknown_station_frames, c.late_frames = self.windower.unknown_station, self.windower.late
        c.frames += len(ch)
        g = int(np.sum(ch.good))
        c.good += g
        c.bad += len(ch) - g
        c.too_few_lit += int(np.sum(ch.status == _status.TOO_FEW_LIT))
        for code in np.unique(ch.status):
            name = STATUS_NAMES[int(code)]
            c.by_status[name] = c.by_status.get(name, 0) + int(np.sum(ch.status == code))
        if ch.n_stations is not None:
            for k in np.unique(ch.n_stations):
                c.windows_by_stations[int(k)] = c.windows_by_stations.get(int(k), 0) + int(np.sum(ch.n_stations == k))
        return ch
