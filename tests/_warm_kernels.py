"""Compile the package's numba kernels once, in two processes, before the test workers start.

A fresh checkout has no numba cache (``cache=True`` writes it beside the modules on first use): each
pytest-xdist worker then compiles every kernel it meets, both workers the same kernels at the same time
(~1 min of CPU each on 2 cores). ``tests/conftest.py`` runs this file twice instead, one disjoint group
per process, through the same public calls the suite makes, so the specialisations cached here are the
ones the tests load. Usage: ``python tests/_warm_kernels.py pose|filter`` (a second run only loads).

- ``pose``: single-station PnP (the serial and the threaded batch), then the joint solve's start costs
  (its frame kernel is cached by then).
- ``filter``: the joint solve's frame kernel (from given starts: no PnP), then the IMM filter step and
  its station Jacobians, the fused DOP kernel, the optimiser's per-pose kernels and the IMU-aided
  filter's kernels.
(Compilation CPU measured in a fresh clone, both groups at once: 33 s / 39 s; 55 s / 34 s once the PnP
kernel's per-frame calls were inlined (issue 30), which puts ~20 s more into each PnP specialisation —
the serial and the threaded one stay together: in two processes each would compile the inlined chain,
82 s for ``filter``. The DOP and optimiser kernels were in ``pose`` before, a 56 s / 18 s split.)
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

DECK = np.array([[-0.015, 0.0075, 0.0], [-0.015, -0.0075, 0.0], [0.015, 0.0075, 0.0], [0.015, -0.0075, 0.0]])


def _stations(kind):
    from test_joint import two_stations

    return two_stations(np.random.default_rng(0), kind)


def warm_pose() -> None:
    from layoutkit.joint import solve_joint
    from layoutkit.pnp import solve_pnp
    from layoutkit.pnp_lh1 import PARALLEL_MIN_FRAMES

    rng = np.random.default_rng(1)
    for F in (4, PARALLEL_MIN_FRAMES):  # the serial batch and the threaded one
        solve_pnp(DECK, _angles(F, "lh1", rng)[0][:, 0])
    for kind in ("lh1", "lh2"):
        a, sts = _angles(4, kind, rng)
        solve_joint(DECK, a, stations=sts)


def _warm_design_kernels() -> None:
    """The fused DOP kernel and the optimiser's per-pose kernels."""
    from layoutkit.dop_batch import batch_dop
    from layoutkit.geometry import look_at_rotation
    from layoutkit.optimize.kernels import move_values, pose_values

    R = np.tile(look_at_rotation([0.0, 0.0, 1.0]).T, (3, 1, 1))
    batch_dop(DECK, R, np.tile([0.0, 0.0, 2.0], (3, 1)), rho=0.5)
    A, b, w = np.tile(np.eye(6), (2, 1, 1)), np.zeros((2, 3, 6)), np.ones(6)
    pose_values(A, b, 0.5, w)
    move_values(A, b, np.zeros((2, 4, 6, 6)), np.zeros((2, 4, 3, 6)), np.arange(2), [[0]], [[1]], 0.5, w)


def _angles(F, kind, rng):
    """(F, 2, 4, 2) angles of the deck 2 m in front of two stations of ``kind``, and the stations."""
    from layoutkit.geometry import look_at_rotation
    from layoutkit.simulate import simulate_station_angles

    sts = _stations(kind)
    R = np.tile(look_at_rotation([0.0, 0.0, 1.0]).T, (F, 1, 1))
    t = rng.normal(0, 0.05, (F, 3))
    return simulate_station_angles(DECK, R, t, sts, sigma=1e-5, rho=0.0, rng=rng), sts


