"""A batch of runs: plan, validate, resume, hand to an engine, write runs.csv and the store.

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
- **resume**: with ``resume`` the runs whose ``run_key`` the store already holds as finished
  (any status but ``error`` and ``timeout``) are not run again. Each run is committed to the
  store on its own as it ends, by this process alone (never by a worker), so a batch killed
  at any point (even by ``SIGKILL``) leaves a consistent store with every finished run in
  it;
- **validation first**: every case and integrator is built and checked before any run
  starts; bad input raises :class:`~benchmarks.records.InputError` with one line that names
  what is wrong and where, and nothing is written. Sizes are checked before a case is
  built (:func:`problems.check_size`) and step counts before a run is planned
  (:data:`STEP_LIMIT`), unless ``allow_large``; the estimated size of a long run is
  printed;
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
import itertools
import math
import sqlite3
import sys
from pathlib import Path
from typing import Callable, Iterable, TextIO

import cloudpickle
import numpy as np
import pandas as pd
from tqdm import tqdm

import integrators
import problems
from benchmarks.cluster import Cluster
from benchmarks.audit import AuditError, audit, explain
from benchmarks.execute import build, known
from benchmarks.executors import Executor, Outcome, Task, load_plugins, use
from benchmarks.files import FolderInUse, FolderLock, replace_file
from benchmarks.pool import Pool, usable_cpus
from benchmarks.records import (COLUMNS, WHOLE_COLUMNS, InputError, Record, RunSpec,
                                Status, blank_row, identity, one_line, provenance)
from benchmarks.store import STORE_NAME, UNFINISHED, Store, StoreError, load_runs
from problems.spec import SpecError, split_spec, suggest
from studies import STUDIES

#: Time limit of a run (seconds) when neither the run, its suite nor the command sets one.
DEFAULT_TIMEOUT = 3600.0
#: Most steps of a fixed-step run planned without ``allow_large``: a thousand times the
#: longest run of the shipped suites; ``--h 1e-9 --t-end 1`` (10^9 steps) would otherwise
#: run silently for up to an hour.
STEP_LIMIT = 10**8
#: Runs of at least this many steps, or of steps times coordinates, get their estimated
#: size printed before the batch starts.
LONG_STEPS, LONG_WORK = 10**6, 10**8


class OutputError(InputError):
    """Results that could not all be written (a store or ``runs.csv`` that failed while the
    batch ran): one line saying what failed and where every run's record is."""


def study_target(name: str) -> str:
    """The ``module:function`` of a registered study."""
    if name not in STUDIES:
        raise InputError(f"unknown study {name!r}{suggest(name, STUDIES)}; "
                         f"known: {', '.join(sorted(STUDIES))}")
    return STUDIES[name]


def expand(problem_specs, integrator_specs, hs=(), rtols=(), atols=(), t_end=None,
           timeout=None, origin="") -> list[RunSpec]:
    """Every combination: ``hs`` go to fixed-step methods, ``rtols x atols`` to adaptive ones.

    An empty list leaves the method's own default for that setting.
    """
    runs = []
    for p, i in itertools.product(problem_specs, integrator_specs):
        key = split_spec(i)[0]
        if key not in integrators.REGISTRY:
            integrators.make(i)  # raises the error that names the unknown key
        if integrators.cls_of(key).adaptive:
            for rtol, atol in itertools.product(rtols or [None], atols or [None]):
                runs.append(RunSpec(p, i, None, rtol, atol, t_end, timeout, origin))
        else:
            runs.extend(RunSpec(p, i, h, None, None, t_end, timeout, origin)
                        for h in (hs or [None]))
    return runs


