"""The drift gate: run a suite and compare every accuracy metric with a committed baseline.

::

    python -m benchmarks.check --suite ci --baseline benchmarks/baselines/ci.json
    python -m benchmarks.check --suite ci --baseline benchmarks/baselines/ci.json --update

Each run of the suite is matched to the baseline's run of the same identity
(:func:`benchmarks.records.identity`: problem, integrator, setting, horizon). Every
metric is compared in its own direction with its own
:class:`benchmarks.records.Tolerance` (the rule the report's history shares): lower is
better for constraint residuals, energy and invariant errors and final errors; higher is
better for ``scd`` (significant correct digits). A metric regresses when it is worse
than the baseline by more than its relative factor *and* lies above its absolute floor
(values at or below the floor are round-off, which may differ between machines). The drift classes
of ``|g|`` and ``|H - H0|`` that each run recorded (:mod:`benchmarks.drift`) regress when
they grow faster than before (bounded, linear, quadratic, superquadratic, exponential). A
run that finished in the baseline and now does not (``failed``, ``error``, ``timeout``)
is a regression, as is a failed run that now fails earlier. A baseline run missing from
the results is a regression too (the gate must not pass by comparing less); a run new in
the suite is reported, not gated (``--update`` records the suite as it is).

Runs of sensitive (chaotic) problems, ``System.sensitive``, are compared and reported but
never fail the gate: their final states depend on round-off.

The baseline is checked before anything runs: it must be a baseline of the suite asked
for, hold at least one run, and every run must have a ``status`` and ``metrics`` whose
values are numbers or null, none NaN (``+inf`` only for ``scd``, an exact final state). A
gate that compared nothing, or compared against NaN (every comparison with NaN is false),
would pass whatever the code does. The last line of output says how many runs were
compared.

Exit status: 0 when nothing gating regressed (or after ``--update``), 1 on a regression,
2 on bad input (unknown suite, unreadable, empty, malformed or another suite's baseline).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks import suites
from benchmarks.batch import run_specs
from benchmarks.drift import SEVERITY, kind_of
from benchmarks.executors import load_plugins
from benchmarks.files import replace_file
from benchmarks.records import (TOLERANCES, InputError, compare_metric, identity, one_line,
                                provenance)

EXIT_OK, EXIT_REGRESSION, EXIT_INPUT = 0, 1, 2
BASELINE_FORMAT = 1
#: Statuses of runs that completed their horizon.
FINISHED = ("ok",)


#: The recorded drift classes the gate compares (runs.csv columns).
GROWTH = ("pos_growth", "energy_growth")


def metrics_of(row: dict) -> dict[str, float | None]:
    """The accuracy metrics of a ``runs.csv`` row (None where not measured)."""
    out = {}
    for name in TOLERANCES:
        value = row.get(name)
        out[name] = None if value is None or (isinstance(value, float) and math.isnan(value)) \
            else float(value)
    try:
        invariants = json.loads(row.get("invariant_errors") or "{}")
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

    An entry holds ``status``, ``fail_step``, ``sensitive`` and ``metrics``.
    """
    findings: list[Finding] = []
    for rid, cur in current.items():
        gating = not cur.get("sensitive", False)
        base = baseline.get(rid)
        if base is None:
            findings.append(Finding("note", rid, "run", "-", cur["status"],
                                    "not in the baseline", False))
            continue
        bs, cs = base["status"], cur["status"]
        if bs in FINISHED and cs not in FINISHED:
            findings.append(Finding("regression", rid, "status", bs, cs,
                                    "newly fails: " + one_line(cur.get("message") or "")[:200],
                                    gating))
            continue
        if bs not in FINISHED and cs in FINISHED:
            findings.append(Finding("improvement", rid, "status", bs, cs, "now finishes", gating))
            continue
        if bs not in FINISHED:
            if cs != bs:
                findings.append(Finding("regression", rid, "status", bs, cs,
                                        one_line(cur.get("message") or "")[:200], gating))
            elif (base.get("fail_step") is not None and cur.get("fail_step") is not None
                  and cur["fail_step"] != base["fail_step"]):
                kind = "regression" if cur["fail_step"] < base["fail_step"] else "improvement"
                findings.append(Finding(kind, rid, "fail_step", str(base["fail_step"]),
                                        str(cur["fail_step"]), "fails at another step", gating))
            continue
        names = list(dict.fromkeys([*base["metrics"], *cur["metrics"]]))
        for metric in names:
            b, c = base["metrics"].get(metric), cur["metrics"].get(metric)
            if metric not in TOLERANCES and not metric.startswith("inv:"):
                continue
            kind, change = compare_metric(metric, b, c)
            if kind is not None:
                findings.append(Finding(kind, rid, metric, _fmt(b), _fmt(c), change, gating))
        for series in GROWTH:
            b, c = base.get("growth", {}).get(series), cur.get("growth", {}).get(series)
            kind, change = compare_growth(b, c)
            if kind is not None:
                findings.append(Finding(kind, rid, series, b, c, change, gating))
    for rid in baseline:
        if rid not in current:
            findings.append(Finding("regression", rid, "run", baseline[rid]["status"], "-",
                                    "in the baseline, not run", True))
    return findings


