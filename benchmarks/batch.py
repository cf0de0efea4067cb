"""A batch of runs: plan, resume, hand to an engine, write runs.csv and the store.

:func:`run_specs` is the only writer of the results store. It hands every run to an engine
(:class:`~benchmarks.executors.Executor`): the local process pool
(:mod:`benchmarks.pool`, the default, ``jobs`` workers side by side) or a Dask cluster
(:mod:`benchmarks.cluster`, ``cluster = "local:N"`` or ``"tcp://HOST:PORT"``). Either way:

- **isolation**: a run past its time limit is killed and recorded as ``timeout``; a worker
  that dies (a crash in compiled code, an abort, the out-of-memory killer, a cluster
  worker that is lost) costs only the run it held, recorded as ``error`` with the reason;
  the batch goes on;
- **honest wall times**: each run executes in a worker process with one intra-op thread,
  pinned to one core; ``wall_s`` is the median of its timed solves after set-up. What this
  does not control is said in the session's timing note, which the report shows;
- **reuse**: the runs of one problem and method (a sweep over ``h`` or ``rtol``) go to the
  same worker where they can, so a sweep compiles once;
- **identical accuracy**: a run computes the same thing whatever ``jobs`` or the engine is
  (on the same kind of machine), so accuracy columns do not depend on them;
- **chunks**: an ensemble runs as one task per chunk of its lanes
  (:func:`benchmarks.plan.lane_ranges`), spread over the workers like any other tasks;
  when the last chunk ends its parts are merged into the one ensemble record
  (:func:`benchmarks.execute.merge`), whose lanes equal the unchunked run's. A chunk that
  times out, dies or raises makes the ensemble's record that chunk's ``timeout`` or
  ``error``, its message naming the lanes;
- **resume**: with ``resume`` the runs whose ``run_key`` the store already holds as finished
  (any status but ``error`` and ``timeout``) are not run again. Each run is committed to the
  store on its own as it ends, by this process alone (never by a worker), so a batch killed
  at any point (even by ``SIGKILL``) leaves a consistent store with every finished run in
  it;
- **validation first**: every run is planned (:func:`benchmarks.plan.plan`: every case
  and integrator built and checked once, here) before any starts; bad input raises
  :class:`~benchmarks.records.InputError` with one line that names what is wrong and
  where, and nothing is written. The estimated size of a long run is printed. The workers
  receive the planned runs and execute them as they are;
- **duplicates run once**: specs that resolve to the same run (same ``run_key``: problem,
  parameters, method, options and horizon, however they were written) run once; every one
  of them gets its record, and ``runs.csv`` lists the run once;
- **one writer per folder**: a batch holds the lock of its output folder
  (:class:`~benchmarks.files.FolderLock`) from before it opens the store until it ends; a
  second invocation on the same folder is refused with one line before it runs anything.

``runs.csv`` is replaced whole (:func:`benchmarks.files.replace_file`), never truncated:
rows are appended to ``runs.partial.csv`` as runs end (so a batch killed outright leaves
the runs it finished there, as well as in the store), and ``runs.csv`` is written in the
order of the specs when the batch ends, also when it is interrupted. Of a resumed batch it
holds every run of the batch: the runs skipped because they were finished, read back from
the store as stored (their latest finished row), and the runs of this batch.

A store that fails while the batch runs (a full disk, a file damaged meanwhile) costs no
run: the record goes to ``runs.csv`` all the same, the store is not written to again, and
the batch raises :class:`OutputError` (one line) once every run has ended and ``runs.csv``
is written.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import sqlite3
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterable, TextIO

import cloudpickle
import pandas as pd
from tqdm import tqdm

import problems
from benchmarks.execute import merge
from benchmarks.executors import Executor, Outcome, Task, load_plugins, use
from benchmarks.files import FolderInUse, FolderLock, replace_file
from benchmarks.plan import (DEFAULT_TIMEOUT, PlannedRun, check_timeout, firsts, pending, plan,
                             usable_cpus)
from benchmarks.pool import Pool
from benchmarks.records import (COLUMNS, Ending, InputError, Record, RunSpec, Status, one_line,
                                provenance)
from benchmarks.store import STORE_NAME, Store, StoreError
from problems.spec import suggest
from studies import STUDIES


class OutputError(InputError):
    """Results that could not all be written (a store or ``runs.csv`` that failed while the
    batch ran): one line saying what failed and where every run's record is."""


