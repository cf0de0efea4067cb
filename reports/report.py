"""Build the report from a results store: ``report.md`` (figures beside it) and ``report.html``.

Sections, in order, after a folded contents line: the headline (which method wins each
problem for drift, for energy and for cost at matched accuracy, in two tables that open the
page and fit its width, then the overview figure), the history of the drift gate's metrics
across commits (when the store holds several), one collapsible section per problem (summary
table, drift series, work-precision diagrams, accuracy targets, convergence orders fitted
over the asymptotic range), the ensembles (:mod:`reports.ensembles`; ensemble runs appear
there only), the study sections
(tables and figures stored by the studies a suite names, the seed reproduction among them:
:mod:`studies`), the scaling
section when a scaling benchmark's output folder is given (:mod:`reports.scaling`), what
the harness costs when an efficiency benchmark's folder is given (:mod:`reports.efficiency`;
the headline's cost verdicts then mark the families it finds over twice their native
cost per step) and the provenance of the runs shown.

Per-problem sections show the latest run of each identity (problem, integrator, setting,
horizon); the history uses every stored run.
"""

from __future__ import annotations

import json
import math
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks import columns
from benchmarks.columns import MAP, NOTE, TEXT, Column
from benchmarks.files import replace_file
from benchmarks.records import Status
from benchmarks.store import artifact_table, load_artifacts, load_runs, load_series
from reports import (efficiency as efficiency_section, ensembles as ensemble_section, figures,
                     scaling as scaling_section)
from reports.analysis import (COST_AXES, DEFAULT_TARGETS, DEFAULT_X, DEFAULT_Y, LABELS,
                              FIT_MARGIN, MIN_FIT_POINTS, ORDER_TOLERANCE, PRECISION_AXES,
                              Convergence, Target, at_floor, at_sweep_horizon,
                              convergence, cost_winner, drift_winner, energy_winner,
                              fmt, history, is_sensitive, label, largest_floor, latest,
                              representative, setting, standings, targets as target_rows, text,
                              timing)
from reports.document import Bullets, Document, Figure, Para, Table, to_html, to_markdown
from reports.svg import SvgError, clean

TITLE = "driftbench report"
#: Text of a missing value in a finished run: the metric does not apply.
NOT_APPLICABLE = "n/a"
#: Caption of each problem's summary table; a column's ``note`` follows where it is shown.
SUMMARY_NOTE = ("Evaluations are force/residual evaluations; wall is the median of the timed "
                "solves, min and max their spread; growth classes fit the windowed maxima "
                "against t (exponent p of a power law); n/a: does not apply (no reference, no "
                "conserved energy); at reference floor: the final error is within the "
                "reference's own accuracy.")
#: Rows of a study table shown in the report (the study's own files hold all of them).
MAX_STUDY_ROWS = 60


def build(db_path, out_dir, scaling=None, targets=DEFAULT_TARGETS, x=DEFAULT_X,
          y=DEFAULT_Y, efficiency=None) -> list[Path]:
    """Write ``report.md``, its SVG figures and ``report.html`` under ``out_dir``.

    Parameters
    ----------
    db_path, out_dir : path
        The results store, and the folder the report is written to.
    scaling : path, optional
        The output folder of ``python -m benchmarks.perf.scaling``, whose results get a section
        of their own (:class:`reports.scaling.ScalingError` if it holds none).
    targets : sequence of float
        The accuracy targets of each problem's target table.
    x, y : sequence of str
        The work-precision diagrams' cost axes (keys of
        :data:`~reports.analysis.COST_AXES`) and precision axes (keys of
        :data:`~reports.analysis.PRECISION_AXES`).
    efficiency : path, optional
        The output folder of ``python -m benchmarks.perf.efficiency``: the section "What the
        harness costs" and the headline's notes on it
        (:class:`reports.efficiency.EfficiencyError` if it holds none).

    Returns
    -------
    list of Path
        The paths written, the two reports first.
    """
    db_path, out_dir = Path(db_path), Path(out_dir)
    wp = (tuple(COST_AXES[k][0] for k in x), tuple(PRECISION_AXES[k][0] for k in y))
    scaling_data = scaling_section.load(scaling) if scaling is not None else None
    efficiency_data = efficiency_section.load(efficiency) if efficiency is not None else None
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = load_runs(db_path)
    artifacts = load_artifacts(db_path)

    @lru_cache(maxsize=None)
    def series(run_id: int) -> dict:
        return load_series(db_path, run_id)

    current = latest(runs)
    # Ensembles have a section of their own; every other section shows single runs.
    ensembles = current[current["lanes"].notna()] if not current.empty else current
    current = current[current["lanes"].isna()] if not current.empty else current
    with figures.Drawing() as draw:
        doc = _document(runs, current, ensembles, artifacts, series, scaling_data, draw,
                        targets, wp, efficiency_data)
        built = f"Report built {time.strftime('%Y-%m-%d %H:%M:%S %Z')} from {db_path.name}."
        doc.add(Para(built))
        md, written = to_markdown(doc, out_dir)
        md_path, html_path = out_dir / "report.md", out_dir / "report.html"
        replace_file(md_path, md)
        replace_file(html_path, to_html(doc, [built]))
    return [md_path, html_path, *written]


