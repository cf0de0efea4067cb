"""Benchmark: end-to-end wall time of whole suites against the budgets their files declare.

Each suite runs as a user runs it, ``python -m benchmarks.run --suite NAME --out DIR`` in a
fresh interpreter with a fresh output folder: interpreter start, validation, worker start,
compilation, solves, storing and the report all count. The result per suite: wall time,
the suite's ``budget`` (seconds on the reference machine of two cores, from its TOML file),
the run statuses, and the 1-minute load average before and after (other users of the
machine slow every figure down: read the times with it). Exit status 1 when a suite runs
past its budget or the command fails.

``--compile`` measures what compiling costs: each suite runs twice with the compilation
cache (:data:`CACHE_ENV`) in a fresh folder, first cold (that run is the one held to the
budget), then warm, and a ``compile`` line gives, for each, the summed set-up (``setup_s``)
and the summed solve (``wall_s``) of runs.csv and their ratio, and the two end-to-end wall
times with theirs.

Usage::

    python -m benchmarks.perf.suite_time quick ci
    python -m benchmarks.perf.suite_time library --jobs 2 --out results/suite-time
    python -m benchmarks.perf.suite_time default --compile
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from benchmarks import suites
from benchmarks.records import CommandParser

#: The environment variable that points the persistent compilation cache at a folder.
CACHE_ENV = "DRIFTBENCH_COMPILE_CACHE"


def measure(name: str, budget: float | None, out: Path, jobs: int | None = None,
            env: dict | None = None) -> dict:
    """Run suite ``name`` into ``out`` (which must not hold a store) and time it; ``env``
    is the command's environment (default: this process's)."""
    command = [sys.executable, "-m", "benchmarks.run", "--suite", name, "--out", str(out)]
    if jobs is not None:
        command += ["--jobs", str(jobs)]
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    statuses: Counter = Counter()
    setup = solve = 0.0
    if (out / "runs.csv").exists():
        with open(out / "runs.csv", newline="") as f:
            for row in csv.DictReader(f):
                statuses[row["status"]] += 1
                setup += _seconds(row["setup_s"])
                solve += _seconds(row["wall_s"])
    return {"suite": name, "wall_s": wall, "budget_s": budget, "exit": done.returncode,
            "statuses": dict(statuses), "setup_s": setup, "solve_s": solve,
            "load_before": load_before, "load_after": os.getloadavg()[0],
            "within": done.returncode == 0 and (budget is None or wall <= budget),
            "stderr_tail": done.stderr[-2000:] if done.returncode else ""}


def _seconds(text: str) -> float:
    """A runs.csv time, 0 where the run has none (it failed before it, or was skipped)."""
    try:
        value = float(text)
    except ValueError:
        return 0.0
    return value if math.isfinite(value) else 0.0


def compile_cost(name: str, budget: float | None, out: Path, jobs: int | None) -> dict:
    """Run suite ``name`` cold, then warm, in a fresh compilation cache: the cold
    measurement (into ``out``), with the warm one (into :func:`warm_folder`) as ``"warm"``."""
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, CACHE_ENV: cache}
        cold = measure(name, budget, out, jobs, env)
        cold["warm"] = measure(name, budget, warm_folder(out), jobs, env)
    return cold


def warm_folder(out: Path) -> Path:
    """Where the warm run of the suite measured into ``out`` writes."""
    return out.with_name(f"{out.name}-warm")


def _ratio(num: float, den: float) -> str:
    return f"{num / den:.2f}" if den > 0 else "n/a"


def compile_line(r: dict) -> str:
    """The ``compile`` line of a suite measured by :func:`compile_cost`."""

    def part(m: dict) -> str:
        return (f"set-up {m['setup_s']:.1f} s, solve {m['solve_s']:.1f} s "
                f"(set-up / solve {_ratio(m['setup_s'], m['solve_s'])})")

    cold, warm = r, r["warm"]
    return (f"compile {r['suite']}: cold {part(cold)}; warm {part(warm)}; end to end cold "
            f"{cold['wall_s']:.1f} s, warm {warm['wall_s']:.1f} s (warm / cold "
            f"{_ratio(warm['wall_s'], cold['wall_s'])})")


def main(argv=None) -> int:
    p = CommandParser(prog="python -m benchmarks.perf.suite_time",
                                description=__doc__.split("\n")[0])
    p.add_argument("suites", nargs="+", help="suite names or paths")
    p.add_argument("--jobs", type=int, help="passed on to benchmarks.run (default: its own)")
    p.add_argument("--out", type=Path, help="keep each suite's output under OUT/NAME and a "
                                           "JSON summary in OUT/suite_time.json")
    p.add_argument("--compile", action="store_true",
                   help="run each suite cold, then warm, in a fresh compilation cache (the "
                        "warm run's output under OUT/NAME-warm) and print the compile line")
    args = p.parse_args(argv)
    # A bad name or suite file fails here, before anything runs.
    loaded = {name: suites.load(name) for name in args.suites}
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp)
        for name in args.suites:
            out = root / loaded[name].name  # the file's stem, also for a suite given by path
            for folder in (out, warm_folder(out)) if args.compile else (out,):
                if (folder / "driftbench.sqlite").exists():
                    p.error(f"{folder} already holds a store: give a fresh --out")
            if args.compile:
                results.append(compile_cost(name, loaded[name].budget, out, args.jobs))
            else:
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
    for r in results:
        if "warm" in r:
            print(compile_line(r))
            if r["warm"]["exit"]:
                print(f"the warm run of {r['suite']} FAILED (exit {r['warm']['exit']})")
                print(r["warm"]["stderr_tail"], file=sys.stderr)
    ok = all(r["within"] and not r.get("warm", {}).get("exit") for r in results)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
