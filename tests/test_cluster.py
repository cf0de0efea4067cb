"""The Dask engine: a LocalCluster, and a scheduler with two workers started as processes.

Faults come from ``tests/plugins/faulty.py`` (``DRIFTBENCH_TEST_PLUGINS``), which the
client and, through their environment, the Dask workers and their pool processes load. The
runs are short and few: the machine has two cores, shared.
"""

from __future__ import annotations

import csv
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.batch import run_specs
from benchmarks.executors import PLUGIN_ENV, load_plugins
from benchmarks.records import ACCURACY_COLUMNS, CODE_VERSION_ENV, RunSpec
from benchmarks.store import load_runs


# Every test here starts a Dask cluster or scheduler and workers in subprocesses.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"
#: A built-in problem and a user's (loaded from the example file by the client and by
#: every worker).
HEALTHY = [RunSpec("pendulum", "rattle", 0.05, t_end=1.0),
           RunSpec("slider-crank", "lobatto3ab2", 0.1, t_end=1.0)]
SLIDER = str(ROOT / "examples" / "slider_crank.py")


@pytest.fixture(autouse=True)
def plugins(monkeypatch):
    monkeypatch.setenv(PLUGIN_ENV, str(PLUGIN))
    # Client and workers must agree on the code version while the tree is being edited.
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")
    load_plugins()


def children() -> set[int]:
    """The live child processes of this process (from /proc)."""
    pids = set()
    for task in Path("/proc/self/task").iterdir():
        try:
            pids |= {int(p) for p in (task / "children").read_text().split()}
        except FileNotFoundError:  # a thread that ended since the listing: no children
            continue
    return pids


def accuracy(record) -> dict:
    return {c: record.row[c] for c in ACCURACY_COLUMNS}


def integrity(db: Path) -> str:
    with sqlite3.connect(db) as con:
        return con.execute("PRAGMA integrity_check").fetchone()[0]


def test_a_local_cluster_isolates_faults_and_matches_the_local_pool(tmp_path):
    specs = [HEALTHY[0], RunSpec("pendulum", "test-hang", 0.1, t_end=1.0, timeout=5.0),
             RunSpec("pendulum", "test-kill", 0.1, t_end=1.0), HEALTHY[1]]
    before = children()
    records = run_specs(specs, tmp_path / "dask", cluster="local:2", timeout=300.0,
                        load=[SLIDER], log=None)
    # The workers were threads here; their pool processes stopped with the cluster.
    assert children() == before
    status = {r.row["integrator"]: r.row["status"] for r in records}
    assert status == {"rattle": "ok", "test-hang": "timeout", "test-kill": "error",
                      "lobatto3ab2": "ok"}
    message = {r.row["integrator"]: r.row["message"] for r in records}
    # The limit counts from the hand-over to a started pool process, where building the
    # pendulum takes a fraction of a second.
    assert "time limit of 5 s" in message["test-hang"]
    assert "SIGKILL" in message["test-kill"]
    db = tmp_path / "dask" / "driftbench.sqlite"
    assert integrity(db) == "ok" and len(load_runs(db)) == len(specs)
    assert "Dask workers" in load_runs(db)["timing_note"].iloc[0]

    # The same runs in the local pool, bit for bit: each ran in a pool process pinned to
    # a single core with the same thread settings, so nothing may differ.
    alone = run_specs(HEALTHY, tmp_path / "pool", jobs=1, load=[SLIDER], log=None)
    assert [accuracy(r) for r in records if r.row["status"] == "ok"] == \
        [accuracy(r) for r in alone]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(condition, seconds: float, what: str):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.2)
    pytest.fail(f"gave up waiting for {what} after {seconds} s")


def stored(db: Path, sql: str) -> list[tuple]:
    if not db.exists():
        return []
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=30) as con:
        try:
            return con.execute(sql).fetchall()
        except sqlite3.OperationalError:  # the schema is being created
            return []


