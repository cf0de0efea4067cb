"""Nothing lost, nothing falsely green: the store, runs.csv and the command line under
damaged, foreign and read-only files, full disks, oversized input, interruptions and
concurrent invocations.

Every test uses real files under ``tmp_path``. A full or read-only file system is a small
tmpfs mounted for the test; where mounting is not allowed (no root) those tests skip.
"""

from __future__ import annotations

import csv
import errno
import hashlib
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

import problems
from benchmarks import run
from benchmarks.audit import explain
from benchmarks.executors import PLUGIN_ENV
from benchmarks.files import FolderLock, replace_file
from benchmarks.records import CODE_VERSION_ENV
from benchmarks.store import (APPLICATION_ID, DamagedStore, ForeignFile, Store, StoreError,
                              identify, load_runs, load_series)
from test_store import record

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"
PY = sys.executable
GOOD = ["--problems", "pendulum", "--integrators", "rattle", "--h", "0.1", "--t-end", "0.5",
        "--jobs", "1", "--no-report"]


@pytest.fixture(autouse=True)
def plugins(monkeypatch):
    monkeypatch.setenv(PLUGIN_ENV, str(PLUGIN))
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def one_error_line(err: str) -> str:
    """The one line of an error on stderr (no traceback)."""
    assert "Traceback" not in err
    lines = [line for line in err.strip().splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def tmpfs(tmp_path):
    """Mount a small tmpfs; yields a function ``(size, read_only=False) -> Path``."""
    mounted = []

    def mount(size: str, read_only: bool = False, fill=None) -> Path:
        point = tmp_path / f"mnt{len(mounted)}"
        point.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                               str(point)], capture_output=True)
        if done.returncode != 0:
            pytest.skip("cannot mount a tmpfs here (needs root)")
        mounted.append(point)
        if fill is not None:
            fill(point)
        if read_only:
            subprocess.run(["mount", "-o", "remount,ro", str(point)], check=True)
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", "-l", str(point)], check=False)


def make_store(path: Path, runs: int = 3) -> None:
    with Store(path) as store:
        session = store.begin("test")
        for _ in range(runs):
            store.add(session, record())


# --------------------------------------------------------------------------- store files

def _truncated(path):
    make_store(path, 20)
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2 + 100])


def _damaged_pages(path):
    make_store(path, 20)
    data = bytearray(path.read_bytes())
    for offset in range(3 * 4096, len(data), 4096):  # past the schema: the runs' pages
        data[offset:offset + 200] = b"\xab" * 200
    path.write_bytes(bytes(data))


def _foreign_tables(path):
    with sqlite3.connect(path) as con:
        con.execute("CREATE TABLE photos (id INTEGER PRIMARY KEY, name TEXT)")
        con.execute("INSERT INTO photos (name) VALUES ('beach')")
    con.close()


def _foreign_id_with_our_tables(path):
    make_store(path)
    with sqlite3.connect(path) as con:
        con.execute("PRAGMA journal_mode=DELETE")
        con.execute("PRAGMA application_id = 1234")
    con.close()


def _altered(*statements):
    """A store of ours, then ``statements`` run on it (a table or column dropped)."""
    def spoil(path):
        make_store(path)
        with sqlite3.connect(path) as con:
            con.execute("PRAGMA journal_mode=DELETE")
            for statement in statements:
                con.execute(statement)
        con.close()
    return spoil


BAD_FILES = [
    ("empty", lambda p: p.write_bytes(b""), DamagedStore, "empty"),
    ("truncated", _truncated, DamagedStore, "damaged"),
    ("overwritten", lambda p: p.write_bytes(b"results,of,another,tool\n" * 200), ForeignFile,
     "not an SQLite file"),
    ("damaged-pages", _damaged_pages, DamagedStore, "damaged"),
    ("foreign-sqlite", _foreign_tables, ForeignFile, "photos"),
    ("foreign-application-id", _foreign_id_with_our_tables, ForeignFile, "0x4d2"),
    ("missing-table", _altered("DROP TABLE series"), DamagedStore, "no table series"),
    ("missing-column", _altered('ALTER TABLE runs DROP COLUMN "status"'), DamagedStore,
     "no column runs.status"),
]


