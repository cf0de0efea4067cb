"""Command line: ``python -m benchmarks.run`` runs a suite or an ad-hoc selection.

Examples::

    python -m benchmarks.run --suite quick
    python -m benchmarks.run --load my_mechanism.py --problems my-mechanism --integrators rattle
    python -m benchmarks.run --problems sps-receiver pendulum --integrators rattle \\
        lobatto3ab3 --h 0.1 0.05 --t-end 100 --out results/
    python -m benchmarks.run --suite default --jobs 2 --timeout 600 --resume
    python -m benchmarks.run --list

Every run executes in a worker process, ``--jobs`` of them side by side (default: the
usable cores), or on a Dask cluster (``--cluster local:N`` starts one of N workers here,
``--cluster tcp://HOST:PORT`` uses a running scheduler; see :mod:`benchmarks.cluster`); a
run past its time limit (``--timeout``, else its suite group's or suite's ``timeout``,
else one hour; the limit covers building the case, set-up and the timed solves) is killed
and recorded as ``timeout``, a worker that crashes is recorded as ``error`` with its
signal, and the suite goes on (:mod:`benchmarks.batch` says how wall times stay honest).
``--resume`` skips the runs the store already holds as finished (any status but ``error``
and ``timeout``) for the same problem, parameters, options, ``t_end`` and code version. A
suite's studies run on the same workers as its runs, started first.

Writes ``runs.csv`` (one row per run, in suite order, replaced whole at the end, also
when interrupted; while runs end their rows go to ``runs.partial.csv``; after ``--resume``
it lists every run of the suite, the skipped ones as stored), appends the runs to the results store ``driftbench.sqlite`` and builds the report,
all under ``--out``. Bad input (unknown names, malformed suite files, out-of-range
options, inconsistent initial values, an unreachable cluster, a problem above its size
limit or a run above the step limit without ``--allow-large``, a damaged or foreign store,
an output folder another invocation is writing) is reported on one line before any run
starts, with exit status 2. A method that fails is data: its run is recorded ``failed``
and the command exits 0 (:data:`EXIT_OK`) when every run ended ``ok`` or ``failed``. A run
that ended ``error`` (user code or the library raised, a worker crashed) or ``timeout``
has no result; it is recorded with its status and message, the suite goes on, and the
command exits 1 (:data:`EXIT_RUN_ERROR`) at the end, after the report. Results that cannot
all be written (a full disk, a store damaged meanwhile) give one line and exit status 2
once every run has ended; every run's row is in ``runs.csv`` all the same. An interrupted
invocation (Ctrl-C, ``SIGTERM``), also while it validates or writes the report, stops its
workers, keeps every finished run and exits with status 130 (the one line says how to
write the report where it was cut short). :func:`main` returns these statuses to a caller
in Python.
"""

from __future__ import annotations

import argparse
import dataclasses
import signal
import sys
from pathlib import Path

from benchmarks.records import EXIT_INPUT, CommandParser, InputError, RunSpec, one_line

# Everything heavier (JAX, the integrators, the problems, the engines, the report) is
# imported where it is used: multiprocessing imports this module again in every process it
# spawns from the command line (the report's drawing processes), which would otherwise
# import JAX and every integrator for nothing, about a second each.

#: Exit status when every run ended as planned: ``ok``, or ``failed`` (the method failed,
#: which is data).
EXIT_OK = 0
#: Exit status when a run ended without a result (:data:`UNFINISHED`).
EXIT_RUN_ERROR = 1
#: Exit status of an interrupted invocation.
EXIT_INTERRUPTED = 130
#: Statuses of a run that ended without a result: ``--resume`` runs them again.
UNFINISHED = ("error", "timeout")
#: What the exit statuses mean, as ``--help`` says it.
EXIT_STATUSES = (f"exit status: {EXIT_OK} when every run ended ok or failed (a method that "
                 f"fails is data); {EXIT_RUN_ERROR} when a run ended {' or '.join(UNFINISHED)} "
                 f"(recorded with its message; the other runs and the report are written); "
                 f"{EXIT_INPUT} for bad input, refused on one line before any run; "
                 f"{EXIT_INTERRUPTED} when interrupted")


