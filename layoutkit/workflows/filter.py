"""The tracking filter in ``layoutkit replay / live / solve --filter ekf`` (docs/filter.md).

:func:`filter_config` turns the CLI's ``filter_settings`` into an :class:`~layoutkit.filter.EkfConfig`;
:class:`FilterSink` runs the filter beside the frame-by-frame pipeline of a live / replay session
(every decoded sweep in, one JSON line per sweep out, error statistics against a truth, the
filtered pose table); :func:`filter_frames` / :func:`filter_table` do the same for a frame table.
The simulated scenarios and benchmarks are in :mod:`layoutkit.studies.filter_scenarios`.
"""
from __future__ import annotations

import contextlib
import time

import numpy as np

from .. import status as _status
from ..filter import EkfConfig, SweepTracker
from ..filter.consistency import nees, pose_error
from ..filter.jsonline import json_line
from ..geometry import rotvec_to_matrix
from ..lighthouse import Station
from ..units import RAD2DEG

__all__ = ["filter_config", "FilterSink", "FILTER_STATUS_CODES", "filter_frames", "filter_table"]


def filter_config(settings: dict | None, sigma_theta: float, rho: float) -> EkfConfig | None:
    """EkfConfig from the CLI's ``filter_settings`` (see :func:`layoutkit.cli.options.filter_options`)
    and the run's noise model; None for ``--filter none``."""
    if settings is None:
        return None
    return EkfConfig(sigma_theta=sigma_theta, rho=rho, **settings)


