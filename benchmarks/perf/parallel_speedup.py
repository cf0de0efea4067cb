"""Benchmark: how much faster a suite runs on more workers, and that its accuracy is unchanged.

Runs the same suite once per engine (``--jobs`` values for the local process pool, then
``--cluster`` addresses for Dask) through :func:`benchmarks.batch.run_specs`, each into its
own fresh output folder, so nothing is resumed, and reports, per engine, the end-to-end
wall time of the batch (worker start-up, set-up and solves, storing), the speed-up over the
first engine, the 1-minute load average before and after (other users of the machine
distort every figure: read them with it), and whether every accuracy column
(``ACCURACY_COLUMNS``) equals, bit for bit, that of the first engine. A working tree edited
during the measurement (the code version changes) voids that comparison, and is reported.

Usage::

    python -m benchmarks.perf.parallel_speedup                 # quick suite, --jobs 1 and 2
    python -m benchmarks.perf.parallel_speedup --jobs 1 --cluster local:2
    python -m benchmarks.perf.parallel_speedup --suite seed-sps --jobs 1 2 --out results/speedup
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import suites
from benchmarks.batch import run_specs
from benchmarks.records import ACCURACY_COLUMNS, CommandParser, provenance


def default_suite() -> str:
    return "quick" if "quick" in suites.names() else "seed-sps"


def measure(suite_name: str, engines: list[tuple[int | None, str | None]], out: Path) -> dict:
    """Run ``suite_name`` once per engine ``(jobs, cluster)``; return the timings and the
    comparison."""
    suite = suites.load(suite_name)
    repeats = suite.repeats or 3
    results, reference = [], None
    version = provenance()["code_version"]
    for jobs, cluster in engines:
        name = f"jobs {jobs}" if cluster is None else f"cluster {cluster}"
        load_before = os.getloadavg()[0]
        start = time.perf_counter()
        records = run_specs(suite.runs, out / name.replace(" ", "-").replace(":", "-")
                            .replace("/", ""), jobs, cluster=cluster, suite=suite.name,
                            repeats=repeats, timeout=suite.timeout, load=suite.load,
                            log=None)
        wall = time.perf_counter() - start
        accuracy = [[r.row[c] for c in ACCURACY_COLUMNS] for r in records]
        reference = accuracy if reference is None else reference
        results.append({
            "engine": name, "wall_s": wall, "load_before": load_before,
            "load_after": os.getloadavg()[0],
            "statuses": sorted({r.row["status"] for r in records}),
            "accuracy_identical": accuracy == reference,
        })
    for r in results:
        r["speedup"] = results[0]["wall_s"] / r["wall_s"]
    return {"suite": suite.name, "runs": len(suite.runs), "cores": len(os.sched_getaffinity(0)),
            "code_changed": provenance()["code_version"] != version, "results": results}


def main(argv=None) -> int:
    p = CommandParser(prog="python -m benchmarks.perf.parallel_speedup",
                                description=__doc__.split("\n")[0])
    p.add_argument("--suite", default=default_suite(), help="suite to run (default: quick)")
    p.add_argument("--jobs", nargs="*", type=int,
                   help="local pool job counts (default: 1 2, or 1 with --cluster)")
    p.add_argument("--cluster", nargs="*", default=[], metavar="ADDRESS",
                   help="Dask clusters measured after the job counts (local:N, tcp://...)")
    p.add_argument("--out", type=Path, help="keep the runs and a JSON summary here")
    args = p.parse_args(argv)
    jobs = args.jobs if args.jobs is not None else ([1] if args.cluster else [1, 2])
    engines = [(n, None) for n in jobs] + [(None, c) for c in args.cluster]
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        summary = measure(args.suite, engines, out)
        if args.out:
            (out / "parallel_speedup.json").write_text(json.dumps(summary, indent=1))
    print(f"suite {summary['suite']}: {summary['runs']} runs, {summary['cores']} usable cores")
    print(f"{'engine':<22} {'wall [s]':>9} {'speed-up':>8} {'load before/after':>18}  accuracy")
    if summary["code_changed"]:
        print("the working tree changed during the measurement: the accuracy comparison is "
              "void (different code ran)")
    for r in summary["results"]:
        same = "identical" if r["accuracy_identical"] else "DIFFERENT"
        print(f"{r['engine']:<22} {r['wall_s']:>9.1f} {r['speedup']:>8.2f} "
              f"{r['load_before']:>8.2f} / {r['load_after']:<7.2f}  {same}")
    return 0 if all(r["accuracy_identical"] for r in summary["results"]) else 1


if __name__ == "__main__":
    sys.exit(main())