def parser() -> argparse.ArgumentParser:
    from benchmarks.plan import DEVICES, GPU_MIN_LANES, LANES_PER_CHUNK

    p = CommandParser(prog="python -m benchmarks.run", description=__doc__.split("\n")[0],
                      epilog=EXIT_STATUSES)
    p.add_argument("--suite", help="suite name (benchmarks/suites/NAME.toml) or path; default: default")
    p.add_argument("--problems", nargs="+", metavar="SPEC", help="problems, e.g. pendulum sps-ring:N=12")
    p.add_argument("--integrators", nargs="+", metavar="SPEC", help="integrator keys, e.g. rattle lobatto3ab3")
    p.add_argument("--h", nargs="+", type=float, default=[], help="step sizes (fixed-step methods)")
    p.add_argument("--rtol", nargs="+", type=float, default=[], help="relative tolerances (adaptive methods)")
    p.add_argument("--atol", nargs="+", type=float, default=[], help="absolute tolerances (adaptive methods)")
    p.add_argument("--t-end", type=float,
                   help="end time, given to the t_end parameter of every problem that has "
                        "one (default: each problem's own)")
    p.add_argument("--ensemble", type=int, metavar="K",
                   help="run each run from K initial states near the problem's own (lane 0: "
                        "its own), in one compiled loop where the method allows")
    p.add_argument("--seed", type=int, help="seed of the ensemble's initial states (default 0)")
    p.add_argument("--device", choices=DEVICES,
                   help=f"where an ensemble's loop runs: auto (a GPU when JAX sees one and the "
                        f"ensemble has {GPU_MIN_LANES} lanes or more, else the CPU; the "
                        f"default), cpu or gpu; on a GPU an ensemble is one chunk unless "
                        f"--lanes-per-chunk says otherwise; single runs run on the CPU")
    p.add_argument("--lanes-per-chunk", type=int, metavar="L",
                   help=f"split an ensemble into chunks of at most L lanes (nearly equal, "
                        f"never one lane alone), each a task of its own on the workers "
                        f"(default {LANES_PER_CHUNK} on the CPU)")
    p.add_argument("--out", type=Path, default=Path("results"), help="output folder (default: results/)")
    p.add_argument("--repeats", type=int, help="timed solves of each run at least (autorange; the median is reported)")
    p.add_argument("--jobs", type=int, help="runs side by side (default: the usable cores)")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="run on Dask: local:N (N workers here) or tcp://HOST:PORT (a running "
                        "scheduler); default: the local process pool")
    p.add_argument("--timeout", type=float,
                   help="time limit of each run in seconds, overriding the suite's (inf: none)")
    p.add_argument("--resume", action="store_true",
                   help="skip runs the store already holds as finished (same run key)")
    p.add_argument("--no-report", action="store_true", help="do not build the report")
    p.add_argument("--allow-large", action="store_true",
                   help="lift the size limit of problems and the step limit of runs (both "
                        "checked before anything is built)")
    p.add_argument("--load", action="append", default=[], metavar="PATH_OR_MODULE",
                   help="import a Python file or module that registers problems or "
                        "integrators, before anything else (repeatable; trusted code)")
    p.add_argument("--compile-cache", metavar="DIR",
                   help="persistent compilation cache folder, or 'off' (default: "
                        "$DRIFTBENCH_COMPILE_CACHE, else ~/.cache/driftbench/jax)")
    p.add_argument("--list", action="store_true", help="list problems, integrators and suites")
    return p


