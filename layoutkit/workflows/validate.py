"""``layoutkit validate``: Monte-Carlo of a layout over an envelope, compared with its DOP.

Observations are (pose, station) pairs of the envelope where the station lights at least
``min_lit`` sensors and the DOP is defined; frame ``f`` measures pair ``f mod U`` (every pair gets
the same number of frames, ±1). Each frame: true sweep angles from that station, correlated noise
(Chen eq. 19), counter quantisation, single-station PnP, error against truth. The frames run in
chunks as Dask tasks (:func:`validate_chunk`, seeds from ``SeedSequence(seed).spawn``) and stream
into :class:`layoutkit.montecarlo.ErrorSums` plus per-pair sums, so memory is flat in the frame
count (it grows with the envelope: three floats per pair).

Compared: the RMS attitude/position error over all frames against ``sqrt(mean ADOP²)·σθ`` (eq. 24)
over the same frames, and per pair the RMS error against ADOP·σθ (the distribution of ratios).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..units import RAD2DEG

__all__ = ["prepare_validation", "validate_chunk", "run_validate"]


def prepare_validation(layout, envelope, *, mesh=None, units="m", half_angle_deg=60.0, rho=0.0, min_lit=4):
    """Usable (pose, station) pairs with their station-frame poses, lit sets and DOP.

    Returns a dict of arrays: R (U, 3, 3), t (U, 3) body pose in the station frame; lit (U, n);
    station (U,) station index; pose (U,) pose index; adop (U,) deg/rad; pdop (U,) m/rad; plus
    ``poses`` (P), ``uncovered`` (poses no station covers), stations, rotor (S,), clock (S,).
    """
    from ..dop import pose_dop
    from ..visibility import envelope_visibility, facing_mask

    Rw, tw = envelope.poses()
    st = envelope.stations
    other = [s.id for s in st if s.kind != "lh1"]
    if other:
        raise ValueError(f"envelope: station(s) {other} are not LH1; validate simulates LH1 sweeps only")
    pos, nor = layout.positions, layout.normals
    if mesh is not None:
        vis = envelope_visibility(mesh, pos, nor, Rw, tw, st, sensor_half_angle_deg=half_angle_deg)
    else:  # convex body: facing + field of view, no occlusion
        vis = np.stack([facing_mask(pos, nor, *s.world_to_station(Rw, tw), half_angle_deg=half_angle_deg,
                                    fov_deg=s.fov_deg) for s in st], axis=1)
    parts = {k: [] for k in ("R", "t", "lit", "station", "pose", "adop", "pdop")}
    for si, s in enumerate(st):
        Rs, ts = s.world_to_station(Rw, tw)
        v = vis[:, si, :]
        ok = v.sum(1) >= min_lit
        if not ok.any():
            continue
        d = pose_dop(pos, Rs[ok], ts[ok], rho=rho, visible=v[ok])
        good = np.asarray(d.success, bool) & np.isfinite(d.adop) & np.isfinite(d.pdop)
        idx = np.flatnonzero(ok)[good]
        parts["R"].append(Rs[idx])
        parts["t"].append(ts[idx])
        parts["lit"].append(v[idx])
        parts["station"].append(np.full(len(idx), si))
        parts["pose"].append(idx)
        parts["adop"].append(np.asarray(d.adop)[good])
        parts["pdop"].append(np.asarray(d.pdop)[good])
    n = pos.shape[0]
    empty = {"R": np.zeros((0, 3, 3)), "t": np.zeros((0, 3)), "lit": np.zeros((0, n), bool)}
    out = {k: (np.concatenate(v) if v else empty.get(k, np.zeros(0))) for k, v in parts.items()}
    covered = np.zeros(len(Rw), bool)
    covered[out["pose"].astype(int)] = True
    out.update(poses=len(Rw), uncovered=np.flatnonzero(~covered), station_ids=[s.id for s in st],
               rotor=np.array([s.rotor_rpm for s in st]), clock=np.array([s.clock_hz for s in st]))
    return out


def validate_chunk(points, prep, sigma, rho, quantize, chunk):
    """Dask task: frames ``[chunk.start, chunk.start + chunk.count)`` → (ErrorSums, per-pair sums).

    Per-pair sums: ``(n (U,), sum|e|² (U,) rad², sum|d|² (U,) m²)`` over the good frames."""
    from ..montecarlo import ErrorSums, good_frames, simulate_solve

    U = len(prep["adop"])
    idx = (chunk.start + np.arange(chunk.count)) % U
    rng = chunk.rng()
    sums = ErrorSums()
    n_u, e2_u, d2_u = np.zeros(U, np.int64), np.zeros(U), np.zeros(U)
    for si in np.unique(prep["station"][idx]):
        sel = idx[prep["station"][idx] == si]
        e, d, solved = simulate_solve(points, prep["R"][sel], prep["t"][sel], prep["lit"][sel], sigma=sigma,
                                      rho=rho, rng=rng, quantize=quantize, rotor_rpm=float(prep["rotor"][si]),
                                      clock_hz=float(prep["clock"][si]))
        sums.add(e, d, solved, prep["adop"][sel], prep["pdop"][sel])
        good = good_frames(e, solved)
        g = sel[good]
        n_u += np.bincount(g, minlength=U)
        e2_u += np.bincount(g, weights=np.einsum("ij,ij->i", e[good], e[good]), minlength=U)
        d2_u += np.bincount(g, weights=np.einsum("ij,ij->i", d[good], d[good]), minlength=U)
    return sums, (n_u, e2_u, d2_u)


def run_validate(layout, envelope, frames, *, executor, sigma, rho, seed=0, mesh=None, units="m",
                 half_angle_deg=60.0, quantize=True, min_lit=4, chunk_frames=20000, progress=None) -> dict:
    """Monte-Carlo validation of ``layout`` over ``envelope`` with ``frames`` frames (module docstring).

    layout : :class:`Layout` or path; envelope : :class:`Envelope` or path; mesh : path, trimesh or
    None (convex: no occlusion). sigma : rad; executor : from :func:`layoutkit.parallel.open_executor`.
    Returns a JSON-able dict with ``status`` ("ok" or "no_coverage"), the overall comparison and the
    per-pair ratio distribution.
    """
    from ..envelope import Envelope, load_envelope
    from ..layout import Layout, load_layout
    from ..montecarlo import ErrorSums
    from ..parallel import chunk_plan, map_reduce_ordered

    lay = layout if isinstance(layout, Layout) else load_layout(layout)
    env = envelope if isinstance(envelope, Envelope) else load_envelope(envelope)
    if isinstance(mesh, (str, Path)):
        from ..mesh import load_mesh

        mesh = load_mesh(mesh, units)
    prep = prepare_validation(lay, env, mesh=mesh, half_angle_deg=half_angle_deg, rho=rho, min_lit=min_lit)
    U = len(prep["adop"])
    base = {"layout_sensors": lay.n, "poses": prep["poses"], "stations": prep["station_ids"],
            "pairs": U, "uncovered_poses": prep["uncovered"].tolist(), "frames_requested": int(frames),
            "sigma_rad": sigma, "rho": rho, "seed": seed, "chunk_frames": chunk_frames,
            "occlusion": mesh is not None}
    if U == 0:
        return {**base, "status": "no_coverage", "success": False,
                "message": f"no (pose, station) pair of the envelope has {min_lit} lit sensors: nothing to simulate"}
    shared = (lay.positions, executor.share({k: prep[k] for k in ("R", "t", "lit", "station", "adop", "pdop",
                                                                  "rotor", "clock")}), sigma, rho, quantize)

    def merge(acc, res):
        s, (n, e2, d2) = res
        return acc[0].merge(s), (acc[1][0] + n, acc[1][1] + e2, acc[1][2] + d2)

    init = (ErrorSums(), (np.zeros(U, np.int64), np.zeros(U), np.zeros(U)))
    sums, (n_u, e2_u, d2_u) = map_reduce_ordered(
        executor, validate_chunk, chunk_plan(frames, chunk_frames, seed), merge, init, shared_args=shared,
        progress=(lambda c, r: progress(c.count)) if progress else None, key="validate")
    overall = sums.as_dict(sigma)
    have = n_u >= 2
    with np.errstate(invalid="ignore", divide="ignore"):
        r_rot = np.sqrt(e2_u[have] / n_u[have]) * RAD2DEG / (prep["adop"][have] * sigma)
        r_t = np.sqrt(d2_u[have] / n_u[have]) / (prep["pdop"][have] * sigma)
    n_used = max(overall["frames_used"], 1)
    tol = max(5.0 / math.sqrt(2.0 * n_used), 0.02)  # 5 s.e. of an RMS over n frames (1 dof), 2 % floor
    agrees = bool(abs(overall.get("ratio_rot", np.nan) - 1) < tol and abs(overall.get("ratio_trans", np.nan) - 1) < tol)

    def q(a):
        return {f"p{p}": float(np.percentile(a, p)) for p in (5, 50, 95)} | {"max": float(a.max())} if len(a) else {}

    worst = np.argsort(-r_rot)[:5] if len(r_rot) else []
    pairs = np.flatnonzero(have)
    return {**base, "status": "ok", "success": True,
            "message": (f"RMS error / DOP prediction {overall['ratio_rot']:.3f} (attitude), "
                        f"{overall['ratio_trans']:.3f} (position) over {overall['frames_used']} frames; "
                        + ("agrees" if agrees else "DISAGREES") + f" with the DOP prediction to ±{100 * tol:.1f} %"),
            "agrees_with_dop": agrees, "tolerance": tol, "overall": overall,
            "dop_over_envelope": {"adop_deg_per_rad": q(prep["adop"]), "pdop_m_per_rad": q(prep["pdop"])},
            "per_pair_ratio": {"pairs_with_frames": int(have.sum()), "rot": q(r_rot), "trans": q(r_t),
                               "worst_rot": [{"pose": int(prep["pose"][pairs[i]]),
                                              "station": prep["station_ids"][int(prep["station"][pairs[i]])],
                                              "adop_deg_per_rad": float(prep["adop"][pairs[i]]),
                                              "ratio": float(r_rot[i]), "frames": int(n_u[pairs[i]])}
                                             for i in worst]}}
