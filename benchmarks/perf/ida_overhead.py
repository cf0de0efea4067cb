"""Benchmark: what IDA's Python callbacks cost, per internal step, on the pendulum.

``ida-ggl`` and ``ida-index1`` run ``pendulum`` (default 100 s at rtol = atol = 1e-8) after
set-up, several rounds alternating between them so that a change in the machine's load hits
both alike. Per round the solve's wall time, IDA's internal steps and the time spent in our
residual and Jacobian callbacks (``Trajectory.extra``) give:

- wall time per internal step (µs);
- callback time per residual and per Jacobian call (µs);
- ``callback_s / wall_s``, the share of the solve spent in the callbacks. The rest is
  IDA's own work, the binding's one-step calls and our per-step bookkeeping.

The goal: ``callback_s / wall_s`` under :data:`SHARE_GOAL` (the callbacks must not be
nearly all of the cost). Figures are medians over the rounds; the load average at the start
is printed, because on a shared machine every figure here moves with it. The process runs
with the benchmark workers' thread settings (one intra-op thread).

Usage::

    python -m benchmarks.perf.ida_overhead
    python -m benchmarks.perf.ida_overhead --t-end 20 --rtol 1e-10 --rounds 5
"""

from __future__ import annotations

import os
import statistics
import time

from benchmarks.perf.processes import like_a_worker
from benchmarks.records import CommandParser

#: The goal for the share of the solve spent in our callbacks.
SHARE_GOAL = 0.8


def measure(spec: str, t_end: float, rounds: int):
    """Set up ``spec`` on the pendulum and time ``rounds`` solves; yield one dict per round."""
    import integrators
    import problems
    from integrators.base import Grid

    case = problems.make("pendulum").with_t_end(t_end)
    start = time.perf_counter()
    solve = integrators.make(spec).prepare(case, Grid(case.t0, case.t_end))
    setup = time.perf_counter() - start
    for _ in range(rounds):
        start = time.perf_counter()
        traj = solve()
        wall = time.perf_counter() - start
        c, x = traj.counts, traj.extra
        yield {"status": traj.status, "setup_s": setup, "wall_s": wall,
               "steps": c["n_steps"], "residuals": c["n_f_evals"], "jacobians": c["n_jac_evals"],
               "callback_s": x["callback_s"], "residual_s": x["residual_s"],
               "jacobian_s": x["jacobian_s"]}


def main(argv=None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.ida_overhead",
                           description=__doc__.splitlines()[0])
    parser.add_argument("--t-end", type=float, default=100.0, help="horizon (s)")
    parser.add_argument("--rtol", type=float, default=1e-8, help="rtol (atol = rtol)")
    parser.add_argument("--rounds", type=int, default=3, help="timed solves of each key")
    args = parser.parse_args(argv)
    load = like_a_worker()
    print(f"pendulum, t_end = {args.t_end:g} s, rtol = atol = {args.rtol:g}; "
          f"load average at start {load:.2f} on {os.cpu_count()} cores")
    keys = ("ida-ggl", "ida-index1")
    runs = {key: measure(f"{key}:rtol={args.rtol}", args.t_end, args.rounds) for key in keys}
    results = {key: [] for key in keys}
    for _ in range(args.rounds):
        for key in keys:
            results[key].append(next(runs[key]))

    failed = False
    for key in keys:
        rows = results[key]
        if any(r["status"] != "ok" for r in rows):
            print(f"{key}: the solve did not finish: {[r['status'] for r in rows]}")
            failed = True
            continue

        def med(f):
            return statistics.median(f(r) for r in rows)

        share = med(lambda r: r["callback_s"] / r["wall_s"])
        r0 = rows[0]
        print(f"\n{key}: {r0['steps']} steps, {r0['residuals']} residual and "
              f"{r0['jacobians']} Jacobian calls per solve; set-up {r0['setup_s']:.2f} s")
        print(f"  wall per solve          {med(lambda r: r['wall_s']):9.3f} s")
        print(f"  wall per internal step  {med(lambda r: 1e6 * r['wall_s'] / r['steps']):9.1f} us")
        print(f"  per residual call       "
              f"{med(lambda r: 1e6 * r['residual_s'] / r['residuals']):9.1f} us")
        print(f"  per Jacobian call       "
              f"{med(lambda r: 1e6 * r['jacobian_s'] / max(1, r['jacobians'])):9.1f} us")
        verdict = "meets" if share < SHARE_GOAL else "misses"
        print(f"  callback_s / wall_s     {share:9.3f}   ({verdict} the goal < {SHARE_GOAL})")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