def listing() -> str:
    import integrators
    import problems
    from benchmarks import suites
    from studies import STUDIES

    lines = ["problems (name: parameters with defaults [where it comes from]):"]
    for name in problems.names():
        params = ", ".join(f"{k}={v}" for k, v in problems.parameters(name).items())
        lines.append(f"  {name}: {params} [{problems.origin(name)}]")
    lines.append("integrators (key: options with defaults):")
    for key in integrators.keys():
        try:
            opts = integrators.make(key).options()
        except Exception as exc:  # a key whose backend cannot be imported is still listed
            opts = {"unavailable": exc}
        lines.append(f"  {key}: " + ", ".join(f"{k}={v}" for k, v in opts.items()))
    lines.append("suites:")
    for name in suites.names():
        try:
            description = suites.load(name).description.splitlines()[0][:100]
        except (InputError, IndexError) as exc:  # a broken suite is listed with its error
            description = f"(cannot be loaded: {exc})" if isinstance(exc, InputError) else ""
        lines.append(f"  {name}: {description}")
    lines.append("studies:")
    lines.extend(f"  {name}: {target}" for name, target in STUDIES.items())
    return "\n".join(lines)


def argument_ranges() -> dict:
    """Command-line numbers: option -> (test of one value, what each value must be); the
    same ranges as in suite files, and ``--jobs``."""
    from benchmarks import suites
    from benchmarks.plan import WORKERS_PER_CORE, max_workers

    most = max_workers()
    return {**{key: suites.RANGES[key] for key in ("h", "rtol", "atol", "t_end", "timeout",
                                                    "repeats", "ensemble", "seed",
                                                    "lanes_per_chunk")},
            "jobs": (lambda x: 1 <= x <= most,
                     f"from 1 to {most} ({WORKERS_PER_CORE} per usable core)")}


def check_arguments(args) -> None:
    """Refuse out-of-range numbers on the command line, naming the option."""
    for name, (ok, must) in argument_ranges().items():
        value = getattr(args, name)
        for x in value if isinstance(value, list) else ([] if value is None else [value]):
            if not ok(x):
                # As given: a whole number in full (1e+08 would not be what was typed).
                shown = x if isinstance(x, int) else f"{x:g}"
                raise InputError(f"--{name.replace('_', '-')} {shown}: must be {must}")


def plan(args) -> tuple[list[RunSpec], dict, tuple[float, ...]]:
    """The runs, the keyword arguments of :func:`benchmarks.batch.run_specs` (suite name,
    repeats, studies, default time limit, Dask cluster, user code to load) and the suite's
    accuracy targets for the report (empty: the report's defaults); loads ``--load``
    first, so that what it registers can be named."""
    import problems
    from benchmarks import suites
    from benchmarks.plan import expand

    check_arguments(args)
    try:
        loads = [problems.load(source) for source in args.load]
    except problems.LoadError as exc:
        raise InputError(one_line(exc)) from None
    if args.problems or args.integrators:
        if args.suite:
            raise InputError("give either --suite or --problems/--integrators, not both")
        if not (args.problems and args.integrators):
            raise InputError("an ad-hoc selection needs both --problems and --integrators")
        try:
            runs = expand(args.problems, args.integrators, args.h, args.rtol, args.atol,
                          args.t_end, lanes=args.ensemble, seed=args.seed,
                          device=args.device, lanes_per_chunk=args.lanes_per_chunk)
        except ValueError as exc:
            raise InputError(one_line(exc)) from None
        return runs, dict(suite="ad-hoc", repeats=args.repeats or 3, timeout=args.timeout,
                          cluster=args.cluster, load=loads), ()
    suite = suites.load(args.suite or "default")
    runs = suite.runs
    if args.t_end is not None:
        runs = [dataclasses.replace(r, t_end=args.t_end) for r in runs]
    if args.timeout is not None:
        runs = [dataclasses.replace(r, timeout=args.timeout) for r in runs]
    if args.ensemble is not None:
        runs = [dataclasses.replace(r, lanes=args.ensemble, seed=r.seed or 0) for r in runs]
    # How ensembles run: the suite's ensembles take them, its single runs stay single.
    for option in ("seed", "device", "lanes_per_chunk"):
        if getattr(args, option) is not None:
            if all(r.lanes is None for r in runs):
                raise InputError(f"--{option.replace('_', '-')} applies to ensembles only, "
                                 f"and suite {suite.name!r} has none: give --ensemble K too")
            runs = [r if r.lanes is None else
                    dataclasses.replace(r, **{option: getattr(args, option)}) for r in runs]
    # The command line's engine wins over the suite's.
    cluster = args.cluster or (suite.cluster if args.jobs is None else None)
    return runs, dict(suite=suite.name, repeats=args.repeats or suite.repeats or 3,
                      studies=suite.studies, cluster=cluster, load=[*loads, *suite.load],
                      timeout=args.timeout if args.timeout is not None else suite.timeout), \
        suite.targets