def warm_filter() -> None:
    from layoutkit.filter import EkfConfig
    from layoutkit.filter.imm import ImmFilter
    from layoutkit.geometry import look_at_rotation
    from layoutkit.joint import solve_joint
    from layoutkit.lighthouse import measure

    rng = np.random.default_rng(2)
    F = 4
    start = (np.tile(look_at_rotation([0.0, 0.0, 1.0]).T, (F, 1, 1)), np.zeros((F, 3)))
    for kind in ("lh1", "lh2"):
        a, sts = _angles(F, kind, rng)
        solve_joint(DECK, a, stations=sts, initial=start)
        solve_joint(DECK, a, stations=sts, initial=start, dt=np.tile([-0.004, 0.004], (F, 1)),
                    velocity=(np.zeros((F, 3)), np.zeros((F, 3))))
    f = ImmFilter(DECK, sts, EkfConfig())
    f.initialize(0.0, np.eye(3), np.zeros(3), np.eye(6) * 1e-6)
    for k in range(4):
        s, axis = k % 2, (k // 2) % 2
        st = sts[s]
        f.predict(0.01 * (k + 1))
        z = measure((DECK - st.translation) @ st.rotation, st.calibration)[:, axis]
        f.update_sweep(s, axis, np.arange(4), np.ascontiguousarray(z))  # as the tracker passes them
    f.station_jacobians(np.eye(3), np.zeros(3))
    _warm_design_kernels()
    _warm_imu_kernels(sts)


def _warm_imu_kernels(stations) -> None:
    """The IMU-aided filter's kernels (filter/_imu_numba.py), with the argument types its tracker passes."""
    from layoutkit.filter import _imu_numba as K
    from layoutkit.lighthouse import measure

    R, P = np.eye(3), np.eye(15) * 1e-6
    p, v, ba, bg = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    g = np.array([0.0, 0.0, -9.80665])
    acc, gyro = np.tile([0.0, 0.0, 9.80665], (2, 1)), np.zeros((2, 3))
    K.propagate(R, p, v, ba, bg, g, P, acc[0], gyro[0], 0.01, 0.01, 1e-4, 1e-6, 1e-8)
    st = stations[0]
    ang = measure((DECK - st.translation) @ st.rotation, None)[:, 0]
    idx = np.flatnonzero(np.isfinite(ang))
    cp = np.zeros((2, 7))
    qm = np.full(len(DECK) + 1, 30.0)
    ro = cp.copy()
    ro.setflags(write=False)  # a calibrated station's terms come read-only (its frozen calibration)
    for c in (cp[0], ro[0]):
        K.update(R, p, v, ba, bg, P, DECK - np.zeros(3), idx, ang[idx], np.ascontiguousarray(st.rotation, float),
                 np.ascontiguousarray(st.translation, float), st.kind == "lh2", 0, c, False, 1e-8, 30.0, qm,
                 np.zeros(6))
    K.zero_velocity(R, p, v, ba, bg, P, 1e-6)
    K.body_cov(R, P, np.zeros(3), np.empty((12, 12)))
    K.matrix_to_quat(R, np.empty(4))
    # the IMU integration between sweeps, and the offline smoother's recorder and backward pass
    T = np.array([0.0, 0.01])
    K.propagate_span(R, p, v, ba, bg, g, P, T, gyro, acc, 0.0, 0.005, False, 900.0, 0.1, 0.0, 1e-4, 1e-6, 1e-8,
                     np.eye(15), True, np.inf, 0.02)
    K.sample_at(T, gyro, acc, 0.005, np.empty(3), np.empty(3))  # (a late sweep's IMU sample)
    Rk, xk, Pk = np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 12)), np.tile(P, (2, 1, 1))
    K.record_state(R, p, v, ba, bg, P, Rk[0], xk[0], Pk[0])
    K.rts_backward(Rk, xk, Pk, Rk, xk, Pk, np.tile(np.eye(15), (2, 1, 1)), 2, Rk.copy(), xk.copy(), Pk.copy())
    K.body_outputs(Rk, xk, Pk, 2, np.zeros(3), np.empty((2, 12, 12)), np.empty((2, 4)), np.empty((2, 3)))


if __name__ == "__main__":
    {"pose": warm_pose, "filter": warm_filter}[sys.argv[1]]()
