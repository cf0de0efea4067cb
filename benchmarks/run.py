"""Command line: ``python -m benchmarks.run`` runs a suite or an ad-hoc selection.

Examples::

    python -m benchmarks.run --suite quick
    python -m benchmarks.run --problems sps-receiver pendulum --integrators rattle \\
        lobatto3ab3 --h 0.1 0.05 --t-end 100 --out results/
    python -m benchmarks.run --list

Writes ``runs.csv`` (one row per run, appended as each run finishes), appends the runs to
the results store ``driftbench.sqlite`` and builds the report, all under ``--out``. Bad
input (unknown names, malformed suite files, out-of-range options, inconsistent initial
values) is reported on one line before any run starts, with exit status 2. Runs that fail
are data: they are recorded with their status and the command still exits 0.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import integrators
import problems
from benchmarks import suites
from benchmarks.runner import COLUMNS, RunSpec, build, execute, expand
from benchmarks.store import Store


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n")[0])
    p.add_argument("--suite", help="suite name (benchmarks/suites/NAME.toml) or path; default: default")
    p.add_argument("--problems", nargs="+", metavar="SPEC", help="problems, e.g. pendulum sps-ring:N=12")
    p.add_argument("--integrators", nargs="+", metavar="SPEC", help="integrator keys, e.g. rattle lobatto3ab3")
    p.add_argument("--h", nargs="+", type=float, default=[], help="step sizes (fixed-step methods)")
    p.add_argument("--rtol", nargs="+", type=float, default=[], help="relative tolerances (adaptive methods)")
    p.add_argument("--atol", nargs="+", type=float, default=[], help="absolute tolerances (adaptive methods)")
    p.add_argument("--t-end", type=float, help="end time (default: each problem's own)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output folder (default: results/)")
    p.add_argument("--repeats", type=int, help="timed repeats of each solve (median is reported)")
    p.add_argument("--no-report", action="store_true", help="do not build the report")
    p.add_argument("--list", action="store_true", help="list problems, integrators and suites")
    return p


def listing() -> str:
    lines = ["problems (name: parameters with defaults):"]
    for name in problems.names():
        params = ", ".join(f"{k}={v}" for k, v in problems.parameters(name).items())
        lines.append(f"  {name}: {params}")
    lines.append("integrators (key: options with defaults):")
    for key in integrators.keys():
        try:
            opts = integrators.make(key).options()
        except Exception as exc:  # a key whose backend cannot be imported is still listed
            opts = {"unavailable": exc}
        lines.append(f"  {key}: " + ", ".join(f"{k}={v}" for k, v in opts.items()))
    lines.append("suites:")
    for name in suites.names():
        lines.append(f"  {name}: {suites.load(name).description.splitlines()[0][:100]}")
    return "\n".join(lines)


def plan(args) -> tuple[str, list[RunSpec], int]:
    """The suite name, its runs and the repeat count; raises on bad input."""
    if args.problems or args.integrators:
        if args.suite:
            raise ValueError("give either --suite or --problems/--integrators, not both")
        if not (args.problems and args.integrators):
            raise ValueError("an ad-hoc selection needs both --problems and --integrators")
        runs = expand(args.problems, args.integrators, args.h, args.rtol, args.atol, args.t_end)
        return "ad-hoc", runs, args.repeats or 3
    suite = suites.load(args.suite or "default")
    runs = suite.runs
    if args.t_end is not None:
        runs = [RunSpec(r.problem, r.integrator, r.h, r.rtol, r.atol, args.t_end) for r in runs]
    return suite.name, runs, args.repeats or suite.repeats or 3


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.list:
        print(listing())
        return 0
    try:
        name, runs, repeats = plan(args)
        if repeats < 1:
            raise ValueError(f"--repeats = {repeats} must be at least 1")
        for spec in runs:  # every case and option is checked before any run starts
            build(spec)
    except Exception as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / "runs.csv"
    store = Store(args.out / "driftbench.sqlite")
    session = store.begin(suite=name)
    with open(csv_path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for i, spec in enumerate(runs, 1):
            print(f"[{i}/{len(runs)}] {spec.label()}", file=sys.stderr, flush=True)
            record = execute(spec, repeats=repeats)
            writer.writerow(record.row)
            fh.flush()
            store.add(session, record)
            row = record.row
            print(f"    {row['status']}: max|g| {row['max_pos_residual']}, "
                  f"wall {row['wall_s']} s {row['message'] or ''}", file=sys.stderr, flush=True)
    print(f"wrote {csv_path} ({len(runs)} runs)")
    if not args.no_report:
        from reports import build as build_report
        for path in build_report(store.path, args.out):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
