"""Processes of the self-benchmarks: one run under a time limit, its peak memory, the C
yardsticks (compiled here, run as children, compared with ours by their final state), and a
benchmark that solves in its own process set up as a worker is (:func:`like_a_worker`).

Peak memory is the program's own high-water mark of resident memory, ``VmHWM`` in
``/proc/PID/status``, read by the program itself at its end or by its parent while it runs.
Not ``ru_maxrss`` (kilobytes on Linux) from ``os.wait4`` or ``RUSAGE_CHILDREN``: Linux keeps
in it the high-water mark of the memory a process had before it started its program, which
for a child is its parent's (a parent holding 400 MB makes ``/bin/true`` peak at 400 MB);
``RUSAGE_CHILDREN`` gives the largest such figure of the waited-for descendants, not a sum.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: The repository root, where child processes start (so that they import this checkout).
ROOT = Path(__file__).resolve().parents[2]
#: The C yardsticks' sources.
YARDSTICKS = Path(__file__).resolve().parent / "yardstick"
#: Seconds between polls of a running child.
POLL = 0.05


def like_a_worker() -> float:
    """Set up this process as the suite's workers are, before it first computes: the
    persistent compilation cache, one intra-op thread and the one-kernel XLA flag
    (:func:`benchmarks.pool.thread_environment`, :func:`benchmarks.pool.one_xla_thread`).
    Returns the 1-minute load average.

    In a process that has computed already (a test calling a benchmark's ``main``) XLA's
    flags stay as they are: XLA read them when the process's client started, so new ones
    would change nothing it compiles, only the keys of the persistent cache (which hash
    ``XLA_FLAGS``), and every later compilation of the process would miss what was
    compiled before under the old ones: in a test process that had run the ensemble
    benchmark's ``main``, a test of the sparse Jacobians compiled 46 programs afresh and
    took 53 s, against 2.5 s with them read from the cache. Such a process is told so on
    stderr, since its timings are not a worker's: a benchmark that computed before calling
    this (resolving its problems) had timed one trajectory without the one-kernel flag, at
    a quarter to a tenth of a worker's rate.
    """
    from jax._src import xla_bridge

    from benchmarks import compilation, pool

    compilation.enable()
    environment = pool.thread_environment()
    if xla_bridge.backends_are_initialized():
        flags = environment.pop("XLA_FLAGS")
        if os.environ.get("XLA_FLAGS") != flags:
            print("note: XLA started before this process was set up as a worker; its "
                  "flags stay as they were, and timings may differ from a worker's",
                  file=sys.stderr)
    os.environ.update(environment)
    pool.one_blas_thread()
    pool.one_xla_thread()
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def timed_solve(solve) -> tuple:
    """One call of a prepared ``solve``: ``(trajectory, wall_s, cpu_s, late_s)``, where
    ``late_s`` is the set-up the call did (a program compiled on first need:
    :func:`integrators.loop.march`), taken out of both times."""
    late = getattr(solve, "late_setup_s", 0.0)
    start, cpu = time.perf_counter(), time.process_time()
    traj = solve()
    late = getattr(solve, "late_setup_s", 0.0) - late
    return (traj, time.perf_counter() - start - late, time.process_time() - cpu - late,
            late)


def timed_run(case, method):
    """``(trajectory, setup_s, wall_s)`` of ``method`` on ``case`` over its horizon: set-up
    (compilation included, also a program the solve compiled on first need) and the solve
    timed apart (:func:`timed_solve`)."""
    from integrators.base import Grid

    start = time.perf_counter()
    solve = method.prepare(case, Grid(case.t0, case.t_end))
    setup = time.perf_counter() - start
    traj, wall, _, late = timed_solve(solve)
    return traj, setup + late, wall


def peak_rss(pid: int | str = "self") -> int | None:
    """Peak resident set of process ``pid`` since its program started (``VmHWM``, bytes);
    None where ``/proc`` does not give it."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def memory_exhausted(text: str) -> bool:
    """Whether an error text says that an allocation failed."""
    return any(s in text for s in ("RESOURCE_EXHAUSTED", "MemoryError", "Out of memory",
                                   "out of memory", "bad_alloc", "Cannot allocate memory"))


def run_process(command: list[str], limit: float,
                env: dict) -> tuple[str, str, str, int | None]:
    """Run ``command`` from the repository root under a wall-clock ``limit`` (seconds).

    Returns ``(ending, stdout, stderr, peak)``: ``ending`` is ``""`` for a normal exit,
    ``"timeout"`` when it was killed at the limit, else how it ended (``"exit code 1"``,
    ``"killed by SIGKILL"``); ``peak`` is the last :func:`peak_rss` read while it ran (read
    just before a kill; a process that reports its own peak at its end is more exact).
    """
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=out, stderr=err, text=True)
        deadline = time.monotonic() + limit
        killed, peak = False, None
        while True:
            # Read before polling: the status of an exited process no longer has VmHWM.
            peak = peak_rss(proc.pid) or peak
            if proc.poll() is not None:
                break
            if time.monotonic() >= deadline:
                proc.kill()
                proc.wait()
                killed = True
                break
            time.sleep(POLL)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    code = proc.returncode
    if killed:
        ending = "timeout"
    elif code < 0:
        ending = f"killed by {signal.Signals(-code).name}"
    else:
        ending = "" if code == 0 else f"exit code {code}"
    return ending, stdout, stderr, peak


def compile_yardstick(name: str, workdir: Path,
                      flags: tuple[str, ...] = ()) -> tuple[Path | None, str, bool]:
    """Compile the C yardstick ``yardstick/NAME.c`` into ``workdir`` with the system C
    compiler (``cc`` or ``gcc`` from ``PATH``, ``-O2``), ``flags`` (include folders,
    libraries) after the source.

    Returns ``(executable or None, note, failed)``: the note is the command and the
    compiler's version, or why there is no executable; ``failed`` is True when a compiler
    exists and the build failed (no compiler is a skip, not a failure).
    """
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        return None, "no C compiler (cc or gcc) on PATH: the C yardstick is skipped", False
    exe = workdir / name
    command = [compiler, "-O2", "-o", str(exe), str(YARDSTICKS / f"{name}.c"), *flags, "-lm"]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        return None, f"{' '.join(command)} failed: {done.stderr.strip()}", True
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True).stdout
    return exe, f"{' '.join(command)}  [{version.splitlines()[0] if version else compiler}]", False


def state_difference(c_state, state, relative: bool = False) -> tuple[float, float]:
    """Max-norm differences of the final positions and of the final velocities of a C
    yardstick and of ours, each given as the stacked ``(q, v)``; with ``relative``, each
    divided by the larger of 1 and the C state's max-norm of ``q`` (of ``v``)."""
    c_state, state = np.asarray(c_state, float), np.asarray(state, float)
    half = len(c_state) // 2
    out = []
    for c, ours in ((c_state[:half], state[:half]), (c_state[half:], state[half:])):
        scale = max(1.0, float(np.max(np.abs(c)))) if relative else 1.0
        out.append(float(np.max(np.abs(c - ours))) / scale)
    return out[0], out[1]
