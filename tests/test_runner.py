"""The batch on the local pool: isolation, fault injection, parallel runs, determinism,
resume keys, complete records.

The faulty integrators come from ``tests/plugins/faulty.py``, which the batch and its
workers load when ``DRIFTBENCH_TEST_PLUGINS`` names it.
"""

from __future__ import annotations

import io
import sqlite3
from pathlib import Path

import pytest

import integrators
from benchmarks import suites
from benchmarks.batch import run_specs
from benchmarks.plan import plan
from benchmarks.executors import PLUGIN_ENV, Task, load_plugins, pick
from benchmarks.records import ACCURACY_COLUMNS, CODE_VERSION_ENV, InputError, RunSpec
from benchmarks.store import load_artifacts, load_runs

PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"


@pytest.fixture(autouse=True)
def plugins(monkeypatch):
    monkeypatch.setenv(PLUGIN_ENV, str(PLUGIN))
    # Concurrent edits of the working tree must not change run keys within a test.
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")
    load_plugins()


def accuracy(record) -> dict:
    return {c: record.row[c] for c in ACCURACY_COLUMNS}


HEALTHY = [RunSpec("pendulum", "rattle", 0.05, t_end=1.0),
           RunSpec("sps-receiver", "lobatto3ab3", 0.1, t_end=2.0)]


@pytest.mark.slow
def test_faults_are_contained_and_healthy_runs_match_a_serial_run(tmp_path):
    faulty = [RunSpec("pendulum", "test-hang", 0.1, t_end=1.0, timeout=5.0),
              RunSpec("pendulum", "test-kill", 0.1, t_end=1.0),
              RunSpec("pendulum", "test-abort", 0.1, t_end=1.0),
              RunSpec("pendulum", "test-raise", 0.1, t_end=1.0),
              RunSpec("pendulum", "test-nan", 0.1, t_end=1.0)]
    specs = [faulty[0], HEALTHY[0], *faulty[1:], HEALTHY[1]]
    log = io.StringIO()
    records = run_specs(specs, tmp_path / "mixed", jobs=2, timeout=120.0, log=log,
                        studies=["test-study", "test-study-raise"])
    status = {r.row["integrator"]: r.row["status"] for r in records}
    assert status == {"test-hang": "timeout", "rattle": "ok", "test-kill": "error",
                      "test-abort": "error", "test-raise": "error", "test-nan": "failed",
                      "lobatto3ab3": "ok"}
    message = {r.row["integrator"]: r.row["message"] for r in records}
    # The limit counts from the hand-over to a started worker, where building the pendulum
    # takes a fraction of a second: 5 s is reached in its solve.
    assert "time limit of 5 s during solve" in message["test-hang"]
    assert "SIGKILL" in message["test-kill"] and "SIGABRT" in message["test-abort"]
    assert "injected fault in solve" in message["test-raise"]
    assert "not finite" in message["test-nan"]
    # One log line per run and per study.
    assert sum(line.startswith("[") for line in log.getvalue().splitlines()) == len(specs) + 2

    # Every run, faulty or not, is stored once with its key; the file is consistent.
    db = tmp_path / "mixed" / "driftbench.sqlite"
    with sqlite3.connect(db) as con:
        assert con.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    stored = load_runs(db)
    assert sorted(stored["integrator"]) == sorted(s.integrator for s in specs)
    assert stored["run_key"].notna().all()
    assert stored["timing_note"].str.contains("pinned|share cores").all()

    # The study that works stored its table and figure; the one that raised its message.
    art = load_artifacts(db)
    got = {(a.section, a.name, a.kind) for a in art.itertuples()}
    assert {("test-study", "numbers", "table"), ("test-study", "curve", "figure"),
            ("test-study-raise", "error", "table")} <= got
    error = art[art.section == "test-study-raise"].content.iloc[0]
    assert "injected fault in a study" in error

    # The healthy runs beside the faults equal, bit for bit, a serial run of them alone:
    # same code, same thread settings, so nothing may differ.
    alone = run_specs(HEALTHY, tmp_path / "alone", jobs=1, log=None)
    beside = [r for r in records if r.row["status"] == "ok"]
    assert [accuracy(r) for r in beside] == [accuracy(r) for r in alone]


def determinism_specs() -> list[RunSpec]:
    """Every built-in fixed-step method at one step size, and IDA at a fixed tolerance if
    present. Methods that other tests load from user files are left out: the pool's workers
    have not loaded them."""
    specs = [RunSpec("pendulum", key, 0.02, t_end=1.0) for key in integrators.keys()
             if integrators.REGISTRY[key][0].startswith("integrators.")
             and not integrators.cls_of(key).adaptive]
    if "ida-ggl" in integrators.REGISTRY:
        specs.append(RunSpec("pendulum", "ida-ggl", rtol=1e-8, atol=1e-8, t_end=1.0))
    return specs


@pytest.mark.slow
def test_the_same_runs_twice_give_bit_identical_accuracy(tmp_path):
    # Each run twice in one batch, in whichever worker is free (the fault test above
    # compares runs made in different invocations).
    specs = determinism_specs()
    records = run_specs(specs + specs, tmp_path, jobs=2, log=None)
    first, second = records[:len(specs)], records[len(specs):]
    for spec, a, b in zip(specs, first, second):
        assert a.row["status"] == "ok", (spec, a.row["message"])
        # Deterministic code on the same machine: any difference at all is a defect.
        assert accuracy(a) == accuracy(b), spec.integrator
        assert a.row["run_key"] == b.row["run_key"]


