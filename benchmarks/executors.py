"""What every engine that runs a batch shares: tasks, outcomes, and what a worker does.

An engine (an *executor*) takes :class:`Task` objects and reports how each ended as an
:class:`Outcome`; the batch (:mod:`benchmarks.batch`) makes the tasks, turns outcomes into
records and is the only writer of the store. Two engines implement :class:`Executor`: the
local process pool (:mod:`benchmarks.pool`) and a Dask cluster (:mod:`benchmarks.cluster`).
Whichever runs it, a task is carried out by :func:`perform` in a worker process of the
local pool's kind, so a run is isolated, timed and measured the same way everywhere.

User code travels with each run: :func:`use` loads, in the worker, the files and modules
the batch loaded (``--load``, a suite's ``load``) and registers the Python API's
:class:`~problems.Case` objects, pickled by value.

Test-only plugins: the environment variable :data:`PLUGIN_ENV` may name Python files
(separated by ``os.pathsep``) that the parent and every worker load before any task,
under the module name ``driftbench_plugin_<stem>``; the test suite uses it to register
integrators that hang, crash, raise or return NaN.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import sys
import tempfile
import time
import traceback
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Protocol

import cloudpickle

import problems
from benchmarks.execute import execute, forget_cases

#: Environment variable naming test-only plugin files (``os.pathsep``-separated).
PLUGIN_ENV = "DRIFTBENCH_TEST_PLUGINS"


@dataclass
class Task:
    """One unit of work: ``kind`` selects the worker's handler (:data:`HANDLERS`).

    Tasks with the same ``affinity`` (such as the runs of one problem and method at
    several step sizes) go to the same worker where they can, so that they share what it
    compiled.
    """

    id: int
    kind: str
    payload: object
    time_limit: float | None
    label: str
    affinity: object = None


@dataclass
class Outcome:
    """How a task ended.

    ``state`` is ``"done"`` (``result`` holds the handler's return value), ``"timeout"``
    (killed at its time limit), ``"died"`` (the worker process ended, or the machine it ran
    on left the cluster; ``message`` says how) or ``"fail"`` (the task could not be run or
    reported; ``message`` says why). ``phase`` is the last phase the worker announced.
    """

    state: str
    result: object = None
    message: str = ""
    phase: str = ""


class Executor(Protocol):
    """An engine: started once, runs batches of tasks, closed once (a context manager)."""

    def start(self) -> None:
        """Start the workers, without waiting for them (they warm up while the batch
        validates its input)."""

    def ready(self) -> str:
        """Wait until the engine can take tasks; return what the user should know about it
        (a dashboard's address), or ``""``. Raises ``InputError`` when it cannot start."""

    def run(self, tasks: Iterable[Task], report: Callable[[Task, Outcome], None],
            on_start: Callable[[Task], None] | None = None) -> None:
        """Run ``tasks``; call ``report(task, outcome)`` for each as it ends, in any order,
        and ``on_start(task)`` when one is handed to a worker."""

    def note(self, repeats: int) -> str:
        """How this engine keeps wall times honest, in a few sentences for the report."""

    def close(self) -> None:
        """Stop every worker."""


def pick(tasks: deque, affinity, others: set) -> Task:
    """Take the next task off ``tasks`` for a worker whose last task had ``affinity``: the
    first with that affinity; else the first whose affinity no other worker is on (the
    affinities in ``others``); else the first."""
    tests = ((lambda t: t.affinity is not None and t.affinity == affinity),
             (lambda t: t.affinity is None or t.affinity not in others))
    for test in tests:
        for i, task in enumerate(tasks):
            if test(task):
                del tasks[i]
                return task
    return tasks.popleft()


def load_plugins() -> list[str]:
    """Load the test-only plugin files named by :data:`PLUGIN_ENV` (once per process)."""
    loaded = []
    for entry in filter(None, os.environ.get(PLUGIN_ENV, "").split(os.pathsep)):
        path = Path(entry)
        name = f"driftbench_plugin_{path.stem}"
        if name not in sys.modules:
            if path.suffix != ".py" or not path.is_file():
                raise ValueError(f"{PLUGIN_ENV}: {entry} is not a Python file")
            problems.import_file(name, path)
        loaded.append(name)
    return loaded


#: Digest of each case provided by the Python API to this process, by problem name.
_provided: dict[str, str] = {}


def use(loads: Iterable[str] = (), cases: dict[str, bytes] | None = None) -> None:
    """Make user problems known in this process: load files and modules
    (:func:`problems.load`, once each) and register :class:`~problems.Case` objects given
    to the Python API (pickled by value, so a notebook's functions travel with them)
    under their names, replacing an earlier case of the same name."""
    for source in loads:
        problems.load(source)
    for name, blob in (cases or {}).items():
        digest = hashlib.sha256(blob).hexdigest()
        if _provided.get(name) != digest:
            case = cloudpickle.loads(blob)
            problems.REGISTRY.pop(name, None)
            problems.register(name, origin="Python API")(_factory(case))
            _provided[name] = digest
            forget_cases()


def _factory(case):
    """A problem factory without parameters that gives ``case``: the case is all there is
    to a problem of the Python API."""
    return lambda: case


def _run_task(payload, phase: Callable[[str], None]):
    """Execute a planned run (:class:`~benchmarks.plan.PlannedRun`) as it is, with the user
    code it needs."""
    run, repeats, loads, cases = payload
    use(loads, cases)
    deadline = time.monotonic() + run.timeout if run.timeout is not None else None
    return execute(run, repeats=repeats, deadline=deadline, on_phase=phase)


def _study_task(payload, phase: Callable[[str], None]):
    """Run a study ``module:function`` in a fresh folder; return its tables and every file
    it wrote (the batch writes them where it keeps its output: the worker may be another
    machine)."""
    name, target = payload
    try:
        with tempfile.TemporaryDirectory(prefix=f"driftbench-{name}-") as tmp:
            out = Path(tmp)
            module, _, func = target.partition(":")
            phase(f"study {name}")
            tables = getattr(importlib.import_module(module), func)(out)
            if not isinstance(tables, dict):
                raise TypeError(f"study {name!r} returned {type(tables).__name__}, "
                                f"not a dict of tables")
            files = {str(p.relative_to(out)): p.read_bytes()
                     for p in sorted(out.rglob("*")) if p.is_file()}
        return {"tables": dict(tables), "files": files, "error": None}
    except Exception as exc:  # a study that raises is recorded, never fatal
        detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return {"tables": {}, "files": {}, "error": detail}


#: What a worker can do: task kind -> handler(payload, phase) -> picklable result.
HANDLERS: dict[str, Callable] = {"run": _run_task, "study": _study_task}


def perform(kind: str, payload, phase: Callable[[str], None]):
    """Carry out one task in this (worker) process."""
    return HANDLERS[kind](payload, phase)