class FilterSink:
    """The filter's side of a live / replay run: decoded sweeps in, one JSON line per sweep out,
    running error statistics against the truth (when given), a summary at the end.

    points_body : (n, 3) m; stations : the run's stations (None → one ideal LH1 station; a single
    station is used with an identity pose, so poses are in its frame as the pipeline's are);
    config : :class:`EkfConfig`; truth : optional :class:`layoutkit.live.reference.PoseTrack` in the
    same frame; json_out : text stream or None; poses_path : write every output to this pose table
    (status 0 ok / 13 uncertain / 14 lost, codes of :mod:`layoutkit.status`; extras ``cov_rot_deg_*``, ``cov_pos_m_*``; written
    atomically, complete when :meth:`close` / :meth:`summary` runs).
    Memory is flat: outputs are written as they come and only sums are kept.
    """

    def __init__(self, points_body, stations, config: EkfConfig, truth=None, json_out=None, poses_path=None):
        if not stations:
            sts = [Station()]
        elif len(stations) == 1:
            s0 = stations[0]
            sts = [Station(s0.id, np.eye(3), np.zeros(3), s0.kind, s0.rotor_rpm, s0.clock_hz, s0.fov_deg,
                           getattr(s0, "calibration", None))]
        else:
            sts = list(stations)
        self.tracker = self._tracker(points_body, sts, config)
        self.truth = truth
        self.json_out = json_out
        self.seconds = 0.0
        self.cpu_seconds = 0.0
        self.sweeps = 0
        self._poses = None
        if poses_path is not None:
            from ..io.poses import PoseWriter

            self._poses = PoseWriter(poses_path, [f"{k}_{a}" for k in ("cov_rot_deg", "cov_pos_m") for a in "xyz"])
        self._acc = {"n": 0, "e_rot2": 0.0, "e_pos2": 0.0, "s_rot2": 0.0, "s_pos2": 0.0, "nees": 0.0,
                     "max_z": 0.0, "within3": 0}

    def _tracker(self, points_body, stations, config: EkfConfig):
        """The per-sweep tracker the sink runs (the lighthouse-only :class:`SweepTracker`)."""
        return SweepTracker(points_body, stations, config)

    def feed(self, sweeps) -> list:
        """Run the filter over ``sweeps`` (decoded :class:`SweepMeasurement`); returns the outputs."""
        with self._timed():
            outs = []
            push, append, extend = self._push, outs.append, outs.extend
            for m in sweeps:
                self.sweeps += 1
                try:
                    o = push(m)
                except ValueError:  # a sweep of a station the set-up does not have, or of the wrong size
                    continue
                if type(o) is list:
                    extend(o)
                elif o is not None:
                    append(o)
        self._emit(outs)
        return outs

    def _push(self, m):
        """What one sweep makes final: an output, None, or a list of outputs (the smoother's)."""
        return self.tracker.push(m)

    @contextlib.contextmanager
    def _timed(self):
        """The filter's wall and CPU seconds, accumulated."""
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.seconds += time.perf_counter() - t0
            self.cpu_seconds += time.process_time() - c0

    def _emit(self, outs) -> None:
        """The outputs to the JSON lines, the truth statistics and the pose table."""
        if outs and self.json_out is not None:
            self.json_out.write("\n".join(map(json_line, outs)) + "\n")
            self.json_out.flush()
        if outs and self.truth is not None:
            self._compare(outs)
        if outs and self._poses is not None:
            self._poses.write(filter_table({
                "t": np.array([o.t for o in outs]), "rotvec": np.array([o.rotvec for o in outs]),
                "translation": np.array([o.translation for o in outs]),
                "status": np.array([FILTER_STATUS_CODES[o.status] for o in outs]),
                "cov_rot_deg": np.array([o.cov_rot_deg for o in outs]),
                "cov_pos_m": np.array([o.cov_pos_m for o in outs]), "station": np.array([o.station for o in outs])}))

    def close(self) -> None:
        """Finish the pose table (if any)."""
        if self._poses is not None:
            self._poses.close()
            self._poses = None

    def _compare(self, outs) -> None:
        ok = [o for o in outs if o.ok]
        if not ok:
            return
        t = np.array([o.t for o in ok])
        Rr, tr, v = self.truth.at(t)
        if not v.any() or tr is None:
            return
        idx = np.flatnonzero(v)
        rv = np.array([ok[i].rotvec for i in idx])
        p = np.array([ok[i].translation for i in idx])
        from ..geometry import matrix_to_rotvec

        e = np.concatenate([matrix_to_rotvec(Rr[idx] @ np.swapaxes(rotvec_to_matrix(rv), -1, -2)), tr[idx] - p], 1)
        cov = np.array([ok[i].pose_cov for i in idx])
        a = self._acc
        a["n"] += len(idx)
        a["e_rot2"] += float(np.sum(e[:, :3] ** 2))
        a["e_pos2"] += float(np.sum(e[:, 3:] ** 2))
        d = np.diagonal(cov, axis1=1, axis2=2)
        a["s_rot2"] += float(np.sum(d[:, :3]))
        a["s_pos2"] += float(np.sum(d[:, 3:]))
        from ..filter.consistency import nees

        a["nees"] += float(np.nansum(nees(e, cov)))
        z = np.abs(e) / np.sqrt(d)
        a["max_z"] = max(a["max_z"], float(z.max()))
        a["within3"] += int(np.sum(np.all(z <= 3.0, 1)))

    def summary(self, frame_truth: dict | None = None) -> dict:
        """Counters, throughput, and (with a truth) the filtered error vs the filter's covariance and
        vs the frame-by-frame DOP prediction (``frame_truth``: the pipeline's truth summary)."""
        self.close()
        c = self.tracker.counters.as_dict()
        out = {"counters": c, "share_ok": c["ok"] / c["sweeps"] if c["sweeps"] else 0.0,
               "filter_seconds": self.seconds, "filter_cpu_seconds": self.cpu_seconds,
               "sweeps_per_s": self.sweeps / self.seconds if self.seconds else None,
               "sweeps_per_cpu_s": self.sweeps / self.cpu_seconds if self.cpu_seconds else None,
               "angle_noise_rad": float(np.sqrt(getattr(self.tracker.ekf, "noise_scale", 1.0))
                                        * self.tracker.config.sigma_theta),
               "config": {k: getattr(self.tracker.config, k) for k in (
                   "psd_rot", "psd_pos", "constant_acceleration", "gate_angle_p", "gate_sweep_p", "zupt",
                   "hit_timing", "model", "sigma_theta", "rho")}}
        a = self._acc
        if a["n"]:
            n = a["n"]
            t = {"n": n, "rms_rot_deg": float(np.sqrt(a["e_rot2"] / n)) * RAD2DEG,
                 "rms_pos_m": float(np.sqrt(a["e_pos2"] / n)),
                 "cov_rms_rot_deg": float(np.sqrt(a["s_rot2"] / n)) * RAD2DEG,
                 "cov_rms_pos_m": float(np.sqrt(a["s_pos2"] / n)), "mean_nees_6dof": a["nees"] / n,
                 "max_error_over_sigma": a["max_z"], "share_within_3_sigma": a["within3"] / n}
            t["ratio_to_cov_rot"] = t["rms_rot_deg"] / t["cov_rms_rot_deg"]
            t["ratio_to_cov_pos"] = t["rms_pos_m"] / t["cov_rms_pos_m"]
            if frame_truth:
                t["frame_by_frame_rms_rot_deg"] = frame_truth.get("rms_rot_deg")
                t["frame_by_frame_rms_pos_m"] = frame_truth.get("rms_trans_m")
                t["frame_dop_predicted_rot_deg"] = frame_truth.get("predicted_rot_deg")
                t["frame_dop_predicted_pos_m"] = frame_truth.get("predicted_trans_m")
            out["truth"] = t
        return out


