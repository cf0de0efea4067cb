"""Benchmark: ``genalpha`` against Exudyn's generalized-alpha solver, side by side, on
``chain:N`` and ``rigid-chain:N``.

Exudyn (``pip install exudyn``; J. Gerstmayr, Exudyn -- a C++-based Python package for
flexible multibody systems, Multibody Syst. Dyn., 2024) is a C++ multibody code whose
implicit solver is the generalized-alpha method of Arnold and Bruls (2007) on the index-3
equations, the method of :class:`integrators.genalpha.GeneralizedAlpha` with ``formulation
= "index3"``. The same model is built from Exudyn's own items (compiled, no Python in its
steps), with the suite's initial state as their reference configuration:

``chain:N``
    ``NodePoint2D`` + ``MassPoint2D`` of mass ``mass / N``, ``ObjectConnectorDistance`` of
    length ``length / N`` from the ground point at the origin and between neighbours, and
    the weight as a ``LoadForceVector``. Exudyn's constraint is ``|x_k - x_{k-1}| - l = 0``,
    ours its square minus ``l^2``: the same zero set with parallel gradients, so the index-3
    step has the same solution (only ``lambda`` is scaled).
``rigid-chain:N``
    ``NodeRigidBodyEP`` (Euler parameters with their unit-norm constraint) + ``ObjectRigidBody``
    of mass ``mass`` and principal inertia ``(J1, J2, J3)``, ``ObjectJointSpherical``
    between the ground point and ``(0, 0, l)`` of body 1 and between ``(0, 0, -l)`` of body
    ``k`` and ``(0, 0, l)`` of body ``k + 1``, and gravity as a ``LoadMassProportional``.
    The equations of motion agree on the manifold ``|e| = 1, e . e' = 0``; off it, Exudyn's
    body and ours (the Lagrange equations of :mod:`problems.rigid_chain`'s kinetic
    energy) need not. The index-3 step keeps ``|e| = 1`` but not ``e . e' = 0``, so on a
    spinning body the two discrete solutions differ by O(h^2) over a fixed horizon, and
    far less from rest. Measured on ``rigid-chain:N=64`` over 0.05 s with Exudyn's Newton
    at ``1e-12 / 1e-14``: 6.8e-10 in ``q`` and 3.2e-8 in ``v`` at ``h = 5e-4``, 4.3e-11
    and 2.0e-9 at ``h / 4`` (16 times less: not a different model). ``chain:N`` has
    neither a configuration-dependent mass nor velocity-dependent forces: there the two
    end within 1e-13 in ``q`` and 5e-10 in ``v`` (100 steps of ``h = 1e-5``, N up to 4096).

Both run Exudyn's and our generalized-alpha with the same ``rho_inf`` (Exudyn's
``spectralRadius``) and ``h``, Exudyn with its sparse LU (``EigenSparse``, analysed pattern
kept), one thread, its modified Newton and its default tolerances unless told otherwise
(a loose tolerance only flatters its time; its final state must still agree with ours).
Ours is set up once and solved in this process as a worker solves
(:func:`benchmarks.perf.processes.like_a_worker`); Exudyn's time is that of its steps
(``SolveSteps``), without its set-up. Rounds alternate between the two so that a change in
the machine's load hits both; figures are medians over the rounds, and the 1-minute load is
printed.

Per problem and ``N``: time per step of each, the ratio ours / Exudyn (the bar: at most 1),
Newton iterations per step of each, and the max-norm differences of the final positions and
velocities (the bar: 1e-9). The results go to ``OUT/exudyn.json`` and ``OUT/exudyn.csv``
(default ``results/exudyn``).

Usage::

    python -m benchmarks.perf.exudyn
    python -m benchmarks.perf.exudyn --large --rounds 5
    python -m benchmarks.perf.exudyn --problems chain --n 64 256 --steps 500
    python -m benchmarks.perf.exudyn --problems rigid-chain --n 4 --h-rigid-chain 2.5e-4 --steps 200
"""

from __future__ import annotations

import csv
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.perf.processes import like_a_worker, state_difference, timed_solve
from benchmarks.records import EXIT_INPUT, CommandParser

