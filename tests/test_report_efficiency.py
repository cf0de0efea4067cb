"""The report's "What the harness costs": the efficiency benchmark's ratios by family and
problem, the headline's note on a cost verdict naming a family over twice its native cost
per step, and a bad results folder's one line."""

import functools
import json

import pandas as pd
import pytest

from benchmarks.store import Store
from reports import build, efficiency, figures
from reports.__main__ import main
from test_report import run

SECTION = "What the harness costs"


def row(family, problem, ratio, driver="jax", **extra):
    return {"family": family, "driver": driver, "problem": problem,
            "us_per_step": 2.0 * ratio, "yardstick_us_per_step": 2.0,
            "ratio_per_step": ratio, "ratio_per_solve": ratio * 1.01, "steps": 5000,
            "yardstick_steps": 5000, "final_q_difference": 3e-13, **extra}


def write(folder, rows, **top):
    folder.mkdir(parents=True, exist_ok=True)
    data = {"goal_ratio_per_step": 3.0, "rounds": 5, "load": 1.25, "rows": rows, **top}
    (folder / "efficiency.json").write_text(json.dumps(data))
    return folder


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Pendulum: lobatto3ab3 alone reaches the matched accuracy, so it is the cost verdict's
    cheapest by wall time and by evaluations; sps-receiver: lobatto3ab2 alone."""
    db = tmp_path_factory.mktemp("store") / "driftbench.sqlite"
    with Store(db) as st:
        session = st.begin("unit")
        for h, final in ((0.1, 1e-4), (0.05, 2.5e-5)):
            st.add(session, run("pendulum", "rattle", h, final=final))
            st.add(session, run("pendulum", "lobatto3ab3", h, final=final ** 2))
        for h in (0.1, 0.05):
            st.add(session, run("sps-receiver", "lobatto3ab2", h, t_end=50.0))
    return db


@pytest.fixture(autouse=True)
def draw_here(monkeypatch):
    """Figures drawn in this process, one at a time: each report built here would otherwise
    start its own drawing processes, which test_report covers."""
    monkeypatch.setattr(figures, "Drawing", functools.partial(figures.Drawing, jobs=1))


def headline(md: str) -> str:
    return md.split("## Headline")[1].split("\n## ")[0]


def test_the_section_tables_every_ratio_in_markdown_and_html(store, tmp_path):
    eff = write(tmp_path / "eff", [
        row("lobatto3ab3", "pendulum", 1.26, setting="h=0.001", cpu_ratio_per_step=1.1),
        row("ida-ggl", "pendulum", 0.89, driver="native", rtol=1e-8),
        row("baumgarte-rk4", "double-pendulum", 2.8)])
    build(store, tmp_path, efficiency=eff)
    md = (tmp_path / "report.md").read_text()
    html = (tmp_path / "report.html").read_text()
    assert f"## {SECTION}" in md and SECTION in html
    part = md.split(f"## {SECTION}")[1].split("\n## ")[0]
    assert "| lobatto3ab3 | jax | pendulum | h=0.001 | 1.26 | 1.10 | 1.27 | 2.52 | 2 | 5000 " \
           "| 5000 | 3e-13 |" in part
    assert "| ida-ggl | native | pendulum | rtol=1e-08 | 0.89 |  |" in part
    assert "load average 1.25" in part and "5 rounds" in part
    assert "Above 2 here: baumgarte-rk4 (2.80 on double-pendulum)." in part
    assert part.index("baumgarte-rk4") < part.index("ida-ggl") < part.index("| lobatto3ab3")
    # The section comes after the problems, before the provenance.
    assert md.index("## Problem: pendulum") < md.index(SECTION) < md.index("## Provenance")
    for cell in ("1.26", "2.80", "h=0.001", "double-pendulum"):
        assert f"<td>{cell}</td>" in html or f">{cell}</td>" in html


def test_the_headline_marks_a_cost_verdict_over_twice_its_yardstick(store, tmp_path):
    eff = write(tmp_path / "eff", [row("lobatto3ab3", "pendulum", 2.61),
                                   row("lobatto3ab3", "sps-receiver", 1.2),
                                   row("lobatto3ab2", "pendulum", 3.04)])
    build(store, tmp_path, efficiency=eff)
    top = headline((tmp_path / "report.md").read_text())
    # lobatto3ab3 on pendulum: its own problem's ratio; lobatto3ab2 was measured on the
    # pendulum only, and its ratio there stands for it on sps-receiver.
    assert ("† Part of this cost is the harness's: lobatto3ab3: 2.6x its native yardstick "
            "per step on pendulum; lobatto3ab2: 3.0x its native yardstick per step on "
            f"pendulum ({SECTION}).") in top
    drift, cost = [line for line in top.splitlines() if line.startswith("| pendulum |")]
    assert cost.count("lobatto3ab3† (h=") == 2  # by wall time and by evaluations
    assert "†" not in drift
    # Two cells of each problem and the line under the table, in both reports.
    for page in ("report.md", "report.html"):
        assert (tmp_path / page).read_text().count("†") == 5, page


def test_no_note_at_or_below_twice_and_none_without_efficiency_data(store, tmp_path):
    eff = write(tmp_path / "eff", [row("lobatto3ab3", "pendulum", 2.0),
                                   row("lobatto3ab3", "sps-receiver", 9.0),
                                   row("rattle", "pendulum", 4.0)])
    build(store, tmp_path / "with", efficiency=eff)
    build(store, tmp_path / "without")
    with_ = (tmp_path / "with" / "report.md").read_text()
    without = (tmp_path / "without" / "report.md").read_text()
    # 2.0 is not over 2; sps-receiver's 9.0 is not lobatto3ab3's ratio on the pendulum;
    # rattle is in no cost verdict.
    assert "†" not in with_ and "harness's:" not in headline(with_)
    assert SECTION in with_
    assert SECTION not in without and "†" not in without
    assert headline(with_) == headline(without)


def test_a_run_of_the_binding_driver_takes_the_binding_ratio():
    data = {"rows": [row("ida-ggl", "pendulum", 1.1, driver="native"),
                     row("ida-ggl", "pendulum", 6.5, driver="scikit-sundae")]}
    native = pd.Series({"integrator": "ida-ggl", "problem": "pendulum",
                        "options": json.dumps({"driver": "auto"}),
                        "sampling": "every internal step (IDA one-step mode, native driver)"})
    # An auto run that fell back to the binding takes the binding's ratio: what ran counts.
    binding = native.copy()
    binding["sampling"] = ("every internal step (IDA one-step mode, scikit-sundae; native "
                           "driver not built: no C compiler (cc or gcc) on PATH)")
    assert efficiency.ratio(data, native) == (1.1, "pendulum")
    assert efficiency.note(data, native) is None
    assert efficiency.note(data, binding) == \
        "ida-ggl: 6.5x its native yardstick per step on pendulum"
    # The mark follows the name it is about, not a longer name holding it.
    assert efficiency.mark("ida-ggl2 (h=1); tied: ida-ggl", "ida-ggl") == \
        "ida-ggl2 (h=1); tied: ida-ggl†"
    unknown = native.copy()
    unknown["integrator"] = "rattle"
    assert efficiency.ratio(data, unknown) is None


@pytest.mark.parametrize("content, says", [
    (None, "does not exist: run python -m benchmarks.perf.efficiency"),
    ("{not json", "is not valid JSON"),
    (json.dumps({"rows": []}), "lacks goal_ratio_per_step, rounds, load"),
    (json.dumps({"goal_ratio_per_step": 3, "rounds": 5, "load": 1.0, "rows": []}),
     "'rows' must be a non-empty list"),
    (json.dumps({"goal_ratio_per_step": 3, "rounds": 5, "load": 1.0,
                 "rows": [{**row("radau5", "pendulum", 1.4), "ratio_per_step": "1.4"}]}),
     "row 0 (radau5 on pendulum) lacks a valid ratio_per_step"),
    (json.dumps({"goal_ratio_per_step": 3, "rounds": 5, "load": 1.0,
                 "rows": [row("radau5", "pendulum", -1.0)]}), "must be positive"),
])
def test_a_bad_efficiency_folder_is_one_line_exit_2_and_keeps_the_report(
        store, tmp_path, capsys, content, says):
    eff = tmp_path / "eff"
    if content is not None:
        eff.mkdir()
        (eff / "efficiency.json").write_text(content)
    (tmp_path / "report.md").write_text("an earlier report")
    assert main(["--db", str(store), "--out", str(tmp_path), "--efficiency", str(eff)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and says in err, err
    assert str(eff / "efficiency.json") in err
    assert (tmp_path / "report.md").read_text() == "an earlier report"
