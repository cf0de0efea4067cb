"""Benchmark: what the harness costs. Each family against a native yardstick of the same
algorithm, side by side.

A yardstick is a C program (``yardstick/``, compiled here) that runs the same method with
the same formulation, tolerances and error control on the same problem; it must end where
our run ends (final states compared, step counts printed). Rounds alternate between ours
(set up once, then solved in this process, as a worker times a solve) and the yardstick
(its own solve time, measured inside it), so that a change in the machine's load hits
both; figures are medians over the rounds, and the 1-minute load is printed.

Per pair: time per step of each, their steps, the ratio of times per step and of whole
solves, and the final-state difference. The results go to ``OUT/efficiency.json`` and
``OUT/efficiency.csv`` (default ``results/efficiency``), which the documentation's
performance pages show.

Yardsticks so far:

``ida_pendulum``
    SUNDIALS IDA with hand-written C residuals and iteration matrices of the GGL and
    index-1 forms, set up by the suite's own native driver (:mod:`integrators.sundials`),
    for ``ida-ggl`` and ``ida-index1``. With ``--binding`` the scikit-sundae driver
    (Python callbacks) is timed against it too.

``baumgarte_rk``
    The Baumgarte-stabilised ODE hand-written in C for ``pendulum`` and
    ``double-pendulum``, integrated by Kutta's RK4 on the same grid (``--h``) and by
    Dormand-Prince 5(4) under diffrax's step control as the suite sets it (``--rtol``,
    ``--atol``), for ``baumgarte-rk4`` and ``baumgarte-dopri5`` with their default
    ``alpha`` and ``beta``. A round takes the best of 3 solves of each (a solve of a
    millisecond is otherwise at the mercy of a cold start and of the machine's load), and
    the rows give the ratio of processor times as well (``cpu_ratio_per_step``), which a
    loaded machine disturbs less than wall time.

``radau_pendulum``
    Radau IIA (three stages, order 5) on the pendulum's index-3 and stabilised index-2
    forms, hand-written in C step for step as ``radau5`` and ``radau5-ggl`` take it (the
    same Newton, error estimate, step-size and Jacobian-reuse rules, the suite's options
    and tableau); the rows add
    the rejected steps, the Jacobian evaluations and the LU factorisations of both, and
    the ratio of processor times.

``spark_lobatto3ab3``
    The 3-stage Lobatto IIIA-IIIB (SPARK) step of ``lobatto3ab3`` on its structured path,
    hand-written in C for ``pendulum`` and ``sps-receiver``: the same unknowns and residual,
    the same simplified Newton with the same stopping rule and iteration cap, on the same
    grid (``--spark-h``, shrunk as the suite shrinks it), from the suite's initial values.
    Rows add ``h``, the Newton iterations of each and the ratio of processor times; a
    round takes the best of 3 solves of each, as for ``baumgarte_rk``.

Usage::

    python -m benchmarks.perf.efficiency
    python -m benchmarks.perf.efficiency --t-end 20 --rounds 5 --binding
"""

from __future__ import annotations

import csv
import json
import statistics
import tempfile
from pathlib import Path

from benchmarks.perf.processes import (ROOT, compile_yardstick, like_a_worker, run_process,
                                       state_difference, timed_solve)
from benchmarks.records import CommandParser

#: The bar: our time per step over the yardstick's.
RATIO_GOAL = 3.0


def parser() -> CommandParser:
    p = CommandParser(prog="python -m benchmarks.perf.efficiency",
                      description=__doc__.split("\n")[0])
    p.add_argument("--t-end", type=float, default=50.0, help="horizon (default 50)")
    p.add_argument("--rtol", type=float, default=1e-8, help="relative tolerance (1e-8)")
    p.add_argument("--atol", type=float, default=1e-10, help="absolute tolerance (1e-10)")
    p.add_argument("--h", type=float, default=1e-3,
                   help="step of baumgarte-rk4 (default 1e-3)")
    p.add_argument("--spark-h", type=float, default=1e-3,
                   help="step of lobatto3ab3 (default 1e-3)")
    p.add_argument("--rounds", type=int, default=5, help="alternating rounds (default 5)")
    p.add_argument("--binding", action="store_true",
                   help="time the scikit-sundae driver too (slow: Python per residual)")
    p.add_argument("--out", type=Path, default=Path("results/efficiency"),
                   help="folder of efficiency.json and efficiency.csv")
    return p


