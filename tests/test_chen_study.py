"""The Chen (2024) study in simulation, reduced: simulated precision (eq. 23) tracks ADOP·σ, PDOP·σ
(eq. 24). Proof kind: Monte-Carlo against the predicted covariance; tolerance from the sampling
error of an RMS over F frames (relative s.e. ≈ 1/sqrt(2 F · dof))."""

from layoutkit.studies.chen2024 import StudyConfig, dynamic_run, static_groups


def test_static_groups_match_prediction():
    cfg = StudyConfig(groups=4, frames=1500, seed=11)
    groups = static_groups(cfg)
    assert len(groups) == 4
    for g in groups:
        assert g["n_lit"] >= 4
        assert g["gross_failures"] == 0
        # RMS over 1500 frames of a ≥ 1-dof quantity: 5 s.e. ≈ 5 / sqrt(2 · 1500) ≈ 9 %;
        # quantisation adds ~0.2 % variance on top of sigma
        assert abs(g["simulated_sigma_rot_deg"] / g["predicted_sigma_rot_deg"] - 1) < 0.10
        assert abs(g["simulated_sigma_trans_m"] / g["predicted_sigma_trans_m"] - 1) < 0.10


def test_dynamic_run_without_systematic_error_matches_dop_and_with_it_is_worse():
    cfg = StudyConfig(seed=5, dynamic_seconds=30)
    ideal = dynamic_run(cfg, sensor_error_mm=0.0)
    assert ideal["frames"] > 1000
    assert abs(ideal["rms_rot_deg"] / ideal["predicted_rms_rot_deg"] - 1) < 0.10
    assert abs(ideal["rms_trans_m"] / ideal["predicted_rms_trans_m"] - 1) < 0.10
    biased = dynamic_run(cfg, sensor_error_mm=1.0)
    assert biased["rms_rot_deg"] > 2 * ideal["rms_rot_deg"]
