"""Running benchmarks: one run (:func:`execute`) and a batch of runs (:func:`run_specs`).

One run builds the case and the integrator, times set-up and solve separately and measures
the trajectory. Every outcome is a :class:`Record`: a run that fails numerically is
``failed`` with the method's message, a run that raises is ``error`` with the exception,
and neither stops the suite.

A batch runs every run in a worker process (:mod:`benchmarks.worker`), ``jobs`` of them
side by side:

- **isolation**: a run past its time limit is killed and recorded as ``timeout``; a worker
  that dies (a crash in compiled code, an abort, the out-of-memory killer) is recorded as
  ``error`` with the signal or exit code; the batch goes on with a fresh worker;
- **honest wall times**: each worker runs with one intra-op thread, pinned to a core of its
  own when there are at least as many usable cores as jobs, so neighbouring runs never
  share a core; ``wall_s`` is the median of the timed repeats of the solve after
  set-up, and the repeats of a run all happen in its own worker. What this does not control
  (other processes on the machine, shared caches and memory bandwidth) is said in the
  session's ``timing_note`` (:func:`timing_note`), with the load average at the start;
- **reuse**: a worker keeps the cases it built (they are immutable), and with them what
  was compiled for their systems; the runs of one problem and method (a sweep over ``h``
  or ``rtol``) go to the same worker where they can, so a sweep compiles once (the fixed
  step loop takes ``h`` as an argument, :mod:`integrators.loop`). ``setup_s`` of a run
  that reused a compilation is the small remainder;
- **identical accuracy**: a run computes the same thing whatever ``jobs`` is, in a worker
  with the same thread settings pinned to one core, so accuracy columns do not depend on
  ``jobs``;
- **resume**: every run has a ``run_key`` (:func:`run_key`), a hash of what determines its
  results; with ``resume`` the runs whose key the store already holds as finished (any
  status but ``error`` and ``timeout``) are not run again. Each run is committed to the
  store on its own as it ends, by the parent alone, so a batch killed at any point (even
  by ``SIGKILL``) leaves a consistent store with every finished run in it;
- **validation first**: every case and integrator is built and checked before any run
  starts (:func:`validate`); bad input raises :class:`InputError` with one line that names
  what is wrong and where.

``runs.csv`` gets a row per run as it ends (in the order runs end, so a killed batch leaves
the runs it finished) and is rewritten at the end in the order of the specs. Of a resumed
batch it holds every run of the batch: the runs skipped because they were finished, read
back from the store as stored (their latest finished row), and the runs of this batch.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import itertools
import json
import math
import os
import statistics
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, TextIO

import numpy as np

import integrators
import problems
from benchmarks import worker
from benchmarks.metrics import summarize
from integrators.base import COUNTERS, ERROR, FAILED, OK, TIMEOUT, Grid, Trajectory

#: Columns of runs.csv, in order (design notes, section 6, plus the work counters and the
#: resume key).
COLUMNS = (
    "problem", "integrator", "h", "rtol", "atol", "t_end", "status", "message",
    "n_steps", "n_rejected", "n_f_evals", "n_jac_evals", "n_newton", "n_lin_solves",
    "wall_s", "setup_s", "max_pos_residual", "max_vel_residual", "max_energy_error",
    "rel_energy_error", "final_state_error", "scd", "t_final", "q_final", "v_final",
    "invariant_errors", "sampling", "fail_step", "fail_time", "callback_s", "repeats",
    "options", "params", "run_key", "linear_solver", "pattern_nnz",
)

#: The columns that depend on what was computed and not on how long it took: equal, bit for
#: bit, for the same run on the same machine whatever ``jobs`` is.
ACCURACY_COLUMNS = (
    "status", "message", "n_steps", "n_rejected", "n_f_evals", "n_jac_evals", "n_newton",
    "n_lin_solves", "max_pos_residual", "max_vel_residual", "max_energy_error",
    "rel_energy_error", "final_state_error", "scd", "t_final", "q_final", "v_final",
    "invariant_errors", "sampling", "fail_step", "fail_time",
)

#: Time limit of a run (seconds) when neither the run, its suite nor the command sets one.
DEFAULT_TIMEOUT = 3600.0
#: Environment variable that pins the code version in run keys (see :func:`code_version`).
CODE_VERSION_ENV = "DRIFTBENCH_CODE_VERSION"


class InputError(ValueError):
    """Bad input found before any run starts: the message names what and where, on one line."""


@dataclass(frozen=True)
class RunSpec:
    """One run: a problem spec, an integrator spec and the settings that vary in sweeps.

    ``timeout`` is the run's time limit in seconds (``None``: the batch default); ``origin``
    says where the run was asked for (a suite file and line), for error messages. Neither
    takes part in comparisons.
    """

    problem: str
    integrator: str
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    t_end: float | None = None
    timeout: float | None = field(default=None, compare=False)
    origin: str = field(default="", compare=False)

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


def expand(problem_specs, integrator_specs, hs=(), rtols=(), atols=(), t_end=None,
           timeout=None, origin="") -> list[RunSpec]:
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
                runs.append(RunSpec(p, i, None, rtol, atol, t_end, timeout, origin))
        else:
            runs.extend(RunSpec(p, i, h, None, None, t_end, timeout, origin)
                        for h in (hs or [None]))
    return runs


@functools.lru_cache(maxsize=8)
def _case(problem: str):
    # Cases are immutable: the runs of a worker share them, and with them the compiled
    # functions keyed on their Mechanics (a step-size or tolerance sweep compiles once).
    return problems.make(problem)


def build(spec: RunSpec):
    """The case and the integrator of a run spec (raises on bad input)."""
    case = _case(spec.problem)
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


def _settings(case, integ) -> dict:
    """The columns fixed by the case and the integrator before anything runs."""
    opts = integ.options()
    return dict(t_end=case.t_end, options=json.dumps(opts, default=str),
                params=json.dumps(case.params, default=str),
                h=opts.get("h"), rtol=opts.get("rtol"), atol=opts.get("atol"))


def execute(spec: RunSpec, repeats: int = 3, repeat_budget: float = 10.0,
            grid_options: dict | None = None, deadline: float | None = None,
            on_phase: Callable[[str], None] | None = None) -> Record:
    """Run ``spec``: set-up once, solve up to ``repeats`` times, measure the last solve.

    The solve is timed as the median of the repeats; repeats stop early once their total
    passes ``repeat_budget`` seconds, so long runs are solved once or twice, and a repeat is
    not started when it would likely end after ``deadline`` (a ``time.monotonic`` time: the
    run's time limit). Every repeat of a deterministic method gives the same trajectory, so
    which one is measured is moot. ``on_phase`` is told what the run is doing (for the
    message of a run killed at its time limit).

    A trajectory that claims success with a non-finite state or residual is ``failed``: a
    method must never return numbers that look like success.
    """
    phase = on_phase or (lambda text: None)
    try:
        phase("building the case")
        case, integ = build(spec)
        row = _row(spec, **_settings(case, integ))
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
        row.update(wall_s=statistics.median(times), repeats=len(times))
        row.update(trajectory_columns(case, traj))
    except Exception as exc:  # a defect or bad input: recorded, never fatal to the suite
        detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return Record(_row(spec, status=ERROR, message=detail))
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
        callback_s=traj.extra.get("callback_s"), linear_solver=traj.linear_solver,
        pattern_nnz=traj.pattern_nnz,
    )
    if traj.status == OK and (bad := _non_finite(traj)) is not None:
        what, when = bad
        cols.update(status=FAILED, fail_time=when,
                    message=f"the method reported success but {what}")
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in cols.items()}


# ---------------------------------------------------------------------------------------
# Run keys and validation
# ---------------------------------------------------------------------------------------

def code_version() -> str:
    """The version of the code that runs: the git commit, and a hash of the diff if dirty.

    :data:`CODE_VERSION_ENV` overrides it: to resume a sweep across an edit known not to
    change results, or to give a test a version that concurrent edits do not change.
    """
    pinned = os.environ.get(CODE_VERSION_ENV)
    if pinned:
        return pinned
    root = Path(__file__).resolve().parent.parent

    def git(*args) -> bytes:
        try:
            return subprocess.run(["git", *args], cwd=root, capture_output=True,
                                  timeout=30).stdout
        except (OSError, subprocess.SubprocessError):
            return b""

    commit = git("rev-parse", "HEAD").decode().strip() or "unknown"
    diff = git("diff", "HEAD", "--no-ext-diff", "--binary")
    return f"{commit}+{hashlib.sha256(diff).hexdigest()[:12]}" if diff else commit


def _plain(value):
    """A JSON-able form of a parameter or option value (exact for floats)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return repr(value)


def run_key(spec: RunSpec, case, integ, grid_options: dict | None, version: str) -> str:
    """A stable hash of everything that determines a run's results.

    The problem's name and fully resolved parameters (the factory's arguments with
    defaults, and the case's recorded parameters), the integrator's registry key and every
    option (``asdict``), ``t_end``, the recording grid and the code version
    (:func:`code_version`). Floats enter by their shortest round-trip text, so equal
    values give equal keys.
    """
    name, raw = problems.split_spec(spec.problem)
    arguments = problems.parameters(name)
    arguments.update({k: problems.parse_value(v, arguments[k], k) for k, v in raw.items()})
    payload = {
        "problem": name, "arguments": arguments, "params": dict(case.params),
        "integrator": problems.split_spec(spec.integrator)[0], "options": integ.options(),
        "t_end": case.t_end, "grid": grid_options or {}, "code": version,
    }
    text = json.dumps(payload, sort_keys=True, default=_plain, allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def one_line(text: str) -> str:
    """``text`` with its line breaks folded, for one-line error messages."""
    return " ".join(str(text).split())


def check_timeout(value, where: str) -> None:
    """A time limit must be a positive number of seconds (``inf``: none)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise InputError(f"{where}: timeout = {value!r} must be a positive number of "
                         f"seconds (inf for no limit)")


def validate(specs: Iterable[RunSpec], version: str,
             grid_options: dict | None = None) -> list[dict]:
    """Build and check every run before any starts; return each run's fixed columns.

    Each case is built once per problem spec and ``t_end`` (building checks the initial
    values: inconsistent ones raise with their residuals) and each integrator once per
    spec and setting. The returned dicts hold the columns known before the run (``t_end``,
    ``options``, ``params``, the settings) and its ``run_key``.

    Raises
    ------
    InputError
        On the first bad run, with where it was asked for (suite file and line) and what
        is wrong, on one line.
    """
    cases: dict[tuple, object] = {}
    integs: dict[tuple, object] = {}
    out = []
    for spec in specs:
        where = f"{spec.origin}: " if spec.origin else ""
        try:
            if spec.timeout is not None:
                check_timeout(spec.timeout, spec.label())
            ckey = (spec.problem, spec.t_end)
            if ckey not in cases:
                case = problems.make(spec.problem)
                cases[ckey] = case.with_t_end(spec.t_end) if spec.t_end is not None else case
            ikey = (spec.integrator, spec.h, spec.rtol, spec.atol)
            if ikey not in integs:
                integs[ikey] = integrators.make(spec.integrator, h=spec.h, rtol=spec.rtol,
                                                atol=spec.atol)
            case, integ = cases[ckey], integs[ikey]
            fixed = _settings(case, integ)
            fixed["run_key"] = run_key(spec, case, integ, grid_options, version)
        except ValueError as exc:
            raise InputError(one_line(f"{where}{exc}")) from None
        except Exception as exc:  # a defect met while building: still reported on one line
            raise InputError(one_line(f"{where}{spec.label()}: {type(exc).__name__}: {exc}")) \
                from None
        out.append(fixed)
    return out


# ---------------------------------------------------------------------------------------
# Timing note and progress
# ---------------------------------------------------------------------------------------

def timing_note(jobs: int, pinned: bool, cpus: list[int], repeats: int) -> str:
    """How this batch keeps its wall times honest, in a few sentences for the report."""
    load = f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "unknown"
    if jobs == 1:
        placement = f"1 worker process, pinned to core {cpus[0]} of {len(cpus)} usable"
    elif pinned:
        placement = (f"{jobs} worker processes, each pinned to a core of its own (cores "
                     f"{', '.join(map(str, cpus[:jobs]))} of {len(cpus)} usable), so no two "
                     f"runs share a core")
    else:
        placement = (f"{jobs} worker processes on {len(cpus)} usable cores: runs share "
                     f"cores, so wall times are inflated by their neighbours")
    return (f"Each run executes in a worker process with one intra-op thread (XLA, BLAS); "
            f"{placement}. wall_s is the median of up to {repeats} timed repeats of the "
            f"solve after set-up (setup_s, timed once, includes compilation; near zero for "
            f"a run that reused what an earlier run of the same problem and method "
            f"compiled in its worker). Not controlled: "
            f"other processes on the machine and shared caches and memory bandwidth; "
            f"1-minute load average at the start: {load}.")


class Progress:
    """A progress bar on a terminal (tqdm) and one log line per finished run.

    The bar shows the runs in progress and tqdm's estimate of the time left; without a
    terminal only the log lines are written.
    """

    def __init__(self, total: int, log: TextIO | None, bar: bool | None = None):
        self.total, self.log, self.count = total, log, 0
        self.running: dict[int, str] = {}
        if bar is None:
            bar = log is not None and hasattr(log, "isatty") and log.isatty()
        self.bar = None
        if bar and total:
            from tqdm import tqdm

            self.bar = tqdm(total=total, file=log, unit="run", dynamic_ncols=True,
                            leave=True, smoothing=0.1)

    def start(self, task_id: int, label: str) -> None:
        self.running[task_id] = label
        self._postfix()

    def _postfix(self) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(" | ".join(self.running.values())[:160], refresh=True)

    def finish(self, task_id: int, line: str) -> None:
        self.running.pop(task_id, None)
        self.count += 1
        text = f"[{self.count}/{self.total}] {line}"
        if self.bar is not None:
            self.bar.write(text, file=self.log)
            self.bar.update(1)
            self._postfix()
        elif self.log is not None:
            print(text, file=self.log, flush=True)

    def note(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text, file=self.log)
        elif self.log is not None:
            print(text, file=self.log, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _summary(row: dict) -> str:
    parts = [f"{row['status']}"]
    if row.get("max_pos_residual") is not None:
        parts.append(f"max|g| {row['max_pos_residual']:.3g}")
    if row.get("wall_s") is not None:
        parts.append(f"solve {row['wall_s']:.3g} s, set-up {row['setup_s']:.3g} s")
    if row.get("message"):
        parts.append(str(row["message"])[:300])
    return ", ".join(parts)


# ---------------------------------------------------------------------------------------
# Batches
# ---------------------------------------------------------------------------------------

def _outcome_record(spec: RunSpec, fixed: dict, task: worker.Task,
                    outcome: worker.Outcome) -> Record:
    """The record of a run from how its task ended."""
    if outcome.state == "done":
        return outcome.result
    if outcome.state == "timeout":
        message = (f"exceeded the time limit of {task.time_limit:g} s during "
                   f"{outcome.phase or 'start-up'} and was killed")
        return Record(_row(spec, **fixed, status=TIMEOUT, message=message))
    if outcome.state == "died":
        message = f"{outcome.message} during {outcome.phase or 'start-up'}"
        return Record(_row(spec, **fixed, status=ERROR, message=message))
    return Record(_row(spec, **fixed, status=ERROR, message=outcome.message))


#: Columns that hold whole numbers (pandas reads them as floats where some are empty).
_WHOLE = (*COUNTERS, "fail_step", "repeats")


def _stored_rows(store_path: Path, keys: set[str]) -> dict[str, dict]:
    """The latest finished stored row of each run key (for runs.csv of a resumed batch)."""
    from benchmarks.store import UNFINISHED, load_runs

    frame = load_runs(store_path)
    frame = frame[frame["run_key"].isin(keys) & ~frame["status"].isin(UNFINISHED)]
    rows = {}
    for record in frame.sort_values("run_id").to_dict(orient="records"):
        row = {}
        for c in COLUMNS:
            value = record.get(c)
            value = value.item() if isinstance(value, np.generic) else value
            if isinstance(value, float) and math.isnan(value):
                value = None
            elif c in _WHOLE and isinstance(value, float) and value.is_integer():
                value = int(value)
            row[c] = value
        rows[row["run_key"]] = row
    return rows


def _limit(seconds: float) -> float | None:
    """A time limit for the pool: ``None`` for no limit (``inf``)."""
    return None if math.isinf(seconds) else float(seconds)


def run_specs(specs: list[RunSpec], out: Path, jobs: int | None = None, *,
              suite: str = "ad-hoc", repeats: int = 3, timeout: float | None = None,
              resume: bool = False, studies: Iterable[str] = (),
              grid_options: dict | None = None, log: TextIO | None = sys.stderr,
              progress: bool | None = None) -> list[Record]:
    """Run ``specs`` in worker processes, store every run and write ``out/runs.csv``.

    Parameters
    ----------
    specs : list of RunSpec
        The runs, in the order ``runs.csv`` lists them.
    out : Path
        Output folder: ``runs.csv``, the store ``driftbench.sqlite``, study outputs.
    jobs : int, optional
        Runs side by side (default: the usable cores).
    suite : str
        Name recorded with the session.
    repeats : int
        Timed repeats of each solve (the median is reported).
    timeout : float, optional
        Time limit of a run that sets none itself (default :data:`DEFAULT_TIMEOUT`);
        also the time limit of each study.
    resume : bool
        Skip the runs whose ``run_key`` the store holds as finished.
    studies : iterable of str
        Names of studies (``benchmarks.suites.STUDIES``) run after the runs; their tables
        and figures go to the store (``add_table``/``add_figure``, section = the study's
        name), a study that fails is stored as an ``error`` table with its message.
    grid_options : dict, optional
        ``Grid`` options (windows, samples) for every run.
    log : text stream, optional
        Where the progress bar (on a terminal) and one line per run go.
    progress : bool, optional
        Force the progress bar on or off (default: on when ``log`` is a terminal).

    Returns
    -------
    list of Record
        One per spec, in order; runs skipped by ``resume`` carry their stored row only.

    Raises
    ------
    InputError
        Bad input, found before any run starts (nothing is written then).
    """
    from benchmarks.store import STORE_NAME, Store, StoreError
    from benchmarks.suites import study_target

    worker.load_plugins()
    cpus = worker.usable_cpus()
    jobs = len(cpus) if jobs is None else jobs
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"jobs = {jobs!r} must be a whole number of at least 1")
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise InputError(f"repeats = {repeats!r} must be a whole number of at least 1")
    timeout = DEFAULT_TIMEOUT if timeout is None else timeout
    check_timeout(timeout, "timeout")
    studies = list(studies)
    targets = {name: study_target(name) for name in studies}
    specs = list(specs)
    # The workers import and warm up while the runs are validated; no run starts before
    # validation has passed, and bad input stops them unused.
    pool = worker.Pool(jobs)
    pool.start()
    with pool:
        fixed = validate(specs, code_version(), grid_options)
        out = Path(out)
        try:
            out.mkdir(parents=True, exist_ok=True)
            store = Store(out / STORE_NAME)
        except (OSError, StoreError) as exc:
            raise InputError(one_line(f"cannot write results to {out}: {exc}")) from None
        with store:
            records = _run_batch(pool, store, specs, fixed, out, suite=suite, repeats=repeats,
                                 timeout=timeout, resume=resume, targets=targets,
                                 grid_options=grid_options, log=log, progress=progress,
                                 note=timing_note(jobs, pool.pinned, cpus, repeats))
    return records


def _run_batch(pool, store, specs, fixed, out, *, suite, repeats, timeout, resume, targets,
               grid_options, log, progress, note) -> list[Record]:
    """The body of :func:`run_specs` once the input is valid and the store is open."""
    records: list[Record | None] = [None] * len(specs)
    finished = store.finished_keys() if resume else set()
    skipped = [i for i, f in enumerate(fixed) if f["run_key"] in finished]
    if skipped:
        stored = _stored_rows(store.path, {fixed[i]["run_key"] for i in skipped})
        for i in skipped:
            records[i] = Record(stored[fixed[i]["run_key"]])
    # A run's affinity is its problem and method: a sweep over h or rtol stays on one
    # worker, which compiles the method once for it.
    tasks = [worker.Task(i, "run", (spec, repeats, _limit(spec.timeout or timeout), grid_options),
                         _limit(spec.timeout or timeout), spec.label(),
                         (spec.problem, spec.integrator))
             for i, spec in enumerate(specs) if records[i] is None]
    session = store.begin(suite, timing_note=note)
    bar = Progress(len(tasks) + len(targets), log, progress)
    if skipped:
        bar.note(f"resuming: {len(skipped)} of {len(specs)} runs are finished in "
                 f"{store.path} and are not run again")
    csv_path = out / "runs.csv"
    try:
        with open(csv_path, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
            writer.writeheader()

            def report(task: worker.Task, outcome: worker.Outcome) -> None:
                record = _outcome_record(specs[task.id], fixed[task.id], task, outcome)
                record.row["run_key"] = fixed[task.id]["run_key"]
                store.add(session, record)
                writer.writerow(record.row)
                fh.flush()
                records[task.id] = record
                bar.finish(task.id, f"{task.label}: {_summary(record.row)}")

            pool.run(tasks, report, on_start=lambda t: bar.start(t.id, t.label))
            if targets:
                _run_studies(pool, store, session, targets, out, _limit(timeout), bar)
    finally:
        bar.close()
    _write_csv(csv_path, [r.row for r in records if r is not None])
    return records


def _run_studies(pool: worker.Pool, store, session: int, targets: dict[str, str], out: Path,
                 timeout: float, bar: Progress) -> None:
    """Run each study in a worker; store its tables and figures, or its error."""
    import pandas as pd

    tasks = [worker.Task(-1 - k, "study", (name, target, str(out / "studies" / name)),
                         timeout, f"study {name}")
             for k, (name, target) in enumerate(targets.items())]

    def report(task: worker.Task, outcome: worker.Outcome) -> None:
        name = task.payload[0]
        result = outcome.result if outcome.state == "done" else None
        error = (result["error"] if result is not None else
                 f"exceeded the time limit of {task.time_limit:g} s during "
                 f"{outcome.phase} and was killed" if outcome.state == "timeout" else
                 f"{outcome.message} during {outcome.phase or 'start-up'}")
        if error is None:
            try:
                for table, frame in result["tables"].items():
                    store.add_table(session, name, table, frame)
                for figure, svg in result["figures"].items():
                    store.add_figure(session, name, figure, svg)
            except Exception as exc:  # a study's output the store refuses is its error
                error = f"storing its output failed: {type(exc).__name__}: {exc}"
        if error is not None:
            store.add_table(session, name, "error", pd.DataFrame({"message": [error]}))
        status = "ok" if error is None else f"error: {error}"
        bar.finish(task.id, f"{task.label}: {status}")

    pool.run(tasks, report, on_start=lambda t: bar.start(t.id, t.label))


def _write_csv(path: Path, rows: list[dict]) -> None:
    """Write ``rows`` to ``path`` atomically (a killed writer leaves the old file)."""
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(tmp, path)
