"""Benchmark: step throughput of our compiled loop against plain C, and its peak memory.

Throughput
    The speed-of-light yardstick is ``benchmarks/perf/yardstick/rattle_sps.c``: the same RATTLE
    step on sps-receiver as ``rattle`` takes (Newton on the scalar multiplier with the same
    convergence test and tolerance, the linear velocity projection) and the same per-step
    bookkeeping (``|g|``, ``|G v|``, ``|H - H0|`` and their per-window maxima), in plain C.
    It is compiled here with the system C compiler (``cc`` or ``gcc`` from ``PATH``,
    ``-O2``); without one the C side is skipped with a message. ``rattle`` and
    ``lobatto3ab3`` run the same horizon (default ``1e6`` steps of ``h = 1e-3``) with the
    default recording grid. The three alternate, round after round, in this one process, so
    that a change in the machine's load hits them alike (a method whose solves have taken
    more than ``--budget`` seconds sits out the later rounds). JAX is timed around the whole
    ``solve()`` (the compiled loop and the read-back of the trajectory), after set-up and
    compilation; C around its loop, by its own clocks. Each rate is given per second of wall
    clock and per second of CPU time: on a shared machine the wall clock also counts the
    time the scheduler gives to other processes, the CPU time does not. Each figure is the
    median over the rounds, each ratio the median of the per-round ratios, with their
    quartiles and the ratio of each side's fastest round (the round least slowed by other
    processes, as :mod:`timeit` reads its repeats).

    Load: each side's share of its wall clock spent waiting for a core is printed (JAX:
    the run-queue time of this process's threads, Linux ``/proc/self/task/*/schedstat``;
    C: its wall clock less its CPU time, its loop being one thread that never blocks).
    A round is short against the swings of the load, so the two sides of one round can
    meet different loads: on a busy machine the per-round ratios spread widely, hence the
    many rounds. Where the cores are oversubscribed neither ratio is load-robust: besides
    the waits, XLA's compiled loops can then take markedly more CPU time per step than on
    an idle core, for whole runs, while the C loop's CPU time stays as it is; a verdict
    read at such a load says more about the load than about the code.

    The bar: ``rattle`` reaches at least :data:`RATIO_BAR` of the C loop's steps per second
    (wall clock; the CPU-time ratio is printed beside it). The two must also agree: the same
    final state and the same maxima of the three residuals up to accumulated round-off
    (:data:`AGREE_STATE`, :data:`AGREE_RESIDUAL`, :data:`AGREE_ENERGY_REL`).

    This process starts JAX with :data:`integrators.loop.KERNEL_FLAG` (the benchmark
    workers do too), under which XLA compiles the whole time loop into one kernel; the
    report says whether it did. ``--xla-default`` measures without the flag instead. It
    runs with one intra-op thread (XLA's CPU client, BLAS), as the workers do, C being on
    one core; unlike theirs, its ``XLA_FLAGS`` lack the thread flag: they are
    :func:`integrators.loop.xla_options` (with ``--xla-default``, the environment's).

Memory
    ``rattle`` runs ``1e6`` and ``1e7`` steps on sps-receiver, each in a fresh Python
    process, and the peak resident set of each process is its own high-water mark
    (:func:`benchmarks.perf.processes.peak_rss`). The bar: both peaks under
    :data:`MEMORY_BAR` and no growth with the step count beyond :data:`MEMORY_GROWTH`
    (anything the loop kept per step, even one float, would add at least 72 MB over the
    extra ``9e6`` steps).

Figures and verdicts are printed; nothing is asserted silently. The exit status is 1 only
when something did not run or the implementations disagree, not when a bar is missed.

Usage::

    python -m benchmarks.perf.throughput
    python -m benchmarks.perf.throughput --steps 2e6 --rounds 21 --skip-memory
"""

from __future__ import annotations

