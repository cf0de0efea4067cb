"""The results store: round trip, resume keys, study artifacts, old versions, killed writers."""

import json
import os
import sqlite3
import subprocess
import sys
import textwrap

import numpy as np
import pandas as pd
import pytest

from benchmarks.records import COLUMNS, Record
from benchmarks.store import (SCHEMA_VERSION, Store, StoreError, artifact_table, load_artifacts,
                              load_runs, load_series)


def record(problem="pendulum", integrator="rattle", status="ok", run_key=None, **extra):
    """A synthetic run: 2-D samples, a NaN metric and a JSON column, as a run records them."""
    row = {c: None for c in COLUMNS}
    row.update(problem=problem, integrator=integrator, h=0.01, t_end=10.0, status=status,
               message="" if status == "ok" else "Newton failed at step 3",
               n_steps=1000, max_pos_residual=1.5e-15, rel_energy_error=float("nan"),
               q_final=json.dumps([0.5, -0.25]), options=json.dumps({"h": 0.01}),
               nominal_order=2, sensitive=0, t0=0.0, energy_scale=9.81,
               linear_solver="dense", pos_growth="bounded (round-off)")
    row["run_key"] = run_key
    row.update(extra)
    t = np.linspace(0.0, 10.0, 11)
    samples = {"t": t, "q": np.stack([np.cos(t), np.sin(t)], axis=1),
               "v": np.stack([-np.sin(t), np.cos(t)], axis=1)}
    windows = {"t": t[1:], "pos": np.full(10, 1e-15), "vel": np.zeros(10),
               "energy": np.geomspace(1e-10, 1e-6, 10)}
    return Record.from_row(row, windows, samples)


def test_a_run_round_trips_with_provenance_and_series(tmp_path):
    path = tmp_path / "driftbench.sqlite"
    rec = record()
    with Store(path) as st:
        session = st.begin("unit")
        run = st.add(session, rec)
    runs = load_runs(path)
    assert len(runs) == 1
    assert set(COLUMNS) <= set(runs.columns)
    row = runs.iloc[0]
    assert row["run_id"] == run and row["suite"] == "unit" and row["problem"] == "pendulum"
    for column in ("commit", "dirty", "machine", "python", "versions", "session_started",
                   "recorded"):
        assert column in runs.columns
    assert "numpy" in json.loads(row["versions"])
    assert row["max_pos_residual"] == 1.5e-15  # stored as float64: bit-exact
    assert np.isnan(row["rel_energy_error"])  # NaN goes in as NULL and comes back missing
    # What the run knew comes back as it was recorded.
    assert row["nominal_order"] == 2 and row["sensitive"] == 0 and row["energy_scale"] == 9.81
    assert row["linear_solver"] == "dense" and row["pos_growth"] == "bounded (round-off)"
    series = load_series(path, run)
    for group in ("windows", "samples"):
        src = getattr(rec, group)
        assert set(series[group]) == set(src)
        for key, array in src.items():
            assert series[group][key].dtype == np.float64
            np.testing.assert_array_equal(series[group][key], array)
    assert series["samples"]["q"].shape == (11, 2)


def test_the_store_writes_records_without_importing_problems_or_integrators(tmp_path):
    """Layering: the record is complete, so writing and reading it needs no JAX."""
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_store import record
        from benchmarks.store import Store, load_runs
        with Store({str(tmp_path / "s.sqlite")!r}) as st:
            st.add(st.begin("unit"), record(problem="double-pendulum:energy=high", sensitive=1))
        assert load_runs({str(tmp_path / "s.sqlite")!r}).iloc[0]["sensitive"] == 1
        print(sorted(m for m in ("integrators", "problems", "jax") if m in sys.modules))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_finished_keys_leave_out_errors_and_timeouts(tmp_path):
    with Store(tmp_path / "s.sqlite") as st:
        session = st.begin("unit")
        for key, status in (("a", "ok"), ("b", "failed"), ("c", "error"), ("d", "timeout"),
                            ("e", "skipped")):
            st.add(session, record(status=status, run_key=key))
        st.add(session, record(status="ok", run_key=None))
        assert st.finished_keys() == {"a", "b", "e"}


