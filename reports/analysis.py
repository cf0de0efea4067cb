"""What the report computes from stored runs: selections, winners, orders.

Pure functions of the ``load_runs`` frame and the stored series; nothing here imports an
integrator or a problem, and nothing reconstructs what a run knew: energy scales, drift
classes, nominal orders and sensitivity are columns of the stored record.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from benchmarks import records
from benchmarks.drift import fit_order

#: Factor within which two methods count as tied for the smallest drift.
TIE_FACTOR = 10.0
#: Errors below these are round-off and left out of order fits: against a true reference,
#: and against the finest run (which carries its own error).
ORDER_FLOOR = 1e-12
SELF_ORDER_FLOOR = 1e-10

PRECISION = (("final_state_error", "final error"), ("max_pos_residual", "max |g|"),
             ("rel_energy_error", "max rel. energy error"))
COST = (("wall_s", "wall time [s]"), ("n_f_evals", "evaluations"))


def _num(x) -> float:
    """A float, NaN for missing values."""
    try:
        return float(x) if x is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def fmt(x, digits: int = 3) -> str:
    """A number for a table: 3 significant digits, '' for missing (callers say why)."""
    x = _num(x)
    if math.isnan(x):
        return ""
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return f"{x:.{digits}g}"


def text(value) -> str:
    """A text cell: '' for a missing value (None or NaN, as pandas reads empty text)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return str(value)


def base_name(spec: str) -> str:
    """``name`` of a ``name:key=value`` spec."""
    return str(spec).partition(":")[0]


def setting(row) -> str:
    """The swept setting of a run: its step size or tolerances."""
    return records.setting(row.get("h"), row.get("rtol"), row.get("atol"))


def is_ok(row) -> bool:
    return row.get("status") == "ok"


def latest(runs: pd.DataFrame) -> pd.DataFrame:
    """The most recent run of each identity (:func:`benchmarks.records.identity`): a later
    run replaces an earlier one in the per-problem tables (the history keeps them all)."""
    if runs.empty:
        return runs
    key = pd.Series([records.identity(r) for _, r in runs.iterrows()], index=runs.index)
    return runs.loc[~key.duplicated(keep="last")].reset_index(drop=True)


def representative(runs: pd.DataFrame) -> pd.DataFrame:
    """One run per integrator for drift plots and drift winners.

    The longest horizon first (drift is a long-time property); among those, a finished run
    before a failed one; then the coarsest setting (largest ``h`` or ``rtol``), where drift
    shows most.
    """
    if runs.empty:
        return runs
    r = runs.copy()
    r["_ok"] = (r["status"] == "ok").astype(int)
    r["_coarse"] = r["h"].astype(float).fillna(r["rtol"].astype(float)).fillna(0.0)
    r["_t_end"] = r["t_end"].astype(float).fillna(0.0)
    r = r.sort_values(["_t_end", "_ok", "_coarse"], ascending=False)
    return r.drop_duplicates("integrator").drop(columns=["_ok", "_coarse", "_t_end"]) \
        .sort_values("integrator").reset_index(drop=True)


def sweep_horizon(runs: pd.DataFrame) -> float | None:
    """The horizon of the sweeps: the ``t_end`` with the most finished runs of distinct
    settings (ties: the longest). Work-precision, convergence and cost at matched accuracy
    compare runs at this one horizon only: errors over different horizons do not compare.
    """
    ok = runs[(runs["status"] == "ok") & runs["t_end"].notna()]
    if ok.empty:
        return None
    counts = ok.assign(_s=[f"{r['integrator']}|{setting(r)}" for _, r in ok.iterrows()]) \
        .groupby("t_end")["_s"].nunique()
    best = counts.max()
    return float(max(t for t, c in counts.items() if c == best))