def _document(runs, current, ensembles, artifacts, series, scaling_data, draw, targets,
              wp, efficiency_data=None) -> Document:
    """The report's blocks, its figures submitted to ``draw`` (:class:`figures.Drawing`)."""
    members = _families(runs)
    colors = figures.palette(members)
    doc = Document(TITLE)
    _headline(doc, runs, current, ensembles, members, colors, draw, efficiency_data)
    _history(doc, runs, draw)
    for problem in sorted(current["problem"].unique()) if not current.empty else []:
        _problem(doc, problem, current[current["problem"] == problem], series, colors,
                 tuple(targets), wp, draw)
    ensemble_section.section(doc, ensembles, series, colors, draw)
    _studies(doc, artifacts)
    if scaling_data is not None:
        scaling_section.section(doc, scaling_data, draw)
    if efficiency_data is not None:
        efficiency_section.section(doc, efficiency_data)
    _provenance(doc, runs, pd.concat([current, ensembles]))
    return doc


def _families(runs: pd.DataFrame) -> dict[str, list[str]]:
    """Family -> its integrators, both sorted, as the runs recorded them (the integrators'
    ``family`` trait); a method that declares no family counts as a family of its own."""
    if runs.empty:
        return {}
    family = runs["family"]
    named = family.where(family.notna() & (family.astype(str) != ""), runs["integrator"])
    members: dict[str, list[str]] = {}
    for key, name in sorted(set(zip(runs["integrator"], named.astype(str)))):
        members.setdefault(name, []).append(key)
    return dict(sorted(members.items()))


def _scope(runs: pd.DataFrame, current: pd.DataFrame) -> str:
    """One line: how many runs are shown, out of how many, and how many did not finish."""
    if runs.empty:
        return "The results store holds no runs yet."
    n_bad = int((current["status"] != Status.OK).sum())
    return (f"{len(current)} runs shown (the latest of each problem, integrator, setting and "
            f"horizon) out of {len(runs)} stored, over {runs['session'].nunique()} "
            f"invocations; {n_bad} of those shown did not finish (status failed, error or "
            f"timeout).")


# --------------------------------------------------------------------------- headline

