"""Chen et al. (2024) static precision study (Fig. 5) and dynamic runs (Table 2) in simulation.

    .venv/bin/python studies/chen2024_static_precision/run.py            # full: 50 groups × 3600 frames
    .venv/bin/python studies/chen2024_static_precision/run.py --quick    # 10 groups × 600 frames

Same as ``layoutkit study chen2024``; outputs (figure, table, JSON) go next to this file
under ``results/``.
"""
import argparse
from pathlib import Path

from layoutkit.studies.chen2024 import StudyConfig, run_chen2024, write_outputs

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cfg = StudyConfig(groups=10, frames=600, seed=args.seed) if args.quick else StudyConfig(seed=args.seed)
    res = run_chen2024(cfg)
    paths = write_outputs(res, Path(__file__).parent / "results")
    print(res["summary"])
    print(paths)
