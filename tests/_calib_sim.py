"""Simulated calibration captures shared by the calibrate tests and benchmark (known truth)."""
import numpy as np

from layoutkit.geometry import random_rotations, rotvec_to_matrix
from layoutkit.lighthouse import CALIBRATION_PARAMS, Calibration, Station
from layoutkit.simulate import simulate_station_angles, stations_looking_at

FACTORY_SCALE = {"phase": 0.05, "tilt": 0.01, "curve": 0.003, "gib_phase": np.pi, "gib_mag": 0.02,
                 "ogee_phase": np.pi, "ogee_mag": 0.02}
STATION_POSITIONS = [[-2.0, -1.0, 2.0], [2.0, -1.2, 2.0]]


def random_calibration(rng, kind, gib="ideal"):
    """Factory-magnitude parameters (uniform within FACTORY_SCALE); LH2: no common phase (it is the yaw)."""
    p = np.array([[rng.uniform(-1, 1) * FACTORY_SCALE[n] for n in CALIBRATION_PARAMS] for _ in range(2)])
    if kind == "lh1":
        p[:, 5:] = 0.0
    else:
        p[:, 0] -= p[:, 0].mean()
    return Calibration(p, kind, gib)


def sphere_layout(rng, n, radius=0.08):
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return radius * u, u


def capture(rng, *, kind="lh1", n=32, samples=200, sigma=2e-5, offset_rms=0.0, station_error=(0.01, 0.02)):
    """Truth stations (calibrated), start stations (zero calibration, station 1 pose perturbed), body
    samples with random attitudes in a 1 m cube, angles (K, S, n, 2) with facing visibility (cos > 0.2)."""
    truth = stations_looking_at(STATION_POSITIONS, (0, 0, 0), kind=kind,
                                calibrations=[random_calibration(rng, kind), random_calibration(rng, kind)])
    start = stations_looking_at(STATION_POSITIONS, (0, 0, 0), kind=kind)
    s1 = start[1]
    start[1] = Station(id="1", rotation=rotvec_to_matrix(rng.normal(0, station_error[0], 3)) @ s1.rotation,
                       translation=s1.translation + rng.normal(0, station_error[1], 3), kind=kind)
    P, N = sphere_layout(rng, n)
    offsets = rng.normal(0, offset_rms / np.sqrt(3), (n, 3)) if offset_rms else np.zeros((n, 3))
    cap = {"truth": truth, "start": start, "P": P, "N": N, "offsets": offsets, "sigma": sigma}
    cap["R"], cap["t"], cap["angles"] = observe(cap, rng, samples)
    return cap


def observe(cap, rng, samples):
    """New random body poses of a capture's set-up and their angles (truth stations, true sensors)."""
    P, N = cap["P"], cap["N"]
    R = random_rotations(samples, rng)
    t = rng.uniform(-0.5, 0.5, (samples, 3))
    a = simulate_station_angles(P + cap["offsets"], R, t, cap["truth"], sigma=cap["sigma"], rho=0.0, rng=rng)
    nw = np.einsum("kij,nj->kni", R, N)
    pw = np.einsum("kij,nj->kni", R, P) + t[:, None]
    for s, st in enumerate(cap["truth"]):
        d = st.translation - pw
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        a[:, s][~(np.sum(nw * d, -1) > 0.2)] = np.nan
    return R, t, a


def z_scores(res, cap, kind):
    """(estimate - truth) / std for every parameter reported 'ok' (calibration columns and offsets)."""
    from layoutkit.calibrate import _ba_names, station_to_ba

    z = []
    for p in res.parameters:
        w = p.name.split()
        if p.status != "ok" or p.std is None:
            continue
        if "axis" in p.name:
            s, ax = int(w[1]), int(w[3])
            names = _ba_names(kind)[ax]
            if w[4] not in names:
                continue
            tv = station_to_ba(cap["truth"][s].calibration.params, kind)[ax, names.index(w[4])]
            z.append((p.value - tv) / p.std)
        elif "offset" in p.name:
            z.append((p.value - cap["offsets"][int(w[1]), "xyz".index(w[3])]) / p.std)
    return np.asarray(z)