import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import integrators
import problems
from benchmarks import compilation, pool
from benchmarks.perf.processes import compile_yardstick, run_process, state_difference
from benchmarks.records import CommandParser
from integrators.base import Grid
from integrators.loop import kernel_environment

#: The throughput bar: rattle's steps per second over the C loop's.
RATIO_BAR = 0.8
#: The memory bar: peak resident set of a whole run's process (bytes).
MEMORY_BAR = 1 << 30
#: Largest rise of the peak from 1e6 to 1e7 steps that still counts as no growth (bytes):
#: allocator and compilation noise is a few MB; anything kept per step is 72 MB or more.
MEMORY_GROWTH = 16 << 20
#: Agreement of C and rattle, final state (max-norm). Iterating Newton to round-off, the
#: same arithmetic rounded differently (the yardstick built with -O0, with FMA contraction
#: or in x87 extended precision) ends 1e6 steps up to 8e-10 apart: an O(eps) change of g
#: moves the momenta by O(eps / h) per step, and that accumulates. 1e-7 leaves a hundredfold
#: margin and stays far below what a change of the method does (lobatto3ab3, order 4, ends
#: 2e-3 away from rattle, order 2; printed below).
AGREE_STATE = 1e-7
#: Maxima of |g| and |G v| (absolute): both sides sit at round-off, 1e-15 for O(1)
#: coordinates; a Newton stopped at a looser tolerance leaves about that tolerance in g
#: (7e-11 with newton_tol = 1e-10).
AGREE_RESIDUAL = 1e-14
#: Maximum of |H - H0| (relative): 4e-6 at h = 1e-3, moved by about 1e-5 of itself by the
#: round-off differences of the state above (measured 9e-6); a change of the method moves
#: it by O(1).
AGREE_ENERGY_REL = 1e-3

#: Share of a side's wall clock spent waiting for a core above which the report says that
#: the cores were oversubscribed: a process that has a core to itself hardly waits for it.
CONTENDED = 0.1

PROBLEM = "sps-receiver"


def run_c(exe: Path, steps: int, h: float, tol: float) -> dict:
    """One run of the C loop: its rate and results."""
    ending, stdout, stderr, _ = run_process([str(exe), str(steps), repr(h), repr(tol)],
                                            math.inf, dict(os.environ))
    if ending:
        raise RuntimeError(f"the C yardstick ended with {ending}: {stderr.strip()[-2000:]}")
    out = stdout.split()
    n, secs, cpu = int(out[0]), float(out[1]), float(out[10])
    return {"rate": n / secs, "cpu_rate": n / cpu, "q": [float(out[2]), float(out[3])],
            "v": [float(out[4]), float(out[5])],
            "max": {"pos": float(out[6]), "vel": float(out[7]), "energy": float(out[8])},
            "n_newton": int(out[9])}


def prepare(key: str, steps: int, h: float):
    """Build sps-receiver over ``steps`` steps of ``h`` and compile ``key`` for it."""
    case = problems.make(PROBLEM).with_t_end(steps * h)
    integ = integrators.make(key, h=h)
    start = time.perf_counter()
    solve = integ.prepare(case, Grid(case.t0, case.t_end))
    setup = time.perf_counter() - start
    return integ, solve, setup, one_kernel(solve.compiled.as_text())


def one_kernel(hlo: str) -> bool:
    """Whether XLA emitted the time loop as native kernels: no while loop is left in the
    entry computation of the optimised HLO (it runs inside calls marked as kernels)."""
    entry = hlo[hlo.index("\nENTRY"):]
    entry = entry[:entry.index("\n}")]
    return "xla_cpu_small_call" in hlo and " while(" not in entry


def summary(traj) -> dict:
    """What the report and the agreement check need from a trajectory."""
    return {"status": traj.status, "message": traj.message, "steps": traj.counts["n_steps"],
            "q": [float(x) for x in traj.q_final], "v": [float(x) for x in traj.v_final],
            "max": {k: float(np.max(traj.windows[k])) for k in ("pos", "vel", "energy")},
            "n_newton": traj.counts["n_newton"]}


