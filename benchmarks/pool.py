"""The local engine: every run executes in a long-lived worker process that the parent can kill.

Why processes
-------------
A run can hang (a Newton iteration that never returns inside compiled code), kill its process
(a segmentation fault in a C extension, an abort, the out-of-memory killer) or raise. None of
that may cost the other runs of a sweep. The parent (:class:`Pool`) hands one task at a time
to each worker over a pipe, waits on the pipes and on the process sentinels at once, and

- kills a worker whose task passes its time limit (``SIGKILL``: compiled code does not
  answer gentler signals), reporting the task as timed out with the phase it was in;
- notices a worker that died (a negative exit code is the signal) and reports its task with
  the exit code or signal and the phase;
- starts a fresh worker in the slot of a killed or dead one, so the sweep goes on.

Why long-lived
--------------
A fresh interpreter pays for importing JAX and for JAX's first-use compilations of every
primitive that building a case touches (seconds). A worker pays that once and
then runs task after task, keeping those caches warm; it is recycled after
:data:`MAX_TASKS_PER_WORKER` tasks to bound the growth of its caches. A worker is a fresh
interpreter (``fork`` + ``exec`` through :mod:`subprocess`, as the ``spawn`` start method
does): JAX is not fork-safe once initialised, and the parent has initialised it while
validating the cases. Unlike ``multiprocessing``'s ``spawn`` it does not re-import the
parent's main module, so a caller's script needs no ``if __name__ == "__main__"`` guard.
The worker gets the parent's ``sys.path`` and talks to it over a socket pair.

Threads and cores
-----------------
Each worker runs with one intra-op thread (XLA, OpenBLAS, MKL, OpenMP: :data:`THREAD_ENV`,
set in the environment the worker starts with, before anything reads it) and pinned to one
core (``sched_setaffinity``): a core of its own when there are at least as many usable
cores as jobs, else the cores in turn. ``N`` jobs on ``N`` cores then never oversubscribe,
a solve's wall time is that of one core, not of a core shared with a neighbouring run, and
every worker compiles for the same single visible core whatever ``jobs`` is (XLA's CPU
code can depend on the cores it sees; accuracy must not depend on ``jobs``).

Workers die with the parent: on Linux through ``PR_SET_PDEATHSIG`` (so a ``SIGKILL`` of the
parent leaves no orphan running an endless task), elsewhere through a watchdog thread.

What a worker does with a task, and the test-only plugins it loads first, are shared with
the Dask engine (:mod:`benchmarks.executors`), which runs one of these pools on each of its
workers.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Callable, Iterable

import jax
import jax.numpy as jnp
import threadpoolctl

import problems
from benchmarks import compilation
from benchmarks.execute import MAX_EXTRA_S, MAX_SOLVES, MIN_TOTAL_S
from benchmarks.executors import Outcome, Task, load_plugins, perform, pick
from benchmarks.plan import usable_cpus
from integrators.loop import kernel_environment

#: One intra-op thread per worker, so that N jobs on N cores do not oversubscribe.
THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}
XLA_THREAD_FLAGS = "--xla_cpu_multi_thread_eigen=false"
#: Workers that share a GPU (ensembles on ``device = gpu`` or ``auto``) allocate its memory
#: as they need it: by default each JAX process takes 75 % of it when it starts, so a
#: second worker would run out. No effect without a GPU.
GPU_ENV = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}

#: A worker is replaced after this many tasks, which bounds the growth of JAX's caches.
MAX_TASKS_PER_WORKER = 200
#: Seconds a new worker may take to import and warm up before it counts as failed to start.
STARTUP_LIMIT = 300.0
#: After this many workers in a row die before they are ready, the remaining tasks fail.
MAX_START_FAILURES = 3


def one_blas_thread() -> None:
    """One BLAS and OpenMP thread in this process from now on, and in the processes it starts.

    OpenBLAS reads :data:`THREAD_ENV` once, when it loads, and a process that has imported
    numpy and scipy (jaxlib's LAPACK calls are scipy's OpenBLAS) has loaded it with a thread
    per core. Under load the second thread waits for a core, spinning, which makes a small
    dense solve far slower than with one thread, and the tests and the
    perf benchmarks would not time what the suite's workers do. The variables cover
    libraries loaded later and child processes; threadpoolctl sets the limit of those
    already loaded.
    """
    os.environ.update(THREAD_ENV)
    threadpoolctl.threadpool_limits(1)


def one_xla_thread() -> None:
    """Create JAX's CPU client now, with one intra-op thread, and leave this process free to
    run on every core it could before.

    XLA sizes the CPU client's thread pool by the cores the process may run on when the
    client is made. jaxlib's LAPACK kernels (LU, Cholesky, QR) split a large batch across
    that pool and block their own pool thread until the pieces are done; two such kernels
    at once on a pool of two threads wait for each other for ever. A vmapped ensemble
    with dense linear algebra does exactly that (``rattle`` on ``chain:N=8`` with 512 to
    4096 lanes can hang with two threads, never with one).
    The pool's workers are pinned to one core and so have one thread already; this gives
    the same to a process that is not pinned (the tests, the perf benchmarks): it is
    pinned to one core while the client is made, then every thread is given back the
    cores it had. Call it before the first computation; later calls do nothing.
    """
    if not hasattr(os, "sched_setaffinity"):
        return
    cpus = os.sched_getaffinity(0)
    if len(cpus) > 1:
        os.sched_setaffinity(0, {min(cpus)})
    try:
        jax.devices()
    finally:
        if len(cpus) > 1:
            # Affinity is per thread, and the client's threads were made under the pin.
            for tid in os.listdir("/proc/self/task"):
                try:
                    os.sched_setaffinity(int(tid), cpus)
                except OSError:  # a thread that has ended since
                    pass


def thread_environment() -> dict[str, str]:
    """The environment variables a worker starts with (thread limits added to ours,
    :data:`GPU_ENV`, and XLA's options, :func:`integrators.loop.xla_options`: time loops
    as one kernel on the CPU, cheaper compiling, while loops in CUDA graphs on a GPU)."""
    flags = kernel_environment()["XLA_FLAGS"]
    return {**THREAD_ENV, **GPU_ENV, "XLA_FLAGS": f"{flags} {XLA_THREAD_FLAGS}".strip()}


def timing_note(placement: str, repeats: int) -> str:
    """The report's sentences on timing, given where the workers ran (``placement``)."""
    load = f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "unknown"
    return (f"Each run executes in a worker process with one intra-op thread (XLA, BLAS); "
            f"{placement}. wall_s is the median of the timed solves after set-up: at least "
            f"{repeats} and {MIN_TOTAL_S:g} s of solving, up to {MAX_SOLVES} solves or "
            f"{MAX_EXTRA_S:g} s of solving after the first (autorange; wall_min_s and wall_max_s their spread; setup_s, timed "
            f"once, includes compilation; near zero for a run that reused what an earlier "
            f"run of the same problem and method compiled in its worker). Not controlled: "
            f"other processes on the machine and shared caches and memory bandwidth; "
            f"1-minute load average at the start: {load}.")


