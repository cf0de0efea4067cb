"""Benchmark: how much faster a suite runs with more jobs, and that its accuracy is unchanged.

Runs the same suite once per ``--jobs`` value through :func:`benchmarks.runner.run_specs`
(each into its own fresh output folder, so nothing is resumed) and reports, per value, the
end-to-end wall time of the batch (worker start-up, set-up and solves, storing), the
speed-up over the first value, the 1-minute load average before and after (other users of
the machine distort every figure: read them with it), and whether every accuracy column
(``ACCURACY_COLUMNS``) equals, bit for bit, that of the first value. A working tree edited
during the measurement (the code version changes) voids that comparison, and is reported.

Usage::

    python -m benchmarks.parallel_speedup                 # quick suite (seed-sps if absent)
    python -m benchmarks.parallel_speedup --suite seed-sps --jobs 1 2 --out results/speedup
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import suites
from benchmarks.runner import ACCURACY_COLUMNS, code_version, run_specs


def default_suite() -> str:
    return "quick" if "quick" in suites.names() else "seed-sps"


def measure(suite_name: str, jobs: list[int], out: Path) -> dict:
    """Run ``suite_name`` once per entry of ``jobs``; return the timings and the comparison."""
    suite = suites.load(suite_name)
    repeats = suite.repeats or 3
    results, reference = [], None
    version = code_version()
    for n in jobs:
        load_before = os.getloadavg()[0]
        start = time.perf_counter()
        records = run_specs(suite.runs, out / f"jobs{n}", n, suite=suite.name,
                            repeats=repeats, timeout=suite.timeout, log=None)
        wall = time.perf_counter() - start
        accuracy = [[r.row[c] for c in ACCURACY_COLUMNS] for r in records]
        reference = accuracy if reference is None else reference
        results.append({
            "jobs": n, "wall_s": wall, "load_before": load_before,
            "load_after": os.getloadavg()[0],
            "statuses": sorted({r.row["status"] for r in records}),
            "accuracy_identical": accuracy == reference,
        })
    for r in results:
        r["speedup"] = results[0]["wall_s"] / r["wall_s"]
    return {"suite": suite.name, "runs": len(suite.runs), "cores": len(os.sched_getaffinity(0)),
            "code_changed": code_version() != version, "results": results}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.parallel_speedup",
                                description=__doc__.split("\n")[0])
    p.add_argument("--suite", default=default_suite(), help="suite to run (default: quick)")
    p.add_argument("--jobs", nargs="+", type=int, default=[1, 2], help="job counts (default 1 2)")
    p.add_argument("--out", type=Path, help="keep the runs and a JSON summary here")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        summary = measure(args.suite, args.jobs, out)
        if args.out:
            (out / "parallel_speedup.json").write_text(json.dumps(summary, indent=1))
    print(f"suite {summary['suite']}: {summary['runs']} runs, {summary['cores']} usable cores")
    print(f"{'jobs':>4} {'wall [s]':>9} {'speed-up':>8} {'load before/after':>18}  accuracy")
    if summary["code_changed"]:
        print("the working tree changed during the measurement: the accuracy comparison is "
              "void (different code ran)")
    for r in summary["results"]:
        same = "identical" if r["accuracy_identical"] else "DIFFERENT"
        print(f"{r['jobs']:>4} {r['wall_s']:>9.1f} {r['speedup']:>8.2f} "
              f"{r['load_before']:>8.2f} / {r['load_after']:<7.2f}  {same}")
    return 0 if all(r["accuracy_identical"] for r in summary["results"]) else 1


if __name__ == "__main__":
    sys.exit(main())