def study_target(name: str) -> str:
    """The ``module:function`` of a registered study."""
    if name not in STUDIES:
        raise InputError(f"unknown study {name!r}{suggest(name, STUDIES)}; "
                         f"known: {', '.join(sorted(STUDIES))}")
    return STUDIES[name]


def time_left(elapsed: float, finished: list[tuple[bool, float]], cold_left: int,
              warm_left: int, running: list[tuple[bool, float]]) -> float | None:
    """Seconds the batch has left, estimated from the tasks finished so far.

    A task is *cold* when it is the first of its problem and method (its worker compiles
    the method's programs), *warm* when one of them ran before (a sweep's later step
    sizes reuse the programs). With ``c`` and ``w`` the mean durations of the finished
    cold and warm tasks (``w = c`` until a warm one has finished, ``c = w`` the other way
    round), the work left is ``W = cold_left c + warm_left w`` plus, for each running
    task, its mean less the time it has run (at least nothing); the engine has done
    ``D`` seconds of task time in ``elapsed`` seconds, so the time left is
    ``W elapsed / D``, which carries the parallelism actually achieved (workers busy,
    the machine's load) without knowing the number of workers. Separating cold from warm
    tasks matters at the start: a suite's first tasks are nearly all set-up, and a rate
    from them alone overestimates the rest several times.

    Parameters
    ----------
    elapsed : float
        Seconds since the batch started.
    finished : list of (bool, float)
        Each finished task: whether it was cold, and its duration in seconds.
    cold_left, warm_left : int
        Tasks not yet started that will be cold and warm.
    running : list of (bool, float)
        Each running task: whether it is cold, and how long it has run.

    Returns
    -------
    float or None
        ``None`` until a task has finished.
    """
    cold = [d for is_cold, d in finished if is_cold]
    warm = [d for is_cold, d in finished if not is_cold]
    done = sum(cold) + sum(warm)
    if not finished or done <= 0.0:
        return None
    c = sum(cold) / len(cold) if cold else sum(warm) / len(warm)
    w = sum(warm) / len(warm) if warm else c
    work = cold_left * c + warm_left * w
    work += sum(max((c if is_cold else w) - ran, 0.0) for is_cold, ran in running)
    return work * elapsed / done