#: Pose-table status codes of filtered poses (``layoutkit solve --filter ekf --out``): 0 = ok.
#: The filter's statuses as codes of the one table (:mod:`layoutkit.status`): ok 0, uncertain 13, lost 14.
FILTER_STATUS_CODES = {"ok": _status.OK, "uncertain": _status.UNCERTAIN, "lost": _status.LOST}


def filter_frames(fr, layout, config: EkfConfig, stations=None) -> dict:
    """The filter over a frame table (:class:`layoutkit.workflows.frames.Frames`).

    stations : the set-up's :class:`Station` list (world poses, kinds, calibrations) when the
    table has a ``station`` column of several stations; None = one ideal LH1 station (poses in its
    frame, like the frame-by-frame solve).

    Each frame becomes its X and then its Y sweep, both at the frame's time stamp ``t`` (a frame
    table has no sub-frame timing, so ``hit_timing`` is off); the pose reported for the frame is
    the state after its Y sweep. Frames must be in time order (ValueError otherwise). Returns
    dict: t, rotvec (F, 3), translation (F, 3), status (F,) int (:data:`FILTER_STATUS_CODES`,
    -1 before the first start), cov_rot_deg, cov_pos_m (F, 3), counters, and with truth
    the filtered error vs the filter's own covariance.
    """
    from dataclasses import replace

    from ..filter.consistency import Sweep

    t = np.asarray(fr.t, float)
    if np.any(np.diff(t) < 0):
        raise ValueError("frames: time stamps t must be non-decreasing for --filter ekf")
    cfg = replace(config, hit_timing=False)
    st_idx = getattr(fr, "station", None)
    st_idx = np.zeros(len(t), int) if st_idx is None else np.asarray(st_idx, int)
    if stations is None:
        if np.any(st_idx != 0):
            raise ValueError("frames of several stations: the filter needs the stations' poses (--stations)")
        stations = [Station()]
    # a frame table holds LH1 angles [theta_x, theta_y] for every station (LH2 planes converted by the
    # importer): the LH1 model, with the station's calibration only where it is an LH1 one
    stations = [Station(st.id, st.rotation, st.translation, "lh1", st.rotor_rpm, st.clock_hz, st.fov_deg,
                        st.calibration if st.kind == "lh1" else None) for st in stations]
    trk = SweepTracker(layout.positions, stations, cfg)
    kinds = [st.kind for st in trk.stations]
    F = len(t)
    rv = np.full((F, 3), np.nan)
    tr = np.full((F, 3), np.nan)
    status = np.full(F, -1)
    srot = np.full((F, 3), np.nan)
    spos = np.full((F, 3), np.nan)
    cov = np.full((F, 6, 6), np.nan)
    for k in range(F):
        o = None
        for ax in (0, 1):
            o = trk.push(Sweep(float(t[k]), int(st_idx[k]), ax, fr.angles[k, :, ax], kinds[st_idx[k]])) or o
        if o is None:
            continue
        rv[k], tr[k], status[k] = o.rotvec, o.translation, FILTER_STATUS_CODES[o.status]
        srot[k], spos[k], cov[k] = o.cov_rot_deg, o.cov_pos_m, o.pose_cov
    out = {"frames": F, "ok": int(np.sum(status == 0)), "counters": trk.counters.as_dict(),
           "t": t, "rotvec": rv, "translation": tr, "status": status, "cov_rot_deg": srot, "cov_pos_m": spos}
    if fr.truth_rotation is not None:
        from ..geometry import matrix_to_rotvec

        ok = status == 0
        if ok.any():
            e = pose_error(rv[ok], tr[ok], matrix_to_rotvec(fr.truth_rotation[ok]), fr.truth_translation[ok])
            d = np.diagonal(cov[ok], axis1=1, axis2=2)
            out.update(filter_rms_rot_deg=float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1)))) * RAD2DEG,
                       filter_rms_pos_m=float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1)))),
                       filter_cov_rms_rot_deg=float(np.sqrt(np.mean(d[:, :3].sum(1)))) * RAD2DEG,
                       filter_cov_rms_pos_m=float(np.sqrt(np.mean(d[:, 3:].sum(1)))),
                       filter_mean_nees_6dof=float(np.nanmean(nees(e, cov[ok]))))
    return out


