"""The drift gate: run a suite and compare every accuracy metric with a committed baseline.

::

    python -m benchmarks.check --suite ci --baseline benchmarks/baselines/ci.json
    python -m benchmarks.check --suite ci --baseline benchmarks/baselines/ci.json --update

Each run of the suite is matched to the baseline's run of the same identity
(:func:`benchmarks.records.identity`: problem, integrator, setting, horizon) and compared
by :mod:`benchmarks.gate` (the rule the report's history shares). Every metric is
compared in its own direction with its own :class:`~benchmarks.gate.Tolerance`: lower is
better for constraint residuals, energy and invariant errors and final errors; higher is
better for ``scd`` (significant correct digits). A metric regresses when it is worse
than the baseline by more than its relative factor *and* lies above its absolute floor
(values at or below the floor are round-off, which may differ between machines); a final
error's floor is at least the larger of the two runs' reference floors (below it the
change is the reference's), and where both final errors lie below that, their ``scd`` is
not compared either. The
drift classes of ``|g|`` and ``|H - H0|`` that each run recorded (:mod:`benchmarks.drift`)
regress when they grow faster than before (bounded, linear, quadratic, superquadratic,
exponential). A run that finished in the baseline and now does not (``failed``,
``error``, ``timeout``) is a regression, as is a failed run that now fails earlier. A
baseline run missing from the results is a regression too (the gate must not pass by
comparing less); a run new in the suite is reported, not gated (``--update`` records the suite as it is).

Runs of sensitive (chaotic) problems, ``System.sensitive``, are compared and reported but
never fail the gate: their final states depend on round-off.

Round-off decides some metrics of non-chaotic problems too: an adaptive method's step
sequence is a chain of discrete choices, and a last-bit change early on can take it
elsewhere. ``ida-ggl`` on ``flyball-governor`` at rtol 1e-8, started from initial positions
scaled by ``1 + eps`` for ten ``|eps| <= 1e-14``, gave max |g| from 9.7e-12 to 2.2e-9 and a
growth of |g| bounded in eight runs and exponential in two. Such a metric cannot be gated by
a factor of four: any change of round-off (an XLA option, a JAX upgrade) can move it. So
``--update`` probes every finished adaptive run of a non-chaotic problem: it runs it again
from initial positions scaled by ``1 + eps`` for each ``eps`` in :data:`PROBE`, on the same
workers, and a metric or drift class that any probe moves past the gate's tolerance is
written into the run's ``roundoff`` list in the baseline, with the range (``spread``) that
the run and its probes gave each such metric. The gate measures a listed metric from that
range, widened by its tolerance (:func:`benchmarks.gate.compare_metric`): a value that
round-off could have given passes, one four times beyond the worst the probes saw fails. A
listed drift class is compared and reported but never fails the gate; the run's status and
its other metrics gate as for any run. The final error and ``scd`` are probed too, against
the unperturbed run's reference: ``ida-ggl`` on ``andrews`` ended 2.6e-4 from it on one
machine and 3.2e-5 on another, with the same code and the same libraries, and the probes
here span that range (:data:`PROBE`).

The baseline is checked before anything runs: it must be a baseline of the suite asked
for, hold at least one run, and every run must have a ``status`` and ``metrics`` whose
values are numbers or null, none NaN (``+inf`` only for ``scd``, an exact final state). A
gate that compared nothing, or compared against NaN (every comparison with NaN is false),
would pass whatever the code does. The last line of output says how many runs were
compared.

A run that ends ``error`` or ``timeout`` has no metrics to gate or record: the gate then
fails whatever the comparison says, and ``--update`` writes no baseline (a baseline of such
a run would let the same error pass next time); one line counts them.

Exit status: 0 when nothing gating regressed and every run ended ``ok`` or ``failed`` (or
after ``--update``), 1 on a regression or a run that ended ``error`` or ``timeout``, 2 on
bad input (unknown suite, unreadable, empty, malformed or another suite's baseline).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import problems
from benchmarks import suites
from benchmarks.batch import run_specs
from benchmarks.executors import load_plugins
from benchmarks.files import replace_file
from benchmarks.gate import TOLERANCES, Finding, compare, entry
from benchmarks.records import (EXIT_INPUT, CommandParser, InputError, RunSpec, identity,
                                one_line, provenance)
from benchmarks.run import EXIT_RUN_ERROR, UNFINISHED

EXIT_OK, EXIT_REGRESSION = 0, 1
#: Relative perturbations of the initial positions by which ``--update`` finds the metrics
#: that round-off decides (module notes). Two were too few: ``ida-ggl`` on ``andrews``
#: (rtol 1e-6, t = 0.03) ended 2.6e-4 from the reference unperturbed, 3.0e-4 and 2.7e-4 at
#: ``eps = +-1e-15``, but 6.8e-5 and 3.0e-5 at ``+-2e-15`` and 1.7e-5 to 1.6e-4 for ten more
#: ``|eps| <= 2e-14``, and a machine with other round-off had recorded 3.2e-5.
PROBE = (1e-15, -1e-15, 2e-15, -2e-15, 3e-15, -3e-15, 5e-15, -5e-15)
#: What a probe does not loosen: a run's status is always gated.
UNPROBED = ("status", "fail_step")
BASELINE_FORMAT = 1


def entries(records) -> dict[str, dict]:
    """Baseline entries of a suite's records, by run identity (:func:`benchmarks.gate.entry`)."""
    return {identity(record.row): entry(record.row) for record in records}


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
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return True
    try:
        value = float(value)  # JSON's integers have no bound
    except OverflowError:
        return True
    if math.isnan(value):
        return True
    return math.isinf(value) and not (value > 0 and metric in TOLERANCES
                                      and TOLERANCES[metric].direction == "higher")