def _duration(seconds: float) -> str:
    """``seconds`` for a person: ``42 s``, ``3 min``, ``1 h 05 min``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    return f"{minutes} min" if minutes < 60 else f"{minutes // 60} h {minutes % 60:02d} min"


class Progress:
    """A progress bar on a terminal (tqdm) and one log line per finished run.

    The bar shows the tasks done of all, the time elapsed, the estimate of the time left
    (:func:`time_left`, from the tasks finished so far, cold and warm apart), the share of
    the finished runs' time that went to set-up (compiling, on a cold cache), and the runs
    in progress. Without a terminal (a file, a pipe, a test) only the log lines are
    written, one per task, as plain text.

    ``keys`` maps each task's id to what makes its runs share compiled programs (its
    problem and method; a task without one is cold on its own).
    """

    def __init__(self, total: int, log: TextIO | None, bar: bool | None = None,
                 keys: dict[int, object] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.total, self.log, self.count = total, log, 0
        self.clock = clock
        self.began = self.clock()
        self.keys = keys or {}
        self.started_keys: set = set()
        self.running: dict[int, tuple[str, bool, float]] = {}
        self.finished: list[tuple[bool, float]] = []
        self._done_ids: set[int] = set()
        self.setup = self.spent = 0.0
        if bar is None:
            bar = log is not None and hasattr(log, "isatty") and log.isatty()
        self.bar = None
        if bar and total:
            self.bar = tqdm(total=total, file=log, unit="run", dynamic_ncols=True, leave=True,
                            bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}"
                                       "{postfix}]")

    def _key(self, task_id: int) -> object:
        key = self.keys.get(task_id)
        return ("task", task_id) if key is None else key

    def start(self, task_id: int, label: str) -> None:
        key = self._key(task_id)
        cold = key not in self.started_keys
        self.started_keys.add(key)
        self.running[task_id] = (label, cold, self.clock())
        self._postfix()

    def left(self) -> float | None:
        """Seconds left (:func:`time_left`) now."""
        now = self.clock()
        return time_left(now - self.began, self.finished, *self._waiting(),
                         [(cold, now - since) for _, cold, since in self.running.values()])

    def _waiting(self) -> tuple[int, int]:
        """Tasks not started yet that will be cold, and warm."""
        cold_keys = set()
        warm = 0
        for task_id in self.keys:
            if task_id in self.running or task_id in self._done_ids:
                continue
            key = self._key(task_id)
            if key in self.started_keys or key in cold_keys:
                warm += 1
            else:
                cold_keys.add(key)
        return len(cold_keys), warm

    def _postfix(self) -> None:
        if self.bar is None:
            return
        left = self.left()
        parts = ["estimating" if left is None else f"about {_duration(left)} left"]
        if self.spent > 0:
            parts.append(f"set-up {100 * self.setup / self.spent:.0f} % of run time")
        parts.append(" | ".join(label for label, _, _ in self.running.values())[:120])
        self.bar.set_postfix_str(", ".join(p for p in parts if p), refresh=True)

    def finish(self, task_id: int, line: str, setup_s: float | None = None) -> None:
        """Task ``task_id`` ended (``line`` says how); ``setup_s`` is its run's set-up."""
        label, cold, since = self.running.pop(task_id, ("", True, self.clock()))
        duration = self.clock() - since
        self._done_ids.add(task_id)
        self.finished.append((cold, duration))
        if isinstance(setup_s, (int, float)) and math.isfinite(setup_s) and duration > 0:
            self.setup += min(setup_s, duration)
            self.spent += duration
        self.count += 1
        self.note(f"[{self.count}/{self.total}] {line}")
        if self.bar is not None:
            self.bar.update(1)
            self._postfix()

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


def _outcome_record(run: PlannedRun, task: Task, outcome: Outcome) -> Record:
    """The record of a run from how its task ended (a chunk's record: its lanes named)."""
    if outcome.state == "done":
        result = outcome.result
        if task.payload[0].lanes is None or result.ending.message is None:
            return result
        return replace(result, ending=replace(result.ending, message=(
            f"{_lanes(task.payload[0])}: {result.ending.message}")))
    if outcome.state == "timeout":
        message = (f"exceeded the time limit of {task.time_limit:g} s during "
                   f"{outcome.phase or 'start-up'} and was killed")
    elif outcome.state == "died":
        message = f"{outcome.message} during {outcome.phase or 'start-up'}"
    else:
        message = outcome.message
    status = Status.TIMEOUT if outcome.state == "timeout" else Status.ERROR
    if task.payload[0].lanes is not None:
        message = f"{_lanes(task.payload[0])}: {message}"
    return Record(run.run, Ending(status, message))


def _lanes(chunk: PlannedRun) -> str:
    """The lanes of a planned chunk of an ensemble, in words."""
    first, stop = chunk.lanes
    return f"the chunk of lanes {first} to {stop - 1}"


