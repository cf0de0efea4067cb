"""Where a run's set-up goes: tracing, lowering to StableHLO and XLA's code generation.

    python -m benchmarks.perf.compile_profile andrews/rattle rigid-body/lobatto3ab3
    python -m benchmarks.perf.compile_profile pendulum/radau5 --solves 5 --json out.json

Each ``PROBLEM/INTEGRATOR`` pair is set up once in this process, with the workers' XLA
flags (:func:`benchmarks.pool.thread_environment`, added to ``XLA_FLAGS`` of the
environment, so that an option can be tried by setting it there) and the persistent
compilation cache off unless ``--compile-cache`` names one, so that what is timed is a
first compilation. JAX reports the three phases of every compilation (``jax.monitoring``,
in wall-clock seconds); their sums are printed beside the whole set-up and the first solve,
with the programs that took longest. What the first solve compiles (the time loop with the
Newton fallback, where simplified Newton failed, :func:`integrators.newton.deferred_fallback`)
is set-up too and is reported apart. Building the case (its consistency check compiles too)
is timed apart.

Every time is given twice: wall clock and this process's CPU time (``time.process_time``,
all its threads). On a machine shared with other work the wall clock measures the load as
much as the compiler; the CPU time does not, so comparisons (of XLA options, of one
version against another) should read the CPU columns, and the phases as proportions.
``--solves N`` times N more solves after the first and reports their median CPU time, to
set a compile-time saving against the solve time it may cost.
"""

from __future__ import annotations

import collections
import json
import os
import statistics
import sys
import time

from benchmarks import pool
from benchmarks.records import CommandParser

#: The phases of a compilation, by their ``jax.monitoring`` event.
PHASES = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "xla"}


def program_name(name: str) -> str:
    """The function a compilation event names, without the ``jit_`` or ``jit(...)`` that
    lowering and XLA add, so that a program's three phases add up under one name."""
    if name.startswith("jit(") and name.endswith(")"):
        return name[4:-1]
    return name[4:] if name.startswith("jit_") else name


class Clock:
    """Wall and CPU seconds of a ``with`` block (attributes ``wall`` and ``cpu``)."""

    def __enter__(self) -> "Clock":
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self._wall
        self.cpu = time.process_time() - self._cpu


def main(argv=None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.compile_profile",
                           description=__doc__.split("\n")[0])
    parser.add_argument("pairs", nargs="+", metavar="PROBLEM/INTEGRATOR")
    parser.add_argument("--compile-cache", default="off", metavar="DIR",
                        help="persistent cache folder (default: off, a first compilation)")
    parser.add_argument("--solves", type=int, default=0, metavar="N",
                        help="time N solves after the first (median CPU time; default 0)")
    parser.add_argument("--top", type=int, default=3, metavar="K",
                        help="programs listed per pair, longest first (default 3)")
    parser.add_argument("--json", metavar="PATH",
                        help="also write every figure, per pair and per program, as JSON")
    args = parser.parse_args(argv)
    # XLA reads its flags when JAX starts its CPU client: before anything computes.
    os.environ.update(pool.thread_environment())
    pool.one_blas_thread()
    pool.one_xla_thread()
    import jax

    import integrators
    import problems
    from benchmarks import compilation
    from integrators.base import Grid

    compilation.enable(args.compile_cache)
    totals: collections.Counter = collections.Counter()
    programs: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)

    def listen(event, duration, **kwargs):
        if event in PHASES:
            totals[PHASES[event]] += duration
            programs[program_name(str(kwargs.get("fun_name", "?")))][PHASES[event]] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    results = []
    for pair in args.pairs:
        problem, _, method = pair.partition("/")
        with Clock() as built:
            case = problems.make(problem)
        totals.clear()
        programs.clear()
        with Clock() as setup:
            solve = integrators.make(method).prepare(case, Grid(case.t0, case.t_end))
        phases = dict(totals)
        per_program = {name: dict(t) for name, t in programs.items()}
        totals.clear()
        programs.clear()
        with Clock() as first:
            solve()
        # What the first solve compiled (the loop with the Newton fallback, where a method
        # defers it): set-up all the same, which the runner adds to the run's.
        late_phases = dict(totals)
        late_programs = {name: dict(t) for name, t in programs.items()}
        solves = []
        for _ in range(args.solves):
            with Clock() as again:
                solve()
            solves.append(again.cpu)
        late = getattr(solve, "late_setup_s", 0.0)
        results.append(dict(pair=pair, xla_flags=os.environ.get("XLA_FLAGS", ""),
                            case_wall_s=built.wall, case_cpu_s=built.cpu,
                            setup_wall_s=setup.wall, setup_cpu_s=setup.cpu, phases_s=phases,
                            programs_s=per_program, first_solve_wall_s=first.wall,
                            first_solve_cpu_s=first.cpu, first_solve_phases_s=late_phases,
                            first_solve_programs_s=late_programs,
                            solve_cpu_s=statistics.median(solves) if solves else None,
                            late_setup_s=late))
        text = ", ".join(f"{name} {phases.get(name, 0.0):.2f} s" for name in PHASES.values())
        longest = sorted(per_program.items(), key=lambda item: -sum(item[1].values()))
        top = ", ".join(f"{name} {sum(t.values()):.2f} s (xla {t.get('xla', 0.0):.2f})"
                        for name, t in longest[:args.top])
        print(f"{pair}: case {built.wall:.2f} s ({built.cpu:.2f} s CPU); set-up "
              f"{setup.wall:.2f} s ({setup.cpu:.2f} s CPU; {text}; longest: {top}); first "
              f"solve {first.wall:.3f} s ({first.cpu:.3f} s CPU)"
              + (f"; median of {len(solves)} solves {statistics.median(solves):.4f} s CPU"
                 if solves else "")
              + (f", {late:.2f} s of the first solve compiling the loop with the Newton "
                 "fallback (integrators.loop.march)" if late else ""), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
