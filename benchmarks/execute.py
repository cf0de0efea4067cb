"""One run, in one place: build the case and the integrator, time set-up and solve, measure.

:func:`execute` returns a complete :class:`~benchmarks.records.Record`: the settings and
options that ran, what the case and the method declare (``t0``, energy scale, nominal
order, sensitivity), the work counters, the metrics (:mod:`benchmarks.metrics`), the drift
classes of ``|g|`` and ``|H - H0|`` (:mod:`benchmarks.drift`), the linear solver and the
sampling. A run that fails numerically is ``failed`` with the method's message, a run that
raises is ``error`` with the exception (and the ``file:line`` in user code where it
arose), and neither raises here.

:func:`known` gives the columns fixed before anything runs, and the run key; the batch
computes them while validating, so that a run killed at its time limit is recorded with
them too.
"""

from __future__ import annotations

import functools
import json
import math
import statistics
import time
from typing import Callable

import numpy as np

import integrators
import problems
from benchmarks.audit import explain
from benchmarks.drift import ENERGY_REL_FLOOR, POS_FLOOR, classify
from benchmarks.metrics import summarize
from benchmarks.records import Record, RunSpec, Status, blank_row, provenance, run_key
from integrators.base import COUNTERS, Grid, Trajectory
from problems.spec import parse_value, split_spec


@functools.lru_cache(maxsize=8)
def _case(problem: str):
    # Cases are immutable: the runs of a worker share them, and with them the compiled
    # functions keyed on their Mechanics (a step-size or tolerance sweep compiles once).
    return problems.make(problem)


def forget_cases() -> None:
    """Drop the cases this process keeps (a problem's definition was replaced)."""
    _case.cache_clear()


def build(spec: RunSpec):
    """The case and the integrator of a run spec (raises on bad input)."""
    case = _case(spec.problem)
    if spec.t_end is not None:
        case = case.with_t_end(spec.t_end)
    integrator = integrators.make(spec.integrator, h=spec.h, rtol=spec.rtol, atol=spec.atol)
    return case, integrator


def known(spec: RunSpec, case, integ, grid_options: dict | None, version: str) -> dict:
    """The columns fixed by the case and the integrator before anything runs, and the
    run's ``run_key`` (:func:`benchmarks.records.run_key`) for code version ``version``."""
    opts = integ.options()
    name, raw = split_spec(spec.problem)
    arguments = problems.parameters(name)
    arguments.update({k: parse_value(v, arguments[k], k) for k, v in raw.items()})
    resolved = {"problem": name, "arguments": arguments, "params": dict(case.params),
                "integrator": split_spec(spec.integrator)[0], "options": opts,
                "t_end": case.t_end, "grid": grid_options or {}}
    return dict(t_end=case.t_end, options=json.dumps(opts, default=str),
                params=json.dumps(case.params, default=str), h=opts.get("h"),
                rtol=opts.get("rtol"), atol=opts.get("atol"), t0=case.t0,
                energy_scale=case.energy_scale, nominal_order=integ.nominal_order,
                family=integ.family,
                sensitive=int(bool(case.system.sensitive)),
                run_key=run_key(resolved, version))




