"""Benchmark: ``genalpha`` against Exudyn's generalized-alpha solver, side by side, on
``chain:N`` and ``rigid-chain:N``.

Exudyn (``pip install exudyn``; J. Gerstmayr, Exudyn -- a C++-based Python package for
flexible multibody systems, Multibody Syst. Dyn., 2024) is a C++ multibody code whose
implicit solver is the generalized-alpha method of Arnold and Bruls (2007) on the index-3
equations, the method of :class:`integrators.genalpha.GeneralizedAlpha` with ``formulation
= "index3"``: the same ``alpha_m``, ``alpha_f``, ``beta``, ``gamma`` from ``rho_inf``
(Exudyn's ``spectralRadius``), the same starting acceleration (the index-1 solve) and the
same velocity update (on ``chain:N=4`` at ``h = 1e-3``, 50 steps, the two end within 1e-15 in
``q`` and 4e-13 in ``v``). The same model is built from Exudyn's own items (compiled, no
Python in its steps), with the suite's initial state as their reference configuration:

``chain:N``
    ``NodePoint2D`` + ``MassPoint2D`` of mass ``mass / N``, ``ObjectConnectorDistance`` of
    length ``length / N`` from the ground point at the origin and between neighbours, and
    the weight as a ``LoadForceVector``. Exudyn's constraint is ``|x_k - x_{k-1}| - l = 0``,
    ours its square minus ``l^2``: the same zero set with parallel gradients, so the index-3
    step has the same solution (only ``lambda`` is scaled).
``rigid-chain:N``
    ``NodeRigidBodyEP`` (Euler parameters ``e`` with the constraint ``|e|^2 = 1``) +
    ``ObjectRigidBody`` of mass ``mass`` and principal inertia ``J = (J1, J2, J3)``,
    ``ObjectJointSpherical`` between the ground point and ``(0, 0, l)`` of body 1 and
    between ``(0, 0, -l)`` of body ``k`` and ``(0, 0, l)`` of body ``k + 1``, and gravity as
    a ``LoadMassProportional``.

The rigid bodies' equations differ off the manifold ``e . e' = 0``. Ours are the Lagrange
equations of :mod:`problems.rigid_chain`'s kinetic energy ``T`` in ``(e, e')``; Exudyn's
are the Newton-Euler equations ``G^T (J w' + w x J w)`` with ``w = G e'``, ``G = 2 E(e)``.
With ``|e| = 1`` the former exceed the latter by ``2 (e . e') dT/de'`` (its part along
``e``, from ``T``'s ``j_0`` term, goes into the norm constraint's multiplier). The index-3
step keeps ``|e| = 1`` at every step end but ``e . e'`` only to O(h^2), so the two discrete
solutions differ by O(h^2) over a fixed horizon: 6.1e-10 in ``q`` and 2.9e-8 in ``v`` on
``rigid-chain:N=4`` over 0.05 s at ``h = 5e-4``, a quarter of that at ``h / 2`` and a
sixteenth at ``h / 4`` (where ``e . e'`` is 1.9e-7, 4.6e-8, 1.2e-8 in both solutions
alike), whichever side's Newton is tightened. The timed run is the suite's rigid chain; the
agreement is judged on a second, untimed solve of ours in Exudyn's equations
(:func:`exudyn_rigid_body`: that term taken off as a generalised force), which both
compute identically: there the two end within 1e-14 in ``q`` and 3e-12 in ``v`` when
Exudyn's Newton is tight. Each row gives both differences and says which was judged.

Exudyn runs with its sparse LU (``EigenSparse``, analysed pattern kept), one thread, its
modified Newton, and per problem the loosest Newton tolerances (``relativeTolerance``,
``absoluteTolerance``; :data:`EXUDYN_TOLERANCES`) at which its final state is its own
equations' solution to within the bar: its defaults ``1e-8, 1e-10`` on the chain (tighter
ones change its ``v`` by 2e-11), ``1e-10, 1e-12`` on the rigid chain, where its defaults stop
its Newton 1.6e-9 short in ``v`` at ``N = 64`` (8e-11 at the tighter pair, for 7.6 rather
than 6.2 iterations per step there and 6.3 rather than 6.2 at ``N = 1024``). ``genalpha``
runs with its defaults (Newton to round-off). The Newton iterations per step of both are
in the output.

Exudyn's unknowns are positions, so its velocities carry their rounding times ``gamma /
(beta h)``: on the rigid chain, whose far bodies lie ``|x| ~ N`` from the origin, its
``v`` moves by about as much as it differs from ours between two ways of solving the same
step equations (1.3e-9 between its tolerances ``1e-10`` and ``1e-12`` at ``N = 1024``,
growing with ``|x|`` body by body; 1.2e-9 and 7.1e-9 between its modified and full Newton
at ``N = 1024`` and ``4096``), while its ``q`` moves by 1e-12. Agreement is therefore
``|dq| <= 1e-9`` and ``|dv| <= max(1e-9, v_round)``, ``v_round = 4 eps max|q| gamma /
(beta h)`` (:func:`velocity_rounding`; those spreads are 2 to 2.5 times ``eps max|q| gamma
/ (beta h)``), and the row gives ``v_round``.

Times. Exudyn's is that of its steps (``SolveSteps``), without its set-up; ours that of a
prepared solve in this process as a worker solves
(:func:`benchmarks.perf.processes.like_a_worker`), which also records what the suite's
grid asks for (``integrators.base.Grid``: the windows and samples a solve hands back,
the rows its steps use). Such per-solve costs are no cost of a step, so the time per
step of each is the marginal one, ``(t_S - t_1) / (S - 1)`` from a solve of ``S`` steps
and one of a single step; the whole solves' ratio is given too. Rounds alternate between
the two so that a change in the machine's load hits both; each takes the fastest of
``--best-of`` solves of each kind (a short solve is otherwise at the mercy of the
machine's load); figures are medians over the rounds (of the per-round differences
for the marginal times), with the ratio of processor times as well (less disturbed by
load than wall time), and the 1-minute load is printed.

Per problem and ``N``: marginal time per step of each, their ratio (the bar: at most 1),
the ratio of processor times per step and of whole solves, Newton iterations per step of
each, and the max-norm differences of the final positions and velocities (the bar above).
The results go to ``OUT/exudyn.json`` and ``OUT/exudyn.csv`` (default ``results/exudyn``).

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
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.perf.processes import like_a_worker, state_difference, timed_solve
from benchmarks.records import EXIT_INPUT, CommandParser

#: The bars: our time per step over Exudyn's, and the final states' max-norm difference.
RATIO_GOAL, AGREEMENT = 1.0, 1e-9
#: Step size of each problem (the chain's fastest waves need small steps at large N).
STEP = {"chain": 1e-5, "rigid-chain": 5e-4}
#: Exudyn's Newton ``relativeTolerance`` and ``absoluteTolerance`` per problem: the loosest
#: at which its final state is its equations' solution to within the bar (module doc).
EXUDYN_TOLERANCES = {"chain": (1e-8, 1e-10), "rigid-chain": (1e-10, 1e-12)}
#: Units of rounding of ``q`` that Exudyn's ``v`` may carry, times ``gamma / (beta h)``
#: (:func:`velocity_rounding`).
ROUNDING_UNITS = 4.0
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
    p.add_argument("--steps", type=int, default=100,
                   help="steps per solve, at least 2 (default 100)")
    for problem, h in STEP.items():
        p.add_argument(f"--h-{problem}", type=float, default=h, metavar="H",
                       help=f"step size on {problem} (default {h:g})")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds (default 3)")
    p.add_argument("--best-of", type=int, default=3,
                   help="solves of each kind per round, the fastest kept (default 3)")
    p.add_argument("--rho-inf", type=float, default=0.5,
                   help="spectral radius at infinity of both (default 0.5, genalpha's)")
    p.add_argument("--exudyn-rtol", type=float, default=None,
                   help="Exudyn's Newton relativeTolerance (default per problem: "
                        + ", ".join(f"{k} {v[0]:g}" for k, v in EXUDYN_TOLERANCES.items())
                        + ")")
    p.add_argument("--exudyn-atol", type=float, default=None,
                   help="Exudyn's Newton absoluteTolerance (default per problem: "
                        + ", ".join(f"{k} {v[1]:g}" for k, v in EXUDYN_TOLERANCES.items())
                        + ")")
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


def exudyn_rigid_body(case):
    """``rigid-chain``'s case in Exudyn's rigid-body equations (module doc).

    Adds the generalised force ``2 (e_k . e_k') dT/de_k'`` on every body's Euler
    parameters, with ``dT/de'`` the autodiff gradient of the case's own kinetic energy:
    it cancels the term by which the Lagrange equations exceed the Newton-Euler ones off
    ``e . e' = 0`` (its part along ``e_k`` goes into the norm constraint's multiplier).
    """
    import jax
    import jax.numpy as jnp

    N, kinetic, own = case.params["N"], case.system.kinetic, case.system.forces
    on_e = jnp.tile(jnp.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0]), N)

    def forces(t, q, v):
        along = jnp.sum(q.reshape(N, 7)[:, 3:] * v.reshape(N, 7)[:, 3:], axis=1)
        f = 2.0 * jnp.repeat(along, 7) * on_e * jax.grad(kinetic, argnums=1)(q, v)
        return f if own is None else f + own(t, q, v)

    return replace(case, system=replace(case.system, forces=forces))


#: The case whose discrete equations are Exudyn's, per problem (module doc).
SAME_EQUATIONS = {"chain": None, "rigid-chain": exudyn_rigid_body}


def velocity_rounding(q, h: float, rho_inf: float) -> float:
    """``ROUNDING_UNITS eps max|q| gamma / (beta h)``: the rounding of positions that a
    generalized-alpha step solving for positions carries into ``v_{n+1} = v_hat + gamma
    (q_{n+1} - q_hat) / (beta h)``."""
    from integrators.genalpha import Coefficients

    c = Coefficients.from_rho_inf(rho_inf)
    return (ROUNDING_UNITS * float(np.finfo(np.float64).eps) * float(np.max(np.abs(q)))
            * c.gamma / (c.beta * h))


def agrees(dq: float, dv: float, v_round: float) -> bool:
    """The agreement bar: ``dq <= AGREEMENT`` and ``dv <= max(AGREEMENT, v_round)``."""
    return dq <= AGREEMENT and dv <= max(AGREEMENT, v_round)


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
    """One solve from the initial state: final ``q``, ``v``, the steps' wall and processor
    times and Newton iterations. Coordinates are Exudyn's displacements from the reference
    ``q0``."""
    solver = exu.MainSolverImplicitSecondOrder()
    solver.InitializeSolver(mbs, sim)
    start, cpu = time.perf_counter(), time.process_time()
    solver.SolveSteps(mbs, sim)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    steps, newton = solver.it.currentStepIndex - 1, solver.it.newtonStepsCount
    solver.FinalizeSolver(mbs, sim)
    if steps != sim.timeIntegration.numberOfSteps:
        raise RuntimeError(f"Exudyn stopped after {steps} of "
                           f"{int(sim.timeIntegration.numberOfSteps)} steps")
    q = np.asarray(mbs.systemData.GetODE2Coordinates()) + q0
    v = np.asarray(mbs.systemData.GetODE2Coordinates_t())
    return {"q": q, "v": v, "wall": wall, "cpu": cpu, "newton": newton, "steps": steps}


def marginal(long: list[float], short: list[float], steps: int) -> float:
    """Seconds per step beyond a solve's fixed cost: the median over rounds of ``(t_S -
    t_1) / (S - 1)``, from each round's solve of ``S = steps`` steps and of one step."""
    return statistics.median((a - b) / (steps - 1) for a, b in zip(long, short))