#: The bars: our time per step over Exudyn's, and the final states' max-norm difference.
RATIO_GOAL, AGREEMENT = 1.0, 1e-9
#: Step size of each problem (the chain's fastest waves need small steps at large N).
STEP = {"chain": 1e-5, "rigid-chain": 5e-4}
#: What to tell a user without Exudyn.
INSTALL = ("exudyn is not installed: .venv/bin/pip install 'exudyn' "
           "(or .venv/bin/pip install -e '.[perf]')")


def parser() -> CommandParser:
    p = CommandParser(prog="python -m benchmarks.perf.exudyn",
                      description=__doc__.split("\n")[0])
    p.add_argument("--problems", nargs="+", choices=sorted(STEP), default=sorted(STEP),
                   help="problems (default both)")
    p.add_argument("--n", nargs="+", type=int, default=[64, 256, 1024],
                   help="sizes N (default 64 256 1024)")
    p.add_argument("--large", action="store_true", help="add N = 4096")
    p.add_argument("--steps", type=int, default=100, help="steps per solve (default 100)")
    for problem, h in STEP.items():
        p.add_argument(f"--h-{problem}", type=float, default=h, metavar="H",
                       help=f"step size on {problem} (default {h:g})")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds (default 3)")
    p.add_argument("--rho-inf", type=float, default=0.5,
                   help="spectral radius at infinity of both (default 0.5, genalpha's)")
    p.add_argument("--exudyn-rtol", type=float, default=1e-8,
                   help="Exudyn's Newton relativeTolerance (default 1e-8, its own)")
    p.add_argument("--exudyn-atol", type=float, default=1e-10,
                   help="Exudyn's Newton absoluteTolerance (default 1e-10, its own)")
    p.add_argument("--out", type=Path, default=Path("results/exudyn"),
                   help="folder of exudyn.json and exudyn.csv")
    return p


def chain_model(exu, items, case):
    """``chain:N`` in Exudyn's items (module doc); returns the system container and system."""
    p = case.params
    N, q0, v0 = p["N"], np.asarray(case.q0), np.asarray(case.v0)
    l, mk = p["length"] / N, p["mass"] / N
    sc = exu.SystemContainer()
    mbs = sc.AddSystem()
    ground = mbs.AddObject(items.ObjectGround())
    above = mbs.AddMarker(items.MarkerBodyPosition(bodyNumber=ground, localPosition=[0, 0, 0]))
    for k in range(N):
        node = mbs.AddNode(items.NodePoint2D(referenceCoordinates=q0[2 * k:2 * k + 2].tolist(),
                                             initialVelocities=v0[2 * k:2 * k + 2].tolist()))
        mbs.AddObject(items.MassPoint2D(mass=mk, nodeNumber=node))
        point = mbs.AddMarker(items.MarkerNodePosition(nodeNumber=node))
        mbs.AddObject(items.ObjectConnectorDistance(markerNumbers=[above, point], distance=l))
        mbs.AddLoad(items.LoadForceVector(markerNumber=point,
                                          loadVector=[0, -mk * p["gravity"], 0]))
        above = point
    mbs.Assemble()
    return sc, mbs


def rigid_chain_model(exu, items, case):
    """``rigid-chain:N`` in Exudyn's items (module doc)."""
    p = case.params
    N, q0, v0 = p["N"], np.asarray(case.q0), np.asarray(case.v0)
    l = p["half_length"]
    sc = exu.SystemContainer()
    mbs = sc.AddSystem()
    ground = mbs.AddObject(items.ObjectGround())
    above = mbs.AddMarker(items.MarkerBodyRigid(bodyNumber=ground, localPosition=[0, 0, 0]))
    for k in range(N):
        node = mbs.AddNode(items.NodeRigidBodyEP(referenceCoordinates=q0[7 * k:7 * k + 7].tolist(),
                                                 initialVelocities=v0[7 * k:7 * k + 7].tolist()))
        body = mbs.AddObject(items.ObjectRigidBody(
            mass=p["mass"], inertia=[p["J1"], p["J2"], p["J3"], 0, 0, 0], nodeNumber=node))
        upper = mbs.AddMarker(items.MarkerBodyRigid(bodyNumber=body, localPosition=[0, 0, l]))
        mbs.AddObject(items.ObjectJointSpherical(markerNumbers=[above, upper]))
        mbs.AddLoad(items.LoadMassProportional(
            markerNumber=mbs.AddMarker(items.MarkerBodyMass(bodyNumber=body)),
            loadVector=[0, 0, -p["gravity"]]))
        above = mbs.AddMarker(items.MarkerBodyRigid(bodyNumber=body, localPosition=[0, 0, -l]))
    mbs.Assemble()
    return sc, mbs


