"""Benchmark: ensembles in one compiled loop, against one trajectory at a time and plain C.

Rates
    For each method (``rattle``, ``lobatto3ab3``) and problem (``pendulum``, ``sps-receiver``)
    the same horizon (default ``1e4`` steps of ``h = 1e-2``) runs as one trajectory
    (:meth:`~integrators.base.Integrator.prepare`, the suite's single run) and as ensembles
    of ``K`` lanes (:meth:`~integrators.fixed.FixedStep.prepare_ensemble`, one compiled loop
    under ``jax.vmap``) from the problem's perturbed initial states
    (:mod:`problems.ensemble`), with the ensembles' recording grid
    (:data:`benchmarks.plan.ENSEMBLE_GRID`) on both. Each figure is a rate of steps: steps
    per second for one trajectory, lane-steps (lanes times steps) per second for an
    ensemble, timed around the whole ``solve()`` (the compiled loop and the read-back of
    the trajectories), after set-up and compilation, the median of at least ``--repeats``
    solves (autorange, :func:`timed`). The C yardstick (``yardstick/rattle_sps.c``, the
    same RATTLE step on sps-receiver, see :mod:`benchmarks.perf.throughput`) gives plain
    C's steps per second beside them. This process is set up as the suite's workers are
    (one intra-op thread, the one-kernel XLA flag,
    :func:`benchmarks.perf.processes.like_a_worker`), before it first computes: one core.
    The one trajectory runs on the CPU, as the suite's single runs do; the ensembles on
    ``--device`` (``auto``: a GPU where JAX sees one, else the CPU; the platform is printed
    with each figure).

    The bars (issue figures): at 1024 lanes on the pendulum, ``rattle``'s lane-steps per
    second at least :data:`BARS` ``["rattle"]`` times its one-trajectory steps per second,
    ``lobatto3ab3``'s at least ``BARS["lobatto3ab3"]`` times, the one trajectory timed in
    turn with the ensemble (:func:`in_turn`).

The plain step
    With ``--plain``, the pendulum's RATTLE step alone (:func:`plain`: the same equations,
    Newton on the multiplier to ``|g| <= 4e-16``, nothing else: no recording of
    ``|g|``, ``|G v|`` or the energy, no failure test, no segments), and then the suite's
    own ``Rattle.step`` (its Newton and stopping rule) alone in a plain loop, each as one
    trajectory and vmapped over the same lanes. Their rates are what XLA makes of batching
    the bare step on this machine, beside what the suite's loop achieves with its
    bookkeeping.

Memory
    ``--memory-method`` (``rattle``) on ``chain:N=8`` with 16384 lanes at ``h =``
    :data:`MEMORY_H`, in fresh processes: the peak resident set
    (``VmHWM``) of the whole run (drawing the states, compiling, solving, reading back) at
    each of ``--memory-steps``, beside the bytes of the buffers XLA assigned to the compiled
    loop. The loop keeps per lane only its state, the window maxima and three samples, and
    its step count is an argument of one compiled program, whose buffers are fixed when it
    is compiled; so the peak must not grow with the steps. The bar is :data:`MEMORY_BAR` at
    ``1e5`` steps.

Figures and verdicts are printed; the exit status is 1 only when something did not run.

Usage::

    python -m benchmarks.perf.ensemble
    python -m benchmarks.perf.ensemble --lanes 1 256 1024 --skip-memory
    python -m benchmarks.perf.ensemble --device gpu --receiver
    python -m benchmarks.perf.ensemble --methods rattle --problems pendulum --plain
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

import jax
import jax.numpy as jnp
import numpy as np

import integrators
import problems
from benchmarks.execute import more
from benchmarks.perf.processes import (compile_yardstick, like_a_worker, run_process)
from benchmarks.perf.throughput import run_c
from benchmarks.plan import DEVICES, ENSEMBLE_GRID, jax_device
from benchmarks.records import CommandParser
from benchmarks.suites import RANGES
from integrators.base import Grid
from linalg.dense import solve as dense_solve
from problems.ensemble import draw
from problems.spec import SpecError

#: Lane-steps per second over one trajectory's steps per second, at :data:`BAR_LANES` lanes
#: on the pendulum.
BARS = {"rattle": 3.0, "lobatto3ab3": 2.0}
BAR_LANES = 1024
#: Peak resident set of the 16384-lane chain run (bytes).
MEMORY_BAR = 2 << 30
#: Step of the memory runs: at h = 0.01, 3 of 1024 chain lanes failed within 2000 steps
#: and the slowest lane took 11.7 Newton iterations per step (each step of an ensemble
#: costs its slowest lane's); at h = 0.005 every lane was ok, with 8.1 (1024 lanes, one
#: core). Over 1e5 steps of h = 0.005, 71 of 16384 lanes failed (on a GPU).
MEMORY_H = 5e-3
#: Bound on max |g| over the receiver ensemble's lanes, and on a lane's final state against
#: its single run.
RECEIVER_BAR = 1e-12


def timed(solve, repeats: int) -> tuple[float, object]:
    """Median seconds of the solves, timed as the suite times a run (autorange,
    :func:`benchmarks.execute.more`: ``repeats`` solves at least, more while they add up to
    less than a fifth of a second, within its cap), and the last result. The 1e4 steps of
    one pendulum trajectory take about a millisecond: ten solves, not three. Their rate
    still differs from one process to the next on a shared machine (6.5e6 and 9.4e6 steps
    per second for rattle in two processes, the median of 21 solves each, load 0.9)."""
    times: list[float] = []
    while not times or more(times, repeats):
        start = time.perf_counter()
        out = solve()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def in_turn(ensemble, single, repeats: int) -> tuple[float, float, object]:
    """Median seconds of the ensemble's solves and of the one trajectory's, timed in turn:
    after each ensemble solve (autorange, as :func:`timed`) the median of an autorange
    burst of one-trajectory solves. The pair is measured over the same stretch of time: on
    this shared machine a process's rate can drift by a quarter within seconds (a pendulum
    trajectory's first solves at 9.4e6 to 1.1e7 steps per second and the later ones at 7e6),
    which had put the one trajectory, timed first, in a faster stretch than the ensembles.
    Returns ``(ensemble_s, single_s, last ensemble result)``."""
    t_ens, t_one = [], []
    while not t_ens or more(t_ens, repeats):
        start = time.perf_counter()
        out = ensemble()
        t_ens.append(time.perf_counter() - start)
        with jax.default_device(jax_device("cpu")):
            t_one.append(timed(single, repeats)[0])
    return statistics.median(t_ens), statistics.median(t_one), out


def rates(method: str, problem: str, steps: int, h: float, lanes: list[int], repeats: int,
          budget: float, device: jax.Device) -> dict:
    """One trajectory's steps per second (on the CPU) and each ensemble's lane-steps per
    second (on ``device``), with the one trajectory's rate timed in turn with each ensemble
    (:func:`in_turn`) and the ratio of the two; an ensemble expected to take longer than
    ``budget`` seconds per solve is skipped. The expectation comes from the last ensemble's
    rate, or from the one trajectory's for the first ensemble on the CPU; on a GPU the
    first always runs (there a batch's rate is up to hundreds of times the CPU's one
    trajectory)."""
    case = problems.make(problem).with_t_end(steps * h)
    grid = Grid(case.t0, case.t_end, **ENSEMBLE_GRID)
    integ = integrators.make(method, h=h)
    q0s, v0s = draw(case, max(lanes), seed=0)
    with jax.default_device(jax_device("cpu")):
        one = integ.prepare(case, grid)
        seconds, traj = timed(one, repeats)
    single = steps / seconds
    out = {"single": single, "lanes": {}, "ratio": {}}
    print(f"{method} on {problem}: one trajectory {single:.3g} steps/s "
          f"({traj.status}, {traj.counts['n_newton']} Newton iterations)", flush=True)
    for k in lanes:
        expected = k * steps / max(out["lanes"].values(), default=single)
        if expected > budget and (out["lanes"] or device.platform == "cpu"):
            print(f"  {k:6d} lanes: skipped (about {expected:.0f} s per solve, over the "
                  f"budget of {budget:g} s)", flush=True)
            continue
        with jax.default_device(device):
            start = time.perf_counter()
            solve = integ.prepare_ensemble(case, grid, q0s[:k], v0s[:k])
            setup = time.perf_counter() - start
            seconds, alone, trajs = in_turn(solve, one, repeats)
        rate = k * steps / seconds
        out["lanes"][k] = rate
        out["ratio"][k] = rate / (steps / alone)
        bad = sum(t.status != "ok" for t in trajs)
        print(f"  {k:6d} lanes on {device.platform}: {rate:.3g} lane-steps/s = "
              f"{out['ratio'][k]:.2f} x one trajectory timed in turn ({steps / alone:.3g} "
              f"steps/s); solve {seconds:.3g} s, set-up {setup:.3g} s; {bad} lanes failed",
              flush=True)
    return out


def plain(steps: int, h: float, lanes: list[int], repeats: int, device: jax.Device) -> None:
    """RATTLE's step on the pendulum and nothing else (module notes), one trajectory on
    the CPU and vmapped over ``lanes`` on ``device``."""
    case = problems.make("pendulum")
    mech, t = case.mech, jnp.float64(case.t0)

    def step(state, _):
        q0, p0 = state
        F0, G0 = -mech.H_q(q0, p0), mech.G(q0, t)

        def half(lam):
            p_half = p0 + 0.5 * h * (F0 - G0.T @ lam)
            return p_half, q0 + h * mech.H_p(q0, p_half)

        def residual(lam):
            return mech.g(half(lam)[1], t)

        def body(state):
            lam, r, k = state
            lam = lam - dense_solve(jax.jacfwd(residual)(lam), r)
            return lam, residual(lam), k + 1

        lam0 = jnp.zeros(mech.m)
        lam, _, _ = jax.lax.while_loop(
            lambda state: (jnp.max(jnp.abs(state[1])) > 4e-16) & (state[2] < 50), body,
            (lam0, residual(lam0), 0))
        p_half, q1 = half(lam)
        base = p_half - 0.5 * h * mech.H_q(q1, p_half)
        G1 = mech.G(q1, t)
        mu = dense_solve(0.5 * h * G1 @ mech.solve_mass(q1, G1.T), G1 @ mech.H_p(q1, base))
        return (q1, base - 0.5 * h * G1.T @ mu), None

    def run(q0, v0):
        return jax.lax.scan(step, (q0, mech.momentum(q0, v0)), None, length=steps)[0]

    integ = integrators.make("rattle", h=h)
    schur = integ.linear_algebra(mech)

    def run_step(q0, v0):
        # The suite's step (its Newton and stopping rule) with nothing around it.
        carry = integ.start(mech, schur, q0, v0, t)
        return jax.lax.scan(lambda c, _: (integ.step(mech, schur, c, t, h)[0], None), carry,
                            None, length=steps)[0][:2]

    q0s, v0s = draw(case, max(lanes), seed=0)
    for title, fn in (("plain RATTLE step on pendulum (no recording, no failure test, Newton "
                       "to |g| <= 4e-16)", run),
                      ("the suite's Rattle.step alone on pendulum (its stopping rule; no "
                       "recording, no failure rule)", run_step)):
        with jax.default_device(jax_device("cpu")):
            one = jax.jit(fn).lower(q0s[0], v0s[0]).compile()
            seconds, _ = timed(lambda: jax.block_until_ready(one(q0s[0], v0s[0])), repeats)
        single = steps / seconds
        print(f"\n{title}: one trajectory {single:.3g} steps/s")
        for k in lanes:
            with jax.default_device(device):
                batch = jax.jit(jax.vmap(fn)).lower(q0s[:k], v0s[:k]).compile()
                seconds, _ = timed(lambda: jax.block_until_ready(batch(q0s[:k], v0s[:k])),
                                   repeats)
            print(f"  {k:6d} lanes on {device.platform}: {k * steps / seconds:.3g} lane-steps/s "
                  f"= {k * steps / seconds / single:.2f} x its one trajectory", flush=True)


CHILD = """
import json, sys, time
from benchmarks.perf.processes import like_a_worker, peak_rss
like_a_worker()
import jax, integrators, problems
from benchmarks.plan import ENSEMBLE_GRID, jax_device
from integrators.base import Grid
from problems.ensemble import draw
lanes, steps, h = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
device, method = jax_device(sys.argv[4]), sys.argv[5]
case = problems.make("chain:N=8").with_t_end(steps * h)
q0s, v0s = draw(case, lanes, seed=0)
with jax.default_device(device):
    solve = integrators.make(method, h=h).prepare_ensemble(
        case, Grid(case.t0, case.t_end, **ENSEMBLE_GRID), q0s, v0s)
    start = time.perf_counter()
    trajs = solve()
