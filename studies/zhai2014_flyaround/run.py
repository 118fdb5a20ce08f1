"""Zhai et al. (2014) fly-around ground test, reproduced on synthetic renders.

    .venv/bin/python studies/zhai2014_flyaround/run.py [--quick] [--out DIR]

Writes case1_tracking.png, case2_tracking.png (Fig. 5/6 analogues), corner_noise_sensitivity.png,
detector_tilt.png, example_frame.png, results.json and table.md into this folder (or --out).
The logic lives in layoutkit.studies.zhai2014.main (also `layoutkit study zhai2014`).
"""
import argparse
from pathlib import Path

from layoutkit.studies.zhai2014 import main

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="reduced smoke run (5 s samples, fewer repeats; the +filter rows need the full 1 Hz run)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent), help="output folder")
    a = ap.parse_args()
    main(a.out, quick=a.quick)
