"""The planner: runs as asked for become planned runs, with everything known before running.

A run travels one way (docs/design.md, section 2): spec strings are resolved where they enter
(:func:`expand`, called by the command line, the suite files and the Python API), and
:func:`plan` turns the resolved runs into :class:`PlannedRun` values that carry all that is
fixed before a run starts: the problem's parameters, every integrator option, the horizon,
the recording grid, the time limit, and the record's :class:`~benchmarks.records.Run`
part (what the case and the method declare, and the ``run_key``). A worker executes a
planned run as it is (:func:`benchmarks.execute.execute`) and recomputes none of it. A
horizon (``--t-end``, a suite's ``t_end``, the Python API's ``t_end``) is a parameter of
every problem whose factory takes ``t_end`` (:func:`problems.at_horizon`): its case and
reference are built for the horizon that runs, and ``name --t-end T`` is the same run as
``name:t_end=T``.

Planning is where bad input is refused, before anything runs: each problem's size is
checked before its case is built (:func:`problems.check_size`), each case is built once per
problem spec and horizon (building checks the initial values; user problems are audited,
:mod:`benchmarks.audit`), each integrator once per spec and setting (its options checked),
and a fixed-step run of more than :data:`STEP_LIMIT` steps is refused; ``allow_large``
lifts both limits. :func:`pending` applies ``--resume`` and runs every run once.

This module imports no engine (pool, Dask): reading a suite needs only the registries.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
from dataclasses import dataclass
from typing import Iterable

import jax

import integrators
import problems
from benchmarks import compilation
from benchmarks.audit import AuditError, audit, explain
from benchmarks.records import InputError, Run, RunSpec, identity, one_line, run_key
from problems.ensemble import MAX_LANES, MAX_SEED
from problems.source import ArgumentError
from problems.spec import IntegratorSpec, ProblemSpec, SpecError

#: Time limit of a run (seconds) when neither the run, its suite nor the command sets one.
DEFAULT_TIMEOUT = 3600.0
#: Most steps of a fixed-step run planned without ``allow_large``: a thousand times the
#: longest run of the shipped suites; ``--h 1e-9 --t-end 1`` (10^9 steps) would otherwise
#: run silently for up to an hour.
STEP_LIMIT = 10**8
#: Runs of at least this many steps, or of steps times coordinates, get their estimated
#: size printed before the batch starts.
LONG_STEPS, LONG_WORK = 10**6, 10**8


@dataclass(frozen=True)
class PlannedRun:
    """A run ready to execute: everything known before it starts.

    ``problem`` holds every parameter (a factory's ``t_end`` set to the horizon asked for,
    :func:`problems.at_horizon`), ``integrator`` every option of the method that runs;
    ``horizon`` is the ``t_end`` asked for (``None``: the problem's own; the resolved one
    is ``run.t_end``); ``grid`` the :class:`~integrators.base.Grid` options;
    ``timeout`` the time limit in seconds (``None``: no limit); ``run`` the record's
    :class:`~benchmarks.records.Run` part, ``run_key`` included; ``origin`` where the run
    was asked for. For an ensemble, ``device`` is where its loop runs (``cpu`` or ``gpu``,
    :func:`resolve_device`),
    ``chunks`` the lane ranges it runs in (:func:`lane_ranges`), and ``lanes`` the one
    range a task executes (``None``: every lane).
    """

    problem: ProblemSpec
    integrator: IntegratorSpec
    horizon: float | None
    grid: tuple[tuple[str, object], ...]
    timeout: float | None
    run: Run
    origin: str = ""
    device: str = "auto"
    chunks: tuple[tuple[int, int], ...] = ()
    lanes: tuple[int, int] | None = None

    @property
    def label(self) -> str:
        """The run's :func:`~benchmarks.records.identity` (settings and horizon resolved)."""
        return identity(self.run)