def _yardstick_run(exe: Path, form: str, args, y0, yp0) -> dict:
    command = [str(exe), form, repr(args.rtol), repr(args.atol), repr(args.t_end), "1",
               *map(repr, map(float, y0)), *map(repr, map(float, yp0))]
    ending, out, err, _ = run_process(command, 600.0, env=None)
    if ending:
        raise RuntimeError(f"{exe.name} {form}: {ending}: {err.strip()}")
    fields = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.strip()}
    return {"steps": int(fields["steps"][0]), "seconds": float(fields["seconds"][0]),
            "y": [float(x) for x in fields["y"]]}


def ida(args, workdir: Path) -> list[dict]:
    """``ida-ggl`` and ``ida-index1`` on ``pendulum`` against ``ida_pendulum``."""
    import integrators
    import problems
    from integrators import sundials
    from integrators.base import Grid
    from integrators.ida import FORMULATIONS, consistent_values

    libraries = sundials.sundials_libraries()
    flags = (f"-I{ROOT / 'integrators'}", *map(str, libraries),
             f"-Wl,-rpath,{libraries[0].parent}")
    exe, note, failed = compile_yardstick("ida_pendulum", workdir, flags)
    if exe is None:
        raise RuntimeError(note)
    case = problems.make("pendulum").with_t_end(args.t_end)
    rows = []
    for form in ("ggl", "index1"):
        n_mult = FORMULATIONS[form].multiplier_blocks * case.mech.m
        y0, yp0 = consistent_values(case.mech, FORMULATIONS[form].multiplier_blocks,
                                    case.t0, case.q0, case.v0)
        drivers = ["native"] + (["scikit-sundae"] if args.binding else [])
        solves = {d: integrators.make(f"ida-{form}:rtol={args.rtol},atol={args.atol},"
                                      f"driver={d}").prepare(case, Grid(case.t0, case.t_end))
                  for d in drivers}
        ours = {d: [] for d in drivers}
        theirs = []
        for _ in range(args.rounds):
            for d in drivers:
                traj, wall, _, _ = timed_solve(solves[d])
                if traj.status != "ok":
                    raise RuntimeError(f"ida-{form} ({d}): {traj.message}")
                ours[d].append((traj, wall))
            theirs.append(_yardstick_run(exe, form, args, y0, yp0))
        c_steps = theirs[0]["steps"]
        c_wall = statistics.median(r["seconds"] for r in theirs)
        c_state = theirs[0]["y"][:2 * case.mech.n]
        for d in drivers:
            traj = ours[d][0][0]
            wall = statistics.median(w for _, w in ours[d])
            steps = traj.counts["n_steps"]
            dq, dv = state_difference(c_state, [*traj.q_final, *traj.v_final])
            rows.append({
                "family": f"ida-{form}", "driver": d, "problem": "pendulum",
                "yardstick": "ida_pendulum (C, SUNDIALS IDA)", "t_end": args.t_end,
                "rtol": args.rtol, "atol": args.atol, "steps": steps,
                "yardstick_steps": c_steps, "us_per_step": 1e6 * wall / steps,
                "yardstick_us_per_step": 1e6 * c_wall / c_steps,
                "ratio_per_step": (wall / steps) / (c_wall / c_steps),
                "ratio_per_solve": wall / c_wall, "steps_ratio": steps / c_steps,
                "final_q_difference": dq, "final_v_difference": dv,
                "multipliers": n_mult})
    return rows


def _baumgarte_yardstick(exe: Path, problem: str, method: str, setting: list[str],
                         case, method_options) -> dict:
    command = [str(exe), problem, method, repr(method_options.alpha),
               repr(method_options.beta), repr(case.t_end), "3", *setting,
               *map(repr, map(float, case.q0)), *map(repr, map(float, case.v0))]
    ending, out, err, _ = run_process(command, 600.0, env=None)
    if ending:
        raise RuntimeError(f"{exe.name} {problem} {method}: {ending}: {err.strip()}")
    fields = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.strip()}
    return {"steps": int(fields["steps"][0]), "rejected": int(fields["rejected"][0]),
            "seconds": float(fields["seconds"][0]),
            "cpu_seconds": float(fields["cpu_seconds"][0]),
            "y": [float(x) for x in fields["y"]]}