def signal_text(exitcode: int | None) -> str:
    """``exitcode`` of a dead process in words: the signal (with what it usually means) or code."""
    if exitcode is None:
        return "unknown exit status"
    if exitcode >= 0:
        return f"exit code {exitcode}"
    try:
        name = signal.Signals(-exitcode).name
    except ValueError:
        name = f"signal {-exitcode}"
    hint = {
        "SIGKILL": ": killed from outside, often by the out-of-memory killer",
        "SIGSEGV": ": segmentation fault, a crash in compiled code",
        "SIGABRT": ": aborted, typically a failed assertion in compiled code",
        "SIGBUS": ": bus error, a crash in compiled code",
        "SIGFPE": ": arithmetic exception in compiled code",
    }.get(name, "")
    return f"killed by {name}{hint}"


# ---------------------------------------------------------------------------------------
# The child side
# ---------------------------------------------------------------------------------------

def _die_with_parent(parent_pid: int) -> None:
    """End this process when the parent ends, however the parent ends."""
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0) == 0:
            # The parent may have died before prctl took effect.
            if os.getppid() != parent_pid:
                os._exit(1)
            return

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def _warm_up() -> None:
    """Initialise the JAX backend and compile once, so that no task pays the first-use cost."""
    problems.names()
    jax.block_until_ready(jax.jit(lambda x: x * 2.0 + 1.0)(jnp.ones(3)))


def serve(fd: int, parent_pid: int, cpu: int) -> None:
    """Main loop of a worker process: receive a task, send phases and then the result.

    ``fd`` is this end of the socket pair; ``cpu`` the core to pin to (negative: none).
    """
    conn = Connection(fd)
    # Interrupts are the parent's business: it stops its workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    if cpu >= 0:
        os.sched_setaffinity(0, {cpu})
    try:
        # The folder the parent chose reaches us through the environment.
        compilation.enable()
        load_plugins()
        _warm_up()
    except BaseException as exc:
        conn.send(("broken", "".join(traceback.format_exception_only(type(exc), exc)).strip()))
        return
    conn.send(("ready", os.getpid()))
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] == "stop":
            # Everything is sent: skip the interpreter's teardown (JAX's takes most of a
            # second), which the parent would wait for.
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)
        kind, task_id, payload = message
        try:
            result = perform(kind, payload, lambda text: conn.send(("phase", task_id, text)))
            conn.send(("done", task_id, result))
        except Exception as exc:  # a result that cannot be sent, or a defect here
            detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
            conn.send(("fail", task_id, f"worker: {detail}"))