def agreement(c: dict, jax_run: dict) -> tuple[bool, str]:
    """Whether the C loop and rattle agree (final state and the three maxima)."""
    dq = max(state_difference(c["q"] + c["v"], jax_run["q"] + jax_run["v"]))
    dpos = abs(c["max"]["pos"] - jax_run["max"]["pos"])
    dvel = abs(c["max"]["vel"] - jax_run["max"]["vel"])
    de = abs(c["max"]["energy"] - jax_run["max"]["energy"]) / c["max"]["energy"]
    ok = dq <= AGREE_STATE and max(dpos, dvel) <= AGREE_RESIDUAL and de <= AGREE_ENERGY_REL
    text = (f"final (q, v) differ by {dq:.2e} (<= {AGREE_STATE:g}); max|g| by {dpos:.1e}, "
            f"max|G v| by {dvel:.1e} (<= {AGREE_RESIDUAL:g}); max|H - H0| by {de:.1e} "
            f"relative (<= {AGREE_ENERGY_REL:g}); Newton iterations C {c['n_newton']}, "
            f"rattle {jax_run['n_newton']}")
    return ok, text


def run_queue_wait(tasks: str = "/proc/self/task") -> float | None:
    """Seconds this process's threads have spent runnable but waiting for a core (the
    second field of Linux's ``/proc/self/task/*/schedstat``; ``tasks`` is that folder);
    ``None`` where it is not given. A thread that ends takes its count with it: a
    difference of two readings covers the threads alive at both."""
    total = 0
    try:
        names = os.listdir(tasks)
    except OSError:
        return None
    for tid in names:
        try:
            with open(os.path.join(tasks, tid, "schedstat")) as f:
                total += int(f.read().split()[1])
        except FileNotFoundError:   # a thread that has ended since the listing
            continue
        except (OSError, IndexError, ValueError):
            return None
    return total * 1e-9


def ratio_summary(ours: list[float], theirs: list[float]) -> dict:
    """The ratio of two series of per-round rates taken side by side: ``median`` of the
    per-round ratios ``ours[i] / theirs[i]``, their ``quartiles`` (the lower and upper;
    both the one ratio with a single round) and ``fastest``, the fastest round's rate
    over the fastest round's."""
    per_round = [a / b for a, b in zip(ours, theirs, strict=True)]
    quartiles = (statistics.quantiles(per_round, n=4, method="inclusive")[::2]
                 if len(per_round) > 1 else per_round * 2)
    return {"per_round": per_round, "median": statistics.median(per_round),
            "quartiles": tuple(quartiles), "fastest": max(ours) / max(theirs)}