def test_study_tables_and_figures_round_trip(tmp_path):
    path = tmp_path / "s.sqlite"
    table = pd.DataFrame({"mode": [1, 2], "f_hz": [0.1 + 0.2, 1.0 / 3.0], "note": ["x", "y"]})
    svg = '<svg xmlns="http://www.w3.org/2000/svg" width="10" height="10"></svg>'
    with Store(path) as st:
        session = st.begin("study")
        st.add_table(session, "flexible-modal", "frequencies", table)
        st.add_figure(session, "flexible-modal", "modes", svg)
        with pytest.raises(ValueError):
            st.add_figure(session, "flexible-modal", "bad", "not an image")
    arts = load_artifacts(path)
    assert list(arts["kind"]) == ["table", "figure"]
    back = artifact_table(arts.iloc[0]["content"])
    assert list(back.columns) == ["mode", "f_hz", "note"]
    assert back["f_hz"].tolist() == table["f_hz"].tolist()  # JSON floats round-trip exactly
    assert arts.iloc[1]["content"] == svg


# The schema of version 1 (the first committed store), written by hand as an old file would be.
V1_COLUMNS = ["problem", "integrator", "h", "rtol", "atol", "t_end", "status", "message",
              "n_steps", "n_rejected", "n_f_evals", "n_jac_evals", "n_newton", "n_lin_solves",
              "wall_s", "setup_s", "max_pos_residual", "max_vel_residual", "max_energy_error",
              "rel_energy_error", "final_state_error", "scd", "t_final", "q_final", "v_final",
              "invariant_errors", "sampling", "fail_step", "fail_time", "callback_s",
              "repeats", "options", "params"]
V1_SCHEMA = f"""
    CREATE TABLE sessions (id INTEGER PRIMARY KEY, suite TEXT, started REAL, commit_sha TEXT,
                           dirty INTEGER, machine TEXT, python TEXT, versions TEXT);
    CREATE TABLE runs (id INTEGER PRIMARY KEY, session INTEGER REFERENCES sessions(id),
                       {", ".join(f'"{c}"' for c in V1_COLUMNS)});
    CREATE TABLE series (run INTEGER REFERENCES runs(id), name TEXT, data BLOB,
                         PRIMARY KEY (run, name));
    PRAGMA user_version = 1;
"""


def write_v1(path):
    rec = record()
    db = sqlite3.connect(path)
    db.executescript(V1_SCHEMA)
    db.execute("INSERT INTO sessions (suite, started, commit_sha, dirty, machine, python, "
               "versions) VALUES ('old', 0.0, 'abc', 0, 'm', '3.11', '{}')")
    cols = ", ".join(f'"{c}"' for c in V1_COLUMNS)
    db.execute(f"INSERT INTO runs (session, {cols}) VALUES (1, {', '.join('?' * len(V1_COLUMNS))})",
               [rec.row[c] for c in V1_COLUMNS])
    arrays = {**{f"window:{k}": v for k, v in rec.windows.items()},
              **{f"sample:{k}": v for k, v in rec.samples.items()}}
    db.executemany("INSERT INTO series VALUES (1, ?, ?)",
                   [(k, np.asarray(v, "<f8").tobytes()) for k, v in arrays.items()])
    db.commit()
    db.close()
    return rec


def test_version_1_files_load_without_being_modified(tmp_path):
    path = tmp_path / "old.sqlite"
    rec = write_v1(path)
    runs = load_runs(path)
    assert len(runs) == 1 and runs.iloc[0]["suite"] == "old"
    series = load_series(path, 1)
    # Version 1 stored samples flat; the migration restores their shape from sample:t.
    np.testing.assert_array_equal(series["samples"]["q"], rec.samples["q"])
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 1  # readers never write


def test_a_writer_migrates_version_1_in_place_and_appends(tmp_path):
    path = tmp_path / "old.sqlite"
    write_v1(path)
    with Store(path) as st:
        st.add(st.begin("new"), record(run_key="k"))
        assert st.finished_keys() == {"k"}
    with sqlite3.connect(path) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    runs = load_runs(path)
    assert list(runs["suite"]) == ["old", "new"]
    assert np.isnan(runs.iloc[0]["nominal_order"])  # not known for migrated rows


