"""What the report computes from stored runs: selections, winners, targets, orders, history.

Pure functions of the ``load_runs`` frame and the stored series; nothing here imports an
integrator or a problem, and nothing reconstructs what a run knew: energy scales, drift
classes, nominal orders, sensitivity and the reference's accuracy are columns of the stored
record.

Three rules run through every verdict here:

- **Reference floor.** A final error at or below the reference's own accuracy
  (``reference_floor``) says only that the run is at least as accurate as the reference:
  it is shown as "at reference floor", a verdict counts it as the floor itself
  (:func:`accuracy`), and order fits leave it out. Final errors below the round-off
  plateau (:data:`ORDER_FLOOR`) are masked the same way in verdicts and fits.
- **Asymptotic range.** An observed order is fitted only through points whose consecutive
  pairwise orders agree within :data:`ORDER_TOLERANCE`, at least :data:`MIN_FIT_POINTS` of
  them (:func:`fit`); the points left out are named with the reason.
- **Timing spread.** Wall times are medians of repeated solves with their minimum and
  maximum; one run is named faster than another only when its slowest repeat beat the
  other's fastest (:func:`cheapest`; a run solved once is given the widest relative spread
  measured among the problem's finished runs at that horizon). Evaluation counts are exact
  and need no such rule.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from benchmarks import columns, gate, records
from benchmarks.drift import fit_order
from benchmarks.records import Status

#: Factor within which two methods count as tied for the smallest drift.
TIE_FACTOR = 10.0
#: Errors below these are round-off and left out of order fits: against a true reference,
#: and against the finest run (which carries its own error).
ORDER_FLOOR = 1e-12
SELF_ORDER_FLOOR = 1e-10
#: Order fits use only errors above this multiple of the reference floor: an error within
#: it may be up to 1/FIT_MARGIN the reference's own, which bends the slope between two
#: step sizes a factor 2 apart by up to log2(1.1) = 0.14, while a point nearer the floor
#: bends it by up to a whole order.
FIT_MARGIN = 10.0
#: Pairwise orders of an asymptotic range differ by at most this much (:func:`fit`). A
#: quarter order between step sizes a factor 2 apart is an error ratio 2^0.25 = 1.19 off
#: the leading term's: the next term still bends it by about a fifth. The tolerance is
#: wider than the bend FIT_MARGIN allows near the floor (0.14), so a point kept above the
#: floor does not break a range on its own.
ORDER_TOLERANCE = 0.25
#: Fewest points an order is fitted through: two pairwise orders, so that their agreement
#: can show the points are in the asymptotic range; one pairwise order is shown, not fitted.
MIN_FIT_POINTS = 3
#: Default accuracy targets of the target tables (a suite's ``targets`` replace them).
DEFAULT_TARGETS = (1e-4, 1e-8, 1e-12)

#: Precision metrics (work-precision y axes, accuracy targets): name on the command line
#: -> (runs.csv column, label).
PRECISION_AXES = {"final-error": ("final_state_error", "final error"),
                  "g": ("max_pos_residual", "max |g|"),
                  "Gv": ("max_vel_residual", "max |G v + g_t|"),
                  "energy": ("rel_energy_error", "max rel. energy error")}
#: Cost metrics (work-precision x axes): name on the command line -> (column, label).
COST_AXES = {"wall": ("wall_s", "wall time [s]"), "evaluations": ("n_f_evals", "evaluations"),
             "steps": ("n_steps", "steps")}
#: The work-precision axes drawn unless the command line chooses others.
DEFAULT_Y = ("final-error", "g", "energy")
DEFAULT_X = ("wall", "evaluations")
#: The metrics the accuracy-target tables cover.
TARGET_METRICS = ("final-error", "g", "energy")
LABELS = {column: label for column, label in (*PRECISION_AXES.values(), *COST_AXES.values())}


def label(column: str) -> str:
    """A column's label: its axis label (:data:`LABELS`), else its summary table header
    (:mod:`benchmarks.columns`), else its name (an invariant's ``inv:NAME``)."""
    declared = columns.TABLE.get(column)
    return LABELS.get(column) or (declared and declared.header) or column


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
    return row.get("status") == Status.OK


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
    r["_ok"] = (r["status"] == Status.OK).astype(int)
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
    ok = runs[(runs["status"] == Status.OK) & runs["t_end"].notna()]
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
    rep = rep[rep["status"] == Status.OK]
    vals = {r["integrator"]: worst_constraint(r) for _, r in rep.iterrows()}
    vals = {k: v for k, v in vals.items() if not math.isnan(v)}
    if not vals:
        return Winner(None, math.nan, "no finished run")
    best = min(vals, key=vals.get)
    row = rep[rep["integrator"] == best].iloc[0]
    ties = sorted(k for k, v in vals.items() if k != best and v <= TIE_FACTOR * vals[best])
    verdict = f"{best} ({setting(row)}): {fmt(vals[best])}"
    if ties:
        verdict += f"; within {TIE_FACTOR:g}x: {', '.join(ties)}"
    return Winner(best, vals[best], verdict)


def energy_winner(runs: pd.DataFrame) -> Winner:
    """Smallest max relative energy error among the finished representative runs, with
    the drift class its run recorded."""
    rep = representative(runs)
    if "rel_balance_error" in rep and rep["rel_energy_error"].isna().all() \
            and rep["rel_balance_error"].notna().any():
        return _balance_winner(rep)
    rep = rep[(rep["status"] == Status.OK) & rep["rel_energy_error"].notna()]
    if rep.empty:
        return Winner(None, math.nan, "no conserved energy, or no finished run")
    row = rep.loc[rep["rel_energy_error"].astype(float).idxmin()]
    cls = f", {growth_kind(row['energy_growth'])}" if text(row.get("energy_growth")) else ""
    return Winner(row["integrator"], float(row["rel_energy_error"]),
                  f"{row['integrator']} ({setting(row)}): {fmt(row['rel_energy_error'])}{cls}")


def _balance_winner(rep: pd.DataFrame) -> Winner:
    """Without a conserved energy: the smallest max relative energy balance error among
    the finished runs ``rep``, counted only above its quadrature floor (below it the
    quadrature, not the method, sets the number)."""
    rep = rep[rep["status"] == Status.OK]
    value = rep["rel_balance_error"].astype(float)
    rep = rep[value > rep["balance_floor"].astype(float).fillna(0.0)]
    if rep.empty:
        return Winner(None, math.nan, "energy balance: every finished run at its "
                                      "quadrature floor, or none finished")
    row = rep.loc[rep["rel_balance_error"].astype(float).idxmin()]
    return Winner(row["integrator"], float(row["rel_balance_error"]),
                  f"{row['integrator']} ({setting(row)}): {fmt(row['rel_balance_error'])} "
                  f"(energy balance)")


def is_sensitive(runs: pd.DataFrame) -> bool:
    """Whether the runs' problem is declared chaotic (``System.sensitive``)."""
    return "sensitive" in runs and bool((runs["sensitive"] == 1).any())


# --------------------------------------------------------------------------- floors

def reference_floor(row) -> float:
    """The accuracy of the reference a run's final error was measured against; 0 where the
    record holds none (a closed form)."""
    floor = _num(row.get("reference_floor"))
    return 0.0 if math.isnan(floor) else floor


def largest_floor(runs: pd.DataFrame) -> float:
    """The largest reference floor among ``runs``; 0 where none is recorded."""
    return max((reference_floor(r) for _, r in runs.iterrows()), default=0.0)


def at_floor(row) -> bool:
    """Whether a run's final error is at or below its reference's accuracy (floor > 0)."""
    err, floor = _num(row.get("final_state_error")), reference_floor(row)
    return floor > 0.0 and not math.isnan(err) and err <= floor


def accuracies(runs: pd.DataFrame, column: str) -> np.ndarray:
    """The values of a precision metric that a verdict may use, one per row of ``runs``: a
    final error counts as no smaller than the run's reference floor and the round-off
    plateau :data:`ORDER_FLOOR` (below them, the reference or round-off cannot tell runs
    apart)."""
    value = pd.to_numeric(runs[column], errors="coerce").to_numpy(dtype=float)
    if column == "final_state_error":
        floor = pd.to_numeric(runs["reference_floor"], errors="coerce").fillna(0.0) \
            if "reference_floor" in runs else pd.Series(0.0, index=runs.index)
        value = np.where(np.isnan(value), value,
                         np.maximum(value, np.maximum(floor.to_numpy(dtype=float), ORDER_FLOOR)))
    return value


# --------------------------------------------------------------------------- timing

@dataclass(frozen=True)
class Timing:
    """Wall time of a run's timed solves: median, fastest, slowest and how many."""

    median: float
    low: float
    high: float
    repeats: int

    @property
    def measured(self) -> bool:
        """Whether the spread was measured (two solves or more)."""
        return self.repeats >= 2

    def text(self) -> str:
        if math.isnan(self.median):
            return ""
        if not self.measured:
            return f"{fmt(self.median)} (1 solve)"
        return f"{fmt(self.median)} ({fmt(self.low)}-{fmt(self.high)}, {self.repeats} solves)"


def timing(row) -> Timing:
    """The :class:`Timing` of a run (NaN times and one solve where it has none)."""
    n = _num(row.get("repeats"))
    return Timing(_num(row.get("wall_s")), _num(row.get("wall_min_s")),
                  _num(row.get("wall_max_s")), 1 if math.isnan(n) else int(n))


@dataclass
class Pick:
    """The cheapest of some candidate runs by one cost, and who cannot be told from it.

    ``row`` is the cheapest run (None without candidates); ``winner`` says whether it is
    named as the winner (by wall time: only when its slowest solve beat the fastest solve of
    every other candidate); ``ties`` are the integrators whose cost cannot be told from its;
    ``named`` the runs the verdict names (the cheapest and its ties).
    """

    row: pd.Series | None
    winner: bool = False
    ties: list[str] = field(default_factory=list)
    text: str = "none"
    named: list[pd.Series] = field(default_factory=list)


def widest_spread(runs: pd.DataFrame) -> float:
    """The largest slowest-over-fastest ratio of the runs' timed solves (NaN where no run's
    spread was measured)."""
    spreads = [c.high / c.low for c in map(timing, (r for _, r in runs.iterrows()))
               if c.measured and c.low > 0]
    return max(spreads, default=math.nan)


def cheapest(candidates: pd.DataFrame, cost: str, widest: float | None = None) -> Pick:
    """The cheapest of ``candidates`` (one run per integrator) by ``cost``.

    ``cost`` is ``"wall_s"`` or an exact count (``"n_f_evals"``, ``"n_steps"``). By wall
    time the cheapest run is named the winner only when the difference exceeds the timing
    spread: every other candidate's fastest solve is slower than its slowest; candidates
    whose spreads overlap its are ties. A candidate solved once (too long for autorange to
    repeat) is given the relative spread ``widest`` (slowest over fastest; by default the
    widest measured among the candidates): its fastest is its time over that ratio, its
    slowest its time times it. Where no spread was measured, no winner is named. Counts
    are exact: only equal counts tie.
    """
    cands = candidates[candidates[cost].notna()]
    if cands.empty:
        return Pick(None, text="none")
    cands = cands.sort_values(cost, kind="stable")
    best = cands.iloc[0]
    others = cands.iloc[1:]
    name = f"{best['integrator']} ({setting(best)})"
    if cost != "wall_s":
        tied = [r for _, r in others.iterrows() if r[cost] == best[cost]]
        ties = [r["integrator"] for r in tied]
        text = f"{name}: {fmt(best[cost])} {LABELS[cost]}"
        if ties:
            text += f"; tied: {', '.join(ties)}"
        return Pick(best, not ties, ties, text, [best, *tied])
    t = timing(best)
    widest = widest_spread(cands) if widest is None else widest

    # A solve too long for autorange to repeat has no spread of its own: it is given the
    # widest one measured beside it (a ratio), on both sides of its one time.
    slowest = t.high if t.measured else t.high * widest
    tied = [r for _, r in others.iterrows()
            if not (timing(r).low if timing(r).measured else timing(r).low / widest) > slowest]
    ties = [r["integrator"] for r in tied]
    unmeasured = math.isnan(widest)
    text = f"{name}: {t.text()} s"
    if unmeasured and len(cands) > 1:
        text += "; fastest, but no winner: a timing spread was not measured (one solve)"
        return Pick(best, False, ties, text, [best, *tied])
    if ties:
        text += f"; no winner: within the timing spread of {', '.join(ties)}"
    return Pick(best, not ties, ties, text, [best, *tied])


# --------------------------------------------------------------------------- accuracy

def accuracy_metric(runs: pd.DataFrame) -> str | None:
    """The accuracy that cost is matched on: the final error where a reference exists and
    the problem is not chaotic (there it measures how fast nearby solutions separate), else
    the relative energy error; None when neither was measured."""
    ok = runs[runs["status"] == Status.OK]
    columns = ("rel_energy_error",) if is_sensitive(runs) else \
        ("final_state_error", "rel_energy_error")
    for col in columns:
        if ok[col].notna().any():
            return col
    return None


def reaching(runs: pd.DataFrame, column: str, target: float) -> pd.DataFrame:
    """The finished runs whose :func:`accuracy` in ``column`` is at or below ``target``."""
    ok = runs[runs["status"] == Status.OK]
    return ok[accuracies(ok, column) <= target] if len(ok) else ok


def per_integrator(runs: pd.DataFrame, cost: str) -> pd.DataFrame:
    """The cheapest run by ``cost`` of each integrator."""
    runs = runs[runs[cost].notna()]
    if runs.empty:
        return runs
    return runs.loc[runs.groupby("integrator")[cost].idxmin()]


def reach(ok: pd.DataFrame, column: str, level: float):
    """The cheapest finished runs of ``ok`` reaching ``level`` in ``column``, by wall time
    and by evaluations, and the integrators that reach it."""
    hits = reaching(ok, column, level)
    return (cheapest(per_integrator(hits, "wall_s"), "wall_s", widest_spread(ok)),
            cheapest(per_integrator(hits, "n_f_evals"), "n_f_evals"), set(hits["integrator"]))


@dataclass
class Matched:
    """The accuracy that a problem's methods are compared at for cost.

    ``metric`` is the :func:`accuracy_metric`; ``target`` the median over methods of the
    best accuracy each reached; ``ok`` the finished runs at the sweep horizon that measured
    it; ``best`` each method's best accuracy (a final error counts as no better than its
    reference's floor).
    """

    metric: str
    target: float
    ok: pd.DataFrame
    best: pd.Series


def matched(runs: pd.DataFrame) -> Matched | str:
    """The :class:`Matched` accuracy of one problem's runs, or why there is none."""
    runs = at_sweep_horizon(runs)
    metric = accuracy_metric(runs)
    if metric is None:
        return "no accuracy measured"
    ok = runs[(runs["status"] == Status.OK) & runs[metric].notna()]
    if ok.empty:
        return "no finished run with a measured accuracy"
    best = ok.assign(_acc=accuracies(ok, metric)).groupby("integrator")["_acc"].min()
    return Matched(metric, float(np.median(best.values)), ok, best)


@dataclass
class CostWinner(Winner):
    """A cost verdict in its parts: the matched accuracy (``accuracy``), the cheapest run
    reaching it by wall time and by evaluations, the methods that never reach it, and the
    runs each of the two cheapest cells names (``wall_named``, ``evals_named``: the
    cheapest and its ties)."""

    accuracy: str = ""
    by_wall: str = "none"
    by_evals: str = "none"
    missed: list[str] = field(default_factory=list)
    wall_named: list[pd.Series] = field(default_factory=list)
    evals_named: list[pd.Series] = field(default_factory=list)


def cost_winner(runs: pd.DataFrame) -> CostWinner:
    """Cheapest method at matched accuracy, by wall time (with its spread) and by
    evaluations.

    The target is the median over methods of the best accuracy each reached
    (:func:`matched`); each method's cost is its cheapest finished run at or below the
    target; methods that never reach it are named as such.
    """
    m = matched(runs)
    if isinstance(m, str):
        return CostWinner(None, math.nan, m, accuracy=m)
    by_wall, by_evals, reached = reach(m.ok, m.metric, m.target)
    missed = sorted(set(m.best.index) - reached)
    accuracy = f"{LABELS[m.metric]} ≤ {fmt(m.target)} at t_end = {fmt(m.ok['t_end'].iloc[0])}"
    verdict = f"{accuracy}: by wall time {by_wall.text}; by evaluations {by_evals.text}"
    if missed:
        verdict += f"; not reached by {', '.join(missed)}"
    row = by_wall.row
    return CostWinner(row["integrator"] if by_wall.winner else None,
                      _num(row["wall_s"]) if row is not None else math.nan, verdict,
                      accuracy, by_wall.text, by_evals.text, missed, by_wall.named,
                      by_evals.named)


@dataclass
class Standing:
    """Where one method stands on one problem, as the headline figure places it.

    ``wall_s`` and ``n_f_evals`` are the cost of its cheapest run at the matched accuracy
    (:func:`matched`), or, where it never reached it (``reached`` false), of its most
    accurate run; ``drift`` (``max(|g|, |G v + g_t|)``), ``energy`` (max relative energy
    error) and their growth classes are those of its representative run, the run the
    headline's drift and energy columns judge (:func:`representative`). ``finished`` is
    false where that run did not finish.
    """

    integrator: str
    wall_s: float
    n_f_evals: float
    reached: bool
    drift: float
    drift_class: str
    energy: float
    energy_class: str
    finished: bool


def growth_kind(value) -> str:
    """The class word of a stored growth text (``"linear (p = 0.94)"`` -> ``"linear"``)."""
    return text(value).split(" (")[0]


def standings(runs: pd.DataFrame) -> list[Standing]:
    """Each method's :class:`Standing` on one problem's runs, sorted by integrator; methods
    without a finished run at the sweep horizon with a measured accuracy have a NaN cost."""
    m = matched(runs)
    cost = {}
    if not isinstance(m, str):
        acc = m.ok.assign(_acc=accuracies(m.ok, m.metric))
        for key, grp in acc.groupby("integrator"):
            hits = grp[grp["_acc"] <= m.target]
            reached = not hits.empty and hits["wall_s"].notna().any()
            pick = hits.loc[hits["wall_s"].astype(float).idxmin()] if reached else \
                grp.loc[grp["_acc"].astype(float).idxmin()]
            cost[key] = (_num(pick["wall_s"]), _num(pick["n_f_evals"]), reached)
    out = []
    for _, r in representative(runs).iterrows():
        wall, evals, reached = cost.get(r["integrator"], (math.nan, math.nan, False))
        out.append(Standing(r["integrator"], wall, evals, reached, worst_constraint(r),
                            growth_kind(r.get("pos_growth")), _num(r.get("rel_energy_error")),
                            growth_kind(r.get("energy_growth")), r["status"] == Status.OK))
    return out


@dataclass
class Target:
    """One row of an accuracy-target table: the cheapest runs reaching ``target`` in
    ``column``, by wall time and by evaluations, and the integrators that never do."""

    column: str
    target: float
    by_wall: Pick | None
    by_evals: Pick | None
    missed: list[str]
    note: str = ""


def targets(runs: pd.DataFrame, levels=DEFAULT_TARGETS) -> list[Target]:
    """Accuracy-target rows of one problem's runs at the sweep horizon.

    For each measured metric of :data:`TARGET_METRICS` (the final error only where a
    reference exists and the problem is not chaotic) and each level: the cheapest finished
    run reaching it (:func:`cheapest`, by wall time and by evaluations) and the integrators
    that ran but never reached it, with their best value. A final-error level below
    the reference floor or the round-off plateau cannot be checked and says so.
    """
    runs = at_sweep_horizon(runs)
    ok = runs[runs["status"] == Status.OK]
    ran = sorted(set(runs["integrator"]))
    out = []
    for name in TARGET_METRICS:
        column = PRECISION_AXES[name][0]
        if not ok[column].notna().any():
            continue
        if column == "final_state_error" and is_sensitive(runs):
            continue
        floor = max(largest_floor(ok), ORDER_FLOOR) if column == "final_state_error" else 0.0
        best = ok.assign(_acc=accuracies(ok, column)).groupby("integrator")["_acc"].min() \
            .dropna().to_dict()
        for level in sorted(levels, reverse=True):
            if level < floor:
                what = "reference floor" if floor > ORDER_FLOOR else "round-off plateau"
                out.append(Target(column, level, None, None, [],
                                  f"below the {what} ({fmt(floor)}): cannot be checked"))
                continue
            by_wall, by_evals, reached = reach(ok, column, level)
            missed = [f"{k} (best {fmt(best[k])})" if k in best else f"{k} (no finished run)"
                      for k in ran if k not in reached]
            out.append(Target(column, level, by_wall, by_evals, missed))
    return out


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


#: Why a point is left out of an order fit. Below the threshold: the error is the
#: reference's or round-off, not the method's. Above it: outside the asymptotic range
#: (coarser: the leading error term does not dominate yet; finer: the error has left the
#: power law, approaching round-off or the reference), or too few points to find one.
AT_FLOOR, ROUND_OFF, NO_ERROR = "reference floor", "round-off", "no error"
PRE_ASYMPTOTIC, PAST_RANGE = "pre-asymptotic", "past the asymptotic range"
TOO_FEW, DISAGREE = "too few points", "pairwise orders disagree"
#: The reasons of the points above the threshold ("" of the fitted ones).
ABOVE_THRESHOLD = ("", PRE_ASYMPTOTIC, PAST_RANGE, TOO_FEW, DISAGREE)


@dataclass
class Convergence:
    """Error against step size of one fixed-step integrator, and the fit through it.

    ``h`` ascending, ``err`` the error at each. ``fitted`` marks the points the order was
    fitted from (:func:`asymptotic_range`); ``left_out`` says for each point why it was
    not ("" where fitted; the reasons above). ``pairwise`` holds the orders between
    consecutive usable points (those above ``threshold``, the larger of the round-off
    plateau and :data:`FIT_MARGIN` times the reference floor ``floor``), coarsest pair
    first. ``order`` is NaN where no asymptotic range of :data:`MIN_FIT_POINTS` points
    exists.
    """

    integrator: str
    h: np.ndarray
    err: np.ndarray
    order: float
    fitted: np.ndarray
    left_out: list[str]
    pairwise: np.ndarray
    nominal: float
    threshold: float
    floor: float = 0.0

    @property
    def n_fit(self) -> int:
        return int(self.fitted.sum())

    @property
    def usable(self) -> np.ndarray:
        """The points above the threshold: those the pairwise orders join."""
        return np.array([why in ABOVE_THRESHOLD for why in self.left_out], dtype=bool)


def pairwise_orders(h, err) -> np.ndarray:
    """``log(e_i / e_(i+1)) / log(h_i / h_(i+1))`` of consecutive points, in their order."""
    h, err = np.asarray(h, dtype=float), np.asarray(err, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(err[:-1] / err[1:]) / np.log(h[:-1] / h[1:])


def asymptotic_range(pairwise: np.ndarray, tolerance: float = ORDER_TOLERANCE
                     ) -> tuple[int, int] | None:
    """The asymptotic range of ``pairwise`` orders (coarsest pair first): ``(i, j)`` such
    that points ``i..j`` (of the ``len(pairwise) + 1`` points they join) are fitted.

    The rule: the longest run of consecutive pairwise orders whose largest and smallest
    differ by at most ``tolerance``, of at least ``MIN_FIT_POINTS - 1`` orders; of equally
    long runs, the finest (the asymptotic range lies at small h). This is the asymptotic
    range of a convergence study, where the observed order no longer changes under
    refinement (Roache, *Verification and Validation in Computational Science and
    Engineering*, 1998; Oberkampf & Roy, *Verification and Validation in Scientific
    Computing*, 2010): a fit through points outside it averages the leading term's order
    with higher terms' (coarse side) or with round-off and the reference's error (fine
    side). None where no such run exists: two points give one pairwise order, which no
    second one confirms.
    """
    best, longest = None, MIN_FIT_POINTS - 1
    for i in range(len(pairwise)):
        for j in range(i, len(pairwise)):
            run = pairwise[i:j + 1]
            if not np.all(np.isfinite(run)) or run.max() - run.min() > tolerance:
                break
            if len(run) >= longest:  # ties go to the later, finer run
                best, longest = (i, j + 1), len(run)
    return best


def fit(integrator: str, h, err, nominal: float, plateau: float,
        floor: float = 0.0) -> Convergence:
    """Fit the observed order over the asymptotic range (:func:`asymptotic_range`) of the
    points above the round-off ``plateau`` and :data:`FIT_MARGIN` times the reference
    ``floor``: the least-squares slope of ``log err`` against ``log h`` there."""
    h, err = np.asarray(h, dtype=float), np.asarray(err, dtype=float)
    order_h = np.argsort(h, kind="stable")
    h, err = h[order_h], err[order_h]
    threshold = max(plateau, FIT_MARGIN * floor)
    finite = np.isfinite(h) & np.isfinite(err) & (h > 0)
    usable = finite & (err > threshold) & (err > 0)
    left_out = [NO_ERROR if not f else "" if u else
                AT_FLOOR if floor > 0 and e <= FIT_MARGIN * floor else ROUND_OFF
                for f, u, e in zip(finite, usable, err)]
    idx = np.flatnonzero(usable)[::-1]  # coarsest first
    pairwise = pairwise_orders(h[idx], err[idx])
    span = asymptotic_range(pairwise)
    fitted = np.zeros(len(h), dtype=bool)
    order = math.nan
    if span is None:
        why = TOO_FEW if len(idx) < MIN_FIT_POINTS else DISAGREE
        for k in idx:
            left_out[k] = why
    else:
        i, j = span
        fitted[idx[i:j + 1]] = True
        for k in idx[:i]:
            left_out[k] = PRE_ASYMPTOTIC
        for k in idx[j + 1:]:
            left_out[k] = PAST_RANGE
        order, _ = fit_order(h[fitted], err[fitted])
    return Convergence(integrator, h, err, order, fitted, left_out, pairwise, nominal,
                       threshold, floor)


def convergence(runs: pd.DataFrame) -> tuple[list[Convergence], str]:
    """Observed orders of the fixed-step methods and what their error is measured against.

    The error is the final error against the case's reference where one exists, fitted
    above its floor. Without one, it is the max-norm distance of the final state to that of
    the finest finished run of the highest nominal order at the same horizon (a
    self-convergence estimate; that run is left out). Uses the horizon with the most
    distinct step sizes.
    """
    fixed = runs[(runs["status"] == Status.OK) & runs["h"].notna()].copy()
    if fixed.empty:
        return [], "no finished fixed-step run"
    counts = fixed.groupby("t_end")["h"].nunique()
    horizon = max(t for t, c in counts.items() if c == counts.max())
    fixed = fixed[fixed["t_end"] == horizon]
    floor = 0.0
    if fixed["final_state_error"].notna().any():
        fixed["_err"] = fixed["final_state_error"].astype(float)
        floor = largest_floor(fixed)
        basis, plateau = "final error against the reference", ORDER_FLOOR
        if floor > 0:
            basis += (f" (itself accurate to {fmt(floor)}: only errors above "
                      f"{fmt(max(plateau, FIT_MARGIN * floor))} are fitted)")
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
        plateau = SELF_ORDER_FLOOR
    out = []
    for key, grp in fixed.groupby("integrator"):
        grp = grp.sort_values("h")
        nominal = _num(grp["nominal_order"].iloc[0]) if "nominal_order" in grp else math.nan
        out.append(fit(key, grp["h"].values, grp["_err"].values, nominal, plateau, floor))
    return out, f"t_end = {fmt(horizon)}; error: {basis}"


# --------------------------------------------------------------------------- history

@dataclass
class History:
    """The gate's metrics across commits.

    ``commits``: one row per commit (``commit``, ``label``, ``started``, ``dirty``,
    ``runs``), oldest first; ``values``: gated metric (:data:`benchmarks.gate.TOLERANCES`)
    -> frame of run identity x commit label
    (the latest run of each identity within each commit; NaN where not measured);
    ``regressions``: ``(identity, metric, from label, to label, change)`` between
    consecutive commits that measured the run: exactly the gating regressions of
    :func:`benchmarks.gate.compare` (metrics, declared invariants, drift classes, a run
    that no longer finishes or fails earlier). Runs of chaotic problems are shown but, as
    in the gate, never regress.
    """

    commits: pd.DataFrame
    values: dict[str, pd.DataFrame]
    regressions: list[tuple[str, str, str, str, str]]


def history(runs: pd.DataFrame) -> History:
    """The :class:`History` of every stored run."""
    key = runs["commit"].fillna("")
    groups = runs.assign(_commit=key).groupby("_commit", sort=False)
    commits = pd.DataFrame({
        "commit": [c for c, _ in groups],
        "started": [float(g["session_started"].min()) for _, g in groups],
        "dirty": [bool(g["dirty"].astype(bool).any()) for _, g in groups],
        "runs": [len(g) for _, g in groups],
    }).sort_values("started", kind="stable").reset_index(drop=True)
    commits["label"] = [(c[:10] or "unknown") + ("+" if d else "")
                        for c, d in zip(commits["commit"], commits["dirty"])]
    per_commit = {label: latest(runs[key == commit])
                  for commit, label in zip(commits["commit"], commits["label"])}
    rows = {label: {records.identity(r): r for _, r in sub.iterrows()}
            for label, sub in per_commit.items()}
    identities = sorted({i for by_id in rows.values() for i in by_id})
    values = {m: pd.DataFrame(
        [[_num(rows[c][i].get(m)) if i in rows[c] and is_ok(rows[c][i]) else math.nan
          for c in commits["label"]] for i in identities],
        index=identities, columns=list(commits["label"]), dtype=float) for m in gate.TOLERANCES}
    regressions = []
    labels = list(commits["label"])
    for ident in identities:
        seen = [(c, rows[c][ident]) for c in labels if ident in rows[c]]
        for (c0, r0), (c1, r1) in zip(seen, seen[1:]):
            regressions += [(ident, f.metric, c0, c1, f.change or f"{f.baseline} -> {f.current}")
                            for f in gate.compare({ident: gate.entry(r0)},
                                                  {ident: gate.entry(r1)})
                            if f.kind == "regression" and f.gating]
    return History(commits, values, regressions)
