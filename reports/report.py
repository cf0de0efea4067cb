"""Build the report from a results store: ``report.md`` (figures beside it) and ``report.html``.

Sections, in order: the headline (which method wins each problem for drift, for energy and
for cost at matched accuracy), its history across commits (when the store holds several),
the seed reproduction, one section per problem (summary table, drift series, work-precision
diagrams, convergence orders), the study sections (tables and figures stored by study
suites), the scaling section when a scaling benchmark's output folder is given
(:mod:`reports.scaling`) and the provenance of the runs shown.

Per-problem sections show the latest run of each identity (problem, integrator, setting,
horizon); the history uses every stored run.
"""

from __future__ import annotations

import json
import math
import time
from functools import lru_cache
from pathlib import Path

import pandas as pd

from benchmarks.store import artifact_table, load_artifacts, load_runs, load_series
from reports import figures, scaling as scaling_section, seed
from reports.analysis import (Convergence, at_sweep_horizon, convergence, cost_winner,
                              drift_winner, energy_winner, fmt, is_sensitive, latest,
                              representative, setting, text)
from reports.document import Bullets, Document, Figure, Para, Table, to_html, to_markdown
from reports.svg import SvgError, clean

TITLE = "driftbench report"
#: Text of a missing value in a finished run: the metric does not apply.
NOT_APPLICABLE = "n/a"
#: Rows of a study table shown in the report (the study's own files hold all of them).
MAX_STUDY_ROWS = 60


def build(db_path, out_dir, scaling=None) -> list[Path]:
    """Write ``report.md``, its SVG figures and ``report.html`` under ``out_dir``.

    ``scaling`` is the output folder of ``python -m benchmarks.scaling``, whose results
    get a section of their own (:class:`reports.scaling.ScalingError` if it holds none).
    Returns the paths written, the two reports first.
    """
    db_path, out_dir = Path(db_path), Path(out_dir)
    scaling_data = scaling_section.load(scaling) if scaling is not None else None
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = load_runs(db_path)
    artifacts = load_artifacts(db_path)

    @lru_cache(maxsize=None)
    def series(run_id: int) -> dict:
        return load_series(db_path, run_id)

    current = latest(runs)
    colors = figures.palette(set(runs["integrator"]) if not runs.empty else set())

    doc = Document(TITLE)
    doc.add(Para(_scope(runs, current)))
    _headline(doc, current)
    _history(doc, runs)
    seed.section(doc, current, series, colors)
    for problem in sorted(current["problem"].unique()) if not current.empty else []:
        _problem(doc, problem, current[current["problem"] == problem], series, colors)
    _studies(doc, artifacts)
    if scaling_data is not None:
        scaling_section.section(doc, scaling_data)
    _provenance(doc, runs, current)
    built = f"Report built {time.strftime('%Y-%m-%d %H:%M:%S %Z')} from {db_path.name}."
    doc.add(Para(built))

    md, written = to_markdown(doc, out_dir)
    md_path, html_path = out_dir / "report.md", out_dir / "report.html"
    md_path.write_text(md)
    html_path.write_text(to_html(doc, [built]))
    return [md_path, html_path, *written]


def _scope(runs: pd.DataFrame, current: pd.DataFrame) -> str:
    if runs.empty:
        return "The results store holds no runs yet."
    n_bad = int((current["status"] != "ok").sum())
    return (f"{len(current)} runs shown (the latest of each problem, integrator, setting and "
            f"horizon) out of {len(runs)} stored, over {runs['session'].nunique()} invocations; "
            f"{n_bad} of those shown did not finish (status failed, error or timeout). Wall "
            f"times are the median of each run's timed solves (runs.csv's repeats column "
            f"counts them) on the machine named in the provenance section and are only "
            f"comparable within one invocation.")


# --------------------------------------------------------------------------- headline

def _headline_rows(current: pd.DataFrame) -> list[list[str]]:
    rows = []
    for problem in sorted(current["problem"].unique()):
        sub = current[current["problem"] == problem]
        rows.append([problem, drift_winner(sub).text, energy_winner(sub).text,
                     cost_winner(sub).text])
    return rows


def _headline(doc: Document, current: pd.DataFrame) -> None:
    doc.heading(2, "Headline")
    if current.empty:
        doc.add(Para("No runs."))
        return
    doc.add(Para("Drift: the smallest max(|g|, |G v + g_t|) among each method's run at the "
                 "longest horizon (methods within a factor of 10 are named as ties). Energy: "
                 "the smallest max |H - H0| / energy scale among the same runs, with its growth "
                 "class. Cost: at the horizon of the sweeps, the cheapest run (wall time) whose "
                 "accuracy (final error where a reference exists, else the energy error) is at "
                 "or below the median of the best accuracies the methods reached."))
    doc.add(Table(["problem", "drift", "energy", "cost at matched accuracy"],
                  _headline_rows(current)))


