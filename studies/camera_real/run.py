"""The camera cross-check on real photographs (issue 28).

    .venv/bin/python studies/camera_real/run.py [--quick] [--data DIR] [--out DIR]

Writes results.json, table.md, attitude_errors.png, predicted_vs_observed.png, detections.png,
calibration_residuals.png and camera.yml into this folder (or --out). Data: the 13 OpenCV sample
photos (default tests/data/camera, identical to shared/data/camera). The logic lives in
layoutkit.studies.camera_real.main.
"""
import argparse
from pathlib import Path

from layoutkit.studies.camera_real import DEFAULT_DATA, main

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="60 instead of 200 Monte-Carlo draws")
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="folder of left*.jpg + left_intrinsics.yml")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent), help="output folder")
    a = ap.parse_args()
    main(a.out, a.data, quick=a.quick)