def _headline(doc: Document, runs: pd.DataFrame, current: pd.DataFrame,
              ensembles: pd.DataFrame, members: dict, colors: dict, draw,
              efficiency_data=None) -> None:
    """Winners among the single runs (``current``; ensembles have their own verdicts),
    first of all: the verdict tables open the page, narrow enough to fit its width (two
    tables, cells that wrap), and the rules, the overview figure and the families follow.
    With ``efficiency_data``, a cost cell naming a family over twice its native cost per
    step is marked and a line under the table says by how much."""
    doc.heading(2, "Headline")
    doc.add(Para(_scope(runs, pd.concat([current, ensembles]))))
    if current.empty:
        doc.add(Para("No single runs: the runs here are ensembles, whose verdicts are in "
                     "their own section (Ensembles)." if not ensembles.empty else "No runs."))
        return
    problems = sorted(current["problem"].unique())
    subs = {p: current[current["problem"] == p] for p in problems}
    costs = {p: cost_winner(sub) for p, sub in subs.items()}
    doc.add(Table(["problem", "least drift: max(|g|, |G v + g_t|)",
                   "least energy error: max |H - H0| / scale (or |H - H0 - W|: balance)"],
                  [[p, drift_winner(subs[p]).text, energy_winner(subs[p]).text]
                   for p in problems],
                  "Drift and energy: each method's run at the longest horizon", fit=True))
    notes: dict[str, None] = {}

    def marked(cell: str, named: list) -> str:
        if efficiency_data is None:
            return cell
        for run in named:
            found = efficiency_section.note(efficiency_data, run)
            if found:
                notes[found] = None
                cell = efficiency_section.mark(cell, run["integrator"])
        return cell

    doc.add(Table(["problem", "matched accuracy", "cheapest by wall time [s]",
                   "cheapest by evaluations"],
                  [[p, costs[p].accuracy, marked(costs[p].by_wall, costs[p].wall_named),
                    marked(costs[p].by_evals, costs[p].evals_named)]
                   for p in problems],
                  "Cost at matched accuracy, at the sweeps' horizon", fit=True))
    if notes:
        doc.add(Para(f"{efficiency_section.MARK} Part of this cost is the harness's: "
                     + "; ".join(notes) + f" ({efficiency_section.SECTION})."))
    doc.add(Para("Drift: the smallest max(|g|, |G v + g_t|) of each method's run at the "
                 "longest horizon (ties within 10x). Energy: the smallest max |H - H0| / "
                 "energy scale of the same runs, with its growth class. Cost: at the sweeps' "
                 "horizon, the matched accuracy is the median of the best accuracies the "
                 "methods reached (final error where a reference exists, counted no better "
                 "than the reference, else energy error); the cheapest run reaching it is "
                 "named by wall time only when its slowest solve beat every other's fastest "
                 "(a run solved once gets the widest spread measured beside it), and by "
                 "force evaluations. Wall times are the median of each run's timed solves, "
                 "with the fastest and slowest and their number in brackets, on the machine "
                 "named in the provenance section; they are only comparable within one "
                 "invocation."))
    doc.add(Figure("headline", draw(figures.overview,
                                    {p: standings(sub) for p, sub in subs.items()},
                                    {p: c.integrator for p, c in costs.items()}),
                   "Every problem and method run singly (ensembles: their own section): "
                   "the cell's colour is the growth class of max |g| "
                   "in the method's run at the longest horizon, its text max(|g|, |G v + g_t|) "
                   "of that run; a black frame marks the cost winner by wall time at matched "
                   "accuracy (none where the fastest are within each other's timing spread). "
                   "Each problem's section places its methods by cost against drift and "
                   "energy error."))
    if members:
        doc.add(Para("Families (one hue each in the figures, a shade and marker per "
                     "integrator): " + "; ".join(f"{f}: {', '.join(k)}"
                                                 for f, k in members.items()) + "."))


def _history(doc: Document, runs: pd.DataFrame, draw) -> None:
    if runs.empty or runs["commit"].nunique(dropna=False) < 2:
        return
    doc.heading(2, "History across commits")
    hist = history(runs)
    doc.add(Para("The drift gate's metrics for every run identity (problem, integrator, "
                 "setting, horizon) across the commits in the store, oldest first; each "
                 "commit shows the latest run of each identity it ran (+: the working tree "
                 "differed from the commit). A regression is a change between consecutive "
                 "commits that ran the identity that the gate would fail: a metric worse by "
                 "more than its tolerance, or a finished run that no longer finishes. Runs of "
                 "chaotic problems are drawn but never regress, as in the gate."))
    doc.add(Table(["commit", "first run", "runs"],
                  [[c["label"], time.strftime("%Y-%m-%d %H:%M", time.localtime(c["started"])),
                    str(c["runs"])] for _, c in hist.commits.iterrows()]))
    doc.add(Figure("history", draw(figures.history, hist),
                   "One panel per gated metric, one grey line per run identity; red crosses "
                   "mark regressions (listed below)."))
    if hist.regressions:
        doc.add(Table(["run", "metric", "from", "to", "change"],
                      [[i, label(m), c0, c1, ch] for i, m, c0, c1, ch in
                       hist.regressions], "Regressions between consecutive commits"))
    else:
        doc.add(Para("No regression between consecutive commits."))