class Interrupted(BaseException):
    """SIGINT or SIGTERM: stop the workers, keep what finished.

    A ``BaseException``, as ``KeyboardInterrupt`` is, so that no ``except Exception`` on
    the way (the Dask client has some) swallows it.
    """


#: Signals received by this invocation: a Ctrl-C in a terminal reaches the worker
#: processes too, and a worker that dies of it while the runs are validated can surface as
#: an error before the parent's own signal does; the exit status is still 130.
_received: list[str] = []


def _interrupt(signum, frame):
    _received.append(signal.Signals(signum).name)
    raise Interrupted(_received[-1])


def main(argv=None) -> int:
    import problems
    from benchmarks import compilation
    from benchmarks.executors import load_plugins

    args = parser().parse_args(argv)
    if args.list:
        try:
            load_plugins()
            for source in args.load:
                problems.load(source)
        except problems.LoadError as exc:
            print(f"error: {one_line(exc)}", file=sys.stderr)
            return EXIT_INPUT
        print(listing())
        return 0
    _received.clear()
    previous = {s: signal.signal(s, _interrupt) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            cache = compilation.enable(args.compile_cache)
        except OSError as exc:
            raise InputError(f"--compile-cache: {one_line(exc)}") from None
        # Read before anything compiles: validating the runs writes to the cache.
        cold = compilation.cold(cache)
        load_plugins()
        runs, options, targets = plan(args)
        # The engines and the report stage are imported once the input is read: --list
        # and a bad command line or suite file need neither.
        from benchmarks.batch import run_specs
        from reports import build as build_report

        records = run_specs(runs, args.out, args.jobs, resume=args.resume,
                            allow_large=args.allow_large, **options,
                            start_notes=[compilation.first_run_note(cache)] if cold else [])
        counts: dict[str, int] = {}
        for record in records:
            counts[record.row["status"]] = counts.get(record.row["status"], 0) + 1
        summary = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
        print(f"wrote {args.out / 'runs.csv'} ({len(records)} runs: {summary or 'none'})")
        unfinished = sum(counts.get(status, 0) for status in UNFINISHED)
        code = EXIT_RUN_ERROR if unfinished else EXIT_OK
        if unfinished:
            print(f"error: {unfinished} of {len(records)} runs ended "
                  f"{' or '.join(UNFINISHED)}: their messages are in {args.out / 'runs.csv'}",
                  file=sys.stderr)
        if not args.no_report:
            store = args.out / "driftbench.sqlite"
            try:
                for path in build_report(store, args.out,
                                         **({"targets": targets} if targets else {})):
                    print(f"wrote {path}")
            except OSError as exc:  # a full disk: the runs are written, the report is not
                print(f"error: the report under {args.out} could not be written: "
                      f"{one_line(exc)}", file=sys.stderr)
                return EXIT_INPUT
            except Interrupted:
                print(f"interrupted ({_received[0]}) while writing the report: every run "
                      f"is in {args.out}; python -m reports --db {store} --out {args.out} "
                      f"writes it", file=sys.stderr)
                return EXIT_INTERRUPTED
        return code
    except (InputError, Interrupted) as exc:
        if not _received:
            print(f"error: {one_line(exc)}", file=sys.stderr)
            return EXIT_INPUT
        where = (f"the runs that finished are in {args.out}"
                 if (args.out / "runs.partial.csv").exists()
                 or (args.out / "runs.csv").exists() else "no run had finished")
        print(f"interrupted ({_received[0]}): {where}; run again with --resume to finish "
              f"the rest", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


if __name__ == "__main__":
    code = main()
    # Past main, shutting down (the workers' and JAX's exit hooks) is not to be
    # interrupted: a second Ctrl-C there printed a traceback and lost the exit status.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)
