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

``ida``
    SUNDIALS IDA called from C on the GGL and index-1 forms of ``pendulum`` (``--t-end``)
    and ``andrews`` (``--andrews-t-end``, 0.1 s by default: the Test Set's 0.03 s is too
    short a solve to time against the machine's noise), for ``ida-ggl`` and ``ida-index1``: the residual and
    iteration matrix that the suite's native driver compiles (:func:`ida_model`, one
    source of the physics), set up by that driver's own C (:mod:`integrators.sundials`).
    The rows add the ratio of processor times; the steps must be the native driver's
    within :data:`IDA_STEPS_GOAL`. With ``--binding`` the scikit-sundae driver (Python
    callbacks) is timed against it too.

``baumgarte_rk``
    The Baumgarte-stabilised ODE hand-written in C for ``pendulum`` and
    ``double-pendulum``, integrated by Kutta's RK4 on the same grid (``--h``) and by
    Dormand-Prince 5(4) under diffrax's step control as the suite sets it (``--rtol``,
    ``--atol``), for ``baumgarte-rk4`` and ``baumgarte-dopri5`` with their default
    ``alpha`` and ``beta``. A round takes the best of 3 solves of each (a solve of a
    millisecond is otherwise at the mercy of a cold start and of the machine's load), and
    the rows give the ratio of processor times as well (``cpu_ratio_per_step``), which a
    loaded machine disturbs less than wall time.

``radau5``
    Radau IIA (three stages, order 5) on the index-3 and stabilised index-2 forms of
    ``pendulum`` and ``andrews`` (the same horizons as ``ida``), written in C step for step
    as ``radau5`` and ``radau5-ggl`` take it (the same Newton, error estimate, index
    scaling, ``multiplier_atol``, step-size and Jacobian-reuse rules with ``thet``, the
    suite's options and tableau), on the residual and its blocks ``dR/dy``, ``dR/dy'``
    generated from the problem's functions (:func:`radau_model`); the rows add the
    rejected steps, the Jacobian evaluations and the LU factorisations of both, and the
    ratio of processor times.

``spark_lobatto3ab3``
    The 3-stage Lobatto IIIA-IIIB (SPARK) step of ``lobatto3ab3`` on its structured path,
    hand-written in C for ``pendulum`` and ``sps-receiver``: the same unknowns and residual,
    the same simplified Newton with the same stopping rule and iteration cap, on the same
    grid (``--spark-h``, shrunk as the suite shrinks it), from the suite's initial values.
    Rows add ``h``, the Newton iterations of each and the ratio of processor times; a
    round takes the best of 3 solves of each, as for ``baumgarte_rk``.

``dense_andrews``
    ``rattle``, ``genalpha`` and ``lobatto3ab3`` on ``andrews`` (a configuration-dependent
    mass that is not diagonal, six constraints), each on the structured path the suite
    takes there, hand-written in C: the same unknowns, residual, start and warm start, the
    same simplified Newton (``genalpha``'s with Anderson mixing) with its stopping rule
    and, where it does not converge, the same Newton with the exact Jacobian (BiCGSTAB
    preconditioned by the simplified correction), on the same grid (``--dense-h``, the
    suites' 1e-4 by default). The model's functions and the derivatives that Newton uses
    are C generated at run time from the problem's own autodiff-derived ones
    (:func:`andrews_model`), so that the physics has one source. The Test Set's horizon
    (0.03 s, 300 steps) is too short a solve to time, so the horizon is ``--dense-t-end``
    (0.5 s, 5000 steps, by default); the final states are compared relative to their size (``beta`` reaches
    hundreds of radians). The drive keeps speeding the mechanism up, so that later steps
    take more Newton iterations, and more of them Newton with the exact Jacobian. Rows add
    ``h``, the Newton iterations of each, the steps on which the yardstick's exact Newton
    took over and its BiCGSTAB iterations, the ratio of processor times, and a ``note``
    where the ratio misses the goal (:func:`dense_note`); a round takes the best of 3
    solves of each.

Usage::

    python -m benchmarks.perf.efficiency
    python -m benchmarks.perf.efficiency --t-end 20 --rounds 5 --binding
"""

from __future__ import annotations

import csv
import json
import math
import statistics
import tempfile
from pathlib import Path

from benchmarks.perf.processes import (ROOT, compile_yardstick, like_a_worker, run_process,
                                       state_difference, timed_solve)
from benchmarks.records import CommandParser

#: The bar: our time per step over the yardstick's.
RATIO_GOAL = 3.0
#: The bar on the ratio of IDA's steps to the yardstick's, either way: both drivers make the
#: same calls, and only round-off in the residuals (C against XLA's code) may move a
#: step-size decision.
IDA_STEPS_GOAL = 1.15


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
    p.add_argument("--dense-h", type=float, default=1e-4,
                   help="step of rattle, genalpha and lobatto3ab3 on andrews (default 1e-4, "
                        "the suites')")
    p.add_argument("--dense-t-end", type=float, default=0.5,
                   help="their horizon on andrews (default 0.5: 5000 steps of 1e-4)")
    p.add_argument("--andrews-t-end", type=float, default=0.1,
                   help="horizon of the IDA and Radau IIA runs on andrews (default 0.1)")
    p.add_argument("--rounds", type=int, default=5, help="alternating rounds (default 5)")
    p.add_argument("--binding", action="store_true",
                   help="time the scikit-sundae driver too (slow: Python per residual)")
    p.add_argument("--out", type=Path, default=Path("results/efficiency"),
                   help="folder of efficiency.json and efficiency.csv")
    return p


#: The problems of the IDA and Radau IIA comparisons (``--t-end`` sets the pendulum's
#: horizon, ``--andrews-t-end`` andrews').
DAE_PROBLEMS = ("pendulum", "andrews")


def dae_case(args, problem: str):
    """``problem``'s case over the horizon its option gives."""
    import problems

    return problems.make(problem).with_t_end(
        args.andrews_t_end if problem == "andrews" else args.t_end)


def dae_model(folder: Path, case, multiplier_blocks: int, body: str) -> Path:
    """Write ``dae_model.h`` into ``folder`` (made if missing) for the C yardsticks ``ida``
    and ``radau5``: ``case``'s system in a formulation with ``multiplier_blocks`` blocks of
    multipliers, as ``N``/``NEQ`` (unknowns) and ``NQV`` (those of ``q`` and ``v``), then
    ``body``, the functions generated from the problem's own JAX functions. Returns
    ``folder``."""
    mech = case.mech
    neq = 2 * mech.n + multiplier_blocks * mech.m
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "dae_model.h").write_text(
        f"/* {case.name}: generated from its JAX functions by benchmarks/perf/efficiency.py;"
        f" not edited by hand. */\n#define N {neq}\n#define NEQ {neq}\n"
        f"#define NQV {2 * mech.n}\n{body}")
    return folder


def compared(ours: list, theirs: list[dict], y, relative: bool = False) -> dict:
    """The columns every comparison's row has, from its rounds: ``ours`` holds a
    ``(trajectory, wall seconds, CPU seconds)`` per round, ``theirs`` the yardstick's
    outputs (:func:`yardstick_run`), ``y`` the yardstick's final ``(q, v)``. Times are
    medians over the rounds; steps and the final state are the first round's
    (:func:`benchmarks.perf.processes.state_difference`, ``relative`` passed on)."""
    traj = ours[0][0]
    wall = statistics.median(w for _, w, _ in ours)
    # Processor time too: on a loaded machine it is disturbed less than wall time.
    cpu = statistics.median(c for _, _, c in ours)
    c_wall = statistics.median(r["seconds"] for r in theirs)
    c_cpu = statistics.median(r["cpu_seconds"] for r in theirs)
    steps, c_steps = traj.counts["n_steps"], theirs[0]["steps"]
    dq, dv = state_difference(y, [*traj.q_final, *traj.v_final], relative=relative)
    return {"steps": steps, "yardstick_steps": c_steps, "us_per_step": 1e6 * wall / steps,
            "yardstick_us_per_step": 1e6 * c_wall / c_steps,
            "ratio_per_step": (wall / steps) / (c_wall / c_steps),
            "ratio_per_solve": wall / c_wall, "steps_ratio": steps / c_steps,
            "final_q_difference": dq, "final_v_difference": dv,
            "cpu_ratio_per_step": (cpu / steps) / (c_cpu / c_steps)}


def record_seconds(case, traj, rounds: int) -> float:
    """The drift record's share of a solve of ``traj``'s steps on ``case``: the best of
    ``rounds`` times of a :class:`integrators.record.Recorder` fed as many points (the
    run's kept states, repeated in time order) as the run took steps."""
    import time

    import numpy as np

    from integrators.base import Grid
    from integrators.record import Recorder

    steps, kept = traj.counts["n_steps"], traj.samples
    pick = np.minimum(np.arange(steps + 1) * len(kept["t"]) // (steps + 1), len(kept["t"]) - 1)
    t = np.linspace(case.t0, case.t_end, steps + 1)
    q, v = np.asarray(kept["q"])[pick], np.asarray(kept["v"])[pick]
    recorder = Recorder(case.mech, Grid(case.t0, case.t_end))
    best = math.inf
    for _ in range(rounds):
        start = time.perf_counter()
        recorder.start(t[0], q[0], v[0])
        recorder.extend(t[1:], q[1:], v[1:])
        recorder.windows()
        best = min(best, time.perf_counter() - start)
    return best


def with_note(row: dict, record_s: float) -> dict:
    """``row`` with the drift record's time per step, and, where the ratio is above
    :data:`RATIO_GOAL`, a ``note`` saying how much of our time per step it takes."""
    record_us = 1e6 * record_s / row["steps"]
    row["record_us_per_step"] = record_us
    if row["ratio_per_step"] > RATIO_GOAL:
        without = (row["us_per_step"] - record_us) / row["yardstick_us_per_step"]
        row["note"] = (f"of our {row['us_per_step']:.2f} us/step the drift record (|g|, "
                       f"|G v + g_t|, energy and invariants at every step, in batches) takes "
                       f"{record_us:.2f}; the rest is {without:.2f}x the yardstick's")
    return row


def ida_model(folder: Path, case, formulation: str) -> Path:
    """:func:`dae_model` for ``ida``: the native driver's own callbacks
    (:func:`integrators.sundials.functions`)."""
    from integrators import sundials
    from integrators.ida import FORMULATIONS

    form = FORMULATIONS[formulation]
    neq = 2 * case.mech.n + form.multiplier_blocks * case.mech.m
    return dae_model(folder, case, form.multiplier_blocks,
                     sundials.functions(form.residual(case.mech), neq, True))


def ida_yardstick_command(exe: Path, method, case, rounds: int) -> list[str]:
    """The command line of ``ida`` (compiled with :func:`ida_model`'s header) for the IDA
    integrator ``method`` on ``case``: its options and the suite's consistent initial
    values."""
    from integrators.ida import FORMULATIONS, consistent_values

    y0, yp0 = consistent_values(case.mech, FORMULATIONS[method.formulation].multiplier_blocks,
                                case.t0, case.q0, case.v0)
    numbers = [method.rtol, method.atol, method.multiplier_atol, method.max_order,
               method.max_nonlin_iters, method.max_conv_fails, method.first_step,
               method.min_step, method.max_step, case.t0, case.t_end, rounds, *y0, *yp0]
    return [str(exe), *map(repr, map(float, numbers))]


def yardstick_run(command: list[str], counts: tuple[str, ...] = ("steps",)) -> dict:
    """Run a yardstick, ``command`` (its executable first): the integer ``counts`` it
    prints, its best solve times (``seconds``, ``cpu_seconds``) and final ``y``, each on a
    line of its own led by its name. A yardstick that fails raises, with its stderr."""
    ending, out, err, _ = run_process(command, 600.0, env=None)
    if ending:
        raise RuntimeError(f"{' '.join(command[:2])}: {ending}: {err.strip()}")
    fields = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line.strip()}
    return {**{key: int(fields[key][0]) for key in counts},
            "seconds": float(fields["seconds"][0]),
            "cpu_seconds": float(fields["cpu_seconds"][0]),
            "y": [float(x) for x in fields["y"]]}


def ida_yardstick_run(command: list[str]) -> dict:
    """Run ``ida``: its steps, best solve times and final ``y``."""
    return yardstick_run(command)


def compile_ida(folder: Path) -> Path:
    """``ida`` compiled against SUNDIALS from scikit-sundae's wheel, with the header in
    ``folder``."""
    from integrators import sundials

    libraries = sundials.sundials_libraries()
    flags = (f"-I{folder}", f"-I{ROOT / 'integrators'}", *map(str, libraries),
             f"-Wl,-rpath,{libraries[0].parent}")
    exe, note, _ = compile_yardstick("ida", folder, flags)
    if exe is None:
        raise RuntimeError(note)
    return exe


def ida(args, workdir: Path) -> list[dict]:
    """``ida-ggl`` and ``ida-index1`` on ``pendulum`` and ``andrews`` against ``ida``; the
    rows add the ratio of processor times."""
    import integrators
    from integrators.base import Grid
    from integrators.ida import FORMULATIONS

    rows = []
    for problem in DAE_PROBLEMS:
        case = dae_case(args, problem)
        for form in ("ggl", "index1"):
            drivers = ["native"] + (["scikit-sundae"] if args.binding else [])
            methods = {d: integrators.make(f"ida-{form}:rtol={args.rtol},atol={args.atol},"
                                           f"driver={d}") for d in drivers}
            solves = {d: m.prepare(case, Grid(case.t0, case.t_end)) for d, m in methods.items()}
            exe = compile_ida(ida_model(workdir / f"ida-{form}-{problem}", case, form))
            command = ida_yardstick_command(exe, methods["native"], case, 1)
            ours = {d: [] for d in drivers}
            theirs = []
            for _ in range(args.rounds):
                for d in drivers:
                    traj, wall, cpu, _ = timed_solve(solves[d])
                    if traj.status != "ok":
                        raise RuntimeError(f"ida-{form} ({d}) on {problem}: {traj.message}")
                    ours[d].append((traj, wall, cpu))
                theirs.append(ida_yardstick_run(command))
            for d in drivers:
                traj = ours[d][0][0]
                rows.append(with_note({
                    "family": f"ida-{form}", "driver": d, "problem": problem,
                    "yardstick": "ida (C, SUNDIALS IDA)", "t_end": case.t_end,
                    "rtol": args.rtol, "atol": args.atol,
                    **compared(ours[d], theirs, theirs[0]["y"][:2 * case.mech.n]),
                    "multipliers": FORMULATIONS[form].multiplier_blocks * case.mech.m,
                    "steps_goal": IDA_STEPS_GOAL if d == "native" else None},
                    record_seconds(case, traj, args.rounds)))
    return rows


def _baumgarte_yardstick(exe: Path, problem: str, method: str, setting: list[str],
                         case, method_options) -> dict:
    command = [str(exe), problem, method, repr(method_options.alpha),
               repr(method_options.beta), repr(case.t_end), "3", *setting,
               *map(repr, map(float, case.q0)), *map(repr, map(float, case.v0))]
    return yardstick_run(command, ("steps", "rejected"))


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
            rows.append({
                "family": family, "driver": "jax", "problem": problem,
                "yardstick": "baumgarte_rk (C)", "t_end": args.t_end,
                "rtol": args.rtol if "dopri5" in family else None,
                "atol": args.atol if "dopri5" in family else None,
                **compared(ours, theirs, theirs[0]["y"]),
                "multipliers": case.mech.m, "setting": shown,
                "rejected": traj.counts["n_rejected"],
                "yardstick_rejected": theirs[0]["rejected"]})
    return rows


def radau_model(folder: Path, case, formulation: str) -> Path:
    """:func:`dae_model` for ``radau5``: the residual of the formulation
    (:data:`integrators.radau.FORMULATIONS`), its blocks ``J = dR/dy`` and ``B = dR/dy'``
    (:func:`integrators.radau.iteration_blocks`, row-major) as ``jacobian`` and ``mass``,
    and ``EXPONENT``, each component's index minus one."""
    from integrators.radau import FORMULATIONS, iteration_blocks
    from linalg.codegen import c_function

    form, mech = FORMULATIONS[formulation], case.mech
    R = form.residual(mech)
    neq = 2 * mech.n + form.multiplier_blocks * mech.m
    inputs = {"t": (), "y": (neq,), "yp": (neq,)}
    exponent = ", ".join(repr(float(k - 1)) for k in form.indices(mech.n, mech.m))
    body = "".join([
        "#include <math.h>\n",
        f"static const double EXPONENT[N] = {{{exponent}}};\n",
        c_function(R, "residual", inputs, "r"),
        c_function(lambda t, y, yp: iteration_blocks(R, t, y, yp)[0], "jacobian", inputs, "J"),
        c_function(lambda t, y, yp: iteration_blocks(R, t, y, yp)[1], "mass", inputs, "B")])
    return dae_model(folder, case, form.multiplier_blocks, body)


def radau_flags(method, case) -> tuple[str, ...]:
    """The compiler flags of ``radau5`` for the Radau IIA integrator ``method`` on ``case``:
    complex arithmetic as Fortran's (RADAU5's language) is, products and quotients by their
    textbook formulas without C's recovery of infinities and NaNs; ``-DLAPACK_PIVOT`` where
    the suite factorises the stage systems with LAPACK (above
    :data:`integrators.radau.INLINE_MAX` unknowns), whose complex pivot is the largest
    ``|re| + |im|``."""
    from integrators.radau import FORMULATIONS, INLINE_MAX

    mech = case.mech
    neq = 2 * mech.n + FORMULATIONS[method.formulation].multiplier_blocks * mech.m
    return ("-fcx-limited-range",) + (("-DLAPACK_PIVOT",) if neq > INLINE_MAX else ())


def compile_radau(folder: Path, method, case) -> Path:
    """``radau5`` for ``method`` on ``case``, with :func:`radau_model`'s header written into
    ``folder`` and the executable there."""
    radau_model(folder, case, method.formulation)
    exe, note, _ = compile_yardstick("radau5", folder,
                                     (f"-I{folder}", *radau_flags(method, case)))
    if exe is None:
        raise RuntimeError(note)
    return exe


def radau_yardstick_command(exe: Path, method, case, rounds: int) -> list[str]:
    """The command line of ``radau5`` (:func:`compile_radau`) for the Radau IIA integrator
    ``method`` on ``case``: its options, the suite's consistent initial values, and the
    tableau of :func:`integrators.radau.radau_iia` (its eigenbasis ``T`` is a normalisation
    that Newton's norms depend on)."""
    from integrators.ida import consistent_values
    from integrators.radau import FORMULATIONS, radau_iia

    y0, yp0 = consistent_values(case.mech, FORMULATIONS[method.formulation].multiplier_blocks,
                                case.t0, case.q0, case.v0)
    tab = radau_iia()
    numbers = [method.rtol, method.atol, method.multiplier_atol, method.thet,
               method.newton_tol, method.newton_max_iter, method.safety, method.first_step,
               method.max_step, case.t0, case.t_end, rounds, *y0, *yp0, *tab.c,
               *tab.A_inv.ravel(), *tab.T.ravel(), *tab.T_inv.ravel(), tab.gamma, tab.alpha,
               tab.beta, *tab.e]
    return [str(exe), *map(repr, map(float, numbers))]


def radau_yardstick_run(command: list[str]) -> dict:
    """Run ``radau5``: its counts, best solve time and final ``y``."""
    return yardstick_run(command, ("steps", "rejected", "jacobians", "lu", "newton",
                                   "f_evals", "lin_solves"))


def radau(args, workdir: Path) -> list[dict]:
    """``radau5`` (index-3 form) and ``radau5-ggl`` on ``pendulum`` and ``andrews`` against
    ``radau5``."""
    return [_radau_row(args, workdir, family, problem) for problem in DAE_PROBLEMS
            for family in ("radau5", "radau5-ggl")]


def _radau_row(args, workdir: Path, family: str, problem: str) -> dict:
    import integrators
    from integrators.base import Grid

    method = integrators.make(f"{family}:rtol={args.rtol!r},atol={args.atol!r}")
    case = dae_case(args, problem)
    exe = compile_radau(workdir / f"{family}-{problem}", method, case)
    solve = method.prepare(case, Grid(case.t0, case.t_end))
    command = radau_yardstick_command(exe, method, case, 1)
    ours, theirs = [], []
    for _ in range(args.rounds):
        traj, wall, cpu, _ = timed_solve(solve)
        if traj.status != "ok":
            raise RuntimeError(f"{family} on {problem}: {traj.message}")
        ours.append((traj, wall, cpu))
        theirs.append(radau_yardstick_run(command))
    traj = ours[0][0]
    return with_note({
        "family": family, "driver": "jax", "problem": problem,
        "yardstick": "radau5 (C)", "t_end": case.t_end, "rtol": args.rtol,
        "atol": args.atol, **compared(ours, theirs, theirs[0]["y"][:2 * case.mech.n]),
        "multipliers": case.mech.m,
        "rejected": traj.counts["n_rejected"], "yardstick_rejected": theirs[0]["rejected"],
        "jac_evals": traj.counts["n_jac_evals"], "yardstick_jac_evals": theirs[0]["jacobians"],
        "lu": traj.extra["n_lu"], "yardstick_lu": theirs[0]["lu"]},
        record_seconds(case, traj, args.rounds))


def _spark_yardstick(exe: Path, problem: str, n_steps: int, h: float, method, case) -> dict:
    command = [str(exe), problem, str(n_steps), repr(h), repr(method.newton_tol),
               str(method.newton_max_iter), "3", *map(repr, map(float, case.q0)),
               *map(repr, map(float, case.v0))]
    return yardstick_run(command, ("steps", "newton"))


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
        rows.append({
            "family": "lobatto3ab3", "driver": "jax", "problem": problem,
            "yardstick": "spark_lobatto3ab3 (C)", "t_end": args.t_end, "rtol": None,
            "atol": None, **compared(ours, theirs, theirs[0]["y"]),
            "multipliers": case.mech.m, "setting": f"h={plan.h:g}", "h": plan.h,
            "newton": traj.counts["n_newton"], "yardstick_newton": theirs[0]["newton"]})
    return rows


#: The fixed-step families that ``dense_andrews`` writes out, by its name for them.
DENSE_FAMILIES = ("rattle", "genalpha", "lobatto3ab3")


def andrews_model(workdir: Path) -> Path:
    """Write ``andrews_model.h`` into ``workdir``: andrews' functions as straight-line C
    generated from the problem's own autodiff-derived ones
    (:func:`linalg.codegen.c_function`), and lobatto3ab3's stage count and tableau as
    exact hexadecimal constants (``dense_andrews.c`` says what each is)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import integrators
    import problems
    from linalg.codegen import c_function

    mech = problems.make("andrews").mech
    n, m = mech.n, mech.m
    t, p = jnp.asarray(0.0), jnp.zeros(n)

    def hamilton_force(q, v):
        return -mech.H_q(q, p, v)

    def lagrange_force(q, v):
        return mech.force(t, q, v)

    q, qv = {"q": (n,)}, {"q": (n,), "v": (n,)}
    functions = (
        ("mass_matrix", mech.mass, q),
        ("hamilton_force", hamilton_force, qv),
        ("lagrange_force", lagrange_force, qv),
        ("constraint_jacobian", lambda q: mech.G(q, t), q),
        # M, g and G at one q in one function, so that they share its sines and cosines.
        ("configuration", lambda q: jnp.concatenate([jnp.ravel(mech.mass(q)), mech.g(q, t),
                                                     jnp.ravel(mech.G(q, t))]), q),
        ("curvature", lambda q, v: mech.gamma(q, v, t), qv),
        ("energy", lambda q, v: mech.energy(q, v)[None], qv),
        # The Jacobians that the exact Newton's products J x are made of, formed once per
        # iterate as the suite's linearisation is: d(M(q) x)/dq, the forces' (n x 2n: dq,
        # dv), d(G^T lam)/dq and d(G v)/dq.
        ("mass_dq", lambda q, x: jax.jacfwd(mech.mass_times)(q, x), {"q": (n,), "x": (n,)}),
        ("hamilton_force_d", lambda q, v: jnp.hstack(jax.jacfwd(hamilton_force, (0, 1))(q, v)),
         qv),
        ("lagrange_force_d", lambda q, v: jnp.hstack(jax.jacfwd(lagrange_force, (0, 1))(q, v)),
         qv),
        ("gt_dq", lambda q, lam: jax.jacfwd(lambda q: mech.GT(q, t, lam))(q),
         {"q": (n,), "lam": (m,)}),
        ("gv_dq", lambda q, v: jax.jacfwd(lambda q: mech.G_times(q, t, v))(q), qv))
    method = integrators.make("lobatto3ab3")
    A, Ah, b, c, B_inv = method.tableau()

    def table(name, x):
        x = np.asarray(x, dtype=float)
        rows = [", ".join(float(v).hex() for v in row) for row in np.atleast_2d(x)]
        body = ", ".join(f"{{{r}}}" for r in rows) if x.ndim == 2 else rows[0]
        shape = "[S]" * x.ndim
        return f"static const double {name}{shape} = {{{body}}};"

    lines = ["/* Generated by benchmarks/perf/efficiency.py (andrews_model) from problems/"
             "andrews.py through problems/mechanics.py; not edited by hand. */",
             "#ifndef ANDREWS_MODEL_H", "#define ANDREWS_MODEL_H", "#include <math.h>",
             f"#define N {n}", f"#define M {m}", f"#define S {method.stages}",
             table("A", A), table("AH", Ah), table("B", b), table("C", c),
             table("BINV", B_inv)]
    lines += [c_function(f, name, inputs, "out") for name, f, inputs in functions]
    header = workdir / "andrews_model.h"
    header.write_text("\n".join(lines + ["#endif", ""]))
    return header


def dense_yardstick_command(exe: Path, family: str, method, case, n_steps: int, h: float,
                            repeats: int) -> list[str]:
    """The command line of ``dense_andrews`` for ``method`` (of ``family``, one of
    :data:`DENSE_FAMILIES`) on ``case`` (andrews): ``n_steps`` of ``h``, its Newton options,
    genalpha's coefficients (zeros for the others) and the initial values."""
    coefficients = method.coefficients() if family == "genalpha" else (0.0,) * 4
    return [str(exe), family, str(n_steps), repr(h), repr(method.newton_tol),
            str(method.newton_max_iter), str(repeats), *map(repr, map(float, coefficients)),
            *map(repr, map(float, case.q0)), *map(repr, map(float, case.v0))]


def dense_yardstick_run(command: list[str]) -> dict:
    """Run ``dense_andrews``: its steps, Newton iterations (all; the steps on which Newton
    with the exact Jacobian took over, and its BiCGSTAB iterations), best solve times and
    final state."""
    return yardstick_run(command, ("steps", "newton", "exact_steps", "krylov"))


def compile_dense(workdir: Path) -> Path:
    """``dense_andrews`` compiled in ``workdir`` against the model written there."""
    andrews_model(workdir)
    exe, note, _ = compile_yardstick("dense_andrews", workdir, (f"-I{workdir}",))
    if exe is None:
        raise RuntimeError(note)
    return exe


def dense(args, workdir: Path) -> list[dict]:
    """``rattle``, ``genalpha`` and ``lobatto3ab3`` (step ``args.dense_h``) on ``andrews``
    over ``args.dense_t_end`` against ``dense_andrews``."""
    import integrators
    import problems
    from integrators.base import Grid
    from integrators.loop import Plan

    exe = compile_dense(workdir)
    case = problems.make("andrews").with_t_end(args.dense_t_end)
    grid = Grid(case.t0, case.t_end)
    # The compiled loop's grid (h shrunk to divide the horizon): the C steps on it too.
    plan = Plan.make(grid, args.dense_h)
    rows = []
    for family in DENSE_FAMILIES:
        method = integrators.make(family, h=args.dense_h)
        solve = method.prepare(case, grid)
        command = dense_yardstick_command(exe, family, method, case, plan.n_steps, plan.h, 3)
        ours, theirs = [], []
        for _ in range(args.rounds):
            # The best of 3 solves, as the yardstick reports its best of 3.
            solves = [timed_solve(solve) for _ in range(3)]
            traj = solves[0][0]
            if traj.status != "ok":
                raise RuntimeError(f"{family} on andrews: {traj.message}")
            ours.append((traj, min(s[1] for s in solves), min(s[2] for s in solves)))
            theirs.append(dense_yardstick_run(command))
        traj = ours[0][0]
        rows.append({
            "family": family, "driver": "jax", "problem": "andrews",
            "yardstick": "dense_andrews (C)", "t_end": case.t_end, "rtol": None,
            "atol": None, **compared(ours, theirs, theirs[0]["y"], relative=True),
            "multipliers": case.mech.m, "setting": f"h={plan.h:g}", "h": plan.h,
            "newton": traj.counts["n_newton"], "yardstick_newton": theirs[0]["newton"],
            "yardstick_exact_steps": theirs[0]["exact_steps"],
            "yardstick_krylov": theirs[0]["krylov"]})
        rows[-1]["note"] = dense_note(rows[-1])
    return rows


def dense_note(row: dict) -> str:
    """Why a ``dense`` row misses :data:`RATIO_GOAL`, from its own measurements (empty
    where it does not): the ratio of processor times, which the machine's load disturbs
    less than wall-clock time, and the work per step of each side."""
    if row["ratio_per_step"] <= RATIO_GOAL:
        return ""
    work = (f"Newton iterations per step {row['newton'] / row['steps']:.2f} (C "
            f"{row['yardstick_newton'] / row['yardstick_steps']:.2f}), Newton with the exact "
            f"Jacobian on {row['yardstick_exact_steps']} of {row['yardstick_steps']} C steps")
    if row["cpu_ratio_per_step"] <= RATIO_GOAL:
        return (f"wall-clock ratio over the goal, processor-time ratio "
                f"{row['cpu_ratio_per_step']:.2f}x within it: the machine's load; {work}")
    return f"processor-time ratio {row['cpu_ratio_per_step']:.2f}x over the goal too; {work}"


#: The comparisons, each ``(args, workdir) -> rows``.
COMPARISONS = {"ida": ida, "baumgarte": baumgarte, "radau": radau,
               "spark": spark, "dense": dense}


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.rounds < 1 or not args.t_end > 0:
        parser().error("--rounds must be >= 1 and --t-end > 0")
    if not args.spark_h > 0:
        parser().error(f"--spark-h = {args.spark_h} must be > 0")
    if not (args.dense_h > 0 and args.dense_t_end > 0):
        parser().error("--dense-h and --dense-t-end must be > 0")
    if not args.andrews_t_end > 0:
        parser().error(f"--andrews-t-end = {args.andrews_t_end} must be > 0")
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
    met = all(r["ratio_per_step"] <= RATIO_GOAL
              and r.get("steps_goal", math.inf) >= max(r["steps_ratio"], 1 / r["steps_ratio"])
              for r in native)
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