def at_sweep_horizon(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs (finished or not) at :func:`sweep_horizon`."""
    t = sweep_horizon(runs)
    return runs.iloc[0:0] if t is None else runs[runs["t_end"].astype(float) == t]


def worst_constraint(row) -> float:
    """``max(max |g|, max |G v + g_t|)``: the drift a run shows at either level."""
    vals = [_num(row.get("max_pos_residual")), _num(row.get("max_vel_residual"))]
    vals = [v for v in vals if not math.isnan(v)]
    return max(vals) if vals else math.nan


@dataclass
class Winner:
    """A headline verdict: the winner, its value, and the text that explains it."""

    integrator: str | None
    value: float
    text: str


def drift_winner(runs: pd.DataFrame) -> Winner:
    """Smallest ``max(|g|, |G v + g_t|)`` among the finished representative runs."""
    rep = representative(runs)
    rep = rep[rep["status"] == "ok"]
    vals = {r["integrator"]: worst_constraint(r) for _, r in rep.iterrows()}
    vals = {k: v for k, v in vals.items() if not math.isnan(v)}
    if not vals:
        return Winner(None, math.nan, "no finished run")
    best = min(vals, key=vals.get)
    row = rep[rep["integrator"] == best].iloc[0]
    ties = sorted(k for k, v in vals.items() if k != best and v <= TIE_FACTOR * vals[best])
    verdict = f"{best} ({setting(row)}, t_end={fmt(row['t_end'])}): {fmt(vals[best])}"
    if ties:
        verdict += f"; within {TIE_FACTOR:g}x: {', '.join(ties)}"
    return Winner(best, vals[best], verdict)


def energy_winner(runs: pd.DataFrame) -> Winner:
    """Smallest max relative energy error among the finished representative runs, with
    the drift class its run recorded."""
    rep = representative(runs)
    rep = rep[(rep["status"] == "ok") & rep["rel_energy_error"].notna()]
    if rep.empty:
        return Winner(None, math.nan, "no conserved energy, or no finished run")
    row = rep.loc[rep["rel_energy_error"].astype(float).idxmin()]
    cls = f", {row['energy_growth']}" if text(row.get("energy_growth")) else ""
    return Winner(row["integrator"], float(row["rel_energy_error"]),
                  f"{row['integrator']} ({setting(row)}): {fmt(row['rel_energy_error'])}{cls}")


def is_sensitive(runs: pd.DataFrame) -> bool:
    """Whether the runs' problem is declared chaotic (``System.sensitive``)."""
    return "sensitive" in runs and bool((runs["sensitive"] == 1).any())


def accuracy_metric(runs: pd.DataFrame) -> str | None:
    """The accuracy that cost is matched on: the final error where a reference exists and
    the problem is not chaotic (there it measures how fast nearby solutions separate), else
    the relative energy error; None when neither was measured."""
    ok = runs[runs["status"] == "ok"]
    columns = ("rel_energy_error",) if is_sensitive(runs) else \
        ("final_state_error", "rel_energy_error")
    for col in columns:
        if ok[col].notna().any():
            return col
    return None


def cost_winner(runs: pd.DataFrame) -> Winner:
    """Cheapest method (wall time) at matched accuracy.

    The target is the median over methods of the best accuracy each reached; each method's
    cost is its cheapest finished run at or below the target; methods that never reach it
    are named as such.
    """
    runs = at_sweep_horizon(runs)
    metric = accuracy_metric(runs)
    if metric is None:
        return Winner(None, math.nan, "no accuracy measured")
    ok = runs[(runs["status"] == "ok") & runs[metric].notna() & runs["wall_s"].notna()].copy()
    ok[metric] = ok[metric].astype(float)
    if ok.empty:
        return Winner(None, math.nan, "no finished run with a measured accuracy")
    best = ok.groupby("integrator")[metric].min()
    target = float(np.median(best.values))
    hits = ok[ok[metric] <= target]
    cheapest = hits.loc[hits.groupby("integrator")["wall_s"].idxmin()]
    row = cheapest.loc[cheapest["wall_s"].astype(float).idxmin()]
    missed = sorted(set(best.index) - set(cheapest["integrator"]))
    label = dict(PRECISION)[metric]
    verdict = (f"{row['integrator']} ({setting(row)}): {fmt(row['wall_s'])} s, "
               f"{fmt(row['n_f_evals'])} evaluations for {label} ≤ {fmt(target)} at "
               f"t_end = {fmt(row['t_end'])}")
    if missed:
        verdict += f"; not reached by {', '.join(missed)}"
    return Winner(row["integrator"], float(row["wall_s"]), verdict)


def options(row) -> dict:
    try:
        return json.loads(row.get("options") or "{}")
    except (TypeError, ValueError):
        return {}


def final_state(row) -> np.ndarray | None:
    """``(q, v)`` at ``t_final`` as stored, or None."""
    try:
        q = json.loads(row.get("q_final") or "null")
        v = json.loads(row.get("v_final") or "null")
    except (TypeError, ValueError):
        return None
    if not q or v is None:
        return None
    return np.concatenate([np.asarray(q, float), np.asarray(v, float)])


@dataclass
class Convergence:
    """Error against step size of one fixed-step integrator."""

    integrator: str
    h: np.ndarray
    err: np.ndarray
    order: float
    n_fit: int
    nominal: float


def convergence(runs: pd.DataFrame) -> tuple[list[Convergence], str]:
    """Observed orders of the fixed-step methods and what their error is measured against.

    The error is the final error against the case's reference where one exists. Without
    one, it is the max-norm distance of the final state to that of the finest finished run
    of the highest nominal order at the same horizon (a self-convergence estimate; that
    run is left out). Uses the horizon with the most distinct step sizes.
    """
    fixed = runs[(runs["status"] == "ok") & runs["h"].notna()].copy()
    if fixed.empty:
        return [], "no finished fixed-step run"
    counts = fixed.groupby("t_end")["h"].nunique()
    horizon = max(t for t, c in counts.items() if c == counts.max())
    fixed = fixed[fixed["t_end"] == horizon]
    if fixed["final_state_error"].notna().any():
        fixed["_err"] = fixed["final_state_error"].astype(float)
        basis, floor = "final error against the reference", ORDER_FLOOR
    else:
        fixed["_order"] = fixed["nominal_order"].astype(float).fillna(0.0)
        ref = fixed.sort_values(["_order", "h"], ascending=[False, True]).iloc[0]
        y_ref = final_state(ref)
        if y_ref is None:
            return [], "no final states stored"
        fixed = fixed[fixed["run_id"] != ref["run_id"]]
        errs = []
        for _, r in fixed.iterrows():
            y = final_state(r)
            errs.append(float(np.max(np.abs(y - y_ref))) if y is not None and
                        y.shape == y_ref.shape else math.nan)
        fixed["_err"] = errs
        basis = (f"max-norm distance of the final (q, v) to the finest run "
                 f"({ref['integrator']}, {setting(ref)}), no reference exists")
        floor = SELF_ORDER_FLOOR
    out = []
    for key, grp in fixed.groupby("integrator"):
        grp = grp.sort_values("h")
        h, err = grp["h"].astype(float).values, grp["_err"].values
        order, n = fit_order(h, err, floor=floor)
        nominal = _num(grp["nominal_order"].iloc[0]) if "nominal_order" in grp else math.nan
        out.append(Convergence(key, h, err, order, n, nominal))
    return out, f"t_end = {fmt(horizon)}; error: {basis}"
