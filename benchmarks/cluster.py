"""The Dask engine: a batch's runs on the workers of a ``distributed`` cluster.

``Cluster("local:N")`` starts a :class:`distributed.LocalCluster` of ``N`` workers on this
machine, as threads of this process (each hands its runs to a process of its own, below, so
worker processes would add only start-up time and compete for the cores);
``Cluster("tcp://HOST:PORT")`` connects
to a running scheduler, whose workers (``dask worker tcp://HOST:PORT --nthreads 1``) may be
on any machine that has this code and its dependencies at the same version (a worker that
runs another code version gives ``error`` records that say so, never results under the
wrong run key).

The semantics are those of the local pool (:mod:`benchmarks.pool`), because each Dask
worker runs a pool of one worker process of its own (:class:`_Host`) and every task is
carried out there:

- **isolation**: a run past its time limit is killed there (``SIGKILL``) and recorded
  ``timeout``; a run that kills its process is recorded ``error`` with the signal; a Dask
  worker of a ``tcp://`` cluster that dies or leaves it (``SIGKILL``, a lost machine) costs
  only the run it held, recorded ``error`` with the reason, and its nanny, if it has one,
  starts a fresh one;
- **honest wall times**: one run at a time per Dask worker, its process pinned to a core
  that the worker claims on its machine (a lock file per core, so workers on one machine
  take different cores while there are enough);
- **reuse**: a Dask worker keeps its pool process, and with it what it compiled; the runs
  of one problem and method go to the same worker where they can (this client hands each
  worker its next task itself, as the local pool does);
- **one writer**: results come back to this client, which alone writes the store.

Ctrl-C stops the client: every finished run is already stored; runs in flight on a
``tcp://`` cluster finish or reach their time limit there and are discarded.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import queue
import socket
import tempfile
import threading
import time
from collections import deque
from typing import Callable, Iterable

import distributed

from benchmarks.executors import Outcome, Task, pick
from benchmarks.plan import cluster_address, usable_cpus
from benchmarks.pool import STARTUP_LIMIT, Pool, timing_note
from benchmarks.records import InputError, one_line, provenance

#: Seconds to wait for a scheduler to answer, and for a cluster to have a worker.
CONNECT_LIMIT = 30.0
#: Seconds between looks at the cluster's workers while tasks run.
POLL = 0.25


class _GatherLeftovers(logging.Filter):
    """Drop asyncio's "Task exception was never retrieved" for ``distributed``'s ``AllExit``.

    ``Client._gather`` waits on each key in a task of its own and stops at the first that
    ends without a result; the others then end with ``AllExit``, which nobody retrieves,
    and asyncio logs each with a traceback. It happens when a result is gathered with a
    time limit and its future is cancelled meanwhile (:func:`_outcome`, when a worker
    leaves): an internal leftover of the gather, not an error of the run, which is
    reported as ``error`` with its reason.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        return type(error).__name__ != "AllExit"


logging.getLogger("asyncio").addFilter(_GatherLeftovers())


# ---------------------------------------------------------------------------------------
# The worker side: one pool process per Dask worker
# ---------------------------------------------------------------------------------------

def claim_core() -> tuple[int, bool, object]:
    """A core for the caller, whether it is its own, and the claim (an open lock file, or
    None; the claim lasts until it is closed or the process ends).

    The first usable core whose lock file (in the temporary folder) nobody holds. When
    every core is taken, a core shared with another worker (the timing note says so).
    """
    cpus = usable_cpus()
    for cpu in cpus:
        handle = open(os.path.join(tempfile.gettempdir(), f"driftbench-core-{cpu}.lock"), "w")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        return cpu, True, handle
    return cpus[os.getpid() % len(cpus)], False, None