# ---------------------------------------------------------------------------------------
# The parent side
# ---------------------------------------------------------------------------------------

@dataclass
class _Slot:
    cpu: int | None
    proc: subprocess.Popen | None = None
    conn: Connection | None = None
    ready: bool = False
    started: float = 0.0
    task: Task | None = None
    assigned: float = 0.0
    phase: str = ""
    done: int = 0
    affinity: object = None


class Pool:
    """``jobs`` worker slots, each pinned to its own core when there are enough cores.

    Use as a context manager; :meth:`run` hands out tasks and reports each
    :class:`Outcome` through a callback as soon as it is known.
    """

    def __init__(self, jobs: int, cpus: list[int] | None = None):
        if jobs < 1:
            raise ValueError(f"jobs = {jobs} must be at least 1")
        self.cpus = usable_cpus() if cpus is None else cpus
        # Every worker is pinned to one core, even a lone one, so that every worker compiles
        # for the same one visible core whatever ``jobs`` is: XLA's CPU code may depend on
        # the cores it sees, and accuracy must not depend on ``jobs``.
        can_pin = hasattr(os, "sched_setaffinity")
        self.pinned = can_pin and jobs <= len(self.cpus)
        self.slots = [_Slot(self.cpus[i % len(self.cpus)] if can_pin else None)
                      for i in range(jobs)]
        self.start_failures = 0
        self.start_error = ""
        self.interrupted = False

    def note(self, repeats: int) -> str:
        """How this pool keeps wall times honest, in a few sentences for the report."""
        jobs, cpus = len(self.slots), self.cpus
        if jobs == 1:
            placement = f"1 worker process, pinned to core {cpus[0]} of {len(cpus)} usable"
        elif self.pinned:
            placement = (f"{jobs} worker processes, each pinned to a core of its own (cores "
                         f"{', '.join(map(str, cpus[:jobs]))} of {len(cpus)} usable), so no "
                         f"two runs share a core")
        else:
            placement = (f"{jobs} worker processes on {len(cpus)} usable cores: runs share "
                         f"cores, so wall times are inflated by their neighbours")
        return timing_note(placement, repeats)

    def __enter__(self) -> "Pool":
        return self

    def start(self) -> None:
        """Start every worker now (they import and warm up in the background)."""
        for slot in self.slots:
            if slot.proc is None:
                self._spawn(slot)

    def ready(self) -> str:
        """The pool takes tasks at once (a worker that is still warming up gets its task
        when it is ready)."""
        return ""

    def __exit__(self, *exc) -> None:
        self.close()

    def _spawn(self, slot: _Slot) -> None:
        ours, theirs = socket.socketpair()
        env = {**os.environ, **thread_environment(),
               "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        command = (f"from benchmarks.pool import serve; "
                   f"serve({theirs.fileno()}, {os.getpid()}, "
                   f"{-1 if slot.cpu is None else slot.cpu})")
        try:
            # A session of its own: a Ctrl-C in the terminal reaches the parent alone, which
            # stops the workers; a worker that died of it would read as a crashed run.
            slot.proc = subprocess.Popen([sys.executable, "-c", command], env=env,
                                         pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL,
                                         start_new_session=True)
        finally:
            theirs.close()
        slot.conn, slot.ready = Connection(ours.detach()), False
        slot.started, slot.done, slot.phase, slot.affinity = time.monotonic(), 0, "", None

    def _retire(self, slot: _Slot, kill: bool) -> int | None:
        """End the slot's worker (``kill``: at once); return its exit code."""
        code = None
        if slot.proc is not None:
            if kill:
                slot.proc.kill()
            try:
                code = slot.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                slot.proc.kill()
                code = slot.proc.wait()
        if slot.conn is not None:
            slot.conn.close()
        slot.proc, slot.conn, slot.ready = None, None, False
        return code

    def _finish(self, slot: _Slot, outcome: Outcome) -> tuple[Task, Outcome]:
        task = slot.task
        outcome.phase = outcome.phase or slot.phase
        slot.task, slot.phase = None, ""
        return task, outcome

    def _receive(self, slot: _Slot) -> tuple[list[tuple[Task, Outcome]], bool]:
        """Read every message waiting on ``slot``: the tasks that ended, and whether it died."""
        ended = []
        while slot.conn.poll():
            try:
                message = slot.conn.recv()
            except (EOFError, OSError):
                return ended, True
            kind = message[0]
            if kind == "ready":
                slot.ready = True
                self.start_failures = 0
            elif kind == "broken":
                self.start_error = message[1]
            elif kind == "phase" and slot.task is not None and message[1] == slot.task.id:
                slot.phase = message[2]
            elif kind in ("done", "fail") and slot.task is not None and message[1] == slot.task.id:
                outcome = (Outcome("done", result=message[2]) if kind == "done"
                           else Outcome("fail", message=message[2]))
                ended.append(self._finish(slot, outcome))
                slot.done += 1
        return ended, False

    def _pick(self, slot: _Slot, queue: deque) -> Task:
        """Take the next task for ``slot`` off ``queue`` (:func:`executors.pick`)."""
        others = {s.affinity for s in self.slots if s is not slot and s.task is not None}
        return pick(queue, slot.affinity, others)

    def _assign(self, slot: _Slot, queue: deque, on_start) -> None:
        if slot.done >= MAX_TASKS_PER_WORKER:
            slot.conn.send(("stop",))
            self._retire(slot, kill=False)
            self._spawn(slot)
            return
        task = self._pick(slot, queue)
        slot.task, slot.assigned, slot.phase = task, time.monotonic(), "hand-over"
        slot.affinity = task.affinity
        slot.conn.send((task.kind, task.id, task.payload))
        if on_start is not None:
            on_start(task)

    def run(self, tasks: Iterable[Task], report: Callable[[Task, Outcome], None],
            on_start: Callable[[Task], None] | None = None) -> None:
        """Run ``tasks``; call ``report(task, outcome)`` for each as it ends, in any order."""
        queue = deque(tasks)
        while queue or any(s.task is not None for s in self.slots):
            if self.interrupted:
                while queue:
                    report(queue.popleft(), Outcome("fail", message="the pool was stopped"))
                if not any(s.task is not None for s in self.slots):
                    return
            if self.start_failures >= MAX_START_FAILURES:
                why = self.start_error or "the worker process ended before it was ready"
                while queue:
                    report(queue.popleft(), Outcome("fail", message=f"no worker could be "
                                                    f"started ({why})"))
                if not any(s.task is not None for s in self.slots):
                    return
            for slot in self.slots:
                if slot.proc is None and queue and self.start_failures < MAX_START_FAILURES:
                    self._spawn(slot)
                if slot.ready and slot.task is None and queue:
                    self._assign(slot, queue, on_start)
            live = [s for s in self.slots if s.proc is not None]
            if not live:
                continue
            now = time.monotonic()
            limits = [s.assigned + s.task.time_limit - now for s in live
                      if s.task is not None and s.task.time_limit is not None]
            limits += [s.started + STARTUP_LIMIT - now for s in live if not s.ready]
            wait([s.conn for s in live], timeout=max(0.0, min(limits)) if limits else None)
            for slot in live:
                ended, died = self._receive(slot)
                for task, outcome in ended:
                    report(task, outcome)
                now = time.monotonic()
                if died:
                    was_ready = slot.ready
                    code = self._retire(slot, kill=False)
                    if slot.task is not None:
                        report(*self._finish(slot, Outcome(
                            "died", message=f"the worker process died ({signal_text(code)})")))
                    elif not was_ready:
                        self.start_failures += 1
                        self.start_error = self.start_error or signal_text(code)
                elif (slot.task is not None and slot.task.time_limit is not None
                      and now - slot.assigned > slot.task.time_limit):
                    self._retire(slot, kill=True)
                    report(*self._finish(slot, Outcome("timeout")))
                elif not slot.ready and now - slot.started > STARTUP_LIMIT:
                    self._retire(slot, kill=True)
                    self.start_failures += 1
                    self.start_error = f"not ready after {STARTUP_LIMIT:g} s"

    def interrupt(self) -> None:
        """Kill the workers that are running a task; :meth:`run` reports those tasks as
        died, and the tasks not yet started as failed. Safe to call from another thread:
        it sets a flag and sends signals."""
        self.interrupted = True
        for slot in self.slots:
            proc = slot.proc
            if slot.task is not None and proc is not None:
                proc.kill()

    def close(self) -> None:
        """Stop every worker: idle ones are asked to stop, busy or starting ones are killed."""
        for slot in self.slots:
            if slot.proc is None:
                continue
            idle = slot.ready and slot.task is None
            if idle:
                with contextlib.suppress(OSError, ValueError):
                    slot.conn.send(("stop",))
            self._retire(slot, kill=not idle)