def _ensemble_record(run: PlannedRun, ended: list[tuple[Task, Outcome]]) -> Record:
    """The record of an ensemble from how its chunks' tasks ended: the merge of their parts
    (:func:`benchmarks.execute.merge`), or the record of the first chunk, in lane order,
    that gave none."""
    for task, outcome in sorted(ended, key=lambda pair: pair[0].payload[0].lanes):
        if outcome.state != "done" or isinstance(outcome.result, Record):
            return _outcome_record(run, task, outcome)
    return merge(run, [outcome.result for _, outcome in ended])


def engine(jobs: int | None, cluster: str | None) -> Executor:
    """The engine of a batch: a Dask cluster when ``cluster`` names one, else a local pool
    of ``jobs`` workers (default: the usable cores)."""
    if cluster is not None:
        if jobs is not None:
            raise InputError("give either jobs (the local pool) or a cluster, not both")
        # Imported here: Dask takes about a second to import, only its engine needs it, and
        # it is an optional extra.
        try:
            from benchmarks.cluster import Cluster
        except ModuleNotFoundError as exc:
            raise InputError(f"a cluster needs Dask's distributed ({exc.name} is not "
                             f"installed): pip install 'driftbench[cluster]'") from None

        return Cluster(cluster)
    jobs = len(usable_cpus()) if jobs is None else jobs
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"jobs = {jobs!r} must be a whole number of at least 1")
    return Pool(jobs)


def user_code(loads: Iterable[str] = (), cases=()) -> tuple[tuple[str, ...], dict[str, bytes]]:
    """Load user files and modules here and make ``cases`` (:class:`~problems.Case`
    objects) known by name; return what a worker needs to do the same.

    Raises
    ------
    InputError
        A source that cannot be loaded (its file:line and what went wrong), or a case
        whose name a registered problem has.
    """
    try:
        loaded = tuple(problems.load(source) for source in loads)
    except problems.LoadError as exc:
        raise InputError(one_line(exc)) from None
    blobs = {}
    for case in cases:
        if problems.ORIGINS.get(case.name, "Python API") != "Python API":
            raise InputError(f"case {case.name!r}: a problem of that name is registered "
                             f"({problems.ORIGINS[case.name]}); give the case another name")
        blobs[case.name] = cloudpickle.dumps(case)
    use(loaded, blobs)
    return loaded, blobs


def _digest(loaded: tuple[str, ...], blobs: dict[str, bytes]) -> str:
    """A hash of the user code a batch runs (file contents, pickled cases), for run keys:
    the code version covers only the library."""
    if not loaded and not blobs:
        return ""
    h = hashlib.sha256()
    for source in loaded:
        module = sys.modules.get(source) if not source.endswith(".py") else None
        path = Path(source if module is None else getattr(module, "__file__", "") or "")
        h.update(source.encode() + (path.read_bytes() if path.is_file() else b""))
    for name, blob in sorted(blobs.items()):
        h.update(name.encode() + blob)
    return f"+user:{h.hexdigest()[:12]}"