@pytest.mark.parametrize("spoil, kind, words", [b[1:] for b in BAD_FILES],
                         ids=[b[0] for b in BAD_FILES])
def test_damaged_and_foreign_store_files_are_refused_and_left_as_they_were(
        spoil, kind, words, tmp_path):
    path = tmp_path / "driftbench.sqlite"
    spoil(path)
    before = digest(path)
    for open_it in (Store, load_runs):
        with pytest.raises(kind) as caught:
            open_it(path)
        message = str(caught.value)
        assert "\n" not in message and str(path) in message and words in message
        assert "move it aside" in message
    assert digest(path) == before


def test_a_series_whose_shape_does_not_fit_its_data_is_a_damaged_store(tmp_path):
    path = tmp_path / "driftbench.sqlite"
    _altered("UPDATE series SET shape = '[7, 3]' WHERE name = 'sample:q'")(path)
    with pytest.raises(DamagedStore, match="series 'sample:q' of run 1: ValueError"):
        load_series(path, 1)


def test_the_command_line_refuses_a_damaged_store_with_one_line(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    _damaged_pages(out / "driftbench.sqlite")
    before = digest(out / "driftbench.sqlite")
    assert run.main([*GOOD, "--out", str(out)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "damaged results store" in line and "driftbench.sqlite" in line
    assert digest(out / "driftbench.sqlite") == before
    assert not (out / "runs.csv").exists()


def test_a_store_written_before_the_application_id_opens_and_gets_it(tmp_path):
    path = tmp_path / "driftbench.sqlite"
    make_store(path)
    with sqlite3.connect(path) as con:  # what this code wrote before it set the id
        con.execute("PRAGMA application_id = 0")
    con.close()
    before = digest(path)
    assert identify(path) == 0 and len(load_runs(path)) == 3
    assert digest(path) == before  # a reader does not set it
    make_store(path, 1)
    assert identify(path) == APPLICATION_ID and len(load_runs(path)) == 4


def test_a_new_store_is_created_whole_or_not_at_all(tmp_path, monkeypatch):
    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "link", full)
    with pytest.raises(OSError):
        Store(tmp_path / "driftbench.sqlite")
    assert list(tmp_path.iterdir()) == []  # no empty store, no temporary file


def test_a_store_in_a_read_only_folder_is_readable(tmpfs):
    folder = tmpfs("4m", read_only=True, fill=lambda p: make_store(p / "driftbench.sqlite"))
    runs = load_runs(folder / "driftbench.sqlite")
    assert list(runs["problem"]) == ["pendulum"] * 3


# --------------------------------------------------------------------------- runs.csv

def test_a_failed_write_on_a_full_disk_leaves_the_old_file_and_no_temporary(tmpfs):
    folder = tmpfs("64k")
    target = folder / "runs.csv"
    replace_file(target, "old\n")
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as fh:  # fill the file system to its last block
        try:
            while True:
                fh.write(b"x" * 4096)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    with pytest.raises(OSError) as caught:
        replace_file(target, "new\n" * 100_000)
    assert caught.value.errno == errno.ENOSPC
    assert target.read_text() == "old\n"
    assert sorted(p.name for p in folder.iterdir()) == ["filler", "runs.csv"]


@pytest.mark.slow
def test_a_store_that_fails_midway_loses_no_run_from_runs_csv(tmp_path, capsys, monkeypatch):
    def full(self, session, record):
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(Store, "add", full)
    out = tmp_path / "out"
    argv = ["--problems", "pendulum", "--integrators", "rattle", "--h", "0.1", "0.05",
            "--t-end", "0.5", "--jobs", "1", "--no-report", "--out", str(out)]
    assert run.main(argv) == 2
    err = capsys.readouterr().err
    final = err.strip().splitlines()[-1]
    assert final.startswith("error: not every result was written") and "disk is full" in final
    with open(out / "runs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["h"], r["status"]) for r in rows] == [("0.1", "ok"), ("0.05", "ok")]
    assert not (out / "runs.partial.csv").exists()


def test_a_second_invocation_on_a_folder_in_use_is_refused(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "runs.csv").write_text("the other invocation's rows\n")
    lock = FolderLock(out)
    lock.acquire()
    try:
        assert run.main([*GOOD, "--out", str(out)]) == 2
    finally:
        lock.release()
    line = one_error_line(capsys.readouterr().err)
    assert "being written by another invocation" in line and f"process {os.getpid()}" in line
    assert (out / "runs.csv").read_text() == "the other invocation's rows\n"


@pytest.mark.slow
def test_duplicate_runs_run_once(tmp_path):
    out = tmp_path / "out"
    # The same run three times: twice as written, once with its default parameter spelled out.
    argv = ["--problems", "pendulum", "pendulum:L=1.0", "--integrators", "rattle", "--h",
            "0.1", "0.1", "--t-end", "0.5", "--jobs", "1", "--no-report", "--out", str(out)]
    assert run.main(argv) == 0
    with open(out / "runs.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 1
    assert len(load_runs(out / "driftbench.sqlite")) == 1


# --------------------------------------------------------------------------- size guard

@pytest.mark.slow
def test_an_oversized_problem_exits_2_with_one_line_in_little_memory(tmp_path):
    # A wrapper process measures the peak memory of the command line and its workers
    # alone (RUSAGE_CHILDREN of the wrapper).
    wrapper = ("import resource, subprocess, sys; "
               "done = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
               "print(done.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss);"
               "print(done.stderr, file=sys.stderr)")
    env = {**os.environ, PLUGIN_ENV: str(PLUGIN)}
    done = subprocess.run([PY, "-c", wrapper, PY, "-m", "benchmarks.run", "--problems",
                           "chain:N=1000000000", "--integrators", "rattle", "--jobs", "1",
                           "--out", str(tmp_path / "out")], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    code, peak_kib = map(int, done.stdout.split())
    assert code == 2
    line = one_error_line(done.stderr)
    assert "N = 1000000000" in line and "size limit of 100000" in line and "--allow-large" in line
    assert peak_kib < 1024 * 1024
    assert not (tmp_path / "out").exists()


def test_size_limits_count_whole_number_parameters_but_seeds():
    problems.check_size("sps-lattice:N=64,K=40,seed=123456789")  # the scaling suite's largest
    with pytest.raises(problems.SizeError, match=r"N \* K = 1000 \* 1000 = 1000000"):
        problems.check_size("sps-lattice:N=1000,K=1000")


def test_a_run_of_too_many_steps_is_refused_naming_the_option(tmp_path, capsys):
    argv = ["--problems", "pendulum", "--integrators", "rattle", "--h", "1e-9", "--t-end", "1",
            "--jobs", "1", "--out", str(tmp_path / "out")]
    assert run.main(argv) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "about 1e+09 steps" in line and "limit of 1e+08 steps" in line
    assert "--allow-large" in line
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- smaller items

def test_jax_errors_keep_their_message_not_jax_note():
    import jax

    with pytest.raises(OverflowError) as caught:
        jax.jit(lambda x: x)(99999999999999999999)
    assert caught.value.__notes__  # JAX's note about its removed frames is there
    message = explain(caught.value)
    assert "OverflowError: An overflow was encountered" in message and "removed" not in message


@pytest.mark.parametrize("spec", ["pendulum:L=1,L=2", "pendulum: L=1 , L =2"])
def test_a_parameter_given_twice_is_refused(spec, tmp_path, capsys):
    argv = ["--problems", spec, "--integrators", "rattle", "--out", str(tmp_path / "out")]
    assert run.main(argv) == 2
    assert "'L' is given twice" in one_error_line(capsys.readouterr().err)


def test_a_deeply_nested_suite_file_is_refused_on_one_line(tmp_path, capsys):
    suite = tmp_path / "deep.toml"
    suite.write_text("description = " + "[" * 100_000 + "]" * 100_000 + "\n")
    assert run.main(["--suite", str(suite), "--out", str(tmp_path / "out")]) == 2
    assert "nested too deeply" in one_error_line(capsys.readouterr().err)


def _start(argv, out: Path, **extra) -> subprocess.Popen:
    env = {**os.environ, PLUGIN_ENV: str(PLUGIN), CODE_VERSION_ENV: "test-version"}
    return subprocess.Popen([PY, "-m", "benchmarks.run", *argv, "--out", str(out),
                             "--no-report"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **extra)


def _wait_for(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.1)


@pytest.mark.slow
def test_ctrl_c_during_validation_exits_130(tmp_path):
    started = tmp_path / "building"
    slow = tmp_path / "slow_problem.py"
    slow.write_text(
        "import time\nfrom pathlib import Path\nimport problems\n"
        "from problems.pendulum import pendulum\n\n"
        "@problems.register('test-slow-build')\n"
        "def slow(t_end: float = 1.0):\n"
        f"    Path({str(started)!r}).write_text('yes')\n"
        "    time.sleep(60)\n"
        "    return pendulum()\n")
    proc = _start(["--load", str(slow), "--problems", "test-slow-build", "--integrators",
                   "rattle", "--jobs", "1"], tmp_path / "out")
    _wait_for(started.exists, 120, "validation to start")
    os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole group
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted (SIGINT): no run had finished" in err and "Traceback" not in err


@pytest.mark.slow
def test_ctrl_c_while_the_report_is_written_keeps_the_runs_and_exits_130(
        tmp_path, monkeypatch, capsys):
    """The signal handlers stay in place until the report is written: an interrupt there
    is one line and status 130, not a traceback (SIGINT) or a silent death that left the
    figure workers behind (SIGTERM)."""
    import reports

    def interrupted(*args, **kwargs):
        run._interrupt(signal.SIGTERM, None)

    monkeypatch.setattr(reports, "build", interrupted)
    assert run.main([*GOOD[:-1], "--out", str(tmp_path)]) == 130  # with the report
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith(
        "interrupted (SIGTERM) while writing the report: every run is in ")
    assert f"python -m reports --db {tmp_path / 'driftbench.sqlite'}" in err
    with open(tmp_path / "runs.csv") as fh:
        assert [r["status"] for r in csv.DictReader(fh)] == ["ok"]


@pytest.mark.slow
def test_an_interrupted_resume_keeps_the_skipped_runs_in_runs_csv(tmp_path):
    out = tmp_path / "out"
    first = ["--problems", "pendulum", "--integrators", "rattle", "lobatto3ab2", "--h", "0.1",
             "--t-end", "0.5", "--jobs", "1"]
    # The finished runs may come from this process: only the resumed batch is interrupted.
    assert run.main([*first, "--out", str(out), "--no-report"]) == 0
    # The same runs and one that hangs: the resumed batch skips two and runs the third.
    proc = _start([*first[:5], "test-hang", *first[5:], "--resume"], out)
    _wait_for(lambda: proc.poll() is not None or _sessions(out) == 2, 240,
              "the resumed batch to start")
    time.sleep(1)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    with open(out / "runs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["integrator"], r["status"]) for r in rows] == [("rattle", "ok"),
                                                              ("lobatto3ab2", "ok")]


def _sessions(out: Path) -> int:
    """Sessions in the store under ``out`` (a batch opens one once it starts running)."""
    try:
        with sqlite3.connect(f"file:{out / 'driftbench.sqlite'}?mode=ro", uri=True) as con:
            return con.execute("SELECT count(*) FROM sessions").fetchone()[0]
    except sqlite3.Error:
        return 0
