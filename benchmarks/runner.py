"""Running one benchmark: build the case and the integrator, time set-up and solve, measure.

Every outcome is a :class:`Record`: a run that fails numerically is ``failed`` with the
method's message, a run that raises is ``error`` with the exception, and neither stops the
suite.
"""

from __future__ import annotations

import itertools
import json
import math
import statistics
import time
import traceback
from dataclasses import dataclass, field

import numpy as np

import integrators
import problems
from benchmarks.metrics import summarize
from integrators.base import ERROR, COUNTERS, Grid, Trajectory

#: Columns of runs.csv, in order (design notes, section 6, plus the work counters).
COLUMNS = (
    "problem", "integrator", "h", "rtol", "atol", "t_end", "status", "message",
    "n_steps", "n_rejected", "n_f_evals", "n_jac_evals", "n_newton", "n_lin_solves",
    "wall_s", "setup_s", "max_pos_residual", "max_vel_residual", "max_energy_error",
    "rel_energy_error", "final_state_error", "scd", "t_final", "q_final", "v_final",
    "invariant_errors", "sampling", "fail_step", "fail_time", "callback_s", "repeats",
    "options", "params",
)


@dataclass(frozen=True)
class RunSpec:
    """One run: a problem spec, an integrator spec and the settings that vary in sweeps."""

    problem: str
    integrator: str
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    t_end: float | None = None

    def label(self) -> str:
        setting = f"h={self.h:g}" if self.h is not None else (
            f"rtol={self.rtol:g}" if self.rtol is not None else "defaults")
        return f"{self.problem} / {self.integrator} / {setting}"


@dataclass
class Record:
    """A finished run: its ``runs.csv`` row and its drift series and samples."""

    row: dict
    windows: dict[str, np.ndarray] = field(default_factory=dict)
    samples: dict[str, np.ndarray] = field(default_factory=dict)


def expand(problem_specs, integrator_specs, hs=(), rtols=(), atols=(), t_end=None) -> list[RunSpec]:
    """Every combination: ``hs`` go to fixed-step methods, ``rtols x atols`` to adaptive ones.

    An empty list leaves the method's own default for that setting.
    """
    runs = []
    for p, i in itertools.product(problem_specs, integrator_specs):
        key = problems.split_spec(i)[0]
        if key not in integrators.REGISTRY:
            integrators.make(i)  # raises the error that names the unknown key
        if integrators.cls_of(key).adaptive:
            for rtol, atol in itertools.product(rtols or [None], atols or [None]):
                runs.append(RunSpec(p, i, None, rtol, atol, t_end))
        else:
            runs.extend(RunSpec(p, i, h, None, None, t_end) for h in (hs or [None]))
    return runs


def build(spec: RunSpec):
    """The case and the integrator of a run spec (raises on bad input)."""
    case = problems.make(spec.problem)
    if spec.t_end is not None:
        case = case.with_t_end(spec.t_end)
    integrator = integrators.make(spec.integrator, h=spec.h, rtol=spec.rtol, atol=spec.atol)
    return case, integrator


def _row(spec: RunSpec, **values) -> dict:
    row = {c: None for c in COLUMNS}
    row.update(problem=spec.problem, integrator=spec.integrator, h=spec.h, rtol=spec.rtol,
               atol=spec.atol, t_end=spec.t_end)
    row.update(values)
    return row


def execute(spec: RunSpec, repeats: int = 3, repeat_budget: float = 10.0,
            grid_options: dict | None = None) -> Record:
    """Run ``spec``: set-up once, solve up to ``repeats`` times, measure the last solve.

    The solve is timed as the median of the repeats; repeats stop early once their total
    passes ``repeat_budget`` seconds, so long runs are solved once or twice. Every repeat of
    a deterministic method gives the same trajectory, so which one is measured is moot.
    """
    try:
        case, integ = build(spec)
        opts = integ.options()
        row = _row(spec, t_end=case.t_end, options=json.dumps(opts, default=str),
                   params=json.dumps(case.params, default=str),
                   h=opts.get("h"), rtol=opts.get("rtol"), atol=opts.get("atol"))
        grid = Grid(case.t0, case.t_end, **(grid_options or {}))
        start = time.perf_counter()
        solve = integ.prepare(case, grid)
        row["setup_s"] = time.perf_counter() - start
        times: list[float] = []
        while True:
            start = time.perf_counter()
            traj = solve()
            times.append(time.perf_counter() - start)
            if len(times) >= repeats or sum(times) >= repeat_budget:
                break
    except Exception as exc:  # a defect or bad input: recorded, never fatal to the suite
        detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return Record(_row(spec, status=ERROR, message=detail))
    row.update(wall_s=statistics.median(times), repeats=len(times))
    row.update(trajectory_columns(case, traj))
    return Record(row, traj.windows, traj.samples)


def trajectory_columns(case, traj: Trajectory) -> dict:
    """The columns that come from the trajectory and the metrics."""
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
        callback_s=traj.extra.get("callback_s"),
    )
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in cols.items()}