def throughput(steps: int, h: float, rounds: int, budget: float, workdir: Path) -> bool:
    """The side-by-side timing; returns False if something did not run or disagreed."""
    exe, note, _ = compile_yardstick("rattle_sps", workdir)
    print(f"C yardstick: {note}")
    keys = ["rattle", "lobatto3ab3"]
    methods = {}
    for key in keys:
        integ, solve, setup, kernel = prepare(key, steps, h)
        methods[key] = {"integ": integ, "solve": solve, "rates": [], "time": 0.0}
        print(f"{key}: set-up {setup:.2f} s; time loop compiled as one kernel: "
              f"{'yes' if kernel else 'no'}")
    tol = methods["rattle"]["integ"].newton_tol
    c_runs, results = [], {}
    load_before = os.getloadavg()[0]
    for r in range(rounds):
        if exe is not None:
            c_runs.append(run_c(exe, steps, h, tol))
        for key, m in methods.items():
            # A slow method gets fewer rounds, but at least one.
            if r > 0 and m["time"] > budget:
                continue
            waited, start, cpu = run_queue_wait(), time.perf_counter(), time.process_time()
            traj = m["solve"]()
            elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
            after = run_queue_wait()
            waited = None if waited is None or after is None else after - waited
            m["time"] += elapsed
            m["rates"].append((r, steps / elapsed, steps / cpu,
                               None if waited is None else waited / elapsed))
            results[key] = summary(traj)
    load_after = os.getloadavg()[0]
    print(f"\n{steps:.3g} steps of h = {h:g} on {PROBLEM}, {rounds} alternating rounds; "
          f"1-minute load average {load_before:.2f} before, {load_after:.2f} after "
          f"(other processes share the cores: read the rates with it)")
    ok = True

    def line(name: str, wall: list[float], cpu: list[float]) -> str:
        return (f"  {name:12s} {statistics.median(wall):9.3g} steps/s wall clock, "
                f"{statistics.median(cpu):9.3g} per CPU second  (rounds, wall: "
                f"{', '.join(f'{x:.3g}' for x in wall)})")

    if c_runs:
        print(line("C", [c["rate"] for c in c_runs], [c["cpu_rate"] for c in c_runs]))
    for key, m in methods.items():
        res = results[key]
        print(line(key, [x[1] for x in m["rates"]], [x[2] for x in m["rates"]]))
        print(f"  {'':12s} status {res['status']}, max|g| {res['max']['pos']:.2e}, "
              f"max|G v| {res['max']['vel']:.2e}, max|H - H0| {res['max']['energy']:.3e}, "
              f"{res['n_newton']} Newton iterations")
        if res["status"] != "ok" or res["steps"] != steps:
            print(f"  {key} did not complete: {res['message']}")
            ok = False
    if not c_runs:
        print("  ratio rattle / C: not measured (no C yardstick)")
        return ok
    ratios = {}
    timed = methods["rattle"]["rates"]
    for i, clock in ((1, "wall clock"), (2, "CPU time")):
        field = "rate" if i == 1 else "cpu_rate"
        ratio = ratio_summary([x[i] for x in timed], [c_runs[x[0]][field] for x in timed])
        ratios[clock] = ratio["median"]
        low, high = ratio["quartiles"]
        rounds_text = ", ".join(f"{x:.2f}" for x in ratio["per_round"])
        print(f"  ratio rattle / C by {clock}: {ratio['median']:.3f} (median of "
              f"{len(timed)} rounds; quartiles {low:.3f} to {high:.3f}; fastest rounds "
              f"{ratio['fastest']:.3f}; rounds {rounds_text})")
    c_wait = statistics.median(max(0.0, 1.0 - c["rate"] / c["cpu_rate"]) for c in c_runs)
    ours = [x[3] for x in timed if x[3] is not None]
    print(f"  waiting for a core, share of the wall clock (median over the rounds): C "
          f"{c_wait:.0%}, rattle "
          + (f"{statistics.median(ours):.0%}" if ours else "not measured (no schedstat)")
          + ("; the cores were oversubscribed: the ratios above measure the load as much "
             "as the code" if max([c_wait, *ours]) > CONTENDED else ""))
    held = ratios["wall clock"] >= RATIO_BAR
    print(f"  bar: rattle >= {RATIO_BAR} x C in steps per second (wall clock): "
          f"{'holds' if held else 'NOT met'}"
          + ("" if held == (ratios["CPU time"] >= RATIO_BAR) else
             f"; by CPU time it {'holds' if not held else 'is NOT met'}: the load moved it"))
    agree, text = agreement(c_runs[-1], results["rattle"])
    print(f"  C and rattle agree: {'yes' if agree else 'NO'}: {text}")
    if "lobatto3ab3" in results:
        other, ours = results["lobatto3ab3"], results["rattle"]
        d = max(state_difference(other["q"] + other["v"], ours["q"] + ours["v"]))
        print(f"  for scale: lobatto3ab3 ends {d:.2e} away from rattle (their different "
              f"discretisation errors)")
    return ok and agree


