"""One run, in one place: build the case and the integrator, time set-up and solve, measure.

:func:`execute` takes a :class:`~benchmarks.plan.PlannedRun` (everything known before the
run, its ``run_key`` included, fixed by the planner) and returns a complete
:class:`~benchmarks.records.Record`: the planned :class:`~benchmarks.records.Run` part,
how the run ended, its timing, its work counters, its metrics (:mod:`benchmarks.metrics`)
with the drift classes of ``|g|`` and ``|H - H0|`` (:mod:`benchmarks.drift`), the linear
solver and the sampling. A run that fails numerically is ``failed`` with the method's
message, a run that raises is ``error`` with the exception (and the ``file:line`` in user
code where it arose), and neither raises here.

An ensemble (:mod:`problems.ensemble`) may run in chunks of its lanes, each a task of its
own on any worker (:func:`benchmarks.plan.lane_ranges`): a planned run whose ``lanes``
names a range executes those lanes and returns their :class:`Part`, and :func:`merge`
makes the one ensemble record of the parts, wherever they ran, with no case at hand. An
ensemble run whole is the merge of its one part, so a chunked ensemble's record equals the
unchunked one's in everything but its timing.
"""

from __future__ import annotations

import functools
import json
import math
import statistics
import time
from dataclasses import dataclass, replace
from typing import Callable

import jax
import numpy as np

import integrators
import problems
from benchmarks import compilation
from benchmarks.columns import computed, of_part
from benchmarks.audit import explain
from benchmarks.drift import ENERGY_REL_FLOOR, POS_FLOOR, classify
from benchmarks.metrics import summarize, unscored
from benchmarks.plan import PlannedRun, jax_device, plan
from benchmarks.records import (QUANTILES, Ending, Metrics, Record, RunSpec, Spread, Status,
                                Timing, Work, provenance)
from integrators.base import COUNTERS, Grid, Trajectory
from problems import ensemble
from problems.source import located
from problems.spec import ProblemSpec


def _case(problem: ProblemSpec):
    # problems.make keeps the case: the runs of a worker share it, and with it the compiled
    # functions keyed on its Mechanics (a step-size or tolerance sweep compiles once).
    with compilation.kept_for(problem):
        return problems.make(problem)


@functools.lru_cache(maxsize=4)
def _lanes(problem: ProblemSpec, lanes: int, seed: int, first: int):
    # The initial states of an ensemble depend on the case alone: every method and step of
    # a worker's sweep starts from the same ones.
    return ensemble.draw(_case(problem), lanes, seed, first)


def forget_cases() -> None:
    """Drop the cases this process keeps (a problem's definition was replaced)."""
    problems.forget()
    _lanes.cache_clear()
    ensemble.forget()


#: Autorange timing (in the manner of :func:`timeit.Timer.autorange`): a run's solve is
#: repeated until it has been timed at least ``repeats`` times and for at least
#: :data:`MIN_TOTAL_S` in all, within a cap of :data:`MAX_SOLVES` solves and
#: :data:`MAX_EXTRA_S` seconds of solving after the first. Most solves take milliseconds,
#: so they get a measured spread at little cost; a long solve is not repeated beyond the cap.
MIN_TOTAL_S = 0.2
MAX_SOLVES = 10
MAX_EXTRA_S = 2.0


def more(times: list[float], repeats: int) -> bool:
    """Whether autorange timing solves once more after the solves timed so far (``times``):
    the minimum (``repeats`` solves, :data:`MIN_TOTAL_S` in all) is not reached, the cap is
    not, and the next solve (expected to last as long as the slowest so far) fits within
    :data:`MAX_EXTRA_S`."""
    extra = sum(times) - times[0]
    return ((len(times) < repeats or sum(times) < MIN_TOTAL_S)
            and len(times) < max(MAX_SOLVES, repeats)
            and extra + max(times) <= MAX_EXTRA_S)