def test_bad_input_raises_before_anything_is_written(tmp_path):
    out = tmp_path / "never"
    with pytest.raises(InputError, match="unknown problem 'pendulm'"):
        run_specs([RunSpec("pendulm", "rattle", 0.1)], out, jobs=1, log=None)
    with pytest.raises(InputError, match="jobs = 0"):
        run_specs(HEALTHY, out, jobs=0, log=None)
    with pytest.raises(InputError, match="unknown study"):
        run_specs(HEALTHY, out, jobs=1, log=None, studies=["flexible-modl"])
    assert not out.exists()


def test_run_key_names_exactly_what_determines_results():
    base = RunSpec("pendulum", "rattle", 0.1, t_end=1.0)
    limit = integrators.make("rattle").options()["newton_max_iter"]
    same = [base, RunSpec("pendulum:L=1.0", f"rattle:newton_max_iter={limit}", 0.1, t_end=1.0),
            RunSpec("pendulum", "rattle", 0.1, t_end=1.0, timeout=5.0)]
    different = [RunSpec("pendulum", "rattle", 0.05, t_end=1.0),
                 RunSpec("pendulum:L=2", "rattle", 0.1, t_end=1.0),
                 RunSpec("pendulum", f"rattle:newton_max_iter={limit + 1}", 0.1, t_end=1.0),
                 RunSpec("pendulum", "rattle", 0.1, t_end=2.0),
                 RunSpec("pendulum", "lobatto3ab2", 0.1, t_end=1.0)]
    keys = [r.run.run_key for r in plan(same + different, "v1")]
    assert len(set(keys[:len(same)])) == 1
    assert len(set(keys)) == 1 + len(different)
    assert plan([base], "v2")[0].run.run_key != keys[0]


def test_suite_timeouts_group_overrides_suite(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text('timeout = 100\n\n[[group]]\nproblems = ["pendulum"]\n'
                    'integrators = ["rattle"]\nh = [0.1]\n\n[[group]]\nproblems = ["pendulum"]\n'
                    'integrators = ["rattle"]\nh = [0.2]\ntimeout = 7\n')
    suite = suites.load(str(path))
    assert [r.timeout for r in suite.runs] == [100.0, 7.0]
    assert suite.runs[1].origin.startswith(f"{path}:8")


def test_runs_of_one_problem_and_method_stay_on_one_worker():
    from collections import deque

    queue = deque(Task(i, "run", None, None, str(i), key)
                  for i, key in enumerate(["b", "a", "c", "b", "a"]))
    # A worker whose last run was of affinity "a", while another worker is on "b": its own
    # affinity first, wherever it stands in the queue ...
    assert [pick(queue, "a", {"b"}).id for _ in range(2)] == [1, 4]
    # ... then the first task no other worker is on, and only then the rest, in order.
    assert [pick(queue, "a-done", {"b"}).id for _ in range(3)] == [2, 0, 3]


@pytest.mark.slow
def test_the_linear_solver_and_pattern_size_are_recorded(tmp_path):
    import csv

    records = run_specs([HEALTHY[0]], tmp_path, jobs=1, log=None)
    row = records[0].row
    # The trajectory names the linear algebra that ran; a run that does not is a defect.
    assert isinstance(row["linear_solver"], str) and row["linear_solver"]
    with open(tmp_path / "runs.csv") as fh:
        written = next(csv.DictReader(fh))
    assert written["linear_solver"] == row["linear_solver"]
    assert written["pattern_nnz"] == ("" if row["pattern_nnz"] is None else str(row["pattern_nnz"]))
    stored = load_runs(tmp_path / "driftbench.sqlite").iloc[0]
    assert stored["linear_solver"] == row["linear_solver"]


def test_a_run_returns_a_complete_record():
    """What the store and the report need is known where the run happens."""
    from benchmarks.drift import SEVERITY, kind_of
    from benchmarks.execute import MAX_SOLVES, MIN_TOTAL_S, execute

    row = execute(RunSpec("pendulum", "rattle", 0.05, t_end=10.0), repeats=2).row
    assert row["status"] == "ok"
    assert row["nominal_order"] == 2 and row["sensitive"] == 0 and row["t0"] == 0.0
    assert row["energy_scale"] == 9.81  # m g L of the unit pendulum
    # RATTLE keeps |g| at round-off and the pendulum's energy error bounded.
    assert kind_of(row["pos_growth"]) == "bounded"
    assert kind_of(row["energy_growth"]) in SEVERITY
    # Autorange: 200 steps take about a millisecond, so the solve is repeated past the
    # two asked for until 0.2 s of solving or ten solves.
    assert 2 <= row["repeats"] <= MAX_SOLVES
    assert row["wall_min_s"] <= row["wall_s"] <= row["wall_max_s"]
    assert row["repeats"] == MAX_SOLVES or row["repeats"] * row["wall_max_s"] >= MIN_TOTAL_S
    chaotic = RunSpec("double-pendulum:energy=high", "rattle", 0.01)
    assert plan([chaotic], "v")[0].run.sensitive == 1


@pytest.mark.parametrize("times, repeats, again", [
    ([0.001], 3, True),                 # fewer than the minimum count
    ([0.001] * 3, 3, True),             # the count is reached, 0.2 s of solving is not
    ([0.001] * 10, 3, False),           # the cap of ten solves
    ([0.1, 0.1, 0.1], 3, False),        # three solves and 0.3 s: enough
    ([0.12, 0.05], 1, True),            # one asked for, 0.2 s not yet reached
    ([2.5], 3, False),                  # a second solve would pass 2 s of extra solving
    ([1.5], 3, True),                   # a second fits,
    ([1.5, 1.5], 3, False),             # a third would not
    ([0.9, 0.9], 3, True),              # a third fits (1.8 s of extra solving)
    ([0.001] * 12, 20, True),           # a count asked for above the cap is honoured
])
def test_autorange_repeats_short_solves_within_its_cap(times, repeats, again):
    from benchmarks.execute import more

    assert more(times, repeats) is again