MODELS = {"chain": chain_model, "rigid-chain": rigid_chain_model}


def settings(exu, h: float, steps: int, rho_inf: float, rtol: float, atol: float):
    """Exudyn's simulation settings: ``steps`` fixed steps of ``h`` of its generalized-alpha
    (index 3) with ``rho_inf``, sparse LU, one thread, nothing written."""
    s = exu.SimulationSettings()
    ti = s.timeIntegration
    ti.numberOfSteps, ti.endTime = steps, steps * h
    ti.adaptiveStep = False
    ti.automaticStepSize = False
    ti.generalizedAlpha.spectralRadius = rho_inf
    ti.generalizedAlpha.useIndex2Constraints = False
    ti.generalizedAlpha.useNewmark = False
    ti.generalizedAlpha.computeInitialAccelerations = True
    ti.newton.relativeTolerance, ti.newton.absoluteTolerance = rtol, atol
    ti.verboseMode = 0
    s.solution.file.write = False
    s.solution.sensors.active = False
    s.linearSolver.solverType = exu.LinearSolverType.EigenSparse
    s.linearSolver.reuseAnalyzedPattern = True
    s.parallel.numberOfThreads = 1
    return s


def exudyn_solve(exu, mbs, sim, q0) -> dict:
    """One solve from the initial state: final ``q``, ``v``, the steps' wall time and Newton
    iterations. Coordinates are Exudyn's displacements from the reference ``q0``."""
    solver = exu.MainSolverImplicitSecondOrder()
    solver.InitializeSolver(mbs, sim)
    start = time.perf_counter()
    solver.SolveSteps(mbs, sim)
    wall = time.perf_counter() - start
    steps, newton = solver.it.currentStepIndex - 1, solver.it.newtonStepsCount
    solver.FinalizeSolver(mbs, sim)
    if steps != sim.timeIntegration.numberOfSteps:
        raise RuntimeError(f"Exudyn stopped after {steps} of "
                           f"{int(sim.timeIntegration.numberOfSteps)} steps")
    q = np.asarray(mbs.systemData.GetODE2Coordinates()) + q0
    v = np.asarray(mbs.systemData.GetODE2Coordinates_t())
    return {"q": q, "v": v, "wall": wall, "newton": newton, "steps": steps}