def run_specs(specs: list[RunSpec], out: Path, jobs: int | None = None, *,
              cluster: str | None = None, suite: str = "ad-hoc", repeats: int = 3,
              timeout: float | None = None, resume: bool = False,
              studies: Iterable[str] = (), grid_options: dict | None = None,
              load: Iterable[str] = (), cases=(), log: TextIO | None | str = "stderr",
              progress: bool | None = None, allow_large: bool = False,
              start_notes: Iterable[str] = (), audit_user: bool = True) -> list[Record]:
    """Run ``specs`` on an engine, store every run and write ``out/runs.csv``.

    Parameters
    ----------
    specs : list of RunSpec
        The runs, in the order ``runs.csv`` lists them.
    out : Path
        Output folder: ``runs.csv``, the store ``driftbench.sqlite``, study outputs.
    jobs : int, optional
        Runs side by side in the local pool (default: the usable cores).
    cluster : str, optional
        A Dask cluster instead of the local pool: ``"local:N"`` starts one of ``N`` workers
        on this machine, ``"tcp://HOST:PORT"`` uses the running scheduler there.
    suite : str
        Name recorded with the session.
    repeats : int
        Timed solves of each run at least, within autorange's cap
        (:func:`benchmarks.execute.more`; the median is reported).
    timeout : float, optional
        Time limit of a run that sets none itself (default :data:`DEFAULT_TIMEOUT`);
        also the time limit of each study.
    resume : bool
        Skip the runs whose ``run_key`` the store holds as finished.
    studies : iterable of str
        Names of studies (:data:`studies.STUDIES`), run on the same workers as the runs
        (started first); their tables and figures go to the store (section = the
        study's name), the files they write to
        ``out/studies/NAME``; a study that fails is stored as an ``error`` table with its
        message.
    grid_options : dict, optional
        ``Grid`` options (windows, samples) for every run.
    load : iterable of str
        User files and modules that register problems and integrators
        (:func:`problems.load`), loaded here and by every worker.
    cases : iterable of Case
        :class:`~problems.Case` objects run under their names (the Python API's), sent to
        the workers pickled by value.
    log : text stream, optional
        Where the progress bar (on a terminal), one line per run and the engine's notes
        (the Dask dashboard's address) go: ``None`` for nowhere; by default the standard
        error stream of the moment of the call (not of the import: a stream that was
        replaced since may be closed).
    progress : bool, optional
        Force the progress bar on or off (default: on when ``log`` is a terminal).
    allow_large : bool
        Lift the size limit of problems (:func:`problems.check_size`) and the step limit
        :data:`STEP_LIMIT`.
    audit_user : bool
        Audit the user problems' functions (:func:`benchmarks.plan.plan`); off only for
        cases whose system was audited before.
    start_notes : iterable of str
        Lines for ``log`` once the input is validated and the output folder taken, just
        before the first task starts (none when no task is left), so that bad input still
        gets its one line alone.

    Returns
    -------
    list of Record
        One per spec, in order; runs skipped by ``resume`` carry their stored row only.

    Raises
    ------
    InputError
        Bad input, found before any run starts (nothing is written then), a damaged or
        foreign store, or an output folder that another invocation is writing.
    OutputError
        A store or ``runs.csv`` that failed while the batch ran, raised once every run has
        ended (its ``records`` are what this function returns otherwise).
    """
    log = sys.stderr if log == "stderr" else log
    load_plugins()
    loaded, blobs = user_code(load, cases)
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise InputError(f"repeats = {repeats!r} must be a whole number of at least 1")
    timeout = DEFAULT_TIMEOUT if timeout is None else timeout
    check_timeout(timeout, "timeout")
    targets = {name: study_target(name) for name in studies}
    specs = list(specs)
    executor = engine(jobs, cluster)
    # The workers import and warm up while the runs are validated; no run starts before
    # validation has passed, and bad input stops them unused.
    with executor:
        executor.start()
        version = provenance()["code_version"]
        keyed = version + _digest(loaded, blobs)
        notes: list[str] = []
        runs = plan(specs, keyed, grid_options, timeout, allow_large, notes,
                    audit_user=audit_user)
        said = executor.ready()
        for line in [*notes, *([said] if said else [])]:
            if log is not None:
                print(line, file=log, flush=True)
        out = Path(out)
        lock = FolderLock(out)
        try:
            out.mkdir(parents=True, exist_ok=True)
            lock.acquire()
        except FolderInUse as exc:
            raise InputError(one_line(exc)) from None
        except OSError as exc:
            raise InputError(one_line(f"cannot write results to {out}: {exc}")) from None
        try:
            try:
                store = Store(out / STORE_NAME)
            except StoreError as exc:
                raise InputError(one_line(exc)) from None
            except OSError as exc:
                raise InputError(one_line(f"cannot write results to {out}: {exc}")) from None
            with store:
                return _run_batch(executor, store, runs, (loaded, blobs), out, suite=suite,
                                  repeats=repeats, timeout=timeout, resume=resume,
                                  targets=targets, log=log, progress=progress,
                                  start_notes=start_notes)
        finally:
            lock.release()