def execute(run: PlannedRun | RunSpec, repeats: int = 3, deadline: float | None = None,
            on_phase: Callable[[str], None] | None = None) -> Record | Part:
    """Run ``run``: set-up once, solve and time by autorange, measure the last solve.

    An ensemble runs on the device its ``device`` option selects
    (:func:`benchmarks.plan.jax_device`), every other run on the CPU. A planned chunk of
    an ensemble (``run.lanes`` set) returns the :class:`Part` of its lanes, or an ``error``
    record where it could not run them.

    Parameters
    ----------
    run : PlannedRun or RunSpec
        The planned run (as the batch's workers receive it); a :class:`RunSpec` is
        planned here first (:func:`benchmarks.plan.plan`, with this code's version), for
        a single run from a test or a notebook.
    repeats : int
        Timed solves at least, within autorange's cap (:func:`more`): ``wall_s`` is their
        median, ``wall_min_s`` and ``wall_max_s`` their spread, ``repeats`` their count.
    deadline : float, optional
        A ``time.monotonic`` time (the run's time limit): a repeat is not started when it
        would likely end after it. Every repeat of a deterministic method gives the same
        trajectory, so which one is measured is moot.
    on_phase : callable, optional
        Told what the run is doing (for the message of a run killed at its time limit).
    """
    if isinstance(run, RunSpec):
        run = plan([run], provenance()["code_version"])[0]
    phase = on_phase or (lambda text: None)
    timing = Timing()
    try:
        phase("building the case")
        case = _case(run.problem)
        if run.horizon is not None:
            case = case.with_t_end(run.horizon)
        integ = integrators.make(run.integrator)
        grid = Grid(case.t0, case.t_end, **dict(run.grid))
        lanes, first = None, 0
        device = jax_device("cpu")
        if run.run.lanes is not None:
            first, stop = run.lanes or (0, run.run.lanes)
            device = jax_device(run.device)
            if device is None:
                raise RuntimeError(f"device {run.device}: JAX sees no GPU on this machine")
            phase("drawing the ensemble's initial states")
            lanes = _lanes(run.problem, stop, run.run.seed, first)
        phase("set-up")
        start = time.perf_counter()
        # Not the run key: it holds the code version, which every edit of any tracked file
        # changes; the identity hashes the code that compiles instead.
        kept = compilation.kept_for(run.problem, run.integrator, run.run.t_end, run.grid,
                                    run.run.lanes, run.run.seed, run.lanes, run.run.options,
                                    platform=device.platform)
        with compilation.Watch() as compiled, jax.default_device(device), kept:
            solve = (integ.prepare(case, grid) if lanes is None else
                     integ.prepare_ensemble(case, grid, *lanes))
        timing = Timing(setup_s=time.perf_counter() - start, setup_cache=compiled.source)
        times: list[float] = []
        while True:
            phase(f"solve (repeat {len(times) + 1}; set-up took {timing.setup_s:.3g} s)")
            late = getattr(solve, "late_setup_s", 0.0)
            start = time.perf_counter()
            with jax.default_device(device):
                traj = solve()
            # A program compiled on first need inside the solve (a time loop's Newton
            # fallback: integrators.loop.march) is set-up, not solving.
            late = getattr(solve, "late_setup_s", 0.0) - late
            times.append(time.perf_counter() - start - late)
            timing = replace(timing, setup_s=timing.setup_s + late)
            if not more(times, repeats):
                break
            # A margin of twice the last solve: repeats vary, and a timing repeat must not
            # turn a finished run into a timeout.
            if deadline is not None and time.monotonic() + 2.0 * times[-1] > deadline:
                break
        phase("measuring")
        extra = (traj if lanes is None else traj[0]).extra
        timing = replace(timing, wall_s=statistics.median(times), repeats=len(times),
                         wall_min_s=min(times), wall_max_s=max(times),
                         callback_s=_given(extra.get("callback_s")))
        if lanes is not None:
            part = measure_part(run, case, traj, timing, first, device.platform)
            return part if run.lanes is not None else merge(run, [part])
        record = measure(run, case, traj, timing)
        return replace(record, work=replace(record.work, device=device.platform))
    except Exception as exc:  # a defect in the method or the user's functions
        return Record(run.run, Ending(Status.ERROR, _where_defined(explain(exc), exc, run)),
                      timing)


def _where_defined(message: str, exc: Exception, run: PlannedRun) -> str:
    """``message``, led by where the run's problem was defined where it is the user's and
    the error arose in none of the user's frames (a transformation JAX replays from a
    traced program, such as ``vmap`` of a callback)."""
    name = run.problem.name
    # A case of the Python API is registered by a factory of ours: no file of the user's.
    if problems.user_frame(exc) or problems.ORIGINS.get(name) in (None, "built-in",
                                                                  "Python API"):
        return message
    return located(f"in problem {name!r}: {message}", problems.REGISTRY.get(name))


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
    return growth_of(traj.windows, case.t0,
                     case.energy_scale if case.mech.has_energy else None)


