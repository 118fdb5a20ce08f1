"""Chunked Monte-Carlo on Dask.

Proof kinds: exact reference — the log-histogram percentile sketch against ``numpy.percentile``
(within its stated bin resolution) and merged halves against one pass (integer-exact); the
streaming precision against the batch chordal-mean :func:`layoutkit.dop.precision`; Monte-Carlo
against the predicted covariance (``layoutkit validate`` RMS error vs ADOP·σ, PDOP·σ); and
reproducibility on a real Dask LocalCluster (2 workers) against the synchronous scheduler
(bit-identical, since seeds come from ``SeedSequence.spawn`` per chunk and merging is in chunk order).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from layoutkit.cli import main
from layoutkit.dop import precision
from layoutkit.montecarlo import ErrorSums, simulate_solve
from layoutkit.parallel import LogHistogram, chunk_plan, map_reduce_ordered
from layoutkit.parallel.scheduler import SynchronousExecutor
from layoutkit.units import RAD2DEG, SIGMA_THETA_PAPER

REPO = Path(__file__).resolve().parents[1]
LAYOUT = REPO / "models" / "chen_target.layout.json"


def test_log_histogram_percentiles_and_exact_merge(rng):
    x = rng.lognormal(mean=-3.0, sigma=1.5, size=200_000)
    h = LogHistogram(1e-6, 10.0, 100).add(x)
    res = 10 ** (1 / 100) - 1
    for q in (0.01, 0.5, 0.9, 0.99, 0.999):
        exact = np.quantile(x, q)
        assert abs(h.quantile(q) / exact - 1) <= res + 1e-3, q
    a = LogHistogram(1e-6, 10.0, 100).add(x[:70_000])
    b = LogHistogram(1e-6, 10.0, 100).add(x[70_000:])
    m = a.merge(b)
    assert np.array_equal(m.counts, h.counts) and (m.under, m.over) == (h.under, h.over)
    assert m.total == len(x)
    with pytest.raises(ValueError, match="different bin edges"):
        a.merge(LogHistogram(1e-6, 10.0, 50))


def test_streaming_precision_equals_batch_chordal_mean(rng):
    from layoutkit.layout import load_layout
    from layoutkit.geometry import rotvec_to_matrix
    from layoutkit.simulate import facing_mask

    lay = load_layout(LAYOUT)
    R = rotvec_to_matrix(np.array([2.9, 0.3, 0.1]))
    t = np.array([0.2, 0.3, 2.0])
    lit = facing_mask(lay.positions, lay.normals, R[None], t[None])[0]
    assert lit.sum() >= 4
    F = 3000
    Rf, tf, vf = np.broadcast_to(R, (F, 3, 3)), np.broadcast_to(t, (F, 3)), np.broadcast_to(lit, (F, lay.n))
    e, d, ok = simulate_solve(lay.positions, Rf, tf, vf, sigma=SIGMA_THETA_PAPER, rho=0.8717,
                              rng=np.random.default_rng(7))
    assert ok.all()
    # batch reference on the solved poses themselves: chordal mean (layoutkit.dop.precision)
    R_est = rotvec_to_matrix(e) @ R
    s_rot, s_t = precision(R_est, t + d)
    # streaming: three chunks merged
    s = ErrorSums()
    for a, b in ((0, 700), (700, 2100), (2100, F)):
        s = s.merge(ErrorSums().add(e[a:b], d[a:b], ok[a:b]))
    assert s.n == F and s.gross == 0
    r, tt = s.precision()
    assert r == pytest.approx(float(s_rot), rel=1e-4)  # mean rotation vector vs chordal mean: O(spread²)
    assert tt == pytest.approx(float(s_t), rel=1e-9)
    one = ErrorSums().add(e, d, ok)
    assert one.precision()[0] == pytest.approx(r, rel=1e-12) and one.n == s.n
    assert np.array_equal(one.hist_rot_deg.counts, s.hist_rot_deg.counts)
    # and it is the precision the DOP predicts (Monte-Carlo vs covariance, 3000 frames: 5 s.e. ≈ 7 %)
    from layoutkit.dop import pose_dop

    dop = pose_dop(lay.positions, R, t, rho=0.8717, visible=lit)
    assert abs(r * RAD2DEG / (dop.adop * SIGMA_THETA_PAPER) - 1) < 0.07


def _square(x, item):
    return item.count * x + item.index


def test_ordered_reduce_is_exact_and_bounded():
    plan = chunk_plan(10_003, 1000, seed=5)
    assert [c.count for c in plan] == [1000] * 10 + [3] and plan[-1].start == 10_000
    # children of SeedSequence(5): chunk seeds do not depend on how the plan is consumed
    assert plan[3].seed.entropy == np.random.SeedSequence(5).spawn(11)[3].entropy
    assert plan[3].rng().random() == np.random.default_rng(np.random.SeedSequence(5).spawn(11)[3]).random()
    order = []
    out = map_reduce_ordered(SynchronousExecutor(), _square, plan, lambda a, r: a + [r], [], shared_args=(2,),
                             max_in_flight=3, progress=lambda it, r: order.append(it.index))
    assert out == [2 * c.count + c.index for c in plan] and order == list(range(11))


@pytest.mark.slow
def test_validate_matches_dop_and_is_identical_on_a_localcluster(tmp_path, small_envelope):
    args = ["validate", str(LAYOUT), "--envelope", small_envelope, "--frames", "12000", "--chunk-frames", "3000",
            "--json"]
    r = CliRunner()
    a = r.invoke(main, args + ["--scheduler", "synchronous"])
    assert a.exit_code == 0, a.output
    ra = json.loads(a.stdout)
    o = ra["overall"]
    assert ra["status"] == "ok" and o["frames"] == 12000 and o["gross_failures"] == 0
    # Monte-Carlo vs predicted covariance: 5 s.e. of an RMS over 12000 frames ≈ 3.2 %, + 0.5 % quantisation
    assert abs(o["ratio_rot"] - 1) < 0.04 and abs(o["ratio_trans"] - 1) < 0.04
    assert ra["agrees_with_dop"]
    b = r.invoke(main, args + ["--workers", "2"])
    assert b.exit_code == 0, b.output
    rb = json.loads(b.stdout)
    assert rb == ra  # bit-identical on 2 worker processes


def test_validate_without_coverage_says_so(tmp_path):
    env = tmp_path / "away.toml"
    env.write_text('count = 10\nseed = 1\nrange_m = [2.0, 3.0]\n[attitude]\nkind = "cone"\n'
                   'nominal_rotvec_deg = [0.0, 0.0, 0.0]\nhalf_angle_deg = 1.0\n')
    r = CliRunner().invoke(main, ["validate", str(LAYOUT), "--envelope", str(env), "--frames", "100",
                                  "--scheduler", "synchronous"])
    assert r.exit_code == 1 and "no_coverage" in r.output


def test_localcluster_workers_import_trimesh_before_any_task():
    """A sweep's Ctrl-C test printed a worker traceback: "cannot import name 'Trimesh' from partially
    initialized module" — a worker unpickled a Trimesh from another worker while its task thread
    was still importing trimesh. Every worker of a real LocalCluster now has the shared modules
    imported by the time the client can run anything there (checked in the worker processes)."""
    import sys

    from layoutkit.parallel.scheduler import WARM_IMPORTS, open_executor

    with open_executor(workers=2) as ex:
        got = ex.client.run(lambda mods=WARM_IMPORTS: [m in sys.modules for m in mods])
    assert len(got) == 2 and all(all(v) for v in got.values()), got