@pytest.fixture
def scheduler(tmp_path):
    """A Dask scheduler and two workers on 127.0.0.1, as the README starts them (a worker
    each, without a nanny, so that a killed one stays dead); yields the address and the
    worker processes."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = open(tmp_path / "dask.log", "w")
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--dashboard-address", "127.0.0.1:0"],
                              env=env, stdout=logs, stderr=logs, cwd=tmp_path)]
    try:
        for _ in range(2):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "dask", "worker", address, "--nthreads", "1",
                 "--no-nanny", "--host", "127.0.0.1", "--no-dashboard"],
                env=env, stdout=logs, stderr=logs, cwd=tmp_path))
        yield address, procs[1:]
    finally:
        for proc in reversed(procs):
            proc.kill()
            proc.wait(timeout=30)
        logs.close()


def test_a_scheduler_and_workers_survive_a_killed_worker_and_resume(tmp_path, scheduler):
    address, workers = scheduler
    out = tmp_path / "out"
    db = out / "driftbench.sqlite"
    suite = tmp_path / "tcp.toml"
    suite.write_text(
        '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle", "lobatto3ab2"]\n'
        'h = [0.1, 0.05]\nt_end = 1.0\n\n'
        '[[group]]\nproblems = ["pendulum"]\nintegrators = ["test-hang"]\nh = [0.1]\n'
        't_end = 1.0\ntimeout = 2\n')
    command = [sys.executable, "-m", "benchmarks.run", "--suite", str(suite), "--cluster",
               address, "--out", str(out), "--no-report"]
    log = open(tmp_path / "first.log", "w")
    first = subprocess.Popen(command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: len(stored(db, "SELECT id FROM runs")) >= 1, 300, "a stored run")
        before = stored(db, "SELECT run_key, status FROM runs ORDER BY id")
        workers[0].send_signal(signal.SIGKILL)
        assert first.wait(timeout=300) == 1  # the hang ended timeout (or error)
    finally:
        first.kill()
        log.close()
    text = (tmp_path / "first.log").read_text()
    assert "dashboard: http" in text and "Traceback" not in text
    assert integrity(db) == "ok"
    after = stored(db, "SELECT run_key, status, message, integrator FROM runs ORDER BY id")
    # Nothing that finished before the kill is lost or changed, and every run has a row.
    assert [row[:2] for row in after[:len(before)]] == before
    assert len(after) == 5
    lost = [row for row in after if row[1] == "error"]
    # The killed worker held at most one run; it is recorded with the reason. The hang,
    # unless it was that run, reached its time limit on the other worker.
    assert len(lost) <= 1 and all("left the cluster" in row[2] for row in lost)
    hang = next(row for row in after if row[3] == "test-hang")
    assert hang[1] == "timeout" or hang in lost
    unfinished = sum(row[1] in ("error", "timeout") for row in after)

    # --resume on the surviving worker runs again only what did not finish.
    second = subprocess.run([*command, "--resume"], cwd=ROOT, capture_output=True, text=True,
                            timeout=300)
    assert second.returncode == 1, second.stderr  # the hang timed out again
    with open(out / "runs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["status"] for r in rows) == ["ok"] * 4 + ["timeout"]
    redone = stored(db, "SELECT integrator FROM runs WHERE session = 2")
    assert len(redone) == unfinished  # the lost run and the timeout, nothing finished


def test_a_result_lost_with_its_worker_is_a_died_run_not_a_hang():
    # The worker computed the run and died before its result was gathered: Dask reschedules
    # the task on the dead worker alone, so the gather would never return.
    from benchmarks.cluster import _outcome

    class Lost:
        cancelled = False

        def result(self, timeout=None):
            time.sleep(timeout)
            raise TimeoutError

        def cancel(self):
            self.cancelled = True

    future, present = Lost(), iter([{"tcp://a": 1}, {}])
    outcome = _outcome(future, "tcp://a", lambda: next(present))
    assert outcome.state == "died" and "left the cluster" in outcome.message
    assert future.cancelled