def _history(doc: Document, runs: pd.DataFrame) -> None:
    if runs.empty or runs["commit"].nunique(dropna=False) < 2:
        return
    doc.heading(2, "History across commits")
    doc.add(Para("The headline computed from the runs of each commit separately (the latest "
                 "run of each identity within that commit), oldest commit first."))
    order = runs.groupby("commit", dropna=False)["session_started"].min().sort_values()
    rows = []
    for commit, started in order.items():
        sub = latest(runs[runs["commit"].isna()] if pd.isna(commit)
                     else runs[runs["commit"] == commit])
        dirty = " (dirty)" if sub["dirty"].astype(bool).any() else ""
        date = time.strftime("%Y-%m-%d %H:%M", time.localtime(started))
        for problem in sorted(sub["problem"].unique()):
            p = sub[sub["problem"] == problem]
            rows.append([f"{text(commit)[:10] or 'unknown'}{dirty}", date, problem,
                         drift_winner(p).text,
                         energy_winner(p).text, cost_winner(p).text])
    doc.add(Table(["commit", "first run", "problem", "drift", "energy",
                   "cost at matched accuracy"], rows))


# --------------------------------------------------------------------------- problems

def _missing(row) -> str:
    """A cell without a value: 'n/a' in a finished run (the metric does not apply), the
    status in one that did not finish (never a blank or a zero)."""
    return NOT_APPLICABLE if row["status"] == "ok" else str(row["status"])


def _cell(row, column: str) -> str:
    """A metric cell: the number, or :func:`_missing`."""
    value = row.get(column)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return _missing(row)
    return fmt(value)


def _invariants(row) -> str:
    try:
        inv = json.loads(row.get("invariant_errors") or "{}")
    except (TypeError, ValueError):
        return ""
    return "; ".join(f"{k}: {fmt(v)}" for k, v in inv.items())


def _summary(doc: Document, runs: pd.DataFrame) -> None:
    with_inv = runs["invariant_errors"].fillna("").astype(bool).any() \
        if "invariant_errors" in runs else False
    columns = ["integrator", "setting", "t_end", "status", "steps", "evaluations", "wall [s]",
               "max |g|", "max |G v + g_t|", "max rel. energy error", "|g| growth",
               "energy growth", "final error", "scd", "linear solver"]
    if with_inv:
        columns.append("invariant errors")
    columns.append("message")
    rows = []
    for _, r in runs.sort_values(["integrator", "h", "rtol"]).iterrows():
        row = [r["integrator"], setting(r), fmt(r["t_end"]), str(r["status"]),
               _cell(r, "n_steps"), _cell(r, "n_f_evals"), _cell(r, "wall_s"),
               _cell(r, "max_pos_residual"), _cell(r, "max_vel_residual"),
               _cell(r, "rel_energy_error"), text(r.get("pos_growth")) or _missing(r),
               text(r.get("energy_growth")) or _missing(r),
               _cell(r, "final_state_error"), _cell(r, "scd"),
               text(r.get("linear_solver")) or _missing(r)]
        if with_inv:
            row.append(_invariants(r) or _missing(r))
        row.append(text(r["message"]))
        rows.append(row)
    doc.add(Table(columns, rows, "Evaluations are force/residual evaluations; growth classes "
                                 "fit the windowed maxima against t (exponent p of a power "
                                 "law); n/a: does not apply (no reference, no conserved "
                                 "energy)."))