stats = device.memory_stats() or {}
print(json.dumps({"ok": sum(t.status == "ok" for t in trajs), "solver": trajs[0].linear_solver,
                  "solve_s": time.perf_counter() - start, "peak_rss": peak_rss(),
                  "platform": device.platform, "device_peak": stats.get("peak_bytes_in_use"),
                  "buffers": solve.compiled.buffer_bytes}))
"""


def memory(lanes: int, counts: list[int], h: float, device: str, method: str) -> bool:
    """Peak memory of the chain ensemble at each step count, in fresh processes."""
    print(f"\npeak memory of {method} on chain:N=8, {lanes} lanes, h = {h:g}, fresh processes:")
    peaks = []
    for steps in counts:
        command = [sys.executable, "-c", CHILD, str(lanes), str(steps), repr(h), device, method]
        ending, stdout, stderr, polled = run_process(command, math.inf, None)
        if ending:
            print(f"  {steps:.0e} steps: ended with {ending}: {stderr.strip()[-500:]}")
            return False
        info = json.loads(stdout.strip().splitlines()[-1])
        peak = info["peak_rss"] or polled
        peaks.append(peak)
        on = f"{info['platform']}, {info['solver']} linear solver"
        if info["device_peak"] is not None:
            on += f", device peak {info['device_peak'] / 2**20:.0f} MiB"
        if info["buffers"] is not None:
            on += f", the loop's buffers {info['buffers'] / 2**20:.0f} MiB"
        print(f"  {steps:.0e} steps ({on}): peak RSS {peak / 2**20:.0f} MiB; {info['ok']} of "
              f"{lanes} lanes ok; solve {info['solve_s']:.1f} s "
              f"({lanes * steps / info['solve_s']:.3g} lane-steps/s)", flush=True)
    verdict = "holds" if max(peaks) < MEMORY_BAR else "NOT met"
    print(f"  under {MEMORY_BAR / 2**30:g} GiB at every step count: {verdict}")
    return True


def receiver(device: jax.Device) -> None:
    """The receiver ensemble on ``device`` against single runs on the CPU (module notes)."""
    case = problems.make("sps-receiver").with_t_end(50.0)
    grid = Grid(case.t0, case.t_end, **ENSEMBLE_GRID)
    q0s, v0s = draw(case, 256, seed=0)
    integ = integrators.make("rattle", h=0.05)
    with jax.default_device(device):
        lanes = integ.prepare_ensemble(case, grid, q0s, v0s)()
    ok = sum(lane.status == "ok" for lane in lanes)
    worst = max(float(np.max(lane.windows["pos"])) for lane in lanes)
    print(f"\nrattle on sps-receiver, 256 lanes on {device.platform}, h = 0.05 to t = 50: "
          f"{ok} lanes ok, max |g| {worst:.3g} (bar {RECEIVER_BAR:g})")
    apart = 0.0
    with jax.default_device(jax_device("cpu")):
        for i in np.random.default_rng(7).choice(256, 5, replace=False):
            single = integ.prepare(case.with_initial(q0s[i], v0s[i]), grid)()
            gap = max(float(np.max(np.abs(lanes[i].q_final - single.q_final))),
                      float(np.max(np.abs(lanes[i].v_final - single.v_final))))
            apart = max(apart, gap)
            print(f"  lane {i:3d} against its single run on the CPU: final q, v within {gap:.3g}")
    holds = ok == 256 and worst <= RECEIVER_BAR and apart <= RECEIVER_BAR
    print(f"  {'holds' if holds else 'NOT met'}")


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.ensemble",
                           description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=float, default=1e4, help="steps per run")
    parser.add_argument("--h", type=float, default=1e-2, help="step size")
    parser.add_argument("--lanes", type=int, nargs="+",
                        default=[1, 16, 256, 1024, 4096, 16384])
    parser.add_argument("--methods", nargs="*", default=list(BARS),
                        help="methods whose rates are measured (none: only the other parts)")
    parser.add_argument("--problems", nargs="+", default=["pendulum", "sps-receiver"])
    parser.add_argument("--repeats", type=int, default=3,
                        help="timed solves at least (autorange; the median is reported)")
    parser.add_argument("--budget", type=float, default=30.0,
                        help="seconds per solve above which an ensemble size is skipped")
    parser.add_argument("--memory-lanes", type=int, default=16384)
    parser.add_argument("--memory-steps", type=float, nargs="+", default=[1e3, 1e4, 1e5])
    parser.add_argument("--memory-h", type=float, default=MEMORY_H,
                        help="step size of the memory runs (module notes)")
    parser.add_argument("--memory-method", default="rattle",
                        help="method spec of the memory runs, such as "
                             "rattle:linear_solver=dense")
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--plain", action="store_true",
                        help="also time the bare RATTLE step on the pendulum (module notes)")
    parser.add_argument("--receiver", action="store_true",
                        help="check the 256-lane sps-receiver ensemble (module notes)")
    parser.add_argument("--device", choices=DEVICES, default="auto",
                        help="where the ensembles run (auto: a GPU where JAX sees one)")
    args = parser.parse_args(argv)
    # The command line's and the suite files' ranges where they mean the same.
    steps = (lambda x: 1 <= x < math.inf, "at least 1")
    for name, values, (ok, must) in [
            ("--lanes", args.lanes, RANGES["ensemble"]),
            ("--memory-lanes", [args.memory_lanes], RANGES["ensemble"]),
            ("--steps", [args.steps], steps), ("--memory-steps", args.memory_steps, steps),
            ("--h", [args.h], RANGES["h"]), ("--memory-h", [args.memory_h], RANGES["h"]),
            ("--repeats", [args.repeats], RANGES["repeats"]),
            ("--budget", [args.budget], RANGES["budget"])]:
        bad = [x for x in values if not ok(x)]
        if bad:
            parser.error(f"{name} {bad[0]:g} must be {must}")
    if not math.isfinite(args.steps * args.h):
        parser.error(f"--steps {args.steps:g} of --h {args.h:g} make no finite horizon")
    # Before anything computes: resolving a problem starts XLA's client, and flags set
    # after that are not applied.
    load = like_a_worker()
    try:  # a misspelt method or problem is one line here, not a traceback later
        for spec in [*args.methods, args.memory_method]:
            integrators.make(spec)
        for spec in args.problems:
            problems.resolve(spec)
    except SpecError as exc:
        parser.error(str(exc))
    device = jax_device(args.device)
    if device is None:
        parser.error("--device gpu, but JAX sees no GPU on this machine")
    print(f"load average (1 min) at start: {load:.2f}; ensembles on {device.platform} "
          f"({device.device_kind}), one trajectory on the CPU")
    steps = int(args.steps)
    results = {(m, p): rates(m, p, steps, args.h, sorted(args.lanes), args.repeats,
                             args.budget, device)
               for p in args.problems for m in args.methods}
    with tempfile.TemporaryDirectory() as tmp:
        exe, note, _ = compile_yardstick("rattle_sps", Path(tmp))
        if exe is not None:
            c = run_c(exe, steps, args.h, 1e-16)
            print(f"\nC yardstick (RATTLE on sps-receiver, one trajectory): {c['rate']:.3g} "
                  f"steps/s")
        else:
            print(f"\nC yardstick: {note}")
    print("\nbars (pendulum, lane-steps/s over one trajectory's steps/s, timed in turn):")
    for method, bar in BARS.items():
        ratio = results.get((method, "pendulum"), {}).get("ratio", {}).get(BAR_LANES)
        if ratio is None:
            print(f"  {method}: not measured at {BAR_LANES} lanes")
            continue
        print(f"  {method} at {BAR_LANES} lanes: {ratio:.2f} x (bar {bar:g} x): "
              f"{'holds' if ratio >= bar else 'NOT met'}")
    if args.plain:
        plain(steps, args.h, sorted(args.lanes), args.repeats, device)
    if args.receiver:
        receiver(device)
    ok = args.skip_memory or memory(args.memory_lanes, [int(n) for n in args.memory_steps],
                                    args.memory_h, device.platform, args.memory_method)
    print(f"load average (1 min) at end: {os.getloadavg()[0]:.2f}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