def check_entries(runs: dict, where: str) -> None:
    """Refuse baseline entries the gate cannot compare with, naming the first bad one.

    Raises
    ------
    InputError
        An entry that is not an object, lacks ``status`` or ``metrics``, or has a metric
        that is not a number or null, or is NaN or infinite (but ``scd = +inf``), or a
        ``floor`` that is not a finite number >= 0 or null.
    """
    for rid, entry in runs.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("status"), str) \
                or not isinstance(entry.get("metrics"), dict):
            raise InputError(f"{where}: run {rid!r} needs a status and metrics; "
                             f"recreate the baseline with --update")
        loose = entry.get("roundoff", [])
        if not isinstance(loose, list) or not all(isinstance(m, str) for m in loose):
            raise InputError(f"{where}: run {rid!r}: roundoff must be a list of metric names; "
                             f"recreate the baseline with --update")
        for metric, value in entry["metrics"].items():
            if _bad_metric(metric, value):
                raise InputError(f"{where}: run {rid!r}: metric {metric} = {value!r:.40} cannot "
                                 f"be compared with; recreate the baseline with --update")
        floor = entry.get("floor")
        if floor is not None and (_bad_metric("floor", floor) or not 0 <= floor < math.inf):
            raise InputError(f"{where}: run {rid!r}: floor = {floor!r:.40} must be a reference "
                             f"floor (a finite number >= 0, or null); recreate the baseline "
                             f"with --update")
        spread = entry.get("spread", {})
        if not isinstance(spread, dict) or not all(
                isinstance(v, list) and len(v) == 2 and v[0] is not None and v[1] is not None
                and not any(_bad_metric(m, x) for x in v) for m, v in spread.items()):
            raise InputError(f"{where}: run {rid!r}: spread must map metric names to two "
                             f"numbers; recreate the baseline with --update")


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