# --------------------------------------------------------------------------- problems

def _missing(row) -> str:
    """A cell without a value: 'n/a' in a finished run (the metric does not apply), the
    status in one that did not finish (never a blank or a zero)."""
    return NOT_APPLICABLE if row["status"] == Status.OK else str(row["status"])


def _cell(row, column: Column) -> str:
    """A summary cell as ``column``'s declaration has it (:mod:`benchmarks.columns`): the
    number, the text, a JSON map's entries, or :func:`_missing` (free text: blank); a value
    whose floor applies says so instead of giving the floor's number as the run's."""
    value = row.get(column.name)
    if value is None or (isinstance(value, float) and math.isnan(value)) or value == "":
        return "" if column.format == NOTE else _missing(row)
    if column.format == NOTE:
        return text(value)
    if column.format == MAP:
        try:
            entries = json.loads(value)
        except (TypeError, ValueError):
            return _missing(row)
        return "; ".join(f"{k}: {fmt(v)}" for k, v in entries.items()) or _missing(row)
    if column.kind == TEXT:
        return text(value)
    judged = column.floor
    if judged is not None:
        floor, of = row.get(judged.column), row.get(judged.of)
        if not pd.isna(floor) and floor > 0 and not pd.isna(of) and of <= floor:
            return f"at {judged.label} (≤ {fmt(floor)})"
    return fmt(value)


def _measured(runs: pd.DataFrame, column: Column) -> bool:
    """Whether some run of ``runs`` has a value of ``column``."""
    return column.name in runs and bool(runs[column.name].map(text).astype(bool).any())


def _summary(doc: Document, runs: pd.DataFrame) -> None:
    # A column that applies to some problems only (energy or its balance, invariants) is
    # shown where some run measured it.
    shown = [c for c in columns.summary() if not c.optional or _measured(runs, c)]
    rows = [[r["integrator"], setting(r), fmt(r["t_end"]), str(r["status"]),
             *(_cell(r, c) for c in shown)]
            for _, r in runs.sort_values(["integrator", "h", "rtol"]).iterrows()]
    doc.add(Table(["integrator", "setting", "t_end", "status", *(c.header for c in shown)],
                  rows, " ".join([SUMMARY_NOTE, *(c.note for c in shown if c.note)])))


def _floor_note(runs: pd.DataFrame) -> str:
    """What the problem's reference is accurate to, where the runs recorded it."""
    floor = largest_floor(runs[runs["status"] == Status.OK])
    if floor <= 0:
        return ""
    n = sum(at_floor(r) for _, r in runs.iterrows())
    return (f" The reference is itself accurate to {fmt(floor)} (max-norm on its scored "
            f"components): final errors at or below that ({n} runs) are shown as at the "
            f"reference floor, fit no order and decide no verdict.")