def filter_table(res: dict):
    """:func:`filter_frames` results as a pose table with extras ``cov_rot_deg_{x,y,z}``, ``cov_pos_m_{x,y,z}``."""
    from ..io.poses import PoseTable

    ex = {}
    for name, key in (("cov_rot_deg", "cov_rot_deg"), ("cov_pos_m", "cov_pos_m")):
        for i, ax in enumerate("xyz"):
            ex[f"{name}_{ax}"] = res[key][:, i]
    return PoseTable(res["t"], res["rotvec"], res["translation"], station=res.get("station"), status=res["status"],
                     extras=ex)


class ImuFilterSink(FilterSink):
    """:class:`FilterSink` with the IMU-aided filter (:class:`layoutkit.filter.imu_tracker.ImuSweepTracker`):
    the same outputs, JSON lines (keys of :meth:`layoutkit.filter.tracker.FilterOutput.record`), pose
    table and truth statistics; the summary adds ``imu`` (used, samples, rate, gravity, the filter's
    health: mean NIS per degree of freedom, sweeps rejected by the gate, restarts, the angle-noise
    scale). imu : :class:`layoutkit.io.imu.ImuSamples` on the sweeps' clock, IMU frame = the layout's
    frame. Needs the stations' world poses (two or more stations for a start).

    smooth : a :class:`layoutkit.filter.smoother.SmootherConfig` (``replay --smooth``): the outputs are
    the fixed-lag smoother's (delayed by up to twice its lag; gap poses between sweeps), the last ones
    when the sink is closed; the summary adds ``smoother`` (its counters, lag, seconds). None: the
    causal filter's outputs. (``share_ok`` and the counters stay the causal filter's; ``smoother.share_ok``
    is the share of the smoothed outputs, gap poses included, that are ok.)"""

    def __init__(self, points_body, stations, config: EkfConfig, imu, truth=None, json_out=None, poses_path=None,
                 imu_config=None, smooth=None):
        self.imu = imu
        self._imu_config = imu_config
        super().__init__(points_body, stations, config, truth, json_out, poses_path)
        self.smoother = None
        self.smooth_seconds = 0.0
        if smooth is not None:
            from ..filter.smoother import SmoothedImuTracker

            self.smoother = SmoothedImuTracker(self.tracker, smooth)

    def _push(self, m):
        return super()._push(m) if self.smoother is None else self.smoother.push(m)

    def close(self) -> None:
        if self.smoother is not None:  # the rest of the smoothed outputs, before the pose table closes
            with self._timed():
                outs = self.smoother.finish()
            self._emit(outs)
        super().close()

    def _tracker(self, points_body, stations, config: EkfConfig):
        from ..filter.imu_tracker import ImuSweepTracker

        imu = self.imu
        return ImuSweepTracker(points_body, stations, config, imu.t, imu.gyro, imu.acc, self._imu_config)

    def summary(self, frame_truth: dict | None = None) -> dict:
        trk = self.tracker
        out = super().summary(frame_truth)
        c = trk.counters.as_dict()
        out["share_ok"] = c["ok"] / c["sweeps"] if c["sweeps"] else 0.0
        out["angle_noise_rad"] = float(np.sqrt(trk.noise_scale) * trk.config.sigma_theta)
        judged = c["accepted"] + c["rejected"]
        out["imu"] = {"used": True, **self.imu.summary(), "gravity": trk.gravity,
                      "health": {"mean_nis_per_dof": c["mean_nis_per_dof"], "sweeps_accepted": c["accepted"],
                                 "sweeps_rejected_by_gate": c["rejected"],
                                 "share_rejected": c["rejected"] / judged if judged else None,
                                 "starts": c["inits"], "restarts": c["restarts"], "losts": c["losts"],
                                 "angle_noise_scale": trk.noise_scale,
                                 "gate_p": trk.fc.gate_p},
                      "config": {k: getattr(trk.fc, k) for k in ("gyro_noise", "acc_noise", "gyro_bias_walk",
                                                                 "acc_bias_walk", "gate_p")}
                      | {"imu_position_m": list(trk.ic.imu_position)},
                      "bias_acc_m_s2": None if trk.eskf is None else trk.eskf.ba.tolist(),
                      "bias_gyro_rad_s": None if trk.eskf is None else trk.eskf.bg.tolist()}
        if self.smoother is not None:
            sm = self.smoother
            c = sm.counters.as_dict()
            out["smoother"] = {"lag_s": sm.sc.lag_s, "gap_dt_s": sm.sc.gap_dt_s, **c,
                               "share_ok": c["ok"] / c["outputs"] if c["outputs"] else 0.0}
        return out
