"""The report's ensembles section: drift and energy error as distributions over initial states.

One subsection per problem with ensemble runs (``lanes`` set): a table of each run's
quantiles over its lanes (:class:`benchmarks.records.Spread`) and failed fraction, the
per-lane distributions of each metric per method (box plots from the stored per-lane
tables; final errors where the problem has a reference at the run's end), and the median
lane's accuracy (its final error where there is one) against cost per lane with a band
and bars from the best lane to the worst beside the failed fraction against the setting. The
verdicts name the method with the smallest worst-lane (q100) and the smallest
median-lane (q50) max rel. energy error (max |g| where energy is not conserved), each said
to be which, among the runs whose every lane finished.
"""

from __future__ import annotations

import pandas as pd

from reports import figures
from benchmarks.records import one_line
from reports.analysis import fmt, reference_floor, setting
from reports.document import Document, Figure, Para, Table


def section(doc: Document, runs: pd.DataFrame, series, colors: dict, draw) -> None:
    """Add the section for the ensemble runs among ``runs`` (the latest of each identity);
    nothing when there are none. Figures are drawn by ``draw``
    (:class:`reports.figures.Drawing`)."""
    if runs.empty:
        return
    doc.heading(2, "Ensembles")
    doc.add(Para(
        "Each ensemble runs one method from many initial states near the problem's own "
        "(lane 0 is the problem's own; the others are perturbed and projected onto the "
        "constraints, drawn from the run's seed), in one compiled loop where the method "
        "allows ('one loop') or lane by lane. Quantiles are over the lanes that finished; "
        "wall time is the whole ensemble's solve, and work the sum over its lanes. Final "
        "errors, where the problem has a reference at the run's end, are each lane's "
        "against its own: lane 0's the problem's reference, the others' a tight "
        "integration of the lane's index-1 ODE (scipy's DOP853, projected onto the "
        "constraints) whose floor is its difference to a looser one."))
    for problem in sorted(runs["problem"].unique()):
        _problem(doc, problem, runs[runs["problem"] == problem], series, colors, draw)


def _verdicts(runs: pd.DataFrame) -> str:
    # Only runs whose every lane finished take part: the quantiles are over the lanes that
    # finished, so a run with failed lanes would otherwise be judged on its survivors (its
    # worst lane is one that failed).
    metric = "energy" if runs["energy_q50"].notna().any() else "pos"
    name = "max rel. energy error" if metric == "energy" else "max |g|"
    whole = runs[runs["failed_fraction"].astype(float) == 0]
    parts = []
    for q, which in ((100, "worst lane"), (50, "median lane")):
        column = f"{metric}_q{q}"
        done = whole[whole[column].notna()]
        if done.empty:
            continue
        best = done.loc[done[column].astype(float).idxmin()]
        parts.append(f"smallest {name} of the {which} (q{q}): {best['integrator']} "
                     f"{setting(best)} ({fmt(best[column])})")
    if not parts:
        return "Verdicts: no run finished every lane."
    return ("Verdicts, among the runs whose every lane finished: " + "; ".join(parts) + ".")


def _final(row, q: int) -> str:
    """A quantile of a run's final errors, 'at floor' where its lanes' references cannot
    tell it from their own error."""
    value, floor = pd.to_numeric(row[f"final_q{q}"], errors="coerce"), reference_floor(row)
    return "at floor" if 0 < floor and value <= floor else fmt(value)


def _problem(doc: Document, problem: str, runs: pd.DataFrame, series, colors, draw) -> None:
    doc.heading(3, f"Ensembles: {problem}")
    runs = runs.sort_values(["integrator", "h", "rtol"])
    doc.add(Para(_verdicts(runs)))
    final = runs["final_q50"].notna().any()
    of, scored = ((", of", " and of the final error against each lane's reference "
                   "('at floor': at or below the largest of the lanes' reference floors, so "
                   "known only to be at least as accurate)") if final else (" and of", ""))
    rows = []
    for _, r in runs.iterrows():
        rows.append([r["integrator"], setting(r), f"{int(r['lanes'])} (seed {int(r['seed'])})",
                     "one loop" if r["batched"] == 1 else "lane by lane",
                     f"{float(r['failed_fraction']):.3g}",
                     *(fmt(r[f"pos_q{q}"]) for q in (50, 90, 100)),
                     *(fmt(r[f"energy_q{q}"]) for q in (50, 90, 100)),
                     *(_final(r, q) for q in ((50, 90, 100) if final else ())),
                     fmt(r["wall_s"])])
    doc.add(Table(["integrator", "setting", "lanes", "run as", "failed", "max|g| q50", "q90",
                   "q100", "energy q50", "q90", "q100",
                   *(("final q50", "q90", "q100") if final else ()), "wall s"], rows,
                  f"Quantiles over the lanes that finished of max |g|{of} max rel. energy "
                  f"error{scored}; 'failed' is the fraction of lanes that did not finish "
                  f"(blank quantiles: no lane finished)."))
    failed = runs[pd.to_numeric(runs["failed_fraction"], errors="coerce") > 0]
    if not failed.empty:
        doc.add(Para("Runs with failed lanes: " + "; ".join(
            f"{r['integrator']} {setting(r)}: "
            f"{one_line(r['message'] if isinstance(r['message'], str) else '')[:300]}"
            for _, r in failed.iterrows()) + "."))
    entries = [{"label": f"{r['integrator']} {setting(r)}", "integrator": r["integrator"],
                "lanes": series(int(r["run_id"]))["lanes"]} for _, r in runs.iterrows()]
    entries = [e for e in entries if e["lanes"]]
    if entries:
        doc.add(Figure(f"{problem}-ensemble-distributions",
                       draw(figures.distributions, entries, colors, problem),
                       "Per-lane distributions of the lanes that finished, one box per run: "
                       "the box spans the middle half of them, the whiskers all of them, the "
                       "line the median. Final errors where the problem has a reference, "
                       "with the largest of the lanes' reference floors dashed."))
    doc.add(Figure(f"{problem}-ensemble-cost", draw(figures.ensemble_cost, runs, colors, problem),
                   "Left: the median lane's final error (where a run has none, its max "
                   "rel. energy error, or max |g|) against wall time per lane, the band "
                   "and a bar at each run from the best lane to the worst (lanes that "
                   "finished). Right: the "
                   "fraction of lanes that failed against the setting."))