def _problem(doc: Document, problem: str, runs: pd.DataFrame, series, colors,
             levels: tuple[float, ...], wp: tuple[tuple[str, ...], tuple[str, ...]],
             draw) -> None:
    doc.heading(2, f"Problem: {problem}", collapsible=True)
    n_bad = int((runs["status"] != Status.OK).sum())
    horizons = ", ".join(fmt(x) for x in sorted(runs["t_end"].dropna().unique()))
    doc.add(Para(f"{len(runs)} runs of {runs['integrator'].nunique()} integrators, horizons "
                 f"t_end = {horizons}; {n_bad} did not finish." + _floor_note(runs)))
    if is_sensitive(runs):
        doc.add(Para("This problem is declared chaotic (sensitive): nearby solutions separate "
                     "exponentially, so its final errors and scd measure that separation more "
                     "than a method's accuracy; drift, energy error and cost are the measures "
                     "to compare, and the drift gate does not gate on it."))
    doc.heading(3, f"{problem}: drift and energy error against cost")
    cost = cost_winner(runs)
    doc.add(Figure(f"{problem}-standing",
                   draw(figures.standing, standings(runs), colors, problem, cost.integrator),
                   f"Each method once. Across: the median wall time of its cheapest run "
                   f"reaching the matched accuracy ({cost.accuracy}); hollow markers: the "
                   f"most accurate run of a method that never reached it. Up: max(|g|, "
                   f"|G v + g_t|) and max rel. energy error of its run at the longest horizon, "
                   f"a cross where that run did not finish; the legend gives their growth "
                   f"classes; a black ring marks the cost winner by wall time."))
    doc.heading(3, f"{problem}: summary")
    _summary(doc, runs)
    bad = runs[runs["status"] != Status.OK]
    if not bad.empty:
        doc.add(Para("Runs that did not finish:"))
        doc.add(Bullets([f"{r['integrator']} {setting(r)}: {r['status']}: "
                         f"{text(r['message'])}" for _, r in bad.iterrows()]))

    doc.heading(3, f"{problem}: drift and energy error against time")
    rep = representative(runs)
    entries = []
    for _, r in rep.iterrows():
        failed = r["status"] != Status.OK
        windows = dict(series(int(r["run_id"]))["windows"])
        if pd.isna(r["rel_energy_error"]):
            # |H - H0| of a system without a conserved energy measures nothing.
            windows.pop("energy", None)
        entries.append({"label": f"{r['integrator']} {setting(r)}, t_end={fmt(r['t_end'])}"
                                 + (f" ({r['status']})" if failed else ""),
                        "integrator": r["integrator"], "windows": windows, "failed": failed})
    doc.add(Figure(f"{problem}-drift", draw(figures.drift, entries, colors, problem),
                   "Window maxima of |g| and |H - H0| against t (log-log), one run per "
                   "integrator: the longest horizon, a finished run where there is one, the "
                   "coarsest setting. A cross marks where a failed run stopped; zeros are drawn "
                   "at 1e-17."))

    doc.heading(3, f"{problem}: work-precision")
    sweep = at_sweep_horizon(runs)
    n_ok = int((sweep["status"] == Status.OK).sum())
    horizon = fmt(sweep["t_end"].iloc[0]) if not sweep.empty else "none"
    x, y = wp
    floor = largest_floor(sweep)
    doc.add(Figure(f"{problem}-work-precision",
                   draw(figures.work_precision, sweep, colors, f"{problem}, t_end = {horizon}",
                        x, y, floor),
                   f"{', '.join(LABELS[c] for c in y)} against {', '.join(LABELS[c] for c in x)} "
                   f"at t_end = {horizon} (the horizon of the sweeps); each line joins the "
                   f"finished runs of one integrator over its settings ({n_ok} runs; "
                   f"{len(sweep) - n_ok} that did not finish are not drawn, see the summary)."
                   + (f" Dashed: the reference floor {fmt(floor)}." if floor > 0 else "")))

    doc.heading(3, f"{problem}: accuracy targets")
    rows = target_rows(runs, levels)
    if rows:
        doc.add(Table(["metric", "target", "cheapest by wall time [s]", "cheapest by evaluations",
                       "not reached by"], [_target_row(t) for t in rows],
                      f"The cheapest finished run at t_end = {horizon} whose metric is at or "
                      f"below each target (a final error counts as no better than the "
                      f"reference floor); wall time as median (min-max, solves)."))
    else:
        doc.add(Para("No finished run measured an accuracy."))

    doc.heading(3, f"{problem}: convergence")
    convs, basis = convergence(runs)
    if not any(np.isfinite(c.err).any() for c in convs):
        # An empty log-log frame says nothing a sentence would not.
        doc.add(Para(f"No convergence figure: {basis}." if basis.startswith("no ") else
                     f"No convergence figure: no finished fixed-step run has an error against "
                     f"another ({basis})."))
        return
    doc.add(Figure(f"{problem}-convergence",
                   draw(figures.convergence, convs, colors, f"{problem}: convergence", basis),
                   f"Fixed-step methods only; {basis}. Filled markers: fitted points (the "
                   f"asymptotic range); hollow: outside it (pre-asymptotic, past it, or no "
                   f"range found); faint: at the reference floor or round-off. Dashed: slope "
                   f"of the nominal order."))
    if convs:
        doc.add(Para(f"Orders are fitted over the asymptotic range only: the longest run of "
                     f"consecutive step sizes whose pairwise orders (log of the error ratio "
                     f"over log of the step ratio, coarse to fine) agree within "
                     f"{ORDER_TOLERANCE:g}, at least {MIN_FIT_POINTS} points (two pairwise "
                     f"orders, so that one confirms the other); of equally long runs, the "
                     f"finest. Coarser points are pre-asymptotic (higher error terms still "
                     f"matter), finer ones past the range (round-off or the reference's "
                     f"error); errors within {FIT_MARGIN:g}x of the reference floor or below "
                     f"round-off are never fitted."))
        doc.add(Table(["integrator", "fitted order", "nominal order", "fitted over",
                       "pairwise orders, coarse to fine", "left out"],
                      [_order_row(c) for c in convs]))


