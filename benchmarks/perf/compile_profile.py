"""Where a run's set-up goes: tracing, lowering to StableHLO and XLA's code generation.

    python -m benchmarks.perf.compile_profile andrews/rattle rigid-body/lobatto3ab3

Each ``PROBLEM/INTEGRATOR`` pair is set up once in this process, with the workers' XLA
flags (:func:`benchmarks.pool.thread_environment`) and the persistent compilation cache
off unless ``--compile-cache`` names one, so that what is timed is a first compilation.
JAX reports the three phases of every compilation (``jax.monitoring``); their sums are
printed beside the whole set-up and the first solve, with the programs that took longest
in XLA. Building the case (its consistency check compiles too) is timed apart.
"""

from __future__ import annotations

import collections
import os
import sys
import time

from benchmarks import pool
from benchmarks.records import CommandParser

#: The phases of a compilation, by their ``jax.monitoring`` event.
PHASES = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "xla"}


def main(argv=None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.compile_profile",
                           description=__doc__.split("\n")[0])
    parser.add_argument("pairs", nargs="+", metavar="PROBLEM/INTEGRATOR")
    parser.add_argument("--compile-cache", default="off", metavar="DIR",
                        help="persistent cache folder (default: off, a first compilation)")
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
    programs: collections.Counter = collections.Counter()

    def listen(event, duration, **kwargs):
        if event in PHASES:
            totals[PHASES[event]] += duration
            if PHASES[event] == "xla":
                programs[kwargs.get("fun_name", "?")] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    for pair in args.pairs:
        problem, _, method = pair.partition("/")
        start = time.perf_counter()
        case = problems.make(problem)
        built = time.perf_counter() - start
        totals.clear()
        programs.clear()
        start = time.perf_counter()
        solve = integrators.make(method).prepare(case, Grid(case.t0, case.t_end))
        setup = time.perf_counter() - start
        start = time.perf_counter()
        solve()
        first = time.perf_counter() - start
        phases = ", ".join(f"{name} {totals[name]:.2f} s" for name in PHASES.values())
        top = ", ".join(f"{name} {t:.2f} s" for name, t in programs.most_common(3))
        late = getattr(solve, "late_setup_s", 0.0)
        print(f"{pair}: case {built:.2f} s; set-up {setup:.2f} s ({phases}; longest in XLA: "
              f"{top}); first solve {first:.3f} s"
              + (f", {late:.2f} s of it compiling the loop with the Newton fallback "
                 "(integrators.loop.march)" if late else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