def _run_batch(executor: Executor, store: Store, runs: list[PlannedRun], code, out, *,
               suite, repeats, timeout, resume, targets, log, progress,
               start_notes=()) -> list[Record]:
    """The body of :func:`run_specs` once the input is planned, the folder locked and the
    store open; ``code`` is the loaded sources and the pickled cases."""
    loaded, blobs = code
    records: list[Record | None] = [None] * len(runs)
    todo, skipped = pending(runs, store.finished_keys() if resume else set())
    if skipped:
        stored = store.finished({runs[i].run.run_key for i in skipped})
        for i in skipped:
            records[i] = stored[runs[i].run.run_key]
    # A run's affinity is its problem and method: a sweep over h or rtol stays on one
    # worker, which compiles the method once for it. An ensemble is one task per chunk.
    tasks, owner = [], []
    for i in todo:
        for lanes in runs[i].chunks or [None]:
            chunk = runs[i] if lanes is None else replace(runs[i], lanes=lanes)
            label = runs[i].label if lanes is None else f"{runs[i].label} / {_lanes(chunk)}"
            tasks.append(Task(len(tasks), "run", (chunk, repeats, loaded, blobs),
                              runs[i].timeout, label,
                              (runs[i].run.problem, runs[i].run.integrator)))
            owner.append(i)
    chunks_ended: dict[int, list[tuple[Task, Outcome]]] = {}
    n_unique = len(todo) + len(skipped)
    try:
        session = store.begin(suite, timing_note=executor.note(repeats))
    except sqlite3.Error as exc:  # before any run: nothing is lost
        raise InputError(one_line(f"{store.path}: cannot be written: {exc}")) from None
    # The studies' tasks (ids -1, -2, ...) share nothing compiled with other tasks.
    bar = Progress(len(tasks) + len(targets), log, progress,
                   keys={**{-1 - k: None for k in range(len(targets))},
                         **{task.id: task.affinity for task in tasks}})
    if n_unique < len(runs):
        bar.note(f"{len(runs) - n_unique} of {len(runs)} runs repeat an earlier one "
                 f"(same problem, parameters, method, options and horizon) and run once")
    if skipped:
        bar.note(f"resuming: {len(skipped)} of {len(runs)} runs are finished in "
                 f"{store.path} and are not run again")
    for line in start_notes if tasks or targets else ():
        bar.note(line)
    csv_path, partial = out / "runs.csv", out / "runs.partial.csv"
    failures: list[str] = []

    def fail(what: str) -> None:
        failures.append(what)
        bar.note(f"error: {what}")

    def failed(path: Path) -> bool:
        """Whether writing ``path`` failed already (it is not tried again)."""
        return any(f.startswith(f"{path}:") for f in failures)

    # Opened at the first row, so that no empty file is left by a batch killed before it.
    stream: dict = {}

    def append(row: dict) -> None:
        if not stream:
            stream["fh"] = open(partial, "w", newline="")
            stream["csv"] = csv.DictWriter(stream["fh"], fieldnames=COLUMNS,
                                           extrasaction="ignore")
            stream["csv"].writeheader()
        stream["csv"].writerow(row)
        stream["fh"].flush()

    def report(task: Task, outcome: Outcome) -> None:
        i = owner[task.id]
        if runs[i].chunks:
            ended = chunks_ended.setdefault(i, [])
            ended.append((task, outcome))
            if len(ended) < len(runs[i].chunks):
                bar.finish(task.id, f"{task.label}: {outcome.state}")
                return
            record = _ensemble_record(runs[i], chunks_ended.pop(i))
        else:
            record = _outcome_record(runs[i], task, outcome)
        records[i] = record
        if not failed(partial):
            try:
                append(record.row)
            except OSError as exc:
                fail(f"{partial}: {exc.strerror or exc}; the rows go to {csv_path} at the end")
        if not failed(store.path):
            try:
                store.add(session, record)
            except (sqlite3.Error, OSError) as exc:
                fail(f"{store.path}: storing {task.label} failed ({exc}); it and every later "
                     f"run are in {csv_path} only")
        bar.finish(task.id, f"{runs[i].label}: {_summary(record.row)}",
                   record.row.get("setup_s"))

    # Studies go first, beside the runs: each is one long task, and started last it would
    # leave the other workers idle while it ends.
    limit = None if math.isinf(timeout) else float(timeout)
    studies, report_study = _studies(store, session, targets, out, limit, bar, fail)

    def dispatch(task: Task, outcome: Outcome) -> None:
        (report_study if task.kind == "study" else report)(task, outcome)

    try:
        executor.run(studies + tasks, dispatch, on_start=lambda t: bar.start(t.id, t.label))
    finally:
        bar.close()
        if stream:
            try:
                stream["fh"].close()
            except OSError:  # its last buffered row: runs.csv below gets every row
                pass
        # Also when interrupted: runs.csv then lists the skipped runs and those that ended.
        rows = [r.row for r in records if r is not None]
        try:
            _write_csv(csv_path, rows)
        except OSError as exc:
            fail(f"{csv_path}: {exc.strerror or exc}; it was left as it was, the rows of "
                 f"the runs that ended are in {store.path} and {partial}")
            if partial.is_file() and partial.stat().st_size == 0:
                partial.unlink()
        else:
            try:
                partial.unlink(missing_ok=True)
            except OSError as exc:  # runs.csv holds every row: only the leftover is named
                fail(f"{partial}: {exc.strerror or exc}; it could not be removed, and "
                     f"{csv_path} holds every row")
    records = [records[first] for first in firsts(runs)]
    if failures:
        raise OutputError(one_line(f"not every result was written: {failures[0]}"
                                   + (f" (and {len(failures) - 1} more failures, above)"
                                      if len(failures) > 1 else "")))
    return records