def entries(records) -> dict[str, dict]:
    """Baseline entries of a suite's records, by run identity."""
    out = {}
    for record in records:
        row = record.row
        fail_step = row.get("fail_step")
        out[identity(row)] = {
            "status": row["status"],
            "message": row.get("message") or "",
            "fail_step": int(fail_step) if fail_step is not None else None,
            "sensitive": bool(row.get("sensitive")),
            "metrics": metrics_of(row),
            "growth": {series: kind_of(row.get(series)) for series in GROWTH},
        }
    return out


def table(findings: list[Finding]) -> str:
    """The findings as an aligned text table, regressions first."""
    order = {"regression": 0, "improvement": 1, "note": 2}
    rows = [("verdict", "run", "metric", "baseline", "current", "change")]
    for f in sorted(findings, key=lambda f: (order[f.kind], f.run, f.metric)):
        verdict = f.kind if f.gating or f.kind == "note" else f"{f.kind} (not gating)"
        rows.append((verdict, f.run, f.metric, f.baseline, f.current, f.change))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows)


def _bad_metric(metric: str, value) -> bool:
    """Whether a baseline metric value cannot be compared with (see the module notes)."""
    if value is None:
        return False
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        return True
    return math.isinf(value) and not (value > 0 and metric in TOLERANCES
                                      and TOLERANCES[metric].direction == "higher")


def check_entries(runs: dict, where: str) -> None:
    """Refuse baseline entries the gate cannot compare with, naming the first bad one.

    Raises
    ------
    InputError
        An entry that is not an object, lacks ``status`` or ``metrics``, or has a metric
        that is not a number or null, or is NaN or infinite (but ``scd = +inf``).
    """
    for rid, entry in runs.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("status"), str) \
                or not isinstance(entry.get("metrics"), dict):
            raise InputError(f"{where}: run {rid!r} needs a status and metrics; "
                             f"recreate the baseline with --update")
        for metric, value in entry["metrics"].items():
            if _bad_metric(metric, value):
                raise InputError(f"{where}: run {rid!r}: metric {metric} = {value!r} cannot "
                                 f"be compared with; recreate the baseline with --update")


def read_baseline(path: Path, suite: str | None = None) -> dict:
    """The baseline in ``path``, checked; ``suite`` is the name it must have been made for.

    Raises
    ------
    InputError
        A missing, unreadable, malformed or empty baseline, or one of another suite.
    """
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"baseline {path} does not exist; create it with --update") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"baseline {path} cannot be read: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != BASELINE_FORMAT \
            or not isinstance(data.get("runs"), dict):
        raise InputError(f"baseline {path} is not a format-{BASELINE_FORMAT} drift baseline")
    if suite is not None and data.get("suite") != suite:
        raise InputError(f"baseline {path} was made for suite {data.get('suite')!r}, not "
                         f"{suite!r}; name its suite with --suite or make one with --update")
    if not data["runs"]:
        raise InputError(f"baseline {path} holds no runs, so the gate would compare nothing; "
                         f"make it with --update")
    check_entries(data["runs"], f"baseline {path}")
    return data


def write_baseline(path: Path, suite: str, current: dict) -> None:
    p = provenance()
    data = {
        "format": BASELINE_FORMAT,
        "suite": suite,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "commit": p["commit"],
        "dirty": p["dirty"],
        "machine": p["machine"],
        "versions": json.loads(p["versions"]),
        "runs": dict(sorted(current.items())),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_file(path, json.dumps(data, indent=1, sort_keys=False) + "\n")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.check",
                                description=__doc__.split("\n")[0])
    p.add_argument("--suite", default="ci", help="suite name or path (default: ci)")
    p.add_argument("--baseline", type=Path, required=True, help="baseline JSON file")
    p.add_argument("--update", action="store_true",
                   help="rewrite the baseline from this run instead of gating")
    p.add_argument("--out", type=Path,
                   help="keep runs.csv and the results store here (default: a temporary folder)")
    p.add_argument("--jobs", type=int, help="runs side by side (default: the usable cores)")
    p.add_argument("--timeout", type=float, help="time limit of each run, seconds")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        load_plugins()
        suite = suites.load(args.suite)
        baseline = None if args.update else read_baseline(args.baseline, suite.name)
        with tempfile.TemporaryDirectory(prefix="driftbench-check-") as tmp:
            out = args.out or Path(tmp)
            records = run_specs(suite.runs, out, args.jobs, suite=f"check:{suite.name}",
                                repeats=1, timeout=args.timeout or suite.timeout,
                                load=suite.load)
    except InputError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    current = entries(records)
    if args.update:
        if args.baseline.exists():
            try:
                old = read_baseline(args.baseline)["runs"]
                print(table(compare(old, current)))
            except InputError:
                pass
        write_baseline(args.baseline, suite.name, current)
        print(f"wrote {args.baseline} ({len(current)} runs)")
        return EXIT_OK
    findings = compare(baseline["runs"], current)
    gating = [f for f in findings if f.kind == "regression" and f.gating]
    improvements = [f for f in findings if f.kind == "improvement"]
    compared = len(baseline["runs"].keys() & current.keys())
    missing = len(baseline["runs"].keys() - current.keys())
    if findings:
        print(table(findings))
    print(f"drift gate {'FAILED' if gating else 'passed'}: compared {compared} runs of suite "
          f"{suite.name!r} with {args.baseline} ({missing} of its runs missing, "
          f"{len(current) - compared} new); {len(gating)} gating regressions, "
          f"{len(improvements)} improvements")
    return EXIT_REGRESSION if gating else EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