def compare(exu, items, problem: str, N: int, args) -> dict:
    """``genalpha`` and Exudyn on ``problem:N=N`` over ``args.steps`` steps, alternating.

    A solve that fails makes a row with its ``status`` and no figures."""
    import integrators
    import problems
    from integrators.base import Grid

    h = getattr(args, f"h_{problem.replace('-', '_')}")
    case = problems.make(f"{problem}:N={N}").with_t_end(args.steps * h)
    q0 = np.asarray(case.q0)
    container, mbs = MODELS[problem](exu, items, case)  # the container owns the system
    sim = settings(exu, h, args.steps, args.rho_inf, args.exudyn_rtol, args.exudyn_atol)
    solve = integrators.make(f"genalpha:h={h},rho_inf={args.rho_inf}").prepare(
        case, Grid(case.t0, case.t_end))
    ours, theirs = [], []
    for _ in range(args.rounds):
        traj, wall, _, _ = timed_solve(solve)
        if traj.status != "ok":
            return {"problem": problem, "N": N, "h": h,
                    "status": f"genalpha {traj.status}: {traj.message}"}
        ours.append((traj, wall))
        try:
            theirs.append(exudyn_solve(exu, mbs, sim, q0))
        except RuntimeError as err:
            return {"problem": problem, "N": N, "h": h, "status": str(err)}
    traj = ours[0][0]
    steps = traj.counts["n_steps"]
    wall = statistics.median(w for _, w in ours)
    e_wall = statistics.median(r["wall"] for r in theirs)
    e = theirs[0]
    dq, dv = state_difference([*e["q"], *e["v"]], [*traj.q_final, *traj.v_final])
    us, e_us = 1e6 * wall / steps, 1e6 * e_wall / e["steps"]
    return {"problem": problem, "N": N, "h": h, "status": "ok", "steps": steps,
            "exudyn_steps": e["steps"],
            "rho_inf": args.rho_inf, "us_per_step": us, "exudyn_us_per_step": e_us,
            "ratio_per_step": us / e_us,
            "newton_per_step": traj.counts["n_newton"] / steps,
            "exudyn_newton_per_step": e["newton"] / e["steps"],
            "final_q_difference": dq, "final_v_difference": dv,
            "agree": max(dq, dv) <= AGREEMENT,
            "exudyn_rtol": args.exudyn_rtol, "exudyn_atol": args.exudyn_atol}


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    sizes = sorted(set(args.n + ([4096] if args.large else [])))
    if (args.rounds < 1 or args.steps < 1 or min(sizes) < 1 or not 0 <= args.rho_inf <= 1
            or not min(args.h_chain, args.h_rigid_chain) > 0):
        parser().error("--rounds, --steps and every --n must be >= 1, --rho-inf in [0, 1] "
                       "and the step sizes positive")
    try:
        import exudyn as exu
        from exudyn import itemInterface as items
    except ImportError:
        print(INSTALL, file=sys.stderr)
        return EXIT_INPUT
    load = like_a_worker()
    rows = []
    for problem in args.problems:
        for N in sizes:
            row = compare(exu, items, problem, N, args)
            rows.append({**row, "load": load})
            write(args.out, rows, exu.__version__, args.rounds, load)
            print(f"{problem}:N={N} {row['status']}", flush=True)
    print(f"Exudyn {exu.__version__}; load (1 min) at start: {load:.2f}, at end: "
          f"{os.getloadavg()[0]:.2f}; medians of {args.rounds} alternating rounds of "
          f"{args.steps} steps")
    print(f"{'problem':12} {'N':>5} {'h':>7} {'us/step':>9} {'Exudyn':>9} {'ratio':>7} "
          f"{'Newton':>6} {'Exudyn':>6}  final |dq|  final |dv|")
    for r in rows:
        if r["status"] != "ok":
            print(f"{r['problem']:12} {r['N']:5d} {r['h']:7.2g}  {r['status']}")
            continue
        print(f"{r['problem']:12} {r['N']:5d} {r['h']:7.2g} {r['us_per_step']:9.1f} "
              f"{r['exudyn_us_per_step']:9.1f} {r['ratio_per_step']:6.2f}x "
              f"{r['newton_per_step']:6.2f} {r['exudyn_newton_per_step']:6.2f}  "
              f"{r['final_q_difference']:9.1e}  {r['final_v_difference']:9.1e}"
              f"{'' if r['agree'] else '  (disagree)'}")
    print(f"wrote {args.out / 'exudyn.json'} and {args.out / 'exudyn.csv'}")
    return 0 if all(r["status"] == "ok" and r["ratio_per_step"] <= RATIO_GOAL and r["agree"]
                    for r in rows) else 1


def write(out: Path, rows: list[dict], version: str, rounds: int, load: float) -> None:
    """``OUT/exudyn.json`` and ``OUT/exudyn.csv`` with the rows so far (rewritten after each
    comparison, so that a run stopped part way keeps what it measured)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "exudyn.json").write_text(json.dumps(
        {"exudyn": version, "goal_ratio_per_step": RATIO_GOAL, "agreement": AGREEMENT,
         "rounds": rounds, "load": load, "rows": rows}, indent=1))
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "exudyn.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    raise SystemExit(main())
