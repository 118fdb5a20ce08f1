"""Tracking filter: an error-state EKF on SE(3) updated per lighthouse sweep (docs/filter.md).

- :mod:`.models` — the forward-model protocol ``h(points_body, R, t, station) -> angles`` + Jacobian
  and the registry :data:`FORWARD_MODELS` (plain LH1 / LH2 now; calibrated models plug in).
- :mod:`.ekf` — :class:`EkfConfig` (SI tuning) and :class:`ErrorStateEKF` (predict / sweep update
  with the Chen eq. 19 correlation and chi² gates / zero-velocity update).
- :mod:`.tracker` — :class:`SweepTracker`: PnP (re-)initialisation, lost detection, static detector,
  one :class:`FilterOutput` per sweep.
- :mod:`.consistency` — NEES / NIS over simulated runs.
- :mod:`.imu`, :mod:`.imu_tracker` — the IMU-aided error-state filter and its per-sweep tracker;
  :mod:`.smoother` — its offline fixed-lag Rauch-Tung-Striebel smoother (``replay --smooth``).

numpy/scipy only; imports core modules (lighthouse, noise, pnp, geometry, dop), never live/cli/workflows.
"""
from .ekf import EkfConfig, ErrorStateEKF, SweepUpdate
from .models import FORWARD_MODELS, ForwardModel, PlainSweepModel
from .tracker import STATUSES, FilterOutput, SweepTracker

__all__ = ["EkfConfig", "ErrorStateEKF", "SweepUpdate", "FORWARD_MODELS", "ForwardModel", "PlainSweepModel",
           "STATUSES", "FilterOutput", "SweepTracker"]