def expand(problem_specs, integrator_specs, hs=(), rtols=(), atols=(), t_end=None,
           timeout=None, origin="", lanes=None, seed=None, device=None,
           lanes_per_chunk=None) -> list[RunSpec]:
    """Every combination: ``hs`` go to fixed-step methods, ``rtols x atols`` to adaptive ones.

    Each spec string is resolved here, once (:func:`problems.resolve`,
    :func:`integrators.resolve`); an empty list leaves the method's own default for that
    setting. ``lanes`` (and ``seed``, default 0) make every run an ensemble, run on
    ``device`` (:data:`DEVICES`, default ``auto``) in chunks of ``lanes_per_chunk``
    (:func:`lane_ranges`).

    Raises
    ------
    SpecError
        An unknown name, parameter or option, or a value of the wrong type; a method whose
        spec sets a setting that is also swept (``rattle:h=0.02`` with ``hs``); ``seed``,
        ``device`` or ``lanes_per_chunk`` without ``lanes``.
    """
    if lanes is None:
        given = [name for name, value in (("seed", seed), ("device", device),
                                          ("lanes_per_chunk", lanes_per_chunk))
                 if value is not None]
        if given:
            raise SpecError(f"{given[0]} applies to ensembles only: give the number of lanes "
                            f"too")
    resolved = [problems.resolve(p, origin) for p in problem_specs]
    methods = [integrators.resolve(i, origin) for i in integrator_specs]
    ensemble = ((None, None) if lanes is None else (int(lanes), int(seed or 0))) + (
        device, lanes_per_chunk)
    runs = []
    for i in methods:
        # A setting in the method's spec and a sweep of it: which one runs would be hidden
        # behind a label that names the other.
        for name, sweep in (("h", hs), ("rtol", rtols), ("atol", atols)):
            if sweep and name in i.kwargs:
                raise SpecError(f"integrator {str(i)!r} sets {name} = {i.kwargs[name]!r}, and "
                                f"{name} is also swept ({', '.join(map(str, sweep))}): give "
                                f"it in one place")
    for p, i in itertools.product(resolved, methods):
        if integrators.cls_of(i.name).adaptive:
            for rtol, atol in itertools.product(rtols or [None], atols or [None]):
                runs.append(RunSpec(p, i, None, rtol, atol, t_end, timeout, origin,
                                    *ensemble))
        else:
            runs.extend(RunSpec(p, i, h, None, None, t_end, timeout, origin, *ensemble)
                        for h in (hs or [None]))
    return runs


#: Where an ensemble's compiled loop runs: ``auto`` (a GPU when JAX sees one and the
#: ensemble has at least :data:`GPU_MIN_LANES` lanes, else the CPU), ``cpu`` or ``gpu``
#: (float64 either way). Single runs run on the CPU.
DEVICES = ("auto", "cpu", "gpu")

#: Fewest lanes for which ``auto`` runs an ensemble on a GPU. A GPU step costs about the
#: same for a thousand lanes as for one, and many small ensembles queue for one GPU, so
#: small ensembles are faster on a CPU core; from about a thousand lanes the GPU is ahead
#: for every method (``python -m benchmarks.perf.ensemble --device gpu`` measures it).
GPU_MIN_LANES = 1024

#: Most lanes per chunk of an ensemble (:func:`lane_ranges`) unless a run sets its own. On
#: one core lane-steps per second are highest for a few hundred lanes per vmapped loop
#: (beyond, the loop is memory-bound), so larger ensembles run as several such chunks,
#: side by side on the workers. XLA:CPU compiles the vmapped loop by batch width, and a
#: lane's round-off can depend on it from about a thousand lanes on; at most 512 lanes per
#: chunk keeps every lane's result the same bit for bit whatever the chunking
#: (``tests/test_ensemble.py``).
LANES_PER_CHUNK = 512