def growth_of(w: dict[str, np.ndarray], t0: float, energy_scale: float | None
              ) -> dict[str, str | None]:
    """:func:`growth` from the windows ``w`` of a run that starts at ``t0``; no energy class
    where ``energy_scale`` is ``None`` (no conserved energy)."""
    t = w.get("t")
    if t is None or len(t) == 0:
        return {"pos_growth": None, "energy_growth": None}
    pos = classify(t, w["pos"], t0=t0, floor=POS_FLOOR) if "pos" in w else None
    energy = None
    if energy_scale is not None and "energy" in w:
        energy = classify(t, w["energy"], t0=t0, floor=ENERGY_REL_FLOOR * energy_scale)
    return {"pos_growth": pos.label() if pos is not None else None,
            "energy_growth": energy.label() if energy is not None else None}


def _given(value):
    """``value`` as a plain Python value, ``None`` where it is missing (None or NaN)."""
    if isinstance(value, np.generic):
        value = value.item()
    return None if isinstance(value, float) and math.isnan(value) else value


def measure(run: PlannedRun, case, traj: Trajectory, timing: Timing) -> Record:
    """The record of a run from its trajectory: metrics, work, final state, drift classes.

    A trajectory that claims success but holds a value that is not finite is ``failed``.
    """
    metrics = {k: _given(v) for k, v in summarize(case, traj).items()}
    inv = {k[len("max_inv:"):]: v for k, v in metrics.items() if k.startswith("max_inv:")}
    # A finished run that cannot be scored says why, never leaving a silent gap.
    note = unscored(case, traj)
    message = "; ".join(filter(None, [traj.message, note])) if note else traj.message
    ending = Ending(status=traj.status, message=message, t_final=_given(traj.t_final),
                    q_final=json.dumps([float(x) for x in traj.q_final]),
                    v_final=json.dumps([float(x) for x in traj.v_final]),
                    fail_step=_given(traj.fail_step), fail_time=_given(traj.fail_time),
                    sampling=traj.sampling)
    if traj.status == Status.OK and (bad := _non_finite(traj)) is not None:
        what, when = bad
        ending = replace(ending, status=Status.FAILED, fail_time=when,
                         message=f"the method reported success but {what}")
    work = Work(**{c: _given(traj.counts.get(c, 0)) for c in COUNTERS},
                linear_solver=traj.linear_solver, pattern_nnz=_given(traj.pattern_nnz))
    measured = {name: metrics.get(name) for name in of_part("metrics")}
    measured.update(invariant_errors=json.dumps(inv) if inv else "", **growth(case, traj))
    return Record(run.run, ending, timing, work, Metrics(**measured),
                  windows=traj.windows, samples=traj.samples)


#: The per-lane metrics of an ensemble, by :func:`benchmarks.metrics.summarize` name, and
#: their names in the :class:`~benchmarks.records.Spread` columns.
LANE_METRICS = {"max_pos_residual": "pos", "max_vel_residual": "vel",
                "rel_energy_error": "energy", "final_state_error": "final"}


@dataclass
class Part:
    """What a chunk of an ensemble's lanes gives for the ensemble's record: no case is
    needed to merge parts (:func:`merge`), wherever they ran.

    ``first`` is the index of its first lane; ``table`` its rows of the per-lane table
    (:attr:`Record.lanes`); ``energy`` and ``inv`` each lane's ``max_energy_error`` and
    declared invariants' errors; ``stacks`` each windowed series, one row per lane (NaN
    past a lane's last window), and ``t`` the window ends of its longest lane; ``failure``
    its first failed lane (index and trajectory) or ``None``; ``nominal`` the record of
    lane 0 (in the part that holds it, else ``None``); ``has_energy`` whether the case
    conserves energy; ``timing`` the chunk's and ``device`` the platform it ran on;
    ``notes`` why some of its lanes have no reference (one per block of them).
    """

    first: int
    table: dict[str, np.ndarray]
    energy: np.ndarray
    inv: dict[str, np.ndarray]
    stacks: dict[str, np.ndarray]
    t: np.ndarray
    failure: tuple[int, Trajectory] | None
    nominal: Record | None
    has_energy: bool
    timing: Timing
    device: str
    notes: tuple[str, ...] = ()


