"""Shared benchmark helpers: interleaved rounds, medians, peak memory, result files."""
from __future__ import annotations

import json
import platform
import resource
import time
import tracemalloc
from datetime import datetime, timezone
from pathlib import Path

RESULTS = Path(__file__).parent / "results"


def interleaved(funcs: dict, rounds: int = 5) -> dict:
    """Run each callable once per round, alternating; return per-name lists of seconds."""
    times = {k: [] for k in funcs}
    for _ in range(rounds):
        for k, f in funcs.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return times


def peak_python_memory(func) -> int:
    """Peak bytes allocated by Python/numpy while ``func`` runs (tracemalloc)."""
    tracemalloc.start()
    try:
        func()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def max_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def write_result(name: str, data: dict) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    data = {"benchmark": name, "when": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
            **data}
    p = RESULTS / f"{name}.json"
    p.write_text(json.dumps(data, indent=2) + "\n")
    return p
