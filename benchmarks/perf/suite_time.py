"""Benchmark: end-to-end wall time of whole suites against the budgets their files declare.

Each suite runs as a user runs it, ``python -m benchmarks.run --suite NAME --out DIR`` in a
fresh interpreter with a fresh output folder: interpreter start, validation, worker start,
compilation, solves, storing and the report all count. The result per suite: wall time,
the suite's ``budget`` (seconds on the reference machine of two cores, from its TOML file),
the run statuses, and the 1-minute load average before and after (other users of the
machine slow every figure down: read the times with it). Exit status 1 when a suite runs
past its budget or the command fails.

Usage::

    python -m benchmarks.perf.suite_time quick ci
    python -m benchmarks.perf.suite_time library --jobs 2 --out results/suite-time
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from benchmarks import suites
from benchmarks.records import CommandParser


def measure(name: str, budget: float | None, out: Path, jobs: int | None = None) -> dict:
    """Run suite ``name`` into ``out`` (which must not hold a store) and time it."""
    command = [sys.executable, "-m", "benchmarks.run", "--suite", name, "--out", str(out)]
    if jobs is not None:
        command += ["--jobs", str(jobs)]
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - start
    statuses: Counter = Counter()
    if (out / "runs.csv").exists():
        with open(out / "runs.csv", newline="") as f:
            statuses.update(row["status"] for row in csv.DictReader(f))
    return {"suite": name, "wall_s": wall, "budget_s": budget, "exit": done.returncode,
            "statuses": dict(statuses), "load_before": load_before,
            "load_after": os.getloadavg()[0],
            "within": done.returncode == 0 and (budget is None or wall <= budget),
            "stderr_tail": done.stderr[-2000:] if done.returncode else ""}


def main(argv=None) -> int:
    p = CommandParser(prog="python -m benchmarks.perf.suite_time",
                                description=__doc__.split("\n")[0])
    p.add_argument("suites", nargs="+", help="suite names or paths")
    p.add_argument("--jobs", type=int, help="passed on to benchmarks.run (default: its own)")
    p.add_argument("--out", type=Path, help="keep each suite's output under OUT/NAME and a "
                                           "JSON summary in OUT/suite_time.json")
    args = p.parse_args(argv)
    # A bad name or suite file fails here, before anything runs.
    loaded = {name: suites.load(name) for name in args.suites}
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp)
        for name in args.suites:
            out = root / loaded[name].name  # the file's stem, also for a suite given by path
            if (out / "driftbench.sqlite").exists():
                p.error(f"{out} already holds a store: give a fresh --out")
            results.append(measure(name, loaded[name].budget, out, args.jobs))
    if args.out:
        (args.out / "suite_time.json").write_text(json.dumps(results, indent=1))
    print(f"{'suite':<14} {'wall [s]':>9} {'budget [s]':>10} {'load before/after':>18}  statuses")
    for r in results:
        budget = "none" if r["budget_s"] is None else f"{r['budget_s']:.0f}"
        verdict = "within budget" if r["within"] else (
            f"FAILED (exit {r['exit']})" if r["exit"] else "OVER BUDGET")
        statuses = ", ".join(f"{n} {s}" for s, n in sorted(r["statuses"].items()))
        print(f"{r['suite']:<14} {r['wall_s']:>9.1f} {budget:>10} "
              f"{r['load_before']:>8.2f} / {r['load_after']:<7.2f}  {statuses}: {verdict}")
        if r["stderr_tail"]:
            print(r["stderr_tail"], file=sys.stderr)
    return 0 if all(r["within"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