def execute(spec: RunSpec, version: str | None = None, repeats: int = 3,
            repeat_budget: float = 10.0, grid_options: dict | None = None,
            deadline: float | None = None,
            on_phase: Callable[[str], None] | None = None) -> Record:
    """Run ``spec``: set-up once, solve up to ``repeats`` times, measure the last solve.

    Parameters
    ----------
    spec : RunSpec
        The run.
    version : str, optional
        The code version its run key is computed with (the batch's, so that a run done by
        a worker elsewhere carries the key the batch resumes by); default: this code's.
    repeats : int
        Timed solves at most; ``wall_s`` is their median, ``wall_min_s`` and ``wall_max_s``
        their spread.
    repeat_budget : float
        Repeats stop once their total passes this many seconds, so long runs are solved
        once or twice.
    grid_options : dict, optional
        :class:`~integrators.base.Grid` options (windows, samples).
    deadline : float, optional
        A ``time.monotonic`` time (the run's time limit): a repeat is not started when it
        would likely end after it. Every repeat of a deterministic method gives the same
        trajectory, so which one is measured is moot.
    on_phase : callable, optional
        Told what the run is doing (for the message of a run killed at its time limit).
    """
    phase = on_phase or (lambda text: None)
    try:
        phase("building the case")
        case, integ = build(spec)
        version = version or provenance()["code_version"]
        row = blank_row(spec, **known(spec, case, integ, grid_options, version))
    except Exception as exc:  # bad input or a defect: recorded, never fatal to the suite
        return Record(blank_row(spec, status=Status.ERROR, message=explain(exc)))
    try:
        grid = Grid(case.t0, case.t_end, **(grid_options or {}))
        phase("set-up")
        start = time.perf_counter()
        solve = integ.prepare(case, grid)
        row["setup_s"] = time.perf_counter() - start
        times: list[float] = []
        while True:
            phase(f"solve (repeat {len(times) + 1}; set-up took {row['setup_s']:.3g} s)")
            start = time.perf_counter()
            traj = solve()
            times.append(time.perf_counter() - start)
            if len(times) >= repeats or sum(times) >= repeat_budget:
                break
            # A margin of twice the last solve: repeats vary, and a timing repeat must not
            # turn a finished run into a timeout.
            if deadline is not None and time.monotonic() + 2.0 * times[-1] > deadline:
                break
        phase("measuring")
        row.update(wall_s=statistics.median(times), wall_min_s=min(times),
                   wall_max_s=max(times), repeats=len(times))
        row.update(trajectory_columns(case, traj))
    except Exception as exc:  # a defect in the method or the user's functions
        return Record({**row, "status": Status.ERROR, "message": explain(exc)})
    return Record(row, traj.windows, traj.samples)


def _non_finite(traj: Trajectory) -> tuple[str, float | None] | None:
    """What is not finite in a trajectory that claims success, and when; else None."""
    if not (np.all(np.isfinite(traj.q_final)) and np.all(np.isfinite(traj.v_final))):
        return f"the final state at t = {traj.t_final:.6g} is not finite", traj.t_final
    t = np.asarray(traj.windows.get("t", []))
    for name, series in traj.windows.items():
        bad = ~np.isfinite(np.asarray(series, dtype=float))
        if name != "t" and bad.any():
            first = int(np.argmax(bad))
            when = float(t[first]) if first < len(t) else None
            where = f" from the window ending at t = {when:.6g}" if when is not None else ""
            return f"its {name} series is not finite{where}", when
    return None


def growth(case, traj: Trajectory) -> dict[str, str | None]:
    """Drift classes of ``|g|`` and, where energy is conserved, of ``|H - H0|``
    (:func:`benchmarks.drift.classify` labels), from the windowed maxima."""
    w = traj.windows
    t = w.get("t")
    if t is None or len(t) == 0:
        return {"pos_growth": None, "energy_growth": None}
    pos = classify(t, w["pos"], t0=case.t0, floor=POS_FLOOR) if "pos" in w else None
    energy = None
    if case.mech.has_energy and "energy" in w:
        energy = classify(t, w["energy"], t0=case.t0,
                          floor=ENERGY_REL_FLOOR * case.energy_scale)
    return {"pos_growth": pos.label() if pos is not None else None,
            "energy_growth": energy.label() if energy is not None else None}


def trajectory_columns(case, traj: Trajectory) -> dict:
    """The columns that come from the trajectory: metrics, work, state, drift classes."""
    metrics = summarize(case, traj)
    inv = {k[len("max_inv:"):]: v for k, v in metrics.items() if k.startswith("max_inv:")}
    cols = {k: v for k, v in metrics.items() if not k.startswith("max_inv:")}
    cols.update({c: traj.counts.get(c, 0) for c in COUNTERS})
    cols.update(
        status=traj.status, message=traj.message, t_final=traj.t_final,
        q_final=json.dumps([float(x) for x in traj.q_final]),
        v_final=json.dumps([float(x) for x in traj.v_final]),
        invariant_errors=json.dumps(inv) if inv else "",
        sampling=traj.sampling, fail_step=traj.fail_step, fail_time=traj.fail_time,
        callback_s=traj.extra.get("callback_s"), linear_solver=traj.linear_solver,
        pattern_nnz=traj.pattern_nnz,
    )
    cols.update(growth(case, traj))
    if traj.status == Status.OK and (bad := _non_finite(traj)) is not None:
        what, when = bad
        cols.update(status=Status.FAILED, fail_time=when,
                    message=f"the method reported success but {what}")
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in cols.items()}