def baumgarte(args, workdir: Path) -> list[dict]:
    """``baumgarte-rk4`` (step ``args.h``) and ``baumgarte-dopri5`` (``args.rtol``,
    ``args.atol``) on ``pendulum`` and ``double-pendulum`` against ``baumgarte_rk``."""
    import math

    import integrators
    import problems
    from integrators.base import Grid

    exe, note, failed = compile_yardstick("baumgarte_rk", workdir)
    if exe is None:
        raise RuntimeError(note)
    rows = []
    for problem in ("pendulum", "double-pendulum"):
        case = problems.make(problem).with_t_end(args.t_end)
        # The step count as BaumgarteRK.prepare rounds it; the C grid is the same.
        n_steps = max(1, math.ceil((case.t_end - case.t0) / args.h * (1 - 1e-12)))
        for family, spec, setting, shown in (
                ("baumgarte-rk4", f"baumgarte-rk4:h={args.h!r}", ["rk4", str(n_steps)],
                 f"h={args.h:g}"),
                ("baumgarte-dopri5", f"baumgarte-dopri5:rtol={args.rtol!r},atol={args.atol!r}",
                 ["dopri5", repr(args.rtol), repr(args.atol)], f"rtol={args.rtol:g}")):
            method = integrators.make(spec)
            solve = method.prepare(case, Grid(case.t0, case.t_end))
            ours, theirs = [], []
            for _ in range(args.rounds):
                # The best of 3 solves, as the yardstick reports its best of 3.
                solves = [timed_solve(solve) for _ in range(3)]
                traj = solves[0][0]
                if traj.status != "ok":
                    raise RuntimeError(f"{family} on {problem}: {traj.message}")
                ours.append((traj, min(s[1] for s in solves), min(s[2] for s in solves)))
                theirs.append(_baumgarte_yardstick(exe, problem, setting[0], setting[1:],
                                                   case, method))
            traj = ours[0][0]
            wall = statistics.median(w for _, w, _ in ours)
            # Processor time too: on a loaded machine it is disturbed less than wall time.
            cpu = statistics.median(c for _, _, c in ours)
            c_cpu = statistics.median(r["cpu_seconds"] for r in theirs)
            steps, c_steps = traj.counts["n_steps"], theirs[0]["steps"]
            c_wall = statistics.median(r["seconds"] for r in theirs)
            dq, dv = state_difference(theirs[0]["y"], [*traj.q_final, *traj.v_final])
            rows.append({
                "family": family, "driver": "jax", "problem": problem,
                "yardstick": "baumgarte_rk (C)", "t_end": args.t_end,
                "rtol": args.rtol if "dopri5" in family else None,
                "atol": args.atol if "dopri5" in family else None, "steps": steps,
                "yardstick_steps": c_steps, "us_per_step": 1e6 * wall / steps,
                "yardstick_us_per_step": 1e6 * c_wall / c_steps,
                "ratio_per_step": (wall / steps) / (c_wall / c_steps),
                "ratio_per_solve": wall / c_wall, "steps_ratio": steps / c_steps,
                "final_q_difference": dq, "final_v_difference": dv,
                "multipliers": case.mech.m, "setting": shown,
                "cpu_ratio_per_step": (cpu / steps) / (c_cpu / c_steps),
                "rejected": traj.counts["n_rejected"],
                "yardstick_rejected": theirs[0]["rejected"]})
    return rows


def radau_flags(formulation: str) -> tuple[str, ...]:
    """The compiler flags of ``radau_pendulum`` for a formulation (``-DGGL`` for ``ggl``),
    with complex arithmetic as Fortran's (RADAU5's language) is: products and quotients by
    their textbook formulas, without C's recovery of infinities and NaNs."""
    return ("-fcx-limited-range",) + (("-DGGL",) if formulation == "ggl" else ())


def radau_yardstick_command(exe: Path, method, case, rounds: int) -> list[str]:
    """The command line of ``radau_pendulum`` (compiled for ``method``'s formulation:
    :func:`radau_flags`) for the Radau IIA integrator ``method`` on ``case`` (the
    pendulum): its options, the suite's consistent initial values, and the tableau of
    :func:`integrators.radau.radau_iia` (its eigenbasis ``T`` is a normalisation that
    Newton's norms depend on)."""
    from integrators.ida import consistent_values
    from integrators.radau import FORMULATIONS, radau_iia

    y0, yp0 = consistent_values(case.mech, FORMULATIONS[method.formulation].multiplier_blocks,
                                case.t0, case.q0, case.v0)
    tab = radau_iia()
    numbers = [method.rtol, method.atol, method.multiplier_atol, method.thet,
               method.newton_tol, method.newton_max_iter, method.safety, method.first_step,
               method.max_step, case.t_end, rounds, *y0, *yp0, *tab.c, *tab.A_inv.ravel(),
               *tab.T.ravel(), *tab.T_inv.ravel(), tab.gamma, tab.alpha, tab.beta, *tab.e]
    return [str(exe), *map(repr, map(float, numbers))]