def measure_part(run: PlannedRun, case, trajs: list[Trajectory], timing: Timing, first: int,
                 device: str) -> Part:
    """The :class:`Part` of the lanes ``first, first + 1, ...`` whose trajectories are
    ``trajs``.

    Lane 0 starts from the case's own initial values and is measured against the case's
    reference; the others against their own where the case has one at ``t_end``
    (:func:`problems.ensemble.references`, computed on the CPU whatever device ran the
    lanes, and only when one of them finished; where a block of them could not be made,
    ``notes`` say why).
    """
    ok = np.array([traj.status == Status.OK for traj in trajs])
    refs, notes = [None] * len(trajs), ()
    if ok[max(0, 1 - first):].any():
        with jax.default_device(jax.devices("cpu")[0]):
            refs, notes = ensemble.references(case, run.run.seed, first, first + len(trajs),
                                             run.run.t_end)
    rows = [summarize(case if first + i == 0 else replace(case, reference=ref), traj)
            for i, (traj, ref) in enumerate(zip(trajs, refs))]
    table = {"seed": np.arange(first, first + len(trajs), dtype=float),
             "status": (~ok).astype(float)}
    for name in ("max_pos_residual", "max_vel_residual", "rel_energy_error",
                 "final_state_error", "scd", "reference_floor"):
        table[name] = np.array([row[name] for row in rows], dtype=float)
    table["t_final"] = np.array([traj.t_final for traj in trajs], dtype=float)
    for key in ("fail_step", "fail_time"):
        table[key] = np.array([np.nan if getattr(traj, key) is None else getattr(traj, key)
                               for traj in trajs], dtype=float)
    for key in COUNTERS:
        table[key] = np.array([traj.counts.get(key, 0) for traj in trajs], dtype=float)
    inv = {name[len("max_inv:"):]: np.array([row[name] for row in rows], dtype=float)
           for name in rows[0] if name.startswith("max_inv:")}
    longest = max(trajs, key=lambda traj: len(traj.windows["t"]))
    stacks = {}
    for name in (k for k in longest.windows if k != "t"):
        stack = np.full((len(trajs), len(longest.windows["t"])), np.nan)
        for i, traj in enumerate(trajs):
            series = np.asarray(traj.windows[name], dtype=float)
            stack[i, :len(series)] = series
        stacks[name] = stack
    failed = np.flatnonzero(~ok)
    return Part(first, table, np.array([row["max_energy_error"] for row in rows], dtype=float),
                inv, stacks, np.asarray(longest.windows["t"], dtype=float),
                (first + int(failed[0]), trajs[failed[0]]) if len(failed) else None,
                measure(run, case, trajs[0], timing) if first == 0 else None,
                bool(case.mech.has_energy), timing, device, notes)