class _Host:
    """The pool of one Dask worker: a thread of its own drives a :class:`Pool` of one
    worker process, pinned to the claimed core.

    One thread spawns every pool process: Linux ends a child with its parent *thread*
    (``PR_SET_PDEATHSIG``), so that thread must live as long as the Dask worker.
    """

    def __init__(self):
        # A Dask nanny starts its worker with a low malloc trim threshold; inherited by the
        # pool process it slows compilation, and set-up times would differ
        # from the local pool's.
        os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
        self.cpu, self.own, self.claim = claim_core()
        self.version = provenance()["code_version"]
        self.requests: queue.Queue = queue.Queue()
        self.pool: Pool | None = None
        self.thread = threading.Thread(target=self._serve, name="driftbench-host",
                                       daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        with Pool(1, cpus=[self.cpu]) as pool:
            self.pool = pool
            pool.start()
            while (request := self.requests.get()) is not None:
                task, answer = request
                pool.run([task], lambda t, outcome: answer.put(outcome))

    def stop(self) -> None:
        """Stop the pool process, killing a run in flight (whose result nobody awaits any
        more), and give the core back."""
        self.requests.put(None)
        if self.pool is not None:
            self.pool.interrupt()
        self.thread.join()
        if self.claim is not None:
            self.claim.close()

    def perform(self, task: Task) -> Outcome:
        answer: queue.Queue = queue.Queue(maxsize=1)
        self.requests.put((task, answer))
        return answer.get()

    def describe(self) -> dict:
        return {"host": socket.gethostname(), "cpu": self.cpu, "own": self.own,
                "version": self.version}


# One host per Dask worker, by its address: a ``local:N`` cluster runs its workers as
# threads of one process.
_hosts: dict[str, _Host] = {}
_hosts_lock = threading.Lock()


def _host(address: str) -> _Host:
    """The host of the Dask worker at ``address``, started at the first call."""
    with _hosts_lock:
        if address not in _hosts:
            _hosts[address] = _Host()
        return _hosts[address]


def _start_host(dask_worker: distributed.Worker) -> dict:
    """Start this Dask worker's pool (once); say where it runs (``Client.run`` passes the
    worker)."""
    return _host(dask_worker.address).describe()


def _perform(task: Task, version: str) -> Outcome:
    """Carry out ``task`` in this Dask worker's pool, if it runs code version ``version``."""
    host = _host(distributed.get_worker().address)
    if host.version != version:
        where = host.describe()
        return Outcome("fail", message=f"the Dask worker on {where['host']} runs code version "
                                       f"{where['version']}, this batch {version}")
    return host.perform(task)


# ---------------------------------------------------------------------------------------
# The client side
# ---------------------------------------------------------------------------------------

class Cluster:
    """The Dask engine (:class:`benchmarks.executors.Executor`) on ``address``."""

    def __init__(self, address: str):
        self.workers, self.address = cluster_address(address)
        self.local: distributed.LocalCluster | None = None
        self.client: distributed.Client | None = None
        self.hosts: dict[str, dict] = {}
        self._starting: threading.Thread | None = None
        self._failure = ""

    def __enter__(self) -> "Cluster":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        """Start or reach the cluster, and each worker's pool, in the background (while the
        batch validates its input)."""
        self._starting = threading.Thread(target=self._connect, name="driftbench-connect",
                                          daemon=True)
        self._starting.start()

    def _connect(self) -> None:
        try:
            if self.workers is not None:
                # The workers are threads of this process, talking in-process: each runs
                # its runs in a pool process of its own, which gives the isolation, so
                # worker processes would only add start-up and compete for the cores.
                # One thread per worker: a worker runs one run at a time.
                self.local = distributed.LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=False,
                    dashboard_address="127.0.0.1:0",
                    silence_logs=logging.ERROR)
                self.client = distributed.Client(self.local, timeout=CONNECT_LIMIT)
            else:
                self.client = distributed.Client(self.address, timeout=CONNECT_LIMIT)
            self.client.wait_for_workers(1, timeout=CONNECT_LIMIT)
            self.hosts = self.client.run(_start_host)
        except Exception as exc:  # reported by ready(), in the batch's thread
            self._failure = f"{type(exc).__name__}: {exc}"

    def ready(self) -> str:
        """Wait for the cluster; return its scheduler's and dashboard's addresses."""
        self._starting.join()
        if self._failure:
            self.close()
            where = self.address or f"local:{self.workers}"
            raise InputError(one_line(f"cluster {where}: cannot start or reach it, or it has "
                                      f"no worker: {self._failure}"))
        return (f"Dask cluster {self.client.scheduler.address} with {len(self.hosts)} "
                f"workers; dashboard: {self.dashboard()}")

    def dashboard(self) -> str:
        """The dashboard's address. A local cluster's serves on 127.0.0.1 only, where
        ``Client.dashboard_link`` would name the machine's outward address."""
        if self.local is None:
            return self.client.dashboard_link
        port = self.client.scheduler_info()["services"].get("dashboard")
        return f"http://127.0.0.1:{port}/status" if port else "none"

    def note(self, repeats: int) -> str:
        hosts = sorted({h["host"] for h in self.hosts.values()})
        shared = any(not h["own"] for h in self.hosts.values())
        placement = (f"{len(self.hosts)} Dask workers on {len(hosts)} machine(s) "
                     f"({', '.join(hosts)}), each running one run at a time in a process of "
                     f"its own pinned to one core; "
                     + ("some workers share a core, so wall times are inflated by their "
                        "neighbours" if shared else "no two workers on a machine share a core"))
        return timing_note(placement, repeats)

    def run(self, tasks: Iterable[Task], report: Callable[[Task, Outcome], None],
            on_start: Callable[[Task], None] | None = None) -> None:
        """Run ``tasks``, one at a time per worker; report each as it ends."""
        version = provenance()["code_version"]
        queue_ = deque(tasks)
        running: dict[distributed.Future, tuple[Task, str]] = {}
        last: dict[str, object] = {}  # worker -> affinity of its last task
        alone_since = time.monotonic()
        try:
            while queue_ or running:
                workers = set(self.client.nthreads())
                busy = {w for _, w in running.values()}
                for worker in sorted(workers - busy):
                    if not queue_:
                        break
                    task = pick(queue_, last.get(worker),
                                {t.affinity for t, _ in running.values()})
                    future = self.client.submit(
                        _perform, task, version, workers=[worker], allow_other_workers=False,
                        pure=False, key=f"driftbench-{task.id}-{time.time_ns()}")
                    running[future] = (task, worker)
                    last[worker] = task.affinity
                    if on_start is not None:
                        on_start(task)
                if running:
                    with contextlib.suppress(TimeoutError):
                        distributed.wait(list(running), timeout=POLL,
                                         return_when="FIRST_COMPLETED")
                else:
                    time.sleep(POLL)
                for future in [f for f in running if f.done()]:
                    task, worker = running.pop(future)
                    report(task, _outcome(future, worker, self.client.nthreads))
                gone = set(self.client.nthreads())
                for future, (task, worker) in list(running.items()):
                    if worker not in gone:
                        future.cancel()
                        del running[future]
                        report(task, Outcome("died", message=f"the Dask worker {worker} left "
                                             f"the cluster (killed, crashed or lost)",
                                             phase="its run"))
                if gone:
                    alone_since = time.monotonic()
                elif time.monotonic() - alone_since > STARTUP_LIMIT:
                    while queue_:
                        report(queue_.popleft(), Outcome("fail", message=(
                            f"the cluster had no worker for {STARTUP_LIMIT:g} s")))
        finally:
            for future in running:
                future.cancel()

    def close(self) -> None:
        """Disconnect; stop the workers of a cluster this engine started."""
        if self._starting is not None:
            self._starting.join()
        if self.client is not None:
            with contextlib.suppress(Exception):  # closing what may already be gone
                self.client.close()
        if self.local is not None:
            # Its workers are threads of this process: their hosts stop with it.
            with _hosts_lock:
                hosts = [_hosts.pop(a) for a in self.hosts if a in _hosts]
            for host in hosts:
                host.stop()
            with contextlib.suppress(Exception):
                self.local.close()
        self.client = self.local = None


def _outcome(future: distributed.Future, worker: str,
             present: Callable[[], dict]) -> Outcome:
    """How a finished Dask future's task ended; ``present()`` names the workers still there.

    A result lives on the worker that computed it until it is gathered. If that worker dies
    in between, Dask reschedules the task, which is pinned to the dead worker and so would
    never run again: the gather would wait for ever (seen once in ``tests/test_cluster.py``
    with a worker killed right after its run). The gather is therefore retried every
    :data:`POLL` seconds only while the worker is present.
    """
    while True:
        try:
            return future.result(timeout=POLL)
        except TimeoutError:
            if worker not in present():
                future.cancel()
                return Outcome("died", message=f"the Dask worker {worker} left the cluster "
                               f"before its result was collected", phase="its run")
        except Exception as exc:  # the task could not be carried out on the worker
            return Outcome("fail", message=one_line(
                f"Dask worker {worker}: {type(exc).__name__}: {exc}"))