def check_timeout(value, where: str) -> None:
    """A time limit must be a positive number of seconds (``inf``: none)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise InputError(f"{where}: timeout = {value!r} must be a positive number of "
                         f"seconds (inf for no limit)")


def _steps(fixed: dict) -> float | None:
    """The number of steps of a fixed-step run from its known columns, else None."""
    h = fixed.get("h")
    if h is None or fixed.get("t_end") is None:
        return None
    return (fixed["t_end"] - (fixed.get("t0") or 0.0)) / h


def validate(specs: Iterable[RunSpec], version: str, grid_options: dict | None = None,
             allow_large: bool = False, notes: list[str] | None = None) -> list[dict]:
    """Build and check every run before any starts; return each run's known columns.

    Each problem spec's size is checked before its case is built
    (:func:`problems.check_size`); each case is built once per problem spec and ``t_end``
    (building checks the initial values: inconsistent ones raise with their residuals) and
    each integrator once per spec and setting; a fixed-step run of more than
    :data:`STEP_LIMIT` steps is refused. ``allow_large`` lifts both limits. The returned
    dicts are :func:`benchmarks.execute.known`: the columns fixed before the run, and its
    ``run_key``. The estimated sizes of long runs are appended to ``notes``.

    Raises
    ------
    InputError
        On the first bad run, with where it was asked for (suite file and line) and what
        is wrong, on one line.
    """
    built: dict[RunSpec, tuple] = {}
    audited: set[str] = set()
    out = []
    for spec in specs:
        where = f"{spec.origin}: " if spec.origin else ""
        try:
            if spec.timeout is not None:
                check_timeout(spec.timeout, spec.label())
            if spec not in built:
                if not allow_large:
                    problems.check_size(spec.problem)
                built[spec] = build(spec)
            name = split_spec(spec.problem)[0]
            # The library's own problems are verified by its tests; user code is checked
            # here, once per problem spec, before it can spoil every run.
            if spec.problem not in audited and problems.origin(name) != "built-in":
                audit(built[spec][0])
                audited.add(spec.problem)
            fixed = known(spec, *built[spec], grid_options, version)
            steps = _steps(fixed)
            if steps is not None:
                n = int(built[spec][0].q0.size)
                size = f"about {steps:.3g} steps of {n} coordinates"
                if steps > STEP_LIMIT and not allow_large:
                    raise InputError(f"{spec.label()}: {size} is above the limit of "
                                     f"{STEP_LIMIT:.0e} steps; give a larger h, a shorter "
                                     f"t_end, or {problems.ALLOW_LARGE} to run it anyway")
                if notes is not None and (steps >= LONG_STEPS or steps * n >= LONG_WORK):
                    notes.append(f"note: {spec.label()}: a long run, {size}")
            out.append(fixed)
        except (InputError, AuditError, SpecError) as exc:
            raise InputError(one_line(f"{where}{exc}")) from None
        except Exception as exc:  # user code or a defect met while building: one line
            raise InputError(one_line(f"{where}{spec.label()}: {explain(exc)}")) from None
    return out


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


def _outcome_record(spec: RunSpec, fixed: dict, task: Task, outcome: Outcome) -> Record:
    """The record of a run from how its task ended."""
    if outcome.state == "done":
        return outcome.result
    if outcome.state == "timeout":
        message = (f"exceeded the time limit of {task.time_limit:g} s during "
                   f"{outcome.phase or 'start-up'} and was killed")
    elif outcome.state == "died":
        message = f"{outcome.message} during {outcome.phase or 'start-up'}"
    else:
        message = outcome.message
    status = Status.TIMEOUT if outcome.state == "timeout" else Status.ERROR
    return Record(blank_row(spec, **fixed, status=status, message=message))


def _stored_rows(store_path: Path, keys: set[str]) -> dict[str, dict]:
    """The latest finished stored row of each run key (for runs.csv of a resumed batch)."""
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
            elif c in WHOLE_COLUMNS and isinstance(value, float) and value.is_integer():
                value = int(value)
            row[c] = value
        rows[row["run_key"]] = row
    return rows


def _limit(seconds: float) -> float | None:
    """A time limit for an engine: ``None`` for no limit (``inf``)."""
    return None if math.isinf(seconds) else float(seconds)


def engine(jobs: int | None, cluster: str | None) -> Executor:
    """The engine of a batch: a Dask cluster when ``cluster`` names one, else a local pool
    of ``jobs`` workers (default: the usable cores)."""
    if cluster is not None:
        if jobs is not None:
            raise InputError("give either jobs (the local pool) or a cluster, not both")
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
              load: Iterable[str] = (), cases=(), log: TextIO | None = sys.stderr,
              progress: bool | None = None, allow_large: bool = False) -> list[Record]:
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
        Timed repeats of each solve (the median is reported).
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
        (the Dask dashboard's address) go.
    progress : bool, optional
        Force the progress bar on or off (default: on when ``log`` is a terminal).
    allow_large : bool
        Lift the size limit of problems (:func:`problems.check_size`) and the step limit
        :data:`STEP_LIMIT`.

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
        fixed = validate(specs, keyed, grid_options, allow_large, notes)
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
                return _run_batch(executor, store, specs, fixed, (keyed, loaded, blobs), out,
                                  suite=suite, repeats=repeats, timeout=timeout,
                                  resume=resume, targets=targets, grid_options=grid_options,
                                  log=log, progress=progress)
        finally:
            lock.release()


def _firsts(fixed: list[dict]) -> list[int]:
    """For each run, the index of the first run with its ``run_key`` (itself if none)."""
    first: dict[str, int] = {}
    return [first.setdefault(f["run_key"], i) for i, f in enumerate(fixed)]


def _run_batch(executor: Executor, store: Store, specs, fixed, code, out, *, suite,
               repeats, timeout, resume, targets, grid_options, log, progress) -> list[Record]:
    """The body of :func:`run_specs` once the input is valid, the folder locked and the
    store open; ``code`` is the run keys' version, the loaded sources and the pickled
    cases."""
    keyed, loaded, blobs = code
    records: list[Record | None] = [None] * len(specs)
    firsts = _firsts(fixed)
    unique = [i for i, first in enumerate(firsts) if first == i]
    finished = store.finished_keys() if resume else set()
    skipped = [i for i in unique if fixed[i]["run_key"] in finished]
    if skipped:
        stored = _stored_rows(store.path, {fixed[i]["run_key"] for i in skipped})
        for i in skipped:
            records[i] = Record(stored[fixed[i]["run_key"]])
    # A run's affinity is its problem and method: a sweep over h or rtol stays on one
    # worker, which compiles the method once for it.
    tasks = []
    for i in unique:
        if records[i] is None:
            spec = specs[i]
            limit = _limit(spec.timeout or timeout)
            payload = (spec, keyed, repeats, limit, grid_options, loaded, blobs)
            # Labelled by the identity the store will hold (settings and horizon resolved).
            tasks.append(Task(i, "run", payload, limit, identity(blank_row(spec, **fixed[i])),
                              (spec.problem, spec.integrator)))
    try:
        session = store.begin(suite, timing_note=executor.note(repeats))
    except sqlite3.Error as exc:  # before any run: nothing is lost
        raise InputError(one_line(f"{store.path}: cannot be written: {exc}")) from None
    bar = Progress(len(tasks) + len(targets), log, progress)
    if len(unique) < len(specs):
        bar.note(f"{len(specs) - len(unique)} of {len(specs)} runs repeat an earlier one "
                 f"(same problem, parameters, method, options and horizon) and run once")
    if skipped:
        bar.note(f"resuming: {len(skipped)} of {len(specs)} runs are finished in "
                 f"{store.path} and are not run again")
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
        record = _outcome_record(specs[task.id], fixed[task.id], task, outcome)
        records[task.id] = record
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
        bar.finish(task.id, f"{task.label}: {_summary(record.row)}")

    # Studies go first, beside the runs: each is one long task, and started last it would
    # leave the other workers idle while it ends.
    studies, report_study = _studies(store, session, targets, out, _limit(timeout), bar, fail)

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
        rows = [records[i].row for i in unique if records[i] is not None]
        try:
            _write_csv(csv_path, rows)
            partial.unlink(missing_ok=True)
        except OSError as exc:
            fail(f"{csv_path}: {exc.strerror or exc}; it was left as it was, the rows of "
                 f"the runs that ended are in {store.path} and {partial}")
            if partial.exists() and partial.stat().st_size == 0:
                partial.unlink()
    records = [records[first] for first in firsts]
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