def _studies(store: Store, session: int, targets: dict[str, str], out: Path,
             timeout: float | None, bar: Progress, fail) -> tuple[list[Task], Callable]:
    """The tasks of the studies ``targets`` and the report of each one's end: write its
    files, store its tables and figures, or its error; a store that refuses even the error
    is told to ``fail``."""
    tasks = [Task(-1 - k, "study", (name, target), timeout, f"study {name}")
             for k, (name, target) in enumerate(targets.items())]

    def report(task: Task, outcome: Outcome) -> None:
        name = task.payload[0]
        result = outcome.result if outcome.state == "done" else None
        error = (result["error"] if result is not None else
                 f"exceeded the time limit of {task.time_limit:g} s during "
                 f"{outcome.phase} and was killed" if outcome.state == "timeout" else
                 f"{outcome.message} during {outcome.phase or 'start-up'}")
        if error is None:
            try:
                folder = out / "studies" / name
                for relative, content in result["files"].items():
                    path = folder / relative
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(content)
                for table, frame in result["tables"].items():
                    store.add_table(session, name, table, frame)
                for relative, content in result["files"].items():
                    if relative.endswith(".svg") and "/" not in relative:
                        store.add_figure(session, name, relative[:-4], content.decode())
            except Exception as exc:  # a study's output the store refuses is its error
                error = f"storing its output failed: {type(exc).__name__}: {exc}"
        if error is not None:
            try:
                store.add_table(session, name, "error", pd.DataFrame({"message": [error]}))
            except (sqlite3.Error, OSError) as exc:
                fail(f"{store.path}: storing the error of study {name} failed ({exc}); "
                     f"its error: {error}")
        status = Status.OK if error is None else f"{Status.ERROR}: {error}"
        bar.finish(task.id, f"{task.label}: {status}")

    return tasks, report


def _write_csv(path: Path, rows: list[dict]) -> None:
    """Replace ``path`` with ``rows`` whole (:func:`benchmarks.files.replace_file`: a
    writer that fails or is killed leaves the old file as it was)."""
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=COLUMNS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    replace_file(path, text.getvalue())