def fastest(solve, k: int) -> dict:
    """The fastest of ``k`` calls of ``solve() -> dict`` with ``wall`` and ``cpu``, its
    ``cpu`` the least of them (module doc)."""
    runs = [solve() for _ in range(k)]
    return {**min(runs, key=lambda r: r["wall"]), "cpu": min(r["cpu"] for r in runs)}


def genalpha_solve(solve) -> dict:
    """One call of a prepared solve as :func:`exudyn_solve` reports one."""
    traj, wall, cpu, _ = timed_solve(solve)
    return {"traj": traj, "wall": wall, "cpu": cpu}


def compare(exu, items, problem: str, N: int, args) -> dict:
    """``genalpha`` and Exudyn on ``problem:N=N`` over ``args.steps`` steps, alternating.

    A solve that fails makes a row with its ``status`` and no figures."""
    import integrators
    import problems
    from integrators.base import Grid

    h = getattr(args, f"h_{problem.replace('-', '_')}")
    rtol, atol = (given if given is not None else default for given, default in
                  zip((args.exudyn_rtol, args.exudyn_atol), EXUDYN_TOLERANCES[problem]))
    case = problems.make(f"{problem}:N={N}").with_t_end(args.steps * h)
    q0 = np.asarray(case.q0)
    container, mbs = MODELS[problem](exu, items, case)  # the container owns the system
    sims = [settings(exu, h, n, args.rho_inf, rtol, atol) for n in (args.steps, 1)]
    method = integrators.make(f"genalpha:h={h},rho_inf={args.rho_inf}")
    solves = [method.prepare(c, Grid(c.t0, c.t_end))
              for c in (case, case.with_t_end(case.t0 + h))]
    row = {"problem": problem, "N": N, "h": h}
    ours, theirs = [], []   # per round: (long, short)
    for _ in range(args.rounds):
        runs = [fastest(lambda: genalpha_solve(solve), args.best_of) for solve in solves]
        failed = [r["traj"] for r in runs if r["traj"].status != "ok"]
        if failed:
            return {**row, "status": f"genalpha {failed[0].status}: {failed[0].message}"}
        ours.append(runs)
        try:
            theirs.append([fastest(lambda: exudyn_solve(exu, mbs, sim, q0), args.best_of)
                           for sim in sims])
        except RuntimeError as err:
            return {**row, "status": str(err)}
    traj, e = ours[0][0]["traj"], theirs[0][0]
    steps = traj.counts["n_steps"]
    if steps != args.steps or ours[0][1]["traj"].counts["n_steps"] != 1:
        return {**row, "status": f"genalpha took {steps} steps, not {args.steps}"}
    def per_step(side, key):
        return marginal([r[0][key] for r in side], [r[1][key] for r in side], steps)

    us, e_us, cpu, e_cpu = (per_step(side, key) for key in ("wall", "cpu")
                            for side in (ours, theirs))
    if not min(us, e_us, cpu, e_cpu) > 0:
        # A solve of S steps that took no longer than one of a single step: the load
        # swamped the measurement, and a ratio of it would be noise.
        return {**row, "status": "the marginal time per step is not positive (load too "
                                 "high or --steps too few)"}
    solve_s = statistics.median(r[0]["wall"] for r in ours)
    e_solve_s = statistics.median(r[0]["wall"] for r in theirs)

    final = [*e["q"], *e["v"]]
    dq_suite, dv_suite = state_difference(final, [*traj.q_final, *traj.v_final])
    same = SAME_EQUATIONS[problem]
    if same is None:
        dq, dv, judged = dq_suite, dv_suite, "the suite's"
    else:
        other = method.prepare(same(case), Grid(case.t0, case.t_end))()
        if other.status != "ok":
            return {**row, "status": f"genalpha in Exudyn's equations {other.status}: "
                                     f"{other.message}"}
        dq, dv = state_difference(final, [*other.q_final, *other.v_final])
        judged = "Exudyn's rigid-body"
    v_round = velocity_rounding(e["q"], h, args.rho_inf)
    return {**row, "status": "ok", "steps": steps, "exudyn_steps": e["steps"],
            "rho_inf": args.rho_inf, "us_per_step": 1e6 * us,
            "exudyn_us_per_step": 1e6 * e_us, "ratio_per_step": us / e_us,
            "cpu_ratio_per_step": cpu / e_cpu,
            "solve_ms": 1e3 * solve_s, "exudyn_solve_ms": 1e3 * e_solve_s,
            "ratio_per_solve": solve_s / e_solve_s,
            "newton_per_step": traj.counts["n_newton"] / steps,
            "exudyn_newton_per_step": e["newton"] / e["steps"],
            "equations": judged, "final_q_difference": dq, "final_v_difference": dv,
            "velocity_rounding": v_round, "agree": agrees(dq, dv, v_round),
            "suite_q_difference": dq_suite, "suite_v_difference": dv_suite,
            "exudyn_rtol": rtol, "exudyn_atol": atol}


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    sizes = sorted(set(args.n + ([4096] if args.large else [])))
    tolerances = [x for x in (args.exudyn_rtol, args.exudyn_atol) if x is not None]
    if (args.rounds < 1 or args.best_of < 1 or args.steps < 2 or min(sizes) < 1
            or not 0 <= args.rho_inf <= 1
            or not min(args.h_chain, args.h_rigid_chain) > 0
            or not all(x > 0 for x in tolerances)):
        parser().error("--rounds, --best-of and every --n must be >= 1, --steps >= 2, "
                       "--rho-inf in [0, 1], and the step sizes and Exudyn's tolerances "
                       "positive")
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
          f"{os.getloadavg()[0]:.2f}; medians of {args.rounds} alternating rounds (each "
          f"the fastest of {args.best_of} solves) of {args.steps} steps; time per step "
          f"beyond a solve's fixed cost")
    print(f"{'problem':12} {'N':>5} {'h':>7} {'us/step':>9} {'Exudyn':>9} {'ratio':>7} "
          f"{'cpu':>6} {'solve':>6} {'Newton':>6} {'Exudyn':>6}  final |dq|  final |dv|"
          f"  (equations)  suite |dq|  suite |dv|")
    for r in rows:
        if r["status"] != "ok":
            print(f"{r['problem']:12} {r['N']:5d} {r['h']:7.2g}  {r['status']}")
            continue
        print(f"{r['problem']:12} {r['N']:5d} {r['h']:7.2g} {r['us_per_step']:9.1f} "
              f"{r['exudyn_us_per_step']:9.1f} {r['ratio_per_step']:6.2f}x "
              f"{r['cpu_ratio_per_step']:5.2f}x {r['ratio_per_solve']:5.2f}x "
              f"{r['newton_per_step']:6.2f} {r['exudyn_newton_per_step']:6.2f}  "
              f"{r['final_q_difference']:9.1e}  {r['final_v_difference']:9.1e}"
              f"  ({r['equations']})  {r['suite_q_difference']:9.1e}  "
              f"{r['suite_v_difference']:9.1e}"
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