CHILD = """
import json, sys, time
import integrators, problems
from benchmarks.perf.processes import peak_rss
from integrators.base import Grid
steps, h = int(sys.argv[1]), float(sys.argv[2])
case = problems.make({problem!r}).with_t_end(steps * h)
solve = integrators.make("rattle", h=h).prepare(case, Grid(case.t0, case.t_end))
start = time.perf_counter()
traj = solve()
print(json.dumps({{"status": traj.status, "steps": traj.counts["n_steps"],
                  "solve_s": time.perf_counter() - start, "peak_rss": peak_rss()}}))
"""


def run_peak(steps: int, h: float, env: dict) -> tuple[int | None, dict]:
    """Peak resident set (bytes; None without ``/proc``) of a fresh process that runs rattle
    for ``steps`` steps, and what it reports of its run."""
    command = [sys.executable, "-c", CHILD.format(problem=PROBLEM), str(steps), repr(h)]
    ending, stdout, stderr, polled = run_process(command, math.inf, env)
    if ending:
        raise RuntimeError(f"the {steps:.0e}-step run ended with {ending}: {stderr[-2000:]}")
    info = json.loads(stdout.strip().splitlines()[-1])
    return info.pop("peak_rss") or polled, info


def memory(h: float, counts: list[int]) -> bool:
    """The peak-memory part; returns False if a run failed."""
    env = dict(os.environ)
    print(f"\npeak memory of rattle on {PROBLEM} (h = {h:g}), each run in a fresh process:")
    peaks = []
    for steps in counts:
        peak, info = run_peak(steps, h, env)
        if peak is None:
            print("  no peak memory on this system (no /proc): the bar is not measured")
            return True
        peaks.append(peak)
        print(f"  {steps:.0e} steps: peak RSS {peak / 2**20:7.1f} MiB; status {info['status']}, "
              f"{info['steps']} steps, solve {info['solve_s']:.2f} s")
        if info["status"] != "ok" or info["steps"] != steps:
            print(f"  the {steps:.0e}-step run did not complete: the bar is not measured")
            return False
    under = max(peaks) < MEMORY_BAR
    growth = peaks[-1] - peaks[0]
    flat = growth <= MEMORY_GROWTH
    print(f"  under {MEMORY_BAR / 2**30:g} GiB: {'holds' if under else 'NOT met'}; growth from "
          f"{counts[0]:.0e} to {counts[-1]:.0e} steps {growth / 2**20:+.1f} MiB (no growth: "
          f"<= {MEMORY_GROWTH / 2**20:.0f} MiB): {'holds' if flat else 'NOT met'}")
    return True


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.throughput",
                           description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=float, default=1e6, help="steps per timed run")
    parser.add_argument("--h", type=float, default=1e-3, help="step size")
    parser.add_argument("--rounds", type=int, default=15, help="alternating rounds")
    parser.add_argument("--budget", type=float, default=60.0,
                        help="seconds of solves per method after which it skips rounds")
    parser.add_argument("--memory-steps", type=float, nargs="+", default=[1e6, 1e7])
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--xla-default", action="store_true",
                        help="leave XLA_FLAGS as they are (no one-kernel loop flag)")
    args = parser.parse_args(argv)
    for name, value in (("--rounds", args.rounds), ("--steps", args.steps)):
        if not value >= 1:
            parser.error(f"{name} {value:g} must be at least 1")
    compilation.enable()
    # JAX reads XLA_FLAGS once, when its CPU client starts (at the first computation, not at
    # import): nothing has computed yet.
    if not args.xla_default:
        os.environ.update(kernel_environment())
    pool.one_blas_thread()
    pool.one_xla_thread()
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    ok = True
    if not args.skip_throughput:
        with tempfile.TemporaryDirectory() as tmp:
            ok &= throughput(int(args.steps), args.h, args.rounds, args.budget, Path(tmp))
    if not args.skip_memory:
        ok &= memory(args.h, [int(n) for n in args.memory_steps])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