def merge(run: PlannedRun, parts: list[Part]) -> Record:
    """The record of an ensemble from the :class:`Part` of each chunk of its lanes.

    Per lane (:attr:`Record.lanes`): its seed index, its :class:`~integrators.base.Status`
    as 0 (ok) or 1, the metrics of :func:`benchmarks.metrics.summarize`, the time it
    reached, the step and time of its failure (NaN where it finished) and its work
    counters, in lane order. The record's metrics are the worst lane's (the maxima over the
    lanes that finished; the least scd and the largest reference floor), its work the sum
    over lanes (the work the timed solves did), its drift series the per-window maxima over
    the lanes (with their medians beside them as ``median:NAME``), its final state and
    samples lane 0's, and its :class:`~benchmarks.records.Spread` the quantiles over the
    lanes that finished. Final errors are summed up only where every lane that finished
    has one: where a block of references could not be made, none (its lanes alone would
    make a partial distribution), and the message says why. The ensemble is ``ok`` when
    every lane is; otherwise ``failed``, its message counting the failed lanes and quoting
    the first. Its timing is the sum over the parts (what one
    core running the chunks one after another would take; per part the median of its
    timed solves for ``wall_s``); ``device`` names the platforms they ran on.
    """
    parts = sorted(parts, key=lambda part: part.first)
    table = {name: np.concatenate([part.table[name] for part in parts])
             for name in parts[0].table}
    ok = table["status"] == 0
    nominal = parts[0].nominal
    windows = _envelope(parts)
    # Which lanes each summary is over: final errors only where every lane that finished
    # has one.
    over = {name: ok for name in LANE_METRICS}
    partial = bool(np.isnan(table["final_state_error"][ok]).any())
    if partial:
        over["final_state_error"] = np.zeros_like(ok)
    worst = {name: _worst(np.max, table[name][over[name]]) for name in LANE_METRICS}
    scored = over["final_state_error"]
    worst.update(scd=_worst(np.min, table["scd"][scored]),
                 reference_floor=_worst(np.max, table["reference_floor"][scored]))
    inv = {name: _worst(np.max, np.concatenate([part.inv[name] for part in parts])[ok])
           for name in parts[0].inv}
    energy = np.concatenate([part.energy for part in parts])
    max_energy = _worst(np.max, energy[ok]) if parts[0].has_energy else None
    # A metric declared with its own compute has no rule that combines lanes: none,
    # rather than lane 0's value posing as the ensemble's.
    metrics = nominal.metrics.replace(
        **worst, max_energy_error=max_energy, invariant_errors=json.dumps(inv) if inv else "",
        **growth_of(windows, run.run.t0, run.run.energy_scale if parts[0].has_energy else None),
        **{c.name: None for c in computed()})
    spread = {"failed_fraction": float(np.mean(~ok))}
    for name, short in LANE_METRICS.items():
        values = table[name][over[name]]
        for q in QUANTILES:
            spread[f"{short}_q{q}"] = (_given(np.nanpercentile(values, q))
                                       if len(values) and not np.isnan(values).all() else None)
    ending = nominal.ending
    failures = [part.failure for part in parts if part.failure is not None]
    if failures:
        lane, first = failures[0]
        ending = replace(ending, status=Status.FAILED, fail_step=_given(first.fail_step),
                         fail_time=_given(first.fail_time),
                         message=f"{int((~ok).sum())} of {len(ok)} lanes failed; the first, "
                                 f"lane {lane}: {first.message}")
    # A block of references that could not be made matters only where a lane that
    # finished needed it.
    notes = list(dict.fromkeys(note for part in parts for note in part.notes))
    if notes and partial:
        missing = "no final errors: no reference for " + "; for ".join(notes)
        ending = replace(ending, message="; ".join(filter(None, [ending.message, missing])))
    work = replace(nominal.work, device="+".join(sorted({part.device for part in parts})),
                   **{key: int(table[key].sum()) for key in COUNTERS})
    return Record(run.run, ending, _timing(parts), work, metrics, Spread(**spread),
                  windows=windows, samples=nominal.samples, lanes=table)


def _worst(reduce, values: np.ndarray):
    """``reduce`` over the values that are not NaN, ``None`` where there are none."""
    values = values[~np.isnan(values)]
    return _given(reduce(values)) if len(values) else None


def _timing(parts: list[Part]) -> Timing:
    """The timing of an ensemble run in ``parts``: sums over the parts, the fewest timed
    solves of a part, and the set-up's cache source where the parts agree (else
    ``partial``)."""
    timings = [part.timing for part in parts]

    def total(name):
        values = [getattr(t, name) for t in timings if getattr(t, name) is not None]
        return sum(values) if values else None

    sources = {t.setup_cache for t in timings}
    return Timing(wall_s=total("wall_s"), setup_s=total("setup_s"),
                  setup_cache=sources.pop() if len(sources) == 1 else "partial",
                  repeats=min(t.repeats for t in timings), wall_min_s=total("wall_min_s"),
                  wall_max_s=total("wall_max_s"), callback_s=total("callback_s"))


def _envelope(parts: list[Part]) -> dict[str, np.ndarray]:
    """Per-window maxima over the lanes (and medians, ``median:NAME``) of the windowed
    series; a window is kept where some lane reached it, its end time the longest lane's."""
    t = max((part.t for part in parts), key=len)
    out = {"t": t}
    for name in parts[0].stacks:
        stack = np.full((sum(len(part.table["seed"]) for part in parts), len(t)), np.nan)
        row = 0
        for part in parts:
            rows, width = part.stacks[name].shape
            stack[row:row + rows, :width] = part.stacks[name]
            row += rows
        out[name] = np.nanmax(stack, axis=0)
        out[f"median:{name}"] = np.nanmedian(stack, axis=0)
    return out
