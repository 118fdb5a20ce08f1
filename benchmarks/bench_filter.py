"""Tracking filter (issue 12, docs/filter.md): the "Must show" figures.

    .venv/bin/python benchmarks/bench_filter.py [--quick]

Cases (simulator sweeps: the ``fake-fpga`` tumble, paper noise with rho, 50 MHz quantisation,
Chen target reconstruction ``tests/data/chen_layout.json``):

- dropout: tumble with 60 % of the lit hits dropped, filter vs frame-by-frame PnP (live pipeline):
  share of time with a good pose, RMS attitude / position error (3 seeds × 60 s);
- hidden: two LH1 stations, station 1 hidden 2 s, one sensor reflecting 1 % of its hits off by
  5-50 mrad: largest update correction in prior sigmas, outliers injected / rejected (3 seeds × 20 s);
- consistency: NEES / NIS over 50 tumbles of 10 s against the 95 % chi² bands;
- static: 10 s at rest, the final pose's RMS error over 200 seeds vs the frame DOP bound / sqrt(frames);
- throughput: filter sweeps per second on one core, arrays in (median of 5 rounds), and
  ``layoutkit replay --filter ekf`` end to end (decode + filter) vs ``--filter none``;
- real: the libsurvive sample ``lh1_test_cal_first4s`` (HMD at rest; imported with
  ``layoutkit.workflows.importers.import_libsurvive``): filtered vs frame-by-frame pose jitter per
  station, with and without the static detector (skipped when the file is absent).

Writes benchmarks/results/filter.json (``--quick``: filter_quick.json).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _util import max_rss_bytes, write_result  # noqa: E402

LAYOUT = Path(__file__).parent.parent / "tests" / "data" / "chen_layout.json"


def _pool(rows, key, sub=None):
    vals = [r[key] if sub is None else r[key][sub] for r in rows]
    return {"min": float(np.min(vals)), "max": float(np.max(vals)), "mean": float(np.mean(vals))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (a smoke run, not the figures)")
    args = ap.parse_args(argv)
    from layoutkit.layout import load_layout
    from layoutkit.studies import filter_scenarios as wf

    lay = load_layout(LAYOUT)
    q = args.quick
    out = {"layout": str(LAYOUT.name), "tuning": wf.TUMBLE_CONFIG}
    t0 = time.perf_counter()
    seeds = [0] if q else [0, 1, 2]
    drop = [wf.dropout_scenario(lay, seed=s, duration=20.0 if q else 60.0, dropout=0.6) for s in seeds]
    out["dropout"] = {"runs": drop, "filter_share_min": min(r["filter"]["share_with_pose"] for r in drop),
                      "pnp_share_max": max(r["pnp"]["share_with_pose"] for r in drop)}
    print(f"dropout: filter share >= {out['dropout']['filter_share_min']:.4f}, "
          f"PnP share <= {out['dropout']['pnp_share_max']:.4f}", flush=True)
    hid = [wf.hidden_station_scenario(lay, seed=s, duration=20.0) for s in seeds]
    out["hidden"] = {"runs": hid,
                     "max_correction_over_prior_sigma": max(r["max_correction_over_prior_sigma"] for r in hid),
                     "outliers_injected": sum(r["outliers_injected"] for r in hid),
                     "outliers_rejected": sum(r["outliers_rejected"] for r in hid),
                     "good_angles_rejected": sum(r["good_angles_rejected"] for r in hid)}
    print(f"hidden: max correction {out['hidden']['max_correction_over_prior_sigma']:.2f} prior sigma, "
          f"outliers {out['hidden']['outliers_rejected']}/{out['hidden']['outliers_injected']}", flush=True)
    out["consistency"] = wf.consistency_scenario(lay, runs=10 if q else 50, duration=10.0)
    print(f"consistency: {out['consistency']}", flush=True)
    out["static"] = wf.static_scenario(lay, runs=30 if q else 200, duration=10.0)
    print(f"static: {out['static']}", flush=True)
    out["throughput"] = wf.throughput_scenario(lay, duration=10.0 if q else 30.0, rounds=3 if q else 5)
    print(f"throughput: {out['throughput']['sweeps_per_s_median']:.0f} sweeps/s wall, {out['throughput']['sweeps_per_cpu_s_median']:.0f} per CPU s "
          f"({out['throughput']['x_real_time']:.0f}x real time)", flush=True)
    try:
        out["replay"] = wf.replay_throughput(lay, duration=10.0 if q else 30.0, rounds=3 if q else 5)
        print(f"replay: {out['replay']}", flush=True)
    except AttributeError:  # replay wiring not present
        out["replay"] = None
    rec = Path(__file__).parent.parent / "tests" / "data" / "libsurvive" / "lh1_test_cal_first4s.rec.gz"
    out["real"] = None
    if rec.exists():  # real HMD at rest (libsurvive sample, kept outside the repository)
        import tempfile

        from layoutkit.workflows.importers import import_libsurvive

        with tempfile.TemporaryDirectory() as tmp:
            import_libsurvive(rec, tmp)
            d = Path(tmp)
            out["real"] = {"recording": str(rec), "runs": [
                wf.real_static_jitter(d / "HMD" / "frames.csv", d / "HMD" / "layout.json", d / "stations.json",
                                      zupt=z) for z in (False, True)]}
        for r in out["real"]["runs"]:
            for s, row in r["stations"].items():
                print(f"real HMD station {s} zupt={r['zupt']}: jitter PnP {row.get('pnp_jitter_rot_deg', float('nan')):.4f} deg "
                      f"/ {row.get('pnp_jitter_pos_mm', float('nan')):.3f} mm, filter "
                      f"{row.get('filter_jitter_rot_deg', float('nan')):.4f} deg / {row.get('filter_jitter_pos_mm', float('nan')):.3f} mm",
                      flush=True)
    out["wall_s"] = time.perf_counter() - t0
    out["max_rss_bytes"] = max_rss_bytes()
    p = write_result("filter_quick" if q else "filter", out)
    print(f"wrote {p}")


if __name__ == "__main__":
    main()