def radau_yardstick_run(command: list[str]) -> dict:
    """Run ``radau_pendulum``: its counts, best solve time and final ``y``."""
    ending, out, err, _ = run_process(command, 600.0, env=None)
    if ending:
        raise RuntimeError(f"radau_pendulum: {ending}: {err.strip()}")
    fields = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.strip()}
    counts = {key: int(fields[key][0]) for key in ("steps", "rejected", "jacobians", "lu",
                                                   "newton", "f_evals", "lin_solves")}
    return {**counts, "seconds": float(fields["seconds"][0]),
            "cpu_seconds": float(fields["cpu_seconds"][0]),
            "y": [float(x) for x in fields["y"]]}


def radau(args, workdir: Path) -> list[dict]:
    """``radau5`` (index-3 form) and ``radau5-ggl`` on ``pendulum`` against
    ``radau_pendulum``."""
    return [_radau_row(args, workdir, family) for family in ("radau5", "radau5-ggl")]


def _radau_row(args, workdir: Path, family: str) -> dict:
    import integrators
    import problems
    from integrators.base import Grid

    method = integrators.make(f"{family}:rtol={args.rtol!r},atol={args.atol!r}")
    folder = workdir / method.formulation
    folder.mkdir(exist_ok=True)
    exe, note, failed = compile_yardstick("radau_pendulum", folder,
                                          radau_flags(method.formulation))
    if exe is None:
        raise RuntimeError(note)
    case = problems.make("pendulum").with_t_end(args.t_end)
    solve = method.prepare(case, Grid(case.t0, case.t_end))
    command = radau_yardstick_command(exe, method, case, 1)
    ours, theirs = [], []
    for _ in range(args.rounds):
        traj, wall, cpu, _ = timed_solve(solve)
        if traj.status != "ok":
            raise RuntimeError(f"{family} on pendulum: {traj.message}")
        ours.append((traj, wall, cpu))
        theirs.append(radau_yardstick_run(command))
    traj = ours[0][0]
    wall = statistics.median(w for _, w, _ in ours)
    c_wall = statistics.median(r["seconds"] for r in theirs)
    # Processor time too: on a loaded machine it is disturbed less than wall time.
    cpu = statistics.median(c for _, _, c in ours)
    c_cpu = statistics.median(r["cpu_seconds"] for r in theirs)
    steps, c_steps = traj.counts["n_steps"], theirs[0]["steps"]
    n = case.mech.n
    dq, dv = state_difference(theirs[0]["y"][:2 * n], [*traj.q_final, *traj.v_final])
    return {
        "family": family, "driver": "jax", "problem": "pendulum",
        "yardstick": "radau_pendulum (C)", "t_end": args.t_end, "rtol": args.rtol,
        "atol": args.atol, "steps": steps, "yardstick_steps": c_steps,
        "us_per_step": 1e6 * wall / steps, "yardstick_us_per_step": 1e6 * c_wall / c_steps,
        "ratio_per_step": (wall / steps) / (c_wall / c_steps),
        "ratio_per_solve": wall / c_wall, "steps_ratio": steps / c_steps,
        "final_q_difference": dq, "final_v_difference": dv, "multipliers": case.mech.m,
        "cpu_ratio_per_step": (cpu / steps) / (c_cpu / c_steps),
        "rejected": traj.counts["n_rejected"], "yardstick_rejected": theirs[0]["rejected"],
        "jac_evals": traj.counts["n_jac_evals"], "yardstick_jac_evals": theirs[0]["jacobians"],
        "lu": traj.extra["n_lu"], "yardstick_lu": theirs[0]["lu"]}


def _spark_yardstick(exe: Path, problem: str, n_steps: int, h: float, method, case) -> dict:
    command = [str(exe), problem, str(n_steps), repr(h), repr(method.newton_tol),
               str(method.newton_max_iter), "3", *map(repr, map(float, case.q0)),
               *map(repr, map(float, case.v0))]
    ending, out, err, _ = run_process(command, 600.0, env=None)
    if ending:
        raise RuntimeError(f"{exe.name} {problem}: {ending}: {err.strip()}")
    fields = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.strip()}
    return {"steps": int(fields["steps"][0]), "newton": int(fields["newton"][0]),
            "seconds": float(fields["seconds"][0]),
            "cpu_seconds": float(fields["cpu_seconds"][0]),
            "y": [float(x) for x in fields["y"]]}