def test_a_run_stored_without_the_spread_of_its_solves_reads_as_one_solve(tmp_path):
    """Version 2 -> 3: a run recorded before the spread was kept gets it from its one
    known time, which the report shows as one solve."""
    from reports.analysis import timing

    path = tmp_path / "old.sqlite"
    write_v1(path)
    with sqlite3.connect(path) as db:
        db.execute("UPDATE runs SET wall_s = 2.0, repeats = NULL")
    row = load_runs(path).iloc[0]
    assert (row["wall_min_s"], row["wall_max_s"], row["repeats"]) == (2.0, 2.0, 1)
    t = timing(row)
    assert (t.low, t.high, t.repeats, t.measured) == (2.0, 2.0, 1, False)


def test_version_5_ensembles_lose_lane_0s_final_error_and_single_runs_keep_theirs(tmp_path):
    """Version 5 -> 6: an ensemble's final error, scd and floor were lane 0's and are now
    the worst lane's, so the migration empties them rather than let the history compare
    the two; a single run's stay."""
    path = tmp_path / "old.sqlite"
    final = dict(final_state_error=8.2e-14, scd=12.5, reference_floor=1e-15)
    with Store(path) as st:
        session = st.begin("old")
        st.add(session, record(run_key="single", **final))
        st.add(session, record(run_key="ensemble", lanes=8, seed=1, **final))
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version = 5")
    with Store(path):
        pass
    runs = load_runs(path).set_index("run_key")
    for column, value in final.items():
        assert runs.loc["single", column] == value
        assert np.isnan(runs.loc["ensemble", column])


def test_whole_numbers_stored_as_reals_are_migrated_to_integers(tmp_path):
    """runs.csv of a resumed batch lists a count as 1000, not 1000.0, whoever stored it."""
    path = tmp_path / "old.sqlite"
    write_v1(path)
    with sqlite3.connect(path) as db:
        db.execute("UPDATE runs SET n_steps = 1000.0")
    with Store(path):
        pass
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT typeof(n_steps), n_steps FROM runs").fetchone() == \
            ("integer", 1000)


def test_newer_versions_and_missing_files_are_refused(tmp_path):
    path = tmp_path / "new.sqlite"
    with sqlite3.connect(path) as db:
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(StoreError, match="newer"):
        load_runs(path)
    with pytest.raises(StoreError, match="newer"):
        Store(path)
    with pytest.raises(StoreError, match="no results store"):
        load_runs(tmp_path / "absent.sqlite")


def test_a_killed_writer_keeps_every_finished_run(tmp_path):
    """SIGKILL in the middle of a run's transaction loses that run only."""
    path = tmp_path / "s.sqlite"
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_store import record
        from benchmarks.store import Store
        st = Store({str(path)!r})
        session = st.begin("killed")
        for i in range(3):
            st.add(session, record(run_key=str(i)))
        st.db.execute("BEGIN")
        st.db.execute("INSERT INTO runs (session, status) VALUES (?, 'ok')", (session,))
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == -9, proc.stderr
    runs = load_runs(path)
    assert list(runs["run_key"]) == ["0", "1", "2"]
    assert len(load_series(path, int(runs.iloc[2]["run_id"]))["windows"]) == 4



def test_the_records_status_is_the_integrators():
    """The store and reports read statuses from benchmarks.records (no JAX there); the
    integrators write integrators.base.Status: one vocabulary, member for member."""
    from benchmarks.records import Status
    from integrators.base import Status as IntegratorStatus

    assert [(s.name, s.value) for s in Status] == \
        [(s.name, s.value) for s in IntegratorStatus]
    assert all(a == b for a, b in zip(Status, IntegratorStatus))


def test_every_column_is_a_field_of_the_part_of_the_record_it_declares():
    from dataclasses import fields

    from benchmarks.columns import of_part
    from benchmarks.records import PARTS, Metrics

    for name, part in PARTS.items():
        held = list(Metrics().as_dict()) if part is Metrics else [f.name for f in fields(part)]
        assert sorted(held) == sorted(of_part(name)), name
    assert sorted(c for name in PARTS for c in of_part(name)) == sorted(COLUMNS)