def probe(records, jobs: int | None, timeout: float | None, load
          ) -> dict[str, tuple[list[str], dict[str, list[float]]]]:
    """The metrics and drift classes that round-off decides, and the range it gave each
    such metric, by run identity (module notes).

    Each finished adaptive run of a non-chaotic problem among ``records`` runs again, once
    for each ``eps`` in :data:`PROBE`, from its case's initial positions scaled by ``1 +
    eps`` (a case of the Python API, made consistent by the method as any initial values
    are); what differs from the unperturbed run by more than the gate's tolerance is
    listed, and for each listed metric the least and the greatest value of the run and its
    finished probes (the ``spread`` that :func:`benchmarks.gate.compare` gates against)."""
    probes, cases = [], []
    for i, record in enumerate(records):
        spec, row = record.run, record.row
        if spec.rtol is None or row["status"] != "ok" or entry(row)["sensitive"]:
            continue
        # Built for the run's horizon, so its reference is the run's (problems.at_horizon).
        case = problems.make(problems.at_horizon(spec.problem, spec.t_end))
        for k, eps in enumerate(PROBE):
            name = f"roundoff-probe-{i}-{k}"
            # The unperturbed reference serves the probe: on a problem that is not
            # sensitive a relative change of 1e-15 in q0 moves the exact solution by far
            # less than the errors the gate compares (the final error's floor is 1e-12).
            cases.append(replace(case.with_initial(case.q0 * (1.0 + eps), case.v0),
                                 reference=case.reference, name=name))
            probes.append((i, RunSpec(name, spec.integrator, h=spec.h, rtol=spec.rtol,
                                      atol=spec.atol, t_end=spec.t_end,
                                      origin=f"round-off probe of {identity(row)}")))
    if not probes:
        return {}
    with tempfile.TemporaryDirectory(prefix="driftbench-probe-") as tmp:
        # A probe's system is its run's, audited (or built in) when that run was planned.
        results = run_specs([s for _, s in probes], Path(tmp), jobs, suite="check:probe",
                            repeats=1, timeout=timeout, load=load, cases=cases, log=None,
                            audit_user=False)
    moved: dict[str, set[str]] = {}
    seen: dict[str, dict[str, list[float]]] = {}
    for (i, _), result in zip(probes, results):
        rid, base, probed = identity(records[i].row), entry(records[i].row), entry(result.row)
        for finding in compare({rid: base}, {rid: probed}):
            if finding.kind != "note" and finding.metric not in UNPROBED:
                moved.setdefault(rid, set()).add(finding.metric)
        if probed["status"] == base["status"]:
            for metric, value in probed["metrics"].items():
                seen.setdefault(rid, {}).setdefault(
                    metric, [base["metrics"].get(metric)]).append(value)
    out = {}
    for rid, metrics in moved.items():
        # Only values a baseline may hold (check_entries): the spread must read back.
        spread = {m: [min(v), max(v)] for m, v in seen.get(rid, {}).items()
                  if m in metrics and not any(x is None or _bad_metric(m, x) for x in v)}
        out[rid] = (sorted(metrics), spread)
    return out


def parser() -> argparse.ArgumentParser:
    p = CommandParser(prog="python -m benchmarks.check",
                      description=__doc__.split("\n")[0],
                      epilog=f"exit status: {EXIT_OK} when nothing gating regressed and every "
                             f"run ended ok or failed (or after --update); {EXIT_REGRESSION} on "
                             f"a regression or a run that ended {' or '.join(UNFINISHED)} "
                             f"(--update then writes no baseline); {EXIT_INPUT} for bad input")
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
    unfinished = [identity(r.row) for r in records if r.row["status"] in UNFINISHED]
    if unfinished:
        print(f"error: {len(unfinished)} of {len(records)} runs ended "
              f"{' or '.join(UNFINISHED)}, with no metrics to "
              f"{'record: no baseline written' if args.update else 'gate'} (first: "
              f"{unfinished[0]})", file=sys.stderr)
        if args.update:
            return EXIT_RUN_ERROR
    if args.update:
        try:
            for rid, (metrics, spread) in probe(records, args.jobs,
                                                args.timeout or suite.timeout,
                                                suite.load).items():
                current[rid]["roundoff"] = metrics
                if spread:
                    current[rid]["spread"] = spread
                print(f"round-off decides {', '.join(metrics)} of {rid}"
                      + "".join(f"; {m} {lo:.3g} to {hi:.3g}" for m, (lo, hi) in spread.items()))
        except InputError as exc:
            print(f"error: {one_line(exc)}", file=sys.stderr)
            return EXIT_INPUT
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
    print(f"drift gate {'FAILED' if gating or unfinished else 'passed'}: compared {compared} "
          f"runs of suite {suite.name!r} with {args.baseline} ({missing} of its runs missing, "
          f"{len(current) - compared} new); {len(gating)} gating regressions, "
          f"{len(improvements)} improvements"
          + (f"; {len(unfinished)} runs ended {' or '.join(UNFINISHED)}" if unfinished else ""))
    return EXIT_REGRESSION if gating else EXIT_RUN_ERROR if unfinished else EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
