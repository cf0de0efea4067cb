"""Benchmark: the dense path against the structured one on small systems, family by family.

For each fixed-step family (``--families``) and small problem (:data:`CASES`), one
trajectory runs twice: with ``linear_solver=dense`` (Newton with the exact autodiff
Jacobian of the method's whole system) and with the structured solver that the choice by
structure takes with ``dense_max = 0`` (:func:`linalg.schur.choose`: simplified Newton
through ``S = G M^{-1} G^T``). Printed per pair: each path's status, steps per second,
Newton iterations per step and max ``|g|``; where both ran to the end, the speed ratio,
the largest difference of the final ``(q, v)`` between the paths (the same method and
step; round-off apart, grown by the problem's sensitivity over the horizon) and the path
that ``linear_solver=auto`` takes for that family
(:meth:`integrators.fixed.FixedStep.dense_max`), with ``faster`` or ``SLOWER``. A pair
where the problem's mass allows no structured solver is said so and skipped.

A configuration-dependent mass is measured spelt both ways: as given (``mass=M(q)``) and,
for a problem named ``NAME/kinetic``, as its kinetic energy ``T = v^T M(q) v / 2``
(:func:`build`); the two spellings take one path at one cost
(:attr:`problems.mechanics.Mechanics.kinetic`).

What each number is: steps per second over the wall time of ``solve()`` (the compiled
time loop and the read-back of the trajectory; set-up and compilation excluded), the
median of ``--repeats`` solves, in this one process set up as the suite's workers are
(one intra-op thread, :func:`benchmarks.perf.processes.like_a_worker`): one core.

This is the measurement behind the crossovers of the fixed-step families. Exit status 1
only when a run errs (a failed run is data); bad options: one line and exit status 2.

Usage::

    python -m benchmarks.perf.crossover
    python -m benchmarks.perf.crossover --families rattle lobatto3ab3 --repeats 5
    python -m benchmarks.perf.crossover --problems heavy-top heavy-top/kinetic
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from benchmarks.perf.processes import like_a_worker
from benchmarks.records import CommandParser

#: Families measured by default: the fixed-step families that run Newton (each names its
#: own crossover).
FAMILIES = ("rattle", "lobatto3ab3", "genalpha", "genalpha-ggl", "hht")

#: ``(problem, h, t_end)``: one to eight constraints, constant diagonal masses with and
#: without applied forces, a block-diagonal, configuration-dependent one given by its
#: kinetic energy (rigid bodies), and configuration-dependent masses given as matrix
#: functions, each also spelt as its kinetic energy (``/kinetic``, :func:`build`): the
#: heavy symmetric top in Euler parameters (one 4 x 4 block) and Andrews' mechanism
#: (blocks of one and two coordinates).
CASES = (("pendulum", 0.01, 20.0), ("sps-receiver", 0.05, 50.0),
         ("double-pendulum", 0.01, 10.0), ("car-axis", 1e-3, 3.0),
         ("chain:N=2", 0.01, 10.0), ("chain:N=4", 0.01, 10.0), ("chain:N=8", 0.01, 10.0),
         ("rigid-chain:N=2", 0.005, 2.0),
         ("heavy-top", 0.005, 10.0), ("heavy-top/kinetic", 0.005, 10.0),
         ("andrews", 1e-4, 0.03), ("andrews/kinetic", 1e-4, 0.03))


def build(problem: str, t_end: float):
    """The case ``problem`` over ``[t0, t_end]``: a registered problem, or ``heavy-top`` (the
    heavy symmetric top of ``tests/mechanisms.py``, which the suite does not ship); with
    ``/kinetic``, its mass function ``M(q)`` given instead as the kinetic energy ``T(q, v) =
    v^T M(q) v / 2``."""
    import dataclasses

    import problems

    name, _, spelling = problem.partition("/")
    if name == "heavy-top":
        from tests.mechanisms import heavy_top

        case = heavy_top("mass", t_end=t_end)
    else:
        case = problems.make(name).with_t_end(t_end)
    if spelling != "kinetic":
        return case
    mass = case.system.mass
    if not callable(mass):
        raise ValueError(f"{problem}: the mass is not a function M(q), so there is no other "
                         "spelling to measure")
    twin = dataclasses.replace(case.system, mass=None,
                               kinetic=lambda q, v: 0.5 * v @ (mass(q) @ v))
    return dataclasses.replace(case, system=twin)


def run(case, method, repeats: int):
    """The median wall time of ``repeats`` solves after the first, and the last
    trajectory."""
    from benchmarks.perf.ensemble import timed
    from integrators.base import Grid

    solve = method.prepare(case, Grid(case.t0, case.t_end))
    solve()  # the first solve pays for the loading of the compiled program
    return timed(solve, repeats)


def pair(family: str, problem: str, h: float, t_end: float, repeats: int) -> str | None:
    """One line comparing the two paths; ``None`` where the mass allows no structured one."""
    import integrators

    case = build(problem, t_end)
    mech = case.mech
    structured = mech.schur("auto", dense_max=0).name
    if structured == "dense":
        return None
    out = {}
    for path in ("dense", structured):
        seconds, traj = run(case, integrators.make(family, h=h, linear_solver=path), repeats)
        out[path] = (max(1, traj.counts["n_steps"]) / seconds, traj)

    def show(path):
        rate, traj = out[path]
        return (f"{path:7s} {traj.status:6s} {rate:9.3g} steps/s "
                f"{traj.counts['n_newton'] / max(1, traj.counts['n_steps']):5.2f} it/step "
                f"|g| {float(np.max(traj.windows['pos'])):.1e}")

    line = f"{family:12s} {problem:16s} m={mech.m:<2d} {show('dense')} | {show(structured)}"
    if any(traj.status != "ok" for _, traj in out.values()):
        return line + " | not compared (a run did not reach the end)"
    dense, other = out["dense"][1], out[structured][1]
    gap = float(max(np.max(np.abs(dense.q_final - other.q_final)),
                    np.max(np.abs(dense.v_final - other.v_final))))
    auto = integrators.make(family, h=h).linear_algebra(mech).name
    fast = max(out, key=lambda path: out[path][0])
    return (f"{line} | x{out[structured][0] / out['dense'][0]:5.2f} | apart {gap:.1e} | "
            f"auto: {auto} ({'faster' if auto == fast else 'SLOWER'})")


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="python -m benchmarks.perf.crossover",
                           description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES,
                        help="fixed-step families to measure (default: all of them)")
    parser.add_argument("--problems", nargs="+", default=[c[0] for c in CASES],
                        choices=[c[0] for c in CASES],
                        help="problems to measure (default: all of them)")
    parser.add_argument("--repeats", type=int, default=3, help="timed solves per path")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: must be at least 1")
    load = like_a_worker()
    print(f"dense against structured, one trajectory each (1-minute load {load:.2f}); "
          "ratio = structured / dense steps per second", flush=True)
    errors = 0
    for family in args.families:
        for problem, h, t_end in (c for c in CASES if c[0] in args.problems):
            start = time.perf_counter()
            try:
                line = pair(family, problem, h, t_end, args.repeats)
            except Exception as exc:  # a run that errs is reported, and the rest go on
                errors += 1
                print(f"{family:12s} {problem:16s} error: {exc}", flush=True)
                continue
            print(line or f"{family:12s} {problem:16s} no structured solver for this mass",
                  f"[{time.perf_counter() - start:.0f} s]", flush=True)
    if hasattr(os, "getloadavg"):
        print(f"1-minute load at the end {os.getloadavg()[0]:.2f}")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
