"""Run every benchmark (``benchmarks/bench_*.py``) and list the result files.

    .venv/bin/python benchmarks/run_all.py [--quick]

Each benchmark compares against its issue's anchor in the same run and writes
``benchmarks/results/<name>.json``; this script runs them one after another (never in
parallel: they time things) and prints a one-line summary of each.
"""
import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).parent

if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="pass --quick to every benchmark")
    args = ap.parse_args()
    failed = []
    for script in sorted(HERE.glob("bench_*.py")):
        cmd = [sys.executable, str(script)] + (["--quick"] if args.quick else [])
        print(f"== {script.name}", flush=True)
        t0 = time.time()
        r = subprocess.run(cmd)
        print(f"   ({time.time() - t0:.0f} s, exit {r.returncode})", flush=True)
        if r.returncode:
            failed.append(script.name)
    print("results:", ", ".join(sorted(p.name for p in (HERE / "results").glob("*.json"))))
    sys.exit(1 if failed else 0)