def spark(args, workdir: Path) -> list[dict]:
    """``lobatto3ab3`` (step ``args.spark_h``) on ``pendulum`` and ``sps-receiver`` against
    ``spark_lobatto3ab3``."""
    import integrators
    import problems
    from integrators.base import Grid
    from integrators.loop import Plan

    exe, note, _ = compile_yardstick("spark_lobatto3ab3", workdir)
    if exe is None:
        raise RuntimeError(note)
    rows = []
    for problem in ("pendulum", "sps-receiver"):
        case = problems.make(problem).with_t_end(args.t_end)
        grid = Grid(case.t0, case.t_end)
        # The compiled loop's grid (h shrunk to divide the horizon): the C steps on it too.
        plan = Plan.make(grid, args.spark_h)
        method = integrators.make("lobatto3ab3", h=args.spark_h)
        solve = method.prepare(case, grid)
        ours, theirs = [], []
        for _ in range(args.rounds):
            # The best of 3 solves, as the yardstick reports its best of 3.
            solves = [timed_solve(solve) for _ in range(3)]
            traj = solves[0][0]
            if traj.status != "ok":
                raise RuntimeError(f"lobatto3ab3 on {problem}: {traj.message}")
            ours.append((traj, min(s[1] for s in solves), min(s[2] for s in solves)))
            theirs.append(_spark_yardstick(exe, problem, plan.n_steps, plan.h, method, case))
        traj = ours[0][0]
        wall = statistics.median(w for _, w, _ in ours)
        cpu = statistics.median(c for _, _, c in ours)
        c_wall = statistics.median(r["seconds"] for r in theirs)
        c_cpu = statistics.median(r["cpu_seconds"] for r in theirs)
        steps, c_steps = traj.counts["n_steps"], theirs[0]["steps"]
        dq, dv = state_difference(theirs[0]["y"], [*traj.q_final, *traj.v_final])
        rows.append({
            "family": "lobatto3ab3", "driver": "jax", "problem": problem,
            "yardstick": "spark_lobatto3ab3 (C)", "t_end": args.t_end, "rtol": None,
            "atol": None, "steps": steps, "yardstick_steps": c_steps,
            "us_per_step": 1e6 * wall / steps,
            "yardstick_us_per_step": 1e6 * c_wall / c_steps,
            "ratio_per_step": (wall / steps) / (c_wall / c_steps),
            "ratio_per_solve": wall / c_wall, "steps_ratio": steps / c_steps,
            "final_q_difference": dq, "final_v_difference": dv,
            "multipliers": case.mech.m, "setting": f"h={plan.h:g}", "h": plan.h,
            "cpu_ratio_per_step": (cpu / steps) / (c_cpu / c_steps),
            "newton": traj.counts["n_newton"], "yardstick_newton": theirs[0]["newton"]})
    return rows


#: The comparisons, each ``(args, workdir) -> rows``.
COMPARISONS = {"ida": ida, "baumgarte": baumgarte, "radau": radau,
               "spark": spark}


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.rounds < 1 or not args.t_end > 0:
        parser().error("--rounds must be >= 1 and --t-end > 0")
    if not args.spark_h > 0:
        parser().error(f"--spark-h = {args.spark_h} must be > 0")
    load = like_a_worker()
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for name, compare in COMPARISONS.items():
            rows += compare(args, Path(work))
    print(f"load (1 min) at start: {load:.2f}; medians of {args.rounds} alternating rounds")
    print(f"{'family':16} {'driver':14} {'problem':15} {'us/step':>9} {'C us/step':>9} "
          f"{'ratio':>7} {'solve':>7} {'steps':>8} {'C steps':>8}  final |dq|")
    for r in rows:
        print(f"{r['family']:16} {r['driver']:14} {r['problem']:15} {r['us_per_step']:9.2f} "
              f"{r['yardstick_us_per_step']:9.2f} {r['ratio_per_step']:6.2f}x "
              f"{r['ratio_per_solve']:6.2f}x {r['steps']:8d} {r['yardstick_steps']:8d}  "
              f"{r['final_q_difference']:.1e}")
    args.out.mkdir(parents=True, exist_ok=True)
    for r in rows:
        r["load"] = load
    (args.out / "efficiency.json").write_text(json.dumps(
        {"goal_ratio_per_step": RATIO_GOAL, "rounds": args.rounds, "load": load,
         "rows": rows}, indent=1))
    with open(args.out / "efficiency.csv", "w", newline="") as f:
        # Comparisons may add columns of their own (a step size, rejected steps).
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {args.out / 'efficiency.json'} and {args.out / 'efficiency.csv'}")
    # The goal holds for each family's own driver, not for the scikit-sundae binding.
    native = [r for r in rows if r["driver"] != "scikit-sundae"]
    return 0 if all(r["ratio_per_step"] <= RATIO_GOAL for r in native) else 1


if __name__ == "__main__":
    raise SystemExit(main())
