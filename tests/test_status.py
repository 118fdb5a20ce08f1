"""One status convention (layoutkit/status.py): every pose producer's codes are views of one table,
so a code in a pose table means the same whoever wrote it; results carry success and message.

Proof kind: the code tables of PnP, the live pipeline and DOP checked against the one table
(no code with two meanings), and real results (a PnP solve with a too-few frame, a DOP at a
degenerate pose, a coverage analysis, a camera stream) reporting through it.
"""
import numpy as np

from layoutkit import status
from layoutkit.live import pipeline
from layoutkit import pnp


def test_pnp_and_pipeline_codes_are_views_of_one_table():
    for code, desc in pnp.STATUS_NAMES.items():
        assert status.DESCRIPTIONS[code] == desc
    for code, name in pipeline.STATUS_NAMES.items():
        assert status.NAMES[code] == name
    # the live-only codes are not PnP codes (a poses.csv "3" can only mean not_converged)
    assert not set(pipeline.STATUS_NAMES) - {0, 1, 5, 11} & set(pnp.STATUS_NAMES)
    assert len(set(status.NAMES.values())) == len(status.NAMES) and status.CODES["ok"] == 0


def test_results_report_through_the_table():
    from layoutkit.dop import pose_dop
    from layoutkit.shapes import chen_target

    lay = chen_target()[1]
    R = np.stack([np.diag([1.0, -1.0, -1.0])] * 2)
    t = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0]])
    vis = np.ones((2, lay.n), bool)
    vis[1, 2:] = False  # two sensors: too few
    d = pose_dop(lay.positions, R, t, visible=vis)
    assert list(d.status) == [status.OK, status.TOO_FEW_LIT] and list(d.success) == [True, False]
    from layoutkit.lighthouse import sweep_angles
    from layoutkit.geometry import transform_points

    ang = sweep_angles(transform_points(R, t, lay.positions))
    sol = pnp.solve_pnp(lay.positions, ang, vis)
    assert sol.status[1] == status.TOO_FEW_LIT and not sol.success[1]
    assert status.summarize(sol.status, status.NAMES) == "1 ok, 1 too_few_lit"
    assert status.summarize(np.zeros(3, int)) == "all 3 frames ok"


def test_coverage_and_camera_results_have_success_and_message():
    from layoutkit.camera.stream import track_corners
    from layoutkit.optimize.coverage import analyse_coverage

    lit = np.array([[True, True, False], [False, True, True]])
    rep = analyse_coverage(lit, k=1, m=2)
    assert rep.success is False and rep.status != "ok" and rep.message
    s = track_corners(np.array([0.0, 1.0]), np.full((2, 4, 2), np.nan), 1000.0)
    assert not s.success.any() and s.message.startswith("0 of 2 frames solved")