def _problem(doc: Document, problem: str, runs: pd.DataFrame, series, colors) -> None:
    doc.heading(2, f"Problem: {problem}")
    n_bad = int((runs["status"] != "ok").sum())
    horizons = ", ".join(fmt(x) for x in sorted(runs["t_end"].dropna().unique()))
    doc.add(Para(f"{len(runs)} runs of {runs['integrator'].nunique()} integrators, horizons "
                 f"t_end = {horizons}; {n_bad} did not finish."))
    if is_sensitive(runs):
        doc.add(Para("This problem is declared chaotic (sensitive): nearby solutions separate "
                     "exponentially, so its final errors and scd measure that separation more "
                     "than a method's accuracy; drift, energy error and cost are the measures "
                     "to compare, and the drift gate does not gate on it."))
    doc.heading(3, f"{problem}: summary")
    _summary(doc, runs)
    bad = runs[runs["status"] != "ok"]
    if not bad.empty:
        doc.add(Para("Runs that did not finish:"))
        doc.add(Bullets([f"{r['integrator']} {setting(r)}: {r['status']}: "
                         f"{text(r['message'])}" for _, r in bad.iterrows()]))

    doc.heading(3, f"{problem}: drift and energy error against time")
    rep = representative(runs)
    entries = []
    for _, r in rep.iterrows():
        failed = r["status"] != "ok"
        windows = dict(series(int(r["run_id"]))["windows"])
        if pd.isna(r["rel_energy_error"]):
            # |H - H0| of a system without a conserved energy measures nothing.
            windows.pop("energy", None)
        entries.append({"label": f"{r['integrator']} {setting(r)}, t_end={fmt(r['t_end'])}"
                                 + (f" ({r['status']})" if failed else ""),
                        "integrator": r["integrator"], "windows": windows, "failed": failed})
    slug = _slug(problem)
    doc.add(Figure(f"{slug}-drift", figures.drift(entries, colors, problem),
                   "Window maxima of |g| and |H - H0| against t (log-log), one run per "
                   "integrator: the longest horizon, a finished run where there is one, the "
                   "coarsest setting. A cross marks where a failed run stopped; zeros are drawn "
                   "at 1e-17."))

    doc.heading(3, f"{problem}: work-precision")
    sweep = at_sweep_horizon(runs)
    n_ok = int((sweep["status"] == "ok").sum())
    horizon = fmt(sweep["t_end"].iloc[0]) if not sweep.empty else "none"
    doc.add(Figure(f"{slug}-work-precision",
                   figures.work_precision(sweep, colors, f"{problem}, t_end = {horizon}"),
                   f"Final error, max |g| and max relative energy error against wall time and "
                   f"against force evaluations at t_end = {horizon} (the horizon of the "
                   f"sweeps); each line joins the finished runs of one integrator over its "
                   f"settings ({n_ok} runs; {len(sweep) - n_ok} that did not finish are not "
                   f"drawn, see the summary)."))

    doc.heading(3, f"{problem}: convergence")
    convs, basis = convergence(runs)
    doc.add(Figure(f"{slug}-convergence",
                   figures.convergence(convs, colors, f"{problem}: convergence", basis),
                   f"Fixed-step methods only; {basis}. Dashed: slope of the nominal order."))
    if convs:
        doc.add(Table(["integrator", "fitted order", "nominal order", "points fitted",
                       "step sizes"], [_order_row(c) for c in convs]))


def _order_row(c: Convergence) -> list[str]:
    fitted = "n/a (fewer than 2 step sizes above round-off)" if math.isnan(c.order) \
        else f"{c.order:.2f}"
    nominal = "n/a" if math.isnan(c.nominal) else fmt(c.nominal)
    return [c.integrator, fitted, nominal, str(c.n_fit), ", ".join(fmt(h) for h in c.h)]


def _slug(text: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in text.lower()).strip("-")


# --------------------------------------------------------------------------- studies

def _studies(doc: Document, artifacts: pd.DataFrame) -> None:
    """Each section of stored study artifacts, from the latest session that wrote to it."""
    if artifacts.empty:
        return
    for section in artifacts["section"].drop_duplicates():
        sub = artifacts[artifacts["section"] == section]
        sub = sub[sub["session"] == sub["session"].max()]
        doc.heading(2, f"Study: {section}")
        commit = text(sub["commit"].iloc[0])
        doc.add(Para(f"Stored by invocation {int(sub['session'].iloc[0])} "
                     f"(commit {commit[:10] or 'unknown'})."))
        for _, a in sub.iterrows():
            if a["kind"] == "table":
                table = artifact_table(a["content"])
                shown = table.head(MAX_STUDY_ROWS)
                caption = str(a["name"]) + ("" if len(table) <= MAX_STUDY_ROWS else
                                            f" (first {MAX_STUDY_ROWS} of {len(table)} rows)")
                doc.add(Table([""] + list(shown.columns),
                              [[str(i)] + [_any(v) for v in vals]
                               for i, vals in zip(shown.index, shown.values.tolist())],
                              caption))
            else:
                try:
                    clean(a["content"], "")
                except SvgError as exc:
                    doc.add(Para(f"Figure {a['name']} cannot be shown: {exc}."))
                    continue
                doc.add(Figure(f"study-{_slug(section)}-{_slug(a['name'])}", a["content"],
                               str(a["name"]), trusted=False))


def _any(value) -> str:
    return fmt(value) if isinstance(value, (int, float)) and not isinstance(value, bool) \
        else str(value)


# --------------------------------------------------------------------------- provenance

def _provenance(doc: Document, runs: pd.DataFrame, current: pd.DataFrame) -> None:
    doc.heading(2, "Provenance")
    if runs.empty:
        doc.add(Para("No invocations stored."))
        return
    shown = set(current["session"])
    sessions = runs.drop_duplicates("session").sort_values("session")
    rows = []
    for _, s in sessions.iterrows():
        try:
            versions = json.loads(text(s["versions"]) or "{}")
        except (TypeError, ValueError):
            versions = {}
        rows.append([str(int(s["session"])), text(s["suite"]),
                     time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(s["session_started"])),
                     f"{text(s['commit'])[:12] or 'unknown'}{' (dirty)' if s['dirty'] else ''}",
                     text(s["machine"]), text(s["python"]),
                     ", ".join(f"{k} {v}" for k, v in versions.items() if v),
                     "yes" if s["session"] in shown else "superseded",
                     text(s.get("timing_note")) or "not recorded"])
    doc.add(Table(["invocation", "suite", "started", "commit", "machine", "python",
                   "versions", "runs shown", "timing conditions"], rows))
