"""Benchmark and accuracy study of ``layoutkit.pnp.solve_pnp`` against OpenCV (issue #2 part 8, issue 30 item 1).

What it measures, on the reconstructed Chen target (12 sensors, 12.5 x 12.5 x 6.25 cm) and on
bodies of 24 and 48 sensors in the same box, at random poses 1-3 m in front of the station, inside
the 120 deg field of view, with the paper's angle noise (sigma = 4.014e-5 rad):

1. accuracy: RMS attitude / position error of the batch solver over many frames at rho = 0,
   divided by the Cramer-Rao bound sqrt(mean(ADOP^2)) sigma, sqrt(mean(PDOP^2)) sigma
   (``layoutkit.dop.pose_dop`` at the true poses);
2. robustness: gross failures (attitude error > 1 deg, or a lit sensor behind the station) at
   n = 12 (rho = 0 and rho = 0.8717), at n = 4 coplanar (the top face turned towards the
   station) and at n = 5-6 lit sensors (sensors whose normal is within 60 deg of the direction
   to the station), compared with OpenCV SQPNP (and ITERATIVE) on the same frames;
3. speed at n = 4 (the coplanar top face), 6, 12, 24, 48: solves/s of the compiled solver
   (``lm``, numba, on all of numba's threads and on one), of the numpy reference (``lm-numpy``) and
   of Python loops over ``cv2.solvePnP`` with SOLVEPNP_SQPNP and SOLVEPNP_ITERATIVE on the same
   frames (one OpenCV thread), interleaved rounds, median of >= 5; the ratios to both loops and
   RMS/CRLB of every method at every n;
4. the FLOP ratio at n = 12 (:func:`flop_ratio_rounds`): time per solve (CPU time of a one-thread
   ``solve_pnp`` of 50,000 frames) over the time the solver's arithmetic would take at this core's
   peak, median of 7 rounds, each round against the peak measured just before it (the VM's
   throughput moves ~1.4x over minutes). The arithmetic is the typical path's count (:func:`pnp_flops`,
   ~4.9 kflop at n = 12: POSIT, one Gram build, two residual passes; transcendental calls not
   counted); the peak is a compiled loop of independent scalar multiply-add chains
   (:func:`scalar_peak_flops`), the rate scalar per-frame code can reach;
5. the joint (several stations) solve's speed on one thread (:func:`joint_speed`: Crazyflie deck, two
   calibrated LH2 stations) against its numpy reference in the same run;
6. peak memory (tracemalloc) of a large batch.

Run ``python benchmarks/bench_pnp.py`` (a few minutes) or ``--quick`` (well under a minute).
Writes ``benchmarks/results/pnp.json`` (``pnp_quick.json`` with ``--quick``). The machine's load
changes every figure; run the full benchmark on a quiet machine (the JSON records the load average).
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from layoutkit.dop import gross_failures as dop_gross_failures
from layoutkit.dop import pose_dop
from layoutkit.geometry import attitude_error, random_rotations, rotvec_to_matrix, transform_points
from layoutkit.lighthouse import in_field_of_view, sweep_angles
from layoutkit.noise import sample_angle_noise
from layoutkit.units import RHO_PAPER, SIGMA_THETA_PAPER
from layoutkit.pnp import solve_pnp
from layoutkit.shapes import chen_target

RESULTS = Path(__file__).resolve().parent / "results"
FACING_DEG = 60.0


# ------------------------------------------------------------------------------- frame sets

def sample_positions(F, points_body, rotations, rng, dmin=1.0, dmax=3.0):
    """Translations (F, 3) m: distance U(dmin, dmax), direction such that every sensor is in the FOV."""
    t = np.empty((F, 3))
    todo = np.arange(F)
    while todo.size:
        d = rng.uniform(dmin, dmax, todo.size)
        v = rng.standard_normal((todo.size, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        cand = v * d[:, None]
        ok = np.all(in_field_of_view(transform_points(rotations[todo], cand, points_body)), axis=1)
        t[todo[ok]] = cand[ok]
        todo = todo[~ok]
    return t


def facing(layout, R, t):
    """(F, n) bool: sensor normal within FACING_DEG of the direction to the station."""
    n_lh = np.einsum("fij,nj->fni", R, layout.normals)
    p = transform_points(R, t, layout.positions)
    to_station = -p / np.linalg.norm(p, axis=-1, keepdims=True)
    return np.einsum("fni,fni->fn", n_lh, to_station) >= np.cos(np.deg2rad(FACING_DEG))


def frames_all(layout, F, rng):
    """n = 12: uniform random attitudes, all sensors used."""
    R = random_rotations(F, rng)
    t = sample_positions(F, layout.positions, R, rng)
    return R, t, np.ones((F, len(layout.ids)), bool)


def frames_lit(layout, F, rng, want, subset=None):
    """Frames whose lit set (facing sensors, restricted to ``subset``) has a size in ``want``."""
    Rs, ts, vs = [], [], []
    have = 0
    n = len(layout.ids)
    allowed = np.zeros(n, bool)
    allowed[subset if subset is not None else slice(None)] = True
    while have < F:
        m = 4 * (F - have) + 64
        R = random_rotations(m, rng)
        t = sample_positions(m, layout.positions, R, rng)
        v = facing(layout, R, t) & allowed
        k = v.sum(1)
        ok = np.isin(k, want)
        Rs.append(R[ok]), ts.append(t[ok]), vs.append(v[ok])
        have += int(ok.sum())
    return np.concatenate(Rs)[:F], np.concatenate(ts)[:F], np.concatenate(vs)[:F]


def measure(layout, R, t, rho, rng):
    ang = sweep_angles(transform_points(R, t, layout.positions))
    return ang + sample_angle_noise(ang.shape[:-1], SIGMA_THETA_PAPER, rho, rng)


# ------------------------------------------------------------------------------- solvers

def solve_cv(P, ang, vis, flag, scale=1000.0):
    """Python loop over cv2.solvePnP on normalised coordinates (K = I, no distortion).

    Object points are passed multiplied by ``scale`` and the translation is converted back.
    OpenCV's solvers are not scale invariant: SQPnP (absolute tolerances) returns wrong poses for
    the 4 coplanar top sensors with the object in metres even without noise (204 of 300 frames
    measured) and works in millimetres; ITERATIVE (DLT start) is the other way round at n = 12.
    The benchmark gives each method the unit it works best in and also reports the other.
    """
    import cv2

    F = ang.shape[0]
    uv = np.cos(ang) / np.sin(ang)
    K = np.eye(3)
    rv = np.full((F, 3), np.nan)
    ts = np.full((F, 3), np.nan)
    allvis = bool(vis.all())
    Pc = np.ascontiguousarray(P * scale)
    for f in range(F):
        if allvis:
            obj, img = Pc, uv[f]
        else:
            obj, img = Pc[vis[f]], uv[f][vis[f]]
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=flag)
        except cv2.error:
            ok = False
        if ok:
            rv[f] = rvec[:, 0]
            ts[f] = tvec[:, 0]
    # rotation vectors → matrices after the loop (vectorised; keeps the loop to solvePnP itself)
    good = np.all(np.isfinite(rv), axis=1)
    Rs = np.full((F, 3, 3), np.nan)
    Rs[good] = rotvec_to_matrix(rv[good])
    return Rs, ts / scale


def gross_failures(P, R_est, t_est, R, vis):
    """Count frames with attitude error > 1 deg, a lit sensor at z <= 0, or no solution."""
    bad = ~np.all(np.isfinite(R_est), axis=(1, 2))
    e = np.full(len(R), np.inf)
    e[~bad] = attitude_error(R_est[~bad], R[~bad])
    z = transform_points(np.nan_to_num(R_est), np.nan_to_num(t_est), P)[..., 2]
    behind = np.any((z <= 0) & vis, axis=1)
    return int(np.sum(dop_gross_failures(e, success=~(bad | behind))))


def crlb_ratio(P, R_est, t_est, R, t):
    dop = pose_dop(P, R, t, rho=0.0)
    att = np.sqrt(np.mean(attitude_error(R_est, R) ** 2))
    pos = np.sqrt(np.mean(np.sum((t_est - t) ** 2, axis=1)))
    att_b = np.sqrt(np.mean(dop.adop ** 2)) * np.deg2rad(SIGMA_THETA_PAPER)
    pos_b = np.sqrt(np.mean(dop.pdop ** 2)) * SIGMA_THETA_PAPER
    return {"rms_attitude_deg": float(np.rad2deg(att)), "crlb_attitude_deg": float(np.rad2deg(att_b)),
            "attitude_rms_over_crlb": float(att / att_b), "rms_position_m": float(pos),
            "crlb_position_m": float(pos_b), "position_rms_over_crlb": float(pos / pos_b)}


def plot_efficiency(P, R, t, results, path, bins=10):
    """RMS attitude / position error per decile of the predicted error, against the prediction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    H = pose_dop(P, R, t, rho=0.0).cov * SIGMA_THETA_PAPER ** 2
    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for ax, sl, scale, unit, name in ((axes[0], slice(0, 3), np.rad2deg(1.0), "deg", "attitude"),
                                      (axes[1], slice(3, 6), 1e3, "mm", "position")):
        pred = np.sqrt(np.trace(H[:, sl, sl], axis1=1, axis2=2)) * scale
        edges = np.quantile(pred, np.linspace(0, 1, bins + 1))
        which = np.clip(np.searchsorted(edges, pred, side="right") - 1, 0, bins - 1)
        px = np.array([np.sqrt(np.mean(pred[which == b] ** 2)) for b in range(bins)])
        ax.plot([px.min() * 0.9, px.max() * 1.1], [px.min() * 0.9, px.max() * 1.1], "k--", lw=1,
                label="Cramér–Rao bound")
        for (label, (Re, te)), mk in zip(results.items(), "os^"):
            if name == "attitude":
                err = attitude_error(np.nan_to_num(Re), R) * scale
            else:
                err = np.linalg.norm(np.nan_to_num(te) - t, axis=1) * scale
            y = np.array([np.sqrt(np.mean(err[which == b] ** 2)) for b in range(bins)])
            ax.plot(px, y, mk, ms=5, label=label, alpha=0.8)
        ax.set_xlabel(f"predicted RMS {name} error [{unit}] (decile of frames)")
        ax.set_ylabel(f"measured RMS {name} error [{unit}]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"PnP on the Chen target, n = 12, sigma = {SIGMA_THETA_PAPER:.3g} rad, {len(R)} frames")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------- speed by n

SPEED_N = (4, 6, 12, 24, 48)


def speed_body(n, layout):
    """(points (n, 3), normals or None) of the speed runs: n = 4 the Chen top face (coplanar), 6 a
    non-coplanar subset of the Chen sensors, 12 the Chen target, 24 / 48 points uniform in the same
    12.5 x 12.5 x 6.25 cm box (fixed seed)."""
    if n == 4:
        return layout.positions[[i for i, s in enumerate(layout.ids) if s.startswith("T")]]
    if n == 6:
        return layout.positions[[0, 1, 2, 3, 4, 8]]
    if n == 12:
        return layout.positions
    return np.random.default_rng(1000 + n).uniform(-0.0625, 0.0625, (n, 3)) * [1.0, 1.0, 0.5]


def speed_at(n, layout, F, rounds, rng, cv2):
    """Every method on the same F frames of the n-sensor body (all sensors seen), interleaved rounds."""
    import numba

    P = speed_body(n, layout)
    R = random_rotations(F, rng)
    t = sample_positions(F, P, R, rng)
    ang = sweep_angles(transform_points(R, t, P))
    ang = ang + sample_angle_noise(ang.shape[:-1], SIGMA_THETA_PAPER, 0.0, rng)
    vis = np.ones((F, n), bool)
    threads = numba.get_num_threads()

    def compiled():
        r = solve_pnp(P, ang, method="lm")
        return r.rotation, r.translation

    def compiled_1thread():
        numba.set_num_threads(1)
        try:
            return compiled()
        finally:
            numba.set_num_threads(threads)

    def numpy_ref():
        r = solve_pnp(P, ang, method="lm-numpy")
        return r.rotation, r.translation

    methods = {"layoutkit": compiled, "layoutkit_1thread": compiled_1thread, "layoutkit_numpy": numpy_ref,
               "sqpnp_loop": lambda: solve_cv(P, ang, vis, cv2.SOLVEPNP_SQPNP, 1000.0),
               "iterative_loop": lambda: solve_cv(P, ang, vis, cv2.SOLVEPNP_ITERATIVE, 1.0)}
    if n == 12:  # tracking start: the true pose moved by 0.5 deg, 5 mm (a slowly moving target's last pose)
        R_prev = np.matmul(rotvec_to_matrix(rng.normal(0.0, np.deg2rad(0.5) / np.sqrt(3), (F, 3))), R)
        t_prev = t + rng.normal(0.0, 0.005 / np.sqrt(3), (F, 3))

        def warm():
            r = solve_pnp(P, ang, initial=(R_prev, t_prev))
            return r.rotation, r.translation
        methods["layoutkit_previous_frame_start"] = warm
    compiled(), compiled_1thread()  # compile (or load the cache) outside the timing
    times = {k: [] for k in methods}
    cpu = {k: [] for k in methods}
    last = {}
    for _ in range(rounds):
        for k, f in methods.items():
            c0, t0 = time.process_time(), time.perf_counter()
            last[k] = f()
            times[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    row = {"frames": F, "rounds": rounds, "threads": threads}
    for k in methods:
        med = float(np.median(times[k]))
        Re, te = last[k]
        row[k] = {"median_s": med, "solves_per_s": F / med, "round_s": times[k],
                  "cpu_median_s": float(np.median(cpu[k])), "cpu_best_s": float(np.min(cpu[k])), "round_cpu_s": cpu[k],
                  "gross_failures": gross_failures(P, Re, te, R, vis),
                  **crlb_ratio(P, np.nan_to_num(Re), np.nan_to_num(te), R, t)}
    sq, it = row["sqpnp_loop"]["median_s"], row["iterative_loop"]["median_s"]
    row["ratio_vs_sqpnp"] = sq / row["layoutkit"]["median_s"]
    row["ratio_vs_sqpnp_1thread"] = sq / row["layoutkit_1thread"]["median_s"]
    row["ratio_vs_iterative"] = it / row["layoutkit"]["median_s"]
    row["ratio_vs_iterative_1thread"] = it / row["layoutkit_1thread"]["median_s"]
    row["numpy_ratio_vs_sqpnp"] = sq / row["layoutkit_numpy"]["median_s"]
    # the same on CPU time (one thread each): robust to other processes taking the cores
    c1, csq, cit = (row[k]["cpu_median_s"] for k in ("layoutkit_1thread", "sqpnp_loop", "iterative_loop"))
    row["cpu_ratio_vs_sqpnp_1thread"] = csq / c1
    row["cpu_ratio_vs_iterative_1thread"] = cit / c1
    # best rounds on CPU time: what each method costs when no other process takes its core (on a loaded
    # machine the medians include other processes' cache and core contention)
    b1, bsq, bit = (row[k]["cpu_best_s"] for k in ("layoutkit_1thread", "sqpnp_loop", "iterative_loop"))
    row["cpu_best_ratio_vs_sqpnp_1thread"] = bsq / b1
    row["cpu_best_ratio_vs_iterative_1thread"] = bit / b1
    return row, last, R, t


def pnp_flops(n: int) -> float:
    """Arithmetic (+, -, *, /, sqrt; not tan or atan2) of one solve with n sensors on the typical
    path of the LM solver (layoutkit.pnp_numba): cot of 2n angles, two scatters, POSIT (two
    iterations), one residual + gradient + Gram pass, the 6 x 6 factor and solve, the trial step, one
    residual + gradient pass, the step test with the reused factor. Per sensor: 2 + 2 x 25 + 66 +
    156 + 96 = 370; fixed: eigenvalues, POSIT's 3 x 3 algebra, Cholesky, two solves, Rodrigues ~550."""
    return 370.0 * n + 550.0


@functools.lru_cache(maxsize=None)
def _fma_chains():
    """The compiled loop of :func:`scalar_peak_flops` (compiled once per process)."""
    import numba

    @numba.njit(fastmath={"contract"})
    def chains(m, x):
        a0, a1, a2, a3, a4, a5, a6, a7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
        b, c = 0.9999999, 1e-9
        for _ in range(m):
            a0 = a0 * b + c
            a1 = a1 * b + c
            a2 = a2 * b + c
            a3 = a3 * b + c
            a4 = a4 * b + c
            a5 = a5 * b + c
            a6 = a6 * b + c
            a7 = a7 * b + c
        return a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7

    chains(10, np.ones(8))
    return chains


def scalar_peak_flops(seconds: float = 0.3) -> float:
    """This core's scalar double-precision peak (flop/s): a compiled loop of 8 independent
    multiply-add chains (fused where the CPU has FMA), best of 5 runs of ~``seconds``."""
    chains = _fma_chains()
    x = np.ones(8)
    m = 1_000_000
    t0 = time.perf_counter()
    chains(m, x)
    m = max(int(m * seconds / max(time.perf_counter() - t0, 1e-6)), 1000)
    best = np.inf
    for _ in range(5):
        t0 = time.process_time()
        chains(m, x)
        best = min(best, time.process_time() - t0)
    return 16.0 * m / best


def flop_ratio_rounds(P, F, rounds, rng) -> dict:
    """The FLOP ratio at n = len(P), each round paired with its own anchor: the scalar peak
    (:func:`scalar_peak_flops`, ~0.05 s x 5) measured just before a one-thread ``solve_pnp(method="lm")``
    of F noisy frames (all sensors seen; CPU time). This VM's throughput moves by up to ~1.4x over
    minutes; a round's ratio compares the solve with the peak of the same moment. Returns the per-round
    ratios, their median (the figure) and spread, seconds per solve and peaks."""
    import numba

    R = random_rotations(F, rng)
    t = sample_positions(F, P, R, rng)
    ang = sweep_angles(transform_points(R, t, P))
    ang = ang + sample_angle_noise(ang.shape[:-1], SIGMA_THETA_PAPER, 0.0, rng)
    flops = pnp_flops(len(P))
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        solve_pnp(P, ang[:100], method="lm")  # compiled (or the cache loaded) outside the timing
        ratios, per, peaks = [], [], []
        for _ in range(rounds):
            peak = scalar_peak_flops(0.05)
            c0 = time.process_time()
            solve_pnp(P, ang, method="lm")
            s = (time.process_time() - c0) / F
            ratios.append(s / (flops / peak))
            per.append(s)
            peaks.append(peak)
    finally:
        numba.set_num_threads(threads)
    return {"frames": F, "rounds": rounds, "flops_per_solve": flops, "round_ratio": ratios,
            "round_s_per_solve": per, "round_peak_flops_per_s": peaks,
            "flop_ratio_median": float(np.median(ratios)), "flop_ratio_min": float(np.min(ratios)),
            "flop_ratio_max": float(np.max(ratios)),
            "definition": "per round: CPU time per solve (one thread, F frames) / (pnp_flops / the scalar peak "
                          "measured just before it); median over the rounds"}


# ------------------------------------------------------------------------------- main

def joint_speed(F, rounds, rng):
    """The joint (several stations) solve, ``layoutkit.joint.solve_joint``, on one thread: the Crazyflie
    deck's 4 sensors (models/crazyflie_lighthouse_deck.layout.json) seen by two LH2 stations ~3 m
    away with factory-magnitude calibrations (phase 0.05, tilt 0.01, curve 0.003, gib / ogee 0.02 rad),
    angle noise 1e-4 rad; F frames, solves/s of the compiled kernel (``lm``: per-station starts, start
    selection and LM) and of its LM alone from given starts (the true pose moved by 0.5 deg, 5 mm),
    against the numpy reference (``lm-numpy``) in the same run (interleaved rounds, medians)."""
    import numba

    from layoutkit.geometry import look_at_rotation
    from layoutkit.layout import load_layout
    from layoutkit.joint import solve_joint
    from layoutkit.lighthouse import CALIBRATION_PARAMS, Calibration
    from layoutkit.simulate import simulate_station_angles, stations_looking_at

    P = load_layout(Path(__file__).resolve().parents[1] / "models" / "crazyflie_lighthouse_deck.layout.json").positions
    mag = {"phase": 0.05, "tilt": 0.01, "curve": 0.003, "gib_phase": np.pi, "gib_mag": 0.02, "ogee_phase": np.pi,
           "ogee_mag": 0.02}
    cals = [Calibration(np.array([[rng.uniform(-1, 1) * mag[k] for k in CALIBRATION_PARAMS] for _ in range(2)]),
                        "lh2", gib) for gib in ("ideal", "corrected")]
    sts = stations_looking_at([[-2.0, -1.0, 2.0], [2.0, -1.2, 2.0]], (0, 0, 0), kind="lh2", calibrations=cals)
    R = rotvec_to_matrix(rng.normal(0, 0.2, (F, 3))) @ look_at_rotation([0.0, 0.0, 1.0]).T
    t = rng.uniform(-0.3, 0.3, (F, 3))
    ang = simulate_station_angles(P, R, t, sts, sigma=1e-4, rho=0.0, rng=rng)
    R0 = np.matmul(rotvec_to_matrix(rng.normal(0.0, np.deg2rad(0.5) / np.sqrt(3), (F, 3))), R)
    t0 = t + rng.normal(0.0, 0.005 / np.sqrt(3), (F, 3))
    methods = {"compiled": lambda: solve_joint(P, ang, stations=sts),
               "compiled_lm_from_start": lambda: solve_joint(P, ang, stations=sts, initial=(R0, t0)),
               "numpy": lambda: solve_joint(P, ang, stations=sts, method="lm-numpy"),
               "numpy_lm_from_start": lambda: solve_joint(P, ang, stations=sts, initial=(R0, t0), method="lm-numpy")}
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        last = {k: f() for k, f in methods.items()}  # compile (or load the cache) outside the timing
        cpu = {k: [] for k in methods}
        for _ in range(rounds):
            for k, f in methods.items():
                c0 = time.process_time()
                last[k] = f()
                cpu[k].append(time.process_time() - c0)
    finally:
        numba.set_num_threads(threads)
    row = {"frames": F, "rounds": rounds, "threads": 1, "sensors": len(P), "stations": 2}
    for k in methods:
        med = float(np.median(cpu[k]))
        r = last[k]
        ok = r.success
        err = np.linalg.norm(r.translation[ok] - t[ok], axis=1)
        row[k] = {"cpu_median_s": med, "cpu_best_s": float(np.min(cpu[k])), "solves_per_s": F / med,
                  "round_cpu_s": cpu[k], "ok": int(ok.sum()), "iterations_mean": float(r.iterations[ok].mean()),
                  "position_rms_m": float(np.sqrt(np.mean(err ** 2)))}
    row["ratio_vs_numpy"] = row["numpy"]["cpu_median_s"] / row["compiled"]["cpu_median_s"]
    row["lm_ratio_vs_numpy"] = row["numpy_lm_from_start"]["cpu_median_s"] / row["compiled_lm_from_start"]["cpu_median_s"]
    return row


def print_joint(row):
    print(f"joint, deck + 2 LH2 stations, one thread: {row['compiled']['solves_per_s']:.0f} solves/s "
          f"({row['ratio_vs_numpy']:.1f}x the numpy reference), LM alone from a start "
          f"{row['compiled_lm_from_start']['solves_per_s']:.0f}/s ({row['lm_ratio_vs_numpy']:.1f}x); iterations "
          f"{row['compiled']['iterations_mean']:.2f}, ok {row['compiled']['ok']}/{row['frames']}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short run (a few seconds)")
    ap.add_argument("--seed", type=int, default=20240501)
    ap.add_argument("--out", type=Path, default=None, help="JSON output path")
    ap.add_argument("--figure", type=Path, default=None,
                    help="also write a PNG of RMS error vs the Cramer-Rao bound (e.g. docs/images/pnp_efficiency.png)")
    ap.add_argument("--joint-only", action="store_true",
                    help="only the joint solve's speed row (printed; written only with --out)")
    args = ap.parse_args(argv)
    if args.joint_only:
        row = joint_speed(2000 if args.quick else 10000, 5, np.random.default_rng(args.seed))
        print_joint(row)
        if args.out is not None:
            args.out.write_text(json.dumps({"joint": row}, indent=2))
        return row
    import cv2

    cv2.setNumThreads(1)
    rng = np.random.default_rng(args.seed)
    _, layout = chen_target()
    P = layout.positions
    q = args.quick
    n_acc = 20000 if q else 180000        # n = 12 accuracy / failure frames
    n_small = 2000 if q else 10000        # n = 4 and n = 5-6 frames
    n_speed = 2000 if q else 10000        # speed frames per n
    rounds = 5
    out = {"quick": q, "seed": args.seed, "sigma_theta_rad": SIGMA_THETA_PAPER,
           "machine": platform.platform(), "python": sys.version.split()[0],
           "numpy": np.__version__, "opencv": cv2.__version__}
    print(f"layoutkit PnP benchmark ({'quick' if q else 'full'}), Chen target n = 12")

    # 1 + 2: accuracy vs CRLB and gross failures at n = 12
    R, t, vis = frames_all(layout, n_acc, rng)
    acc = {}
    for rho in (0.0, RHO_PAPER):
        ang = measure(layout, R, t, rho, rng)
        t0 = time.perf_counter()
        res = solve_pnp(P, ang)
        dt = time.perf_counter() - t0
        key = f"rho={rho:g}"
        acc[key] = {"frames": n_acc, "gross_failures": gross_failures(P, res.rotation, res.translation, R, vis),
                    "success": int(res.success.sum()), "seconds": dt,
                    "iterations_hist": np.bincount(res.iterations).tolist()}
        if rho == 0.0:
            acc[key].update(crlb_ratio(P, res.rotation, res.translation, R, t))
        print(f"n=12 {key}: {n_acc} frames, gross failures {acc[key]['gross_failures']}, "
              f"success {acc[key]['success']}, "
              + (f"RMS/CRLB attitude {acc[key]['attitude_rms_over_crlb']:.4f}, position "
                 f"{acc[key]['position_rms_over_crlb']:.4f}" if rho == 0.0 else ""))
    out["n12"] = acc

    # 3: small lit sets, ours vs SQPNP (and ITERATIVE) on the same frames, paper noise
    small = {}
    top = [i for i, s in enumerate(layout.ids) if s.startswith("T")]
    for name, (want, subset) in {"n4_coplanar_top": ([4], top), "n5_6_facing": ([5, 6], None)}.items():
        Rs, ts, vs = frames_lit(layout, n_small, rng, want, subset)
        row = {"frames": n_small}
        for rho in (0.0, RHO_PAPER):
            ang = measure(layout, Rs, ts, rho, rng)
            r = solve_pnp(P, ang, vs)
            g = {"layoutkit": gross_failures(P, r.rotation, r.translation, Rs, vs)}
            # each OpenCV method with the object unit it works best in (see solve_cv), plus the other
            cands = [("sqpnp", cv2.SOLVEPNP_SQPNP, 1000.0), ("iterative", cv2.SOLVEPNP_ITERATIVE, 1.0),
                     ("sqpnp_object_in_metres", cv2.SOLVEPNP_SQPNP, 1.0),
                     ("iterative_object_in_mm", cv2.SOLVEPNP_ITERATIVE, 1000.0)]
            if name.startswith("n4_coplanar"):
                cands.append(("ippe", cv2.SOLVEPNP_IPPE, 1000.0))
            for cv_name, flag, scale in cands:
                Rc, tc = solve_cv(P, ang, vs, flag, scale)
                g[cv_name] = gross_failures(P, Rc, tc, Rs, vs)
            row[f"gross_failures_rho={rho:g}"] = g
            print(f"{name} rho={rho:g}: {n_small} frames, gross failures {g}")
        small[name] = row
    out["small_sets"] = small

    # 3: speed at n = 4, 6, 12, 24, 48 (same frames for every method), 4: FLOP ratio at n = 12
    speed = {}
    for n in SPEED_N:
        speed[f"n={n}"], last, R, t = speed_at(n, layout, n_speed, rounds, rng, cv2)
        s = speed[f"n={n}"]
        print(f"n={n:2d}: compiled {s['layoutkit']['solves_per_s']:9.0f}/s ({s['threads']} threads), one thread "
              f"{s['layoutkit_1thread']['solves_per_s']:9.0f}/s, numpy {s['layoutkit_numpy']['solves_per_s']:8.0f}/s, "
              f"SQPNP {s['sqpnp_loop']['solves_per_s']:7.0f}/s, ITERATIVE {s['iterative_loop']['solves_per_s']:7.0f}/s | "
              f"x SQPNP {s['ratio_vs_sqpnp']:.1f} (1 thread {s['ratio_vs_sqpnp_1thread']:.1f}), x ITERATIVE "
              f"{s['ratio_vs_iterative']:.1f} | RMS/CRLB att {s['layoutkit']['attitude_rms_over_crlb']:.3f} pos "
              f"{s['layoutkit']['position_rms_over_crlb']:.3f} | on CPU time, one thread: x SQPNP "
              f"{s['cpu_ratio_vs_sqpnp_1thread']:.1f}, x ITERATIVE {s['cpu_ratio_vs_iterative_1thread']:.1f} "
              f"(best rounds x SQPNP {s['cpu_best_ratio_vs_sqpnp_1thread']:.1f})")
        if n == 12:
            n12_last, n12_R, n12_t = last, R, t
    # 4: the FLOP ratio at n = 12, each round against the peak of the same moment, on enough frames
    # (50,000: ~50 ms a round) that the wrapper's fixed cost and the timer do not count
    fr = flop_ratio_rounds(P, 50000, 7, rng)
    wall = speed["n=12"]["layoutkit"]["median_s"] / n_speed
    peak = float(np.median(fr["round_peak_flops_per_s"]))
    f12 = fr["flops_per_solve"]
    out["flops"] = {"flops_per_solve_n12": f12, "scalar_peak_flops_per_s": peak,
                    "flop_limit_s_per_solve": f12 / peak,
                    "s_per_solve_one_core": float(np.median(fr["round_s_per_solve"])),
                    "s_per_solve_wall_all_threads": wall,
                    "flop_ratio_one_core": fr["flop_ratio_median"],
                    "flop_ratio_one_core_rounds": fr["round_ratio"],
                    "flop_ratio_one_core_best_round": fr["flop_ratio_min"],
                    "flop_ratio_wall_all_threads": wall / (f12 / peak),
                    "rounds": fr, "definition": fr["definition"]}
    print(f"FLOP ratio at n=12: {fr['flop_ratio_median']:.2f}x the limit on one core, median of {fr['rounds']} "
          f"rounds of {fr['frames']} frames each against the peak measured just before it "
          f"(rounds {fr['flop_ratio_min']:.2f}-{fr['flop_ratio_max']:.2f}x; {f12:.0f} flop per solve, peak "
          f"{peak / 1e9:.1f} GFLOP/s), {out['flops']['flop_ratio_wall_all_threads']:.1f}x in wall time on "
          f"{speed['n=12']['threads']} threads")
    # the n = 12 table of the earlier versions (same keys), and the tracking start
    R, t = n12_R, n12_t
    out["speed"] = {**speed["n=12"], "by_n": speed}
    if args.figure is not None:
        plot_efficiency(P, R, t, {"layoutkit (angle ML)": n12_last["layoutkit"], "OpenCV SQPNP": n12_last["sqpnp_loop"],
                                  "OpenCV ITERATIVE": n12_last["iterative_loop"]}, args.figure)
        print(f"wrote {os.path.relpath(args.figure)}")
    try:
        out["load_average_1_5_15min"] = list(os.getloadavg())
    except OSError:
        pass

    # the joint (several stations) solve on the same LM core, one thread
    out["joint"] = joint_speed(n_speed, rounds, rng)
    print_joint(out["joint"])

    # peak memory of one large batch (chunked, so flat in F)
    Fm = 50000 if q else 200000
    Rm, tm = R[np.arange(Fm) % len(R)], t[np.arange(Fm) % len(R)]
    angm = measure(layout, Rm, tm, 0.0, rng)
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    solve_pnp(P, angm)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    out["memory"] = {"frames": Fm, "input_mb": angm.nbytes / 1e6, "peak_tracemalloc_mb": peak / 1e6,
                     "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3}
    print(f"peak memory solving {Fm} frames: {peak / 1e6:.1f} MB above the {angm.nbytes / 1e6:.1f} MB input "
          f"(process max RSS {out['memory']['ru_maxrss_mb']:.0f} MB)")

    path = args.out or RESULTS / ("pnp_quick.json" if q else "pnp.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"wrote {os.path.relpath(path)}")
    return out


if __name__ == "__main__":
    main()