def _target_row(t: Target) -> list[str]:
    label = LABELS[t.column]
    if t.note:
        return [label, f"≤ {fmt(t.target)}", t.note, t.note, ""]
    return [label, f"≤ {fmt(t.target)}", t.by_wall.text, t.by_evals.text,
            ", ".join(t.missed) or "-"]


def _order_row(c: Convergence) -> list[str]:
    """One row of the order table: the fit and the step sizes it spans, or why there is
    none; each pairwise order; each point left out with its reason."""
    n_usable = int(c.usable.sum())
    if not math.isnan(c.order):
        fitted = f"{c.order:.2f}"
    elif len(c.h) < MIN_FIT_POINTS:
        fitted = f"n/a: {len(c.h)} step size{'s' if len(c.h) > 1 else ''} run, " \
                 f"{MIN_FIT_POINTS} needed"
    elif n_usable < MIN_FIT_POINTS:
        above = "the reference floor" if c.floor > 0 else "round-off"
        fitted = (f"n/a: too few points above {above} ({n_usable} of {len(c.h)} step sizes "
                  f"with error above {fmt(c.threshold)}; {MIN_FIT_POINTS} needed)")
    else:
        fitted = (f"n/a: no {MIN_FIT_POINTS} consecutive step sizes whose pairwise orders "
                  f"agree within {ORDER_TOLERANCE:g}")
    span = "-"
    if c.n_fit:
        hs = c.h[c.fitted]
        span = f"h = {fmt(hs.max())}..{fmt(hs.min())}, {c.n_fit} points"
    nominal = "n/a" if math.isnan(c.nominal) else fmt(c.nominal)
    left = "; ".join(f"{fmt(h)} ({why})" for h, why in
                     sorted(zip(c.h, c.left_out), reverse=True) if why)
    return [c.integrator, fitted, nominal, span,
            ", ".join(f"{p:.2f}" for p in c.pairwise) or "-", left or "-"]


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
                doc.add(Figure(f"study-{section}-{a['name']}", a["content"],
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
                     text(s.get("timing_note")) or "not recorded",
                     _setup_sources(runs[runs["session"] == s["session"]])])
    doc.add(Table(["invocation", "suite", "started", "commit", "machine", "python",
                   "versions", "runs shown", "timing conditions", "set-up compiled"], rows))
    doc.add(Para("Set-up times include compilation. \"From the cache\": every executable of "
                 "the set-up was read from the persistent compilation cache; \"compiled\": "
                 "none was; \"partly\": some were; \"in memory\": the worker had compiled it "
                 "for an earlier run (a sweep over h or rtol). Solve times never include "
                 "compilation."))


#: How :func:`_setup_sources` words each ``setup_cache`` value.
SETUP_SOURCES = {"cold": "compiled", "partial": "partly from the cache",
                 "warm": "from the cache", "memory": "in memory", "off": "compiled (cache off)"}


def _setup_sources(runs: pd.DataFrame) -> str:
    """How many runs of an invocation compiled their set-up, read it from the cache or had
    it in memory (``setup_cache``)."""
    counts = runs["setup_cache"].dropna().value_counts()
    return ", ".join(f"{counts[key]} {word}" for key, word in SETUP_SOURCES.items()
                     if key in counts) or "not recorded"