def lane_ranges(lanes: int, per_chunk: int) -> tuple[tuple[int, int], ...]:
    """The chunks of an ensemble of ``lanes`` lanes, as ``(first, stop)`` ranges of nearly
    equal size: ``ceil(lanes / per_chunk)`` of them, so each holds at most ``per_chunk``
    lanes, but never a lane alone (at most ``lanes // 2`` chunks: a batch of one is
    compiled otherwise than a larger batch, and lobatto3ab3's lane differed at round-off).

    Lane ``i`` is drawn alike in any chunk (:mod:`problems.ensemble`) and integrated by
    the same arithmetic, which XLA compiled alike for every width measured up to
    :data:`LANES_PER_CHUNK`, so such chunkings changed no result, only which workers share
    the work; wider chunks can change a lane's round-off.
    """
    count = max(1, min(-(-lanes // per_chunk), lanes // 2))
    bounds = [k * lanes // count for k in range(count + 1)]
    return tuple(zip(bounds[:-1], bounds[1:]))


def jax_device(name: str) -> jax.Device | None:
    """The JAX device that ``name`` (one of :data:`DEVICES`) selects in this process:
    the first GPU, or the CPU; ``None`` where ``gpu`` is asked for and JAX sees none."""
    try:
        gpus = jax.devices("gpu")
    except RuntimeError:  # no GPU platform in this JAX
        gpus = []
    if name == "cpu" or not gpus:
        return None if name == "gpu" else jax.devices("cpu")[0]
    return gpus[0]


def resolve_device(device: str, lanes: int) -> str:
    """``cpu`` or ``gpu``: where an ensemble of ``lanes`` lanes asked to run on ``device``
    (:data:`DEVICES`) runs in this process's view (``auto``: :data:`GPU_MIN_LANES`)."""
    if device != "auto":
        return device
    return "gpu" if lanes >= GPU_MIN_LANES and jax_device("gpu") is not None else "cpu"


def check_device(device: str, where: str) -> None:
    """A device is one of :data:`DEVICES`, and ``gpu`` one that JAX sees here."""
    if device not in DEVICES:
        raise InputError(f"{where}: device = {device!r} must be one of {', '.join(DEVICES)}")
    if jax_device(device) is None:
        raise InputError(f"{where}: device = 'gpu', but JAX sees no GPU on this machine "
                         f"(platforms: {', '.join(sorted({d.platform for d in jax.devices()}))})"
                         f"; use device auto or cpu")


#: The recording grid of each lane of an ensemble: the loop keeps these per lane, so they are
#: what bounds its memory (a few kilobytes per lane); the windows are enough for the drift
#: classes, and the samples are the initial, middle and final states.
ENSEMBLE_GRID = {"n_windows": 64, "n_samples": 3}


def check_ensemble(lanes, seed, where: str, per_chunk=LANES_PER_CHUNK) -> None:
    """An ensemble has 1 to :data:`~problems.ensemble.MAX_LANES` lanes, a seed from 0 to
    :data:`~problems.ensemble.MAX_SEED` and at least 2 lanes per chunk (a chunk of one lane
    would compile otherwise than a batch)."""
    if isinstance(lanes, bool) or not isinstance(lanes, int) or not 1 <= lanes <= MAX_LANES:
        raise InputError(f"{where}: ensemble = {lanes!r} must be a whole number of lanes "
                         f"from 1 to {MAX_LANES}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise InputError(f"{where}: seed = {seed!r} must be a whole number from 0 to "
                         f"{MAX_SEED}")
    if isinstance(per_chunk, bool) or not isinstance(per_chunk, int) or per_chunk < 2:
        raise InputError(f"{where}: lanes_per_chunk = {per_chunk!r} must be a whole number "
                         f">= 2")


def check_timeout(value, where: str) -> None:
    """A time limit must be a positive number of seconds (``inf``: none)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise InputError(f"{where}: timeout = {value!r} must be a positive number of "
                         f"seconds (inf for no limit)")


def usable_cpus() -> list[int]:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


#: Most worker processes per usable core (``--jobs``, ``local:N``): each is a process that
#: imports JAX and compiles, a few hundred MiB; thousands of them would only exhaust memory.
WORKERS_PER_CORE = 4


def max_workers() -> int:
    """The most worker processes a batch may start on this machine."""
    return WORKERS_PER_CORE * len(usable_cpus())


def cluster_address(address: str) -> tuple[int | None, str | None]:
    """``(N, None)`` for ``local:N``, ``(None, address)`` for ``tcp://HOST:PORT``
    (:class:`benchmarks.cluster.Cluster`).

    Raises
    ------
    InputError
        Any other address.
    """
    local = re.fullmatch(r"local:(\d+)", address.strip())
    if local and not 1 <= int(local.group(1)) <= max_workers():
        raise InputError(f"cluster {address!r}: local:N takes 1 to {max_workers()} workers "
                         f"({WORKERS_PER_CORE} per usable core)")
    if local:
        return int(local.group(1)), None
    if re.fullmatch(r"tcp://[^\s:/]+:\d+", address.strip()):
        return None, address.strip()
    raise InputError(f"cluster {address!r}: must be local:N (N >= 1 workers on this machine) "
                     f"or tcp://HOST:PORT (a running Dask scheduler)")


def known(problem: ProblemSpec, integrator: IntegratorSpec, case, integ, asked: RunSpec,
          grid: dict, version: str, chunks: int | None = None) -> Run:
    """The record's :class:`~benchmarks.records.Run` part of a run of ``integ`` on
    ``case``, its ``run_key`` computed for code version ``version`` (an ensemble's chunks
    are not in it: they change no result)."""
    opts = integ.options()
    resolved = {"problem": problem.name, "arguments": problem.kwargs,
                "params": dict(case.params), "integrator": integrator.name, "options": opts,
                "t_end": case.t_end, "grid": grid}
    if asked.lanes is not None:
        resolved["ensemble"] = [asked.lanes, asked.seed]
        if (asked.device or "auto") != "auto":  # where the lanes run can change round-off
            resolved["device"] = asked.device
    return Run(problem=str(asked.problem), integrator=str(asked.integrator), h=opts.get("h"),
               rtol=opts.get("rtol"), atol=opts.get("atol"), t_end=case.t_end,
               options=json.dumps(opts, default=str),
               params=json.dumps(case.params, default=str), run_key=run_key(resolved, version),
               t0=case.t0, energy_scale=case.energy_scale, nominal_order=integ.nominal_order,
               sensitive=int(bool(case.system.sensitive)), family=integ.family,
               **({} if asked.lanes is None else
                  dict(lanes=asked.lanes, seed=asked.seed, batched=int(integ.batched),
                       chunks=chunks)))


def plan(specs: Iterable[RunSpec], version: str, grid_options: dict | None = None,
         timeout: float = DEFAULT_TIMEOUT, allow_large: bool = False,
         notes: list[str] | None = None, audit_user: bool = True) -> list[PlannedRun]:
    """Check every run and plan it, before any starts.

    Parameters
    ----------
    specs : iterable of RunSpec
        The runs as asked for (spec strings are resolved here where :func:`expand` has
        not done it).
    version : str
        The code version the run keys are computed with (with a digest of the user code).
    grid_options : dict, optional
        :class:`~integrators.base.Grid` options of every run.
    timeout : float
        The time limit of a run that sets none itself (``inf``: none).
    allow_large : bool
        Lift the size limit of problems and :data:`STEP_LIMIT`.
    notes : list of str, optional
        The estimated sizes of long runs, and the audit's notes, are appended to it.
    audit_user : bool
        Audit each user problem (:func:`benchmarks.audit.audit`); off only for cases whose
        system was audited before (the drift gate's round-off probes).

    Returns
    -------
    list of PlannedRun
        One per spec, in order.

    Raises
    ------
    InputError
        On the first bad run, with where it was asked for (suite file and line) and what
        is wrong, on one line.
    """
    grid = dict(grid_options or {})
    cases: dict[tuple, object] = {}
    audited: set[ProblemSpec] = set()
    out = []
    for spec in specs:
        where = f"{spec.origin}: " if spec.origin else ""
        try:
            if spec.timeout is not None:
                check_timeout(spec.timeout, spec.label())
            # The horizon reaches the factory where it takes one: the case, its recorded
            # parameters and its reference are then built for the horizon that runs.
            problem = problems.at_horizon(problems.resolve(spec.problem, spec.origin),
                                          spec.t_end)
            method = integrators.resolve(spec.integrator, spec.origin)
            if (problem, spec.t_end) not in cases:
                if not allow_large:
                    problems.check_size(problem)
                with compilation.kept_for(problem):
                    case = problems.make(problem)
                # The library's own problems are verified by its tests; user code is
                # checked here, once per problem spec, before it can spoil every run.
                if (audit_user and problem not in audited
                        and problems.origin(problem.name) != "built-in"):
                    audit(case, notes)
                    audited.add(problem)
                cases[problem, spec.t_end] = (case if spec.t_end is None else
                                              case.with_t_end(spec.t_end))
            case = cases[problem, spec.t_end]
            integ = integrators.make(method, h=spec.h, rtol=spec.rtol, atol=spec.atol)
            run_grid, chunks, device = grid, (), spec.device or "auto"
            if spec.lanes is not None:
                check_ensemble(spec.lanes, spec.seed, spec.label(),
                               spec.lanes_per_chunk or LANES_PER_CHUNK)
                check_device(device, spec.label())
                device = resolve_device(device, spec.lanes)
                # One GPU runs an ensemble best as one batch: no chunks unless asked for.
                per_chunk = spec.lanes_per_chunk or (MAX_LANES if device == "gpu"
                                                     else LANES_PER_CHUNK)
                run_grid = {**grid, **{k: min(v, grid.get(k, v))
                                       for k, v in ENSEMBLE_GRID.items()}}
                chunks = lane_ranges(spec.lanes, per_chunk)
            run = known(problem, method, case, integ, spec, run_grid, version,
                        len(chunks) or None)
            _check_steps(run, int(case.q0.size), spec.label(), allow_large, notes)
            limit = spec.timeout if spec.timeout is not None else timeout
            out.append(PlannedRun(problem, IntegratorSpec(method.name,
                                                          tuple(integ.options().items()),
                                                          method.text, method.origin),
                                  spec.t_end, tuple(run_grid.items()),
                                  None if math.isinf(limit) else float(limit), run,
                                  spec.origin, device, chunks))
        except (InputError, AuditError, SpecError, ArgumentError) as exc:
            raise InputError(one_line(f"{where}{exc}")) from None
        except Exception as exc:  # user code or a defect met while building: one line
            raise InputError(one_line(f"{where}{spec.label()}: {explain(exc)}")) from None
    return out


def _check_steps(run: Run, n: int, label: str, allow_large: bool,
                 notes: list[str] | None) -> None:
    """Refuse a fixed-step run of more than :data:`STEP_LIMIT` steps of ``n`` coordinates;
    note a long one (``label`` names the run as it was asked for)."""
    if run.h is None or run.t_end is None:
        return
    steps = (run.t_end - (run.t0 or 0.0)) / run.h
    size = f"about {steps:.3g} steps of {n} coordinates"
    if steps > STEP_LIMIT and not allow_large:
        raise InputError(f"{label}: {size} is above the limit of {STEP_LIMIT:.0e} steps; "
                         f"give a larger h, a shorter t_end, or {problems.ALLOW_LARGE} to "
                         f"run it anyway")
    if notes is not None and (steps >= LONG_STEPS or steps * n >= LONG_WORK):
        notes.append(f"note: {label}: a long run, {size}")


def firsts(runs: list[PlannedRun]) -> list[int]:
    """For each run, the index of the first run with its ``run_key`` (itself if none):
    runs that resolve to the same run execute once."""
    first: dict[str, int] = {}
    return [first.setdefault(r.run.run_key, i) for i, r in enumerate(runs)]


def pending(runs: list[PlannedRun], finished: set[str]) -> tuple[list[int], list[int]]:
    """Which runs execute and which ``--resume`` drops: the indices of the first run of
    each ``run_key`` that ``finished`` (the keys a store holds as finished) lacks, and of
    those it holds."""
    unique = [i for i, first in enumerate(firsts(runs)) if first == i]
    return ([i for i in unique if runs[i].run.run_key not in finished],
            [i for i in unique if runs[i].run.run_key in finished])
