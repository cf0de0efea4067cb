"""Benchmark: IFToMM A02 at scale, ``four-bar:N`` on the augmented-system (``kkt``) path.

What runs
    ``rattle`` at ``h = 1e-3`` over the benchmark's 20 s on ``four-bar:N`` for each ``--n``
    (default 40 and 4096), each in a fresh process, N ascending, side by side in one run.
    Every point is scored against the exact parallelogram-branch solution
    (:func:`problems.four_bar.exact_solution`) at its last step. The bar
    (:data:`G_BAR`): the largest N finishes (``ok``), with max ``|g|`` at most
    :data:`G_BAR` and a final-state error at most that of the smallest N.

    Every point runs rattle's default ``newton_tol`` (1e-16: iterate to round-off). The tips
    sit at ``x_i = i + cos(phi)``, so ``g`` is evaluated from coordinates of size ``N`` and
    its round-off is about ``eps N`` (4.5e-13 at N = 4096); Newton's round-off floor counts
    that (:func:`integrators.newton.newton`, :class:`integrators.rattle.Rattle`), so no
    per-N tolerance is needed.

    Measured (2 cores, load 2.65 at start, 2.67 at end): N = 40 (dense) ok, max ``|g|``
    1.4e-14, error 1.15e-4, 2.17 Newton iterations per step, 0.43 ms per step, 497 MiB;
    N = 4096 (``kkt``) ok, max ``|g|`` 2.3e-11, error 1.06e-4, 2.36 iterations per step,
    7.6 ms per step, 1109 MiB: the bar is met. Before, N = 4096 failed: at the first step
    with the default tolerance (the residual stalled at 4.5e-13, above a floor that did not
    see ``|q|``), and at t = 2.70 with ``newton_tol = 8 eps (N + 1)``, because the stall
    exit then accepted residuals up to a thousand times that tolerance (7e-9). What the
    crossings need (measured step by step at N = 1024, where the step starting at the
    singular configuration has ``S_0`` with a pivot of 7e-12 relative): simplified Newton
    diverges there and exact Newton takes over; its ``lambda`` is large (6e7) along the
    constraints that are dependent at ``q_0``, and carried as the next step's first guess
    it led Newton to a root off the parallelogram branch (the cranks stayed horizontal).
    Starting each step from the previous ``mu`` instead crosses on the branch, with 3 to 4
    iterations per step against 8 to 9.

    ``--crossover`` instead times :data:`CROSSOVER_STEPS` steps of the dense and the
    ``kkt`` path for each ``--n`` (the measurement behind
    :data:`linalg.schur.DENSE_KKT_MAX`).

What each number is
    the run's status and final time; max ``|g|`` and ``|G v|`` over its steps; the
    max-norm error of ``(q, v)`` at the end against the exact solution; Newton iterations
    per step; the wall time of ``solve()`` (the compiled time loop, set-up and compilation
    excluded and reported apart) and per step; the process's peak resident memory
    (:func:`benchmarks.perf.processes.peak_rss`), with the linear solver that ran.

Usage::

    python -m benchmarks.perf.four_bar
    python -m benchmarks.perf.four_bar --n 40 1024 4096 --t-end 2
    python -m benchmarks.perf.four_bar --crossover --n 2 4 8 16 32 64
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from benchmarks.perf.processes import like_a_worker, peak_rss, run_process, timed_run
from benchmarks.records import CommandParser

#: The bar on the largest constraint residual at the largest N.
G_BAR = 1e-10
#: Step size (s).
H = 1e-3
#: Steps each path takes per point of ``--crossover``.
CROSSOVER_STEPS = 1000
#: Wall-clock limit of one point (s).
LIMIT = 3600.0


def point(N: int, path: str, t_end: float) -> dict:
    """One run of rattle on ``four-bar:N`` with ``linear_solver=path``; its figures."""
    import integrators
    import problems

    start = time.perf_counter()
    case = problems.make(f"four-bar:N={N}").with_t_end(t_end)
    made = time.perf_counter() - start
    traj, setup, wall = timed_run(case, integrators.make("rattle", h=H, linear_solver=path))
    setup += made
    q_ref, v_ref = case.reference.solution(traj.t_final)
    steps = max(1, traj.counts["n_steps"])
    return {"N": N, "path": path, "linear_solver": traj.linear_solver,
            "status": str(traj.status), "message": traj.message, "t_final": traj.t_final,
            "pos": float(np.max(traj.windows["pos"])), "vel": float(np.max(traj.windows["vel"])),
            "error": float(max(np.max(np.abs(traj.q_final - q_ref)),
                               np.max(np.abs(traj.v_final - v_ref)))),
            "newton": traj.counts["n_newton"] / steps, "steps": traj.counts["n_steps"],
            "wall_s": wall, "per_step_ms": 1e3 * wall / steps, "setup_s": setup,
            "peak_mib": (peak_rss() or 0) / 2**20}


def run_point(N: int, path: str, t_end: float) -> dict:
    """:func:`point` in a fresh process (its own peak memory); a failed process as data."""
    ending, stdout, stderr, peak = run_process(
        [sys.executable, "-m", "benchmarks.perf.four_bar", "--point", str(N), path, str(t_end)],
        LIMIT, dict(os.environ))
    if ending:
        return {"N": N, "path": path, "status": ending, "message": stderr.strip()[-300:],
                "peak_mib": (peak or 0) / 2**20}
    return json.loads(stdout.strip().splitlines()[-1])


def show(r: dict) -> None:
    if "pos" not in r:
        print(f"{r['N']:6d} {r['path']:6} {r['status']}: {r['message']}")
        return
    print(f"{r['N']:6d} {r['linear_solver']:6} {r['status']:7} {r['t_final']:7.3f} "
          f"{r['pos']:9.1e} {r['vel']:9.1e} {r['error']:9.2e} {r['newton']:6.2f} "
          f"{r['wall_s']:8.1f} {r['per_step_ms']:8.3f} {r['setup_s']:7.1f} {r['peak_mib']:8.0f}")
    if r["message"]:
        print(f"  {r['message']}")


HEADER = (f"{'N':>6} {'solver':6} {'status':7} {'t_final':>7} {'max|g|':>9} {'max|Gv|':>9} "
          f"{'error':>9} {'newton':>6} {'solve_s':>8} {'ms/step':>8} {'setup_s':>7} "
          f"{'peak MiB':>8}")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--point"]:
        like_a_worker()
        print(json.dumps(point(int(argv[1]), argv[2], float(argv[3]))))
        return 0
    parser = CommandParser(prog="python -m benchmarks.perf.four_bar",
                           description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[40, 4096], help="sizes N")
    parser.add_argument("--t-end", type=float, default=20.0, help="horizon (s)")
    parser.add_argument("--crossover", action="store_true",
                        help=f"time {CROSSOVER_STEPS} steps of the dense and kkt paths")
    args = parser.parse_args(argv)
    load = os.getloadavg()[0]
    sizes = sorted(set(args.n))
    if args.crossover:
        print(f"four-bar:N, rattle at h = {H:g}, {CROSSOVER_STEPS} steps per path; load "
              f"average at start {load:.2f} on {os.cpu_count()} cores")
        print(HEADER)
        for N in sizes:
            for path in ("dense", "kkt"):
                show(run_point(N, path, CROSSOVER_STEPS * H))
        return 0
    print(f"four-bar:N, rattle at h = {H:g} to t = {args.t_end:g}; "
          f"load average at start {load:.2f} on {os.cpu_count()} cores")
    print(HEADER)
    rows = []
    for N in sizes:
        rows.append(run_point(N, "auto", args.t_end))
        show(rows[-1])
    print(f"load average at end {os.getloadavg()[0]:.2f}")
    small, large = rows[0], rows[-1]
    met = (large.get("status") == "ok" and large["pos"] <= G_BAR
           and small.get("status") == "ok" and large["error"] <= small["error"])
    print(f"four-bar:N={large['N']}: {'meets' if met else 'misses'} the bar (ok, max|g| <= "
          f"{G_BAR:g}, error at most that of N = {small['N']})")
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
