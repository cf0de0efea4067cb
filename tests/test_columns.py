"""A column declared once (benchmarks.columns) reaches runs.csv, the store, the gate and the
report."""

from __future__ import annotations

import csv
import json

import pytest

from benchmarks import check, columns
from benchmarks.batch import run_specs
from benchmarks.gate import TOLERANCES, compare
from benchmarks.records import (ACCURACY_COLUMNS, COLUMNS, CODE_VERSION_ENV, Metrics,
                                RunSpec)
from benchmarks.store import Store, load_runs
from reports.analysis import fmt
from reports.report import build

NAME = "max_abs_q_final"
# The declaration a user would put in a file given to --load: the column and the function
# that computes it from a run, nothing else.
DECLARATION = f'''
import numpy as np
from benchmarks.columns import Column, declare

declare(Column("{NAME}", "metrics", description="max |q| at the final time",
               accuracy=True, better="lower", gate=(4.0, 1e-13), header="max |q(t_end)|",
               place=75, compute=lambda case, traj: float(np.max(np.abs(traj.q_final)))))
'''


@pytest.fixture
def declared(tmp_path):
    """The file that declares the column; the declaration is withdrawn afterwards."""
    path = tmp_path / "metric.py"
    path.write_text(DECLARATION)
    yield path
    if NAME in columns.TABLE:
        columns.withdraw(NAME)


@pytest.mark.slow
def test_a_declared_metric_reaches_runs_csv_the_store_the_gate_and_the_report(
        tmp_path, declared, monkeypatch):
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")
    out = tmp_path / "out"
    out.mkdir()
    # A store written before the column was declared gets it, empty, when next opened.
    Store(out / "driftbench.sqlite").close()
    assert NAME not in COLUMNS
    records = run_specs([RunSpec("pendulum", "rattle", 0.05, t_end=1.0)], out, jobs=1,
                        load=[str(declared)], log=None)
    assert COLUMNS[-1] == NAME and NAME in ACCURACY_COLUMNS and NAME in TOLERANCES
    row = records[0].row
    expected = max(abs(x) for x in json.loads(row["q_final"]))
    assert row["status"] == "ok" and row[NAME] == expected  # computed in the worker

    with open(out / "runs.csv", newline="") as fh:
        written = list(csv.DictReader(fh))
    assert float(written[0][NAME]) == expected

    stored = load_runs(out / "driftbench.sqlite")
    assert stored[NAME].iloc[0] == expected

    baseline = check.entries(records)
    run = next(iter(baseline))
    assert baseline[run]["metrics"][NAME] == expected
    assert not compare(baseline, baseline)
    better = {run: {**baseline[run], "metrics": {**baseline[run]["metrics"],
                                                 NAME: expected / 100}}}
    found = [f for f in compare(better, baseline) if f.metric == NAME]
    assert [(f.kind, f.gating) for f in found] == [("regression", True)]

    md = build(out / "driftbench.sqlite", tmp_path / "report")[0].read_text()
    table = md[md.index("| integrator | setting |"):]
    header = table.splitlines()[0].split(" | ")
    shown = r"max \|q(t_end)\|"  # as Markdown escapes it
    assert shown in header
    cells = next(line for line in table.splitlines() if line.startswith("| rattle |"))
    assert cells.split(" | ")[header.index(shown)] == fmt(expected)


def test_metrics_hold_the_declared_columns_only(declared):
    with pytest.raises(TypeError, match="no_such_metric"):
        Metrics(no_such_metric=1.0)
    columns.declare(columns.Column(NAME, "metrics"))
    assert Metrics(**{NAME: 2.0}).replace(scd=3.0).as_dict()[NAME] == 2.0
    with pytest.raises(ValueError, match="declared already"):
        columns.declare(columns.Column(NAME, "metrics"))
    columns.withdraw(NAME)
    with pytest.raises(ValueError, match="part 'metrics'"):
        columns.declare(columns.Column(NAME, "work"))
