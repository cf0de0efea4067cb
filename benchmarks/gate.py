"""The drift gate's rule: when is a run worse than the same run before?

One rule, used by ``python -m benchmarks.check`` against its baseline and by the report's
history across commits (so the report never needs the gate's heavy imports). Each run is
reduced to an :func:`entry` (status, failing step, sensitivity, metrics, drift classes),
and :func:`compare` lists every regression, improvement and note between two maps of
entries. Every metric is compared in its own direction with its own :class:`Tolerance`,
as its column's declaration gives it (:mod:`benchmarks.columns`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from benchmarks import columns
from benchmarks.columns import Tolerance
from benchmarks.drift import SEVERITY, kind_of
from benchmarks.records import Status, one_line


#: Per-metric tolerances: the ``gate`` of each column's declaration
#: (:mod:`benchmarks.columns`, which says why they are what they are).
TOLERANCES = columns.TOLERANCES
#: Tolerance of every declared invariant's error (``inv:NAME``).
INVARIANT_TOLERANCE = columns.INVARIANT_TOLERANCE


def tolerance(metric: str) -> Tolerance:
    """The :class:`Tolerance` of a gated metric (``inv:NAME`` for a declared invariant)."""
    return INVARIANT_TOLERANCE if metric.startswith("inv:") else TOLERANCES[metric]


def _ratio(base: float, cur: float) -> str:
    return "from 0" if base == 0 else f"x{cur / base:.3g}"


def compare_metric(metric: str, base: float | None, cur: float | None,
                   spread: tuple[float, float] | None = None,
                   floor: float = 0.0) -> tuple[str | None, str]:
    """``("regression" | "improvement" | None, change text)`` for one metric, ``None``
    meaning not measured.

    ``spread``, where given, is the range ``(lo, hi)`` that round-off alone gave the
    baseline's metric (:func:`benchmarks.check.probe`): a regression is then measured from
    its worse end and an improvement from its better end, so that a value anywhere in it
    is neither. ``floor`` raises a ``lower`` metric's absolute floor: for a final error,
    the accuracy of the references it was measured against, below which a change is the
    reference's, not the method's."""
    tol = tolerance(metric)
    tol = Tolerance(tol.direction, tol.factor, max(tol.floor, floor)) \
        if tol.direction == "lower" else tol
    if base is None and cur is None:
        return None, ""
    if cur is None:
        return "regression", "no longer measured"
    if base is None:
        return None, "newly measured"
    if not math.isfinite(cur) and not (tol.direction == "higher" and cur > 0):
        return ("regression", "not finite") if math.isfinite(base) else (None, "")
    lo, hi = (base, base) if spread is None else (min(base, *spread), max(base, *spread))
    if tol.direction == "lower":
        if cur > tol.factor * hi and cur > tol.floor:
            return "regression", _ratio(hi, cur)
        if lo > tol.factor * cur and lo > tol.floor:
            return "improvement", _ratio(lo, cur)
        return None, ""
    c = min(cur, tol.floor)
    digits = math.log10(tol.factor)
    if c < min(lo, tol.floor) - digits:
        return "regression", f"{c - min(lo, tol.floor):+.2f} digits"
    if c > min(hi, tol.floor) + digits:
        return "improvement", f"{c - min(hi, tol.floor):+.2f} digits"
    return None, ""


#: The floor an entry records (as ``floor``): its reference's, which final errors are
#: judged against (:data:`benchmarks.columns.REFERENCE`).
REFERENCE_FLOOR = columns.REFERENCE.column

#: Statuses of runs that completed their horizon.
FINISHED = (Status.OK,)


#: The recorded drift classes the gate compares (runs.csv columns).
GROWTH = ("pos_growth", "energy_growth")


def _given(value):
    """``value``, or None where it is missing (None, or NaN as pandas reads a blank)."""
    return None if value is None or (isinstance(value, float) and math.isnan(value)) \
        else value


def metrics_of(row: dict) -> dict[str, float | None]:
    """The accuracy metrics of a ``runs.csv`` row (None where not measured)."""
    out = {}
    for name in TOLERANCES:
        value = _given(row.get(name))
        out[name] = None if value is None else float(value)
    try:
        invariants = json.loads(_given(row.get("invariant_errors")) or "{}")
    except (TypeError, ValueError):
        invariants = {}
    out.update({f"inv:{k}": (None if v is None else float(v)) for k, v in invariants.items()})
    return out


@dataclass(frozen=True)
class Finding:
    """One difference between the baseline and the current run."""

    kind: str  # "regression", "improvement", "note"
    run: str
    metric: str
    baseline: str
    current: str
    change: str
    gating: bool


def _fmt(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    return f"{x:.3g}"


def compare_growth(base: str | None, cur: str | None) -> tuple[str | None, str]:
    """``("regression" | "improvement" | None, change text)`` for one drift class."""
    if base not in SEVERITY or cur not in SEVERITY or base == cur:
        return None, ""
    kind = "regression" if SEVERITY.index(cur) > SEVERITY.index(base) else "improvement"
    return kind, f"{base} -> {cur}"


def compare(baseline: dict, current: dict) -> list[Finding]:
    """Every regression, improvement and note between two ``{run id: entry}`` maps.

    An entry holds ``status``, ``fail_step``, ``sensitive``, ``metrics`` and ``floor``
    (the reference floor of its final error, where recorded); a baseline
    entry may list in ``roundoff`` the metrics and drift classes that round-off decides
    (:func:`benchmarks.check.probe`), and give in ``spread`` the range round-off gave each
    such metric. A listed metric with a spread is gated against that range widened by its
    tolerance (:func:`compare_metric`); one without (a drift class) is compared but never
    gating.
    """
    findings: list[Finding] = []
    for rid, cur in current.items():
        sensitive = cur.get("sensitive", False)
        base = baseline.get(rid)
        spreads = (base or {}).get("spread", {})
        loose = set((base or {}).get("roundoff", ())) - spreads.keys()

        def gating(metric: str) -> bool:
            return not sensitive and metric not in loose

        if base is None:
            findings.append(Finding("note", rid, "run", "-", cur["status"],
                                    "not in the baseline", False))
            continue
        bs, cs = base["status"], cur["status"]
        if bs in FINISHED and cs not in FINISHED:
            findings.append(Finding("regression", rid, "status", bs, cs,
                                    "newly fails: " + one_line(cur.get("message") or "")[:200],
                                    gating("status")))
            continue
        if bs not in FINISHED and cs in FINISHED:
            findings.append(Finding("improvement", rid, "status", bs, cs, "now finishes",
                                    gating("status")))
            continue
        if bs not in FINISHED:
            if cs != bs:
                findings.append(Finding("regression", rid, "status", bs, cs,
                                        one_line(cur.get("message") or "")[:200],
                                        gating("status")))
            elif (base.get("fail_step") is not None and cur.get("fail_step") is not None
                  and cur["fail_step"] != base["fail_step"]):
                kind = "regression" if cur["fail_step"] < base["fail_step"] else "improvement"
                findings.append(Finding(kind, rid, "fail_step", str(base["fail_step"]),
                                        str(cur["fail_step"]), "fails at another step",
                                        gating("fail_step")))
            continue
        names = list(dict.fromkeys([*base["metrics"], *cur["metrics"]]))
        # The larger of the two runs' reference floors: where both final errors lie below
        # it, neither they nor their digits (scd) can tell the runs apart.
        floors = {REFERENCE_FLOOR: max(base.get("floor") or 0.0, cur.get("floor") or 0.0)}
        for metric in names:
            b, c = base["metrics"].get(metric), cur["metrics"].get(metric)
            if metric not in TOLERANCES and not metric.startswith("inv:"):
                continue
            judged = columns.TABLE[metric].floor if metric in TOLERANCES else None
            floor = floors.get(judged.column, 0.0) if judged is not None else 0.0
            if floor > 0 and judged.of != metric and all(
                    e is not None and e <= floor
                    for e in (base["metrics"].get(judged.of), cur["metrics"].get(judged.of))):
                continue
            spread = spreads.get(metric)
            kind, change = compare_metric(metric, b, c, spread,
                                          floor if judged is not None and judged.of == metric
                                          else 0.0)
            if kind is not None:
                shown = _fmt(b) if spread is None else \
                    f"{_fmt(b)} (round-off {_fmt(min(spread))} to {_fmt(max(spread))})"
                findings.append(Finding(kind, rid, metric, shown, _fmt(c), change,
                                        gating(metric)))
        for series in GROWTH:
            b, c = base.get("growth", {}).get(series), cur.get("growth", {}).get(series)
            kind, change = compare_growth(b, c)
            if kind is not None:
                findings.append(Finding(kind, rid, series, b, c, change, gating(series)))
    for rid in baseline:
        if rid not in current:
            findings.append(Finding("regression", rid, "run", baseline[rid]["status"], "-",
                                    "in the baseline, not run", True))
    return findings


def entry(row) -> dict:
    """What the gate compares of a run's row (a ``runs.csv`` dict or a stored row)."""
    fail_step = _given(row.get("fail_step"))
    floor = _given(row.get(REFERENCE_FLOOR))
    return {
        "status": row["status"],
        "message": _given(row.get("message")) or "",
        "fail_step": None if fail_step is None else int(fail_step),
        "sensitive": bool(_given(row.get("sensitive"))),
        "metrics": metrics_of(row),
        "floor": None if floor is None else float(floor),
        "growth": {series: kind_of(_given(row.get(series))) for series in GROWTH},
    }
