"""The command line as a process: exit codes, SIGKILL then --resume, SIGTERM.

Each test starts ``python -m benchmarks.run`` with the fault-injection plugin, a pinned code
version (concurrent edits of the tree must not change run keys between two invocations)
and a marker in its environment, by which the test finds the invocation's worker
processes in ``/proc``.
"""

from __future__ import annotations

import csv
import os
import signal
import sqlite3
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from benchmarks.executors import PLUGIN_ENV
from benchmarks.records import CODE_VERSION_ENV

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"
MARKER = "DRIFTBENCH_TEST_MARKER"


def start(args, out: Path, marker: str, stderr) -> subprocess.Popen:
    env = {**os.environ, PLUGIN_ENV: str(PLUGIN), CODE_VERSION_ENV: "test-version",
           MARKER: marker}
    return subprocess.Popen([sys.executable, "-m", "benchmarks.run", *args, "--out", str(out),
                             "--no-report"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=stderr, text=True)


def marked_processes(marker: str) -> list[int]:
    """Processes whose environment holds ``marker`` (the invocation and its workers)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if f"{MARKER}={marker}".encode() in (entry / "environ").read_bytes():
                    found.append(int(entry.name))
            except OSError:  # ended meanwhile, or not ours to read
                pass
    return found


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


def integrity(db: Path) -> str:
    with sqlite3.connect(db) as con:
        return con.execute("PRAGMA integrity_check").fetchone()[0]


@pytest.mark.slow
def test_bad_input_exits_2_with_one_line_and_no_traceback(tmp_path):
    proc = start(["--problems", "pendulm", "--integrators", "rattle"], tmp_path / "out",
                 uuid.uuid4().hex, subprocess.PIPE)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 2
    assert stderr.strip().splitlines() == [stderr.strip()]
    assert "unknown problem 'pendulm'" in stderr and "Traceback" not in stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_sigkill_midway_then_resume_loses_and_redoes_nothing(tmp_path):
    out, marker = tmp_path / "out", uuid.uuid4().hex
    db = out / "driftbench.sqlite"
    suite = tmp_path / "resume.toml"
    # The hang comes last, so the invocation is still running when two runs are stored; its
    # group's time limit applies once the command line no longer overrides it.
    suite.write_text('[[group]]\nproblems = ["pendulum"]\n'
                     'integrators = ["rattle", "lobatto3ab2", "lobatto3ab3"]\nh = [0.1]\n'
                     't_end = 0.5\n\n[[group]]\nproblems = ["pendulum"]\n'
                     'integrators = ["test-hang"]\nh = [0.1]\nt_end = 0.5\ntimeout = 2\n')
    args = ["--suite", str(suite), "--jobs", "1"]
    log = tmp_path / "first.log"
    with open(log, "w") as fh:
        first = start([*args, "--timeout", "600"], out, marker, fh)
        wait_for(lambda: len(stored(db, "SELECT id FROM runs")) >= 2, 240, "two stored runs")
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=30)
    # The workers die with their parent: nothing of the invocation keeps running.
    wait_for(lambda: not marked_processes(marker), 20, "the workers to end")
    assert integrity(db) == "ok"
    before = stored(db, "SELECT run_key, status, integrator FROM runs ORDER BY id")
    assert before and all(status == "ok" for _, status, _ in before)
    # Every run the log reported finished is in the store.
    logged = [line for line in log.read_text().splitlines() if ": ok" in line]
    assert len(logged) <= len(before)

    second = start([*args, "--resume"], out, marker, subprocess.PIPE)
    stdout, stderr = second.communicate(timeout=300)
    assert second.returncode == 1, stderr  # the hang ended timeout again: no result
    assert integrity(db) == "ok"
    after = stored(db, "SELECT run_key, status, integrator, session FROM runs ORDER BY id")
    assert [row[:3] for row in after[:len(before)]] == before  # nothing lost or changed
    redone = {key for key, _, _, session in after if session == 2} & {k for k, _, _ in before}
    assert not redone
    by_integrator = {}
    for key, status, integrator, _ in after:
        by_integrator.setdefault(integrator, []).append(status)
    assert by_integrator == {"rattle": ["ok"], "lobatto3ab2": ["ok"], "lobatto3ab3": ["ok"],
                             "test-hang": ["timeout"]}
    # runs.csv of the resumed invocation lists every run of the suite, in order.
    with open(out / "runs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["integrator"], r["status"]) for r in rows] == [
        ("rattle", "ok"), ("lobatto3ab2", "ok"), ("lobatto3ab3", "ok"), ("test-hang", "timeout")]
    assert f"{len(before)} of 4 runs are finished" in stderr


@pytest.mark.parametrize("engine", [["--jobs", "1"], ["--cluster", "local:1"]],
                         ids=["pool", "dask"])
@pytest.mark.slow
def test_sigterm_stops_the_workers_and_keeps_the_store(engine, tmp_path):
    out, marker = tmp_path / "out", uuid.uuid4().hex
    db = out / "driftbench.sqlite"
    proc = start(["--problems", "pendulum", "--integrators", "rattle", "test-hang", "--h",
                  "0.1", "--t-end", "0.5", "--timeout", "600", *engine], out, marker,
                 subprocess.PIPE)
    wait_for(lambda: len(stored(db, "SELECT id FROM runs")) >= 1, 240, "a finished run")
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130
    assert "interrupted (SIGTERM)" in stderr and "Traceback" not in stderr
    # 60 s: a Dask cluster takes seconds to close its workers on a loaded machine.
    wait_for(lambda: not marked_processes(marker), 60, "the workers to end")
    assert integrity(db) == "ok"
    assert stored(db, "SELECT integrator, status FROM runs") == [("rattle", "ok")]


@pytest.mark.slow
def test_suite_time_holds_each_suite_to_its_budget(tmp_path, capsys):
    import json

    from benchmarks.perf import suite_time

    body = ('[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\nh = [0.01]\n'
            't_end = 1.0\n')
    roomy, tight = tmp_path / "roomy.toml", tmp_path / "tight.toml"
    roomy.write_text(f"budget = 600\nrepeats = 1\n{body}")
    tight.write_text(f"budget = 0.01\nrepeats = 1\n{body}")
    out = tmp_path / "out"
    assert suite_time.main([str(roomy), str(tight), "--jobs", "1", "--out", str(out)]) == 1
    results = {Path(r["suite"]).stem: r for r in
               json.loads((out / "suite_time.json").read_text())}
    for name in ("roomy", "tight"):
        assert results[name]["exit"] == 0 and results[name]["statuses"] == {"ok": 1}
    assert results["roomy"]["within"] and not results["tight"]["within"]
    assert "OVER BUDGET" in capsys.readouterr().out
