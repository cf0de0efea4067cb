"""The section "What the harness costs", from the efficiency benchmark's output.

``python -m benchmarks.perf.efficiency --out DIR`` times each family against a native C
yardstick of the same algorithm and writes ``DIR/efficiency.json``; this module reads that
file only (it imports no integrator or problem). It renders the table of ratios (our time
per step over the yardstick's) by family and problem, and words the headline's notes:
where a family named in a cost verdict runs more than :data:`HARNESS_RATIO` times its
yardstick per step, part of its wall time in the report is the harness's, not the method's.
``python -m reports --efficiency DIR`` adds both to the main report.
"""

from __future__ import annotations

import math
import re
from numbers import Real
from pathlib import Path

from reports.analysis import base_name, fmt, text
from reports.document import Document, Para, Table
from reports.scaling import results_file

EFFICIENCY_FILE = "efficiency.json"
SECTION = "What the harness costs"
#: Keys the results file must hold.
REQUIRED = ("goal_ratio_per_step", "rounds", "load", "rows")
#: Keys each row must hold: text, then numbers.
ROW_TEXT = ("family", "driver", "problem")
ROW_NUMBERS = ("us_per_step", "yardstick_us_per_step", "ratio_per_step", "ratio_per_solve",
               "steps", "yardstick_steps", "final_q_difference")
#: Our time per step over the yardstick's above which the headline says so: at 2, the
#: harness takes at least as long per step as the method itself.
HARNESS_RATIO = 2.0
#: The driver that calls IDA through Python callbacks; the benchmark holds it to no goal and
#: a run takes its ratio only when its ``sampling`` says it ran on it.
BINDING = "scikit-sundae"
#: Mark of a headline cell that names a family above :data:`HARNESS_RATIO`.
MARK = "†"


class EfficiencyError(ValueError):
    """An efficiency results folder that is missing or cannot be read."""


def _number(value) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def load(folder) -> dict:
    """The results in ``folder/efficiency.json``; :class:`EfficiencyError` if absent or
    malformed (a missing key, a row without its family, problem or finite numbers, a ratio
    that is not positive)."""
    path = Path(folder) / EFFICIENCY_FILE
    data = results_file(path, "efficiency", REQUIRED, EfficiencyError)
    if not isinstance(data["rows"], list) or not data["rows"]:
        raise EfficiencyError(f"{path}: 'rows' must be a non-empty list of comparisons")
    for key in ("goal_ratio_per_step", "rounds", "load"):
        if not _number(data[key]):
            raise EfficiencyError(f"{path}: {key!r} = {data[key]!r} must be a finite number")
    for i, row in enumerate(data["rows"]):
        if not isinstance(row, dict):
            raise EfficiencyError(f"{path}: row {i} is not an object")
        bad = [k for k in ROW_TEXT if not isinstance(row.get(k), str) or not row[k]] + \
              [k for k in ROW_NUMBERS if not _number(row.get(k))]
        if bad:
            raise EfficiencyError(f"{path}: row {i} ({row.get('family')} on "
                                  f"{row.get('problem')}) lacks a valid {', '.join(bad)}")
        if not (row["ratio_per_step"] > 0 and row["us_per_step"] > 0
                and row["yardstick_us_per_step"] > 0):
            raise EfficiencyError(f"{path}: row {i} ({row['family']} on {row['problem']}): "
                                  f"times per step and their ratio must be positive")
    return data


def _setting(row: dict) -> str:
    if row.get("setting"):
        return str(row["setting"])
    return f"rtol={fmt(row['rtol'])}" if _number(row.get("rtol")) else ""


def section(doc: Document, data: dict) -> None:
    """Append the section: what was compared, the table of ratios, what they mean."""
    doc.heading(2, SECTION)
    doc.add(Para(
        f"Each family against a native yardstick of the same algorithm: a C program that "
        f"runs the same method with the same formulation, tolerances and error control on "
        f"the same problem and ends where our run ends (the final-state difference says how "
        f"closely). {int(data['rounds'])} rounds alternate ours and the yardstick's so that "
        f"the machine's load hits both; the figures are medians over the rounds. 1-minute "
        f"load average {data['load']:.2f} at the start. Ratio per step: our wall time per "
        f"step over the yardstick's (per solve: whole solves; CPU: processor time, which a "
        f"loaded machine disturbs less, where measured); the benchmark's goal is at most "
        f"{fmt(data['goal_ratio_per_step'])} for each family's own driver"
        + (f" ({BINDING}, IDA through Python callbacks, is shown beside it and held to no "
           f"goal)." if any(r["driver"] == BINDING for r in data["rows"]) else ".")))
    rows = sorted(data["rows"], key=lambda r: (r["family"], r["problem"], r["driver"]))
    doc.add(Table(
        ["family", "driver", "problem", "setting", "ratio per step", "CPU ratio per step",
         "ratio per solve", "us/step (ours)", "us/step (yardstick)", "steps (ours)",
         "steps (yardstick)", "final |Δq|"],
        [[r["family"], r["driver"], r["problem"], _setting(r), f"{r['ratio_per_step']:.2f}",
          f"{r['cpu_ratio_per_step']:.2f}" if _number(r.get("cpu_ratio_per_step")) else "",
          f"{r['ratio_per_solve']:.2f}", fmt(r["us_per_step"]),
          fmt(r["yardstick_us_per_step"]), str(int(r["steps"])),
          str(int(r["yardstick_steps"])), fmt(r["final_q_difference"])] for r in rows],
        "Time per step, ours over the native yardstick's, by family and problem "
        "(python -m benchmarks.perf.efficiency)."))
    over = sorted({f"{r['family']} ({r['ratio_per_step']:.2f} on {r['problem']})"
                   for r in rows if r["ratio_per_step"] > HARNESS_RATIO})
    doc.add(Para(
        f"The ratio says how far each family's wall time is from its native cost: at 1 "
        f"the suite runs the method as fast as C does; where it exceeds "
        f"{fmt(HARNESS_RATIO)}, the harness (the layers around the method and its per-step "
        f"measurements) takes longer per step than the method itself, so part of that "
        f"family's cost in this report is the harness's, and its wall times compare with "
        f"other families' by that margin. "
        + (f"Above {fmt(HARNESS_RATIO)} here: {', '.join(over)}." if over else
           f"No family is above {fmt(HARNESS_RATIO)} here.")
        + " Families without a row have no yardstick yet."))


def mark(cell: str, integrator: str) -> str:
    """``cell`` with :data:`MARK` after the first mention of ``integrator`` (a whole name:
    not inside a longer one)."""
    return re.sub(rf"(?<![\w-]){re.escape(integrator)}(?![\w-])",
                  lambda m: m.group(0) + MARK, cell, count=1)


def ratio(data: dict, run) -> tuple[float, str] | None:
    """The ratio per step that applies to a run (a row of the results store), and the
    problem it comes from: the run's own problem where its family was timed there, else
    the family's largest over the problems timed; rows of the
    :data:`BINDING` driver only for a run that ran on it (its ``sampling`` says which
    driver ran, whatever its options asked). None when the family has no yardstick."""
    family = base_name(run["integrator"])
    binding = BINDING in text(run.get("sampling"))
    rows = [r for r in data["rows"]
            if r["family"] == family and (r["driver"] == BINDING) == binding]
    if not rows:
        return None
    problem = base_name(text(run.get("problem")))
    own = [r for r in rows if r["problem"] == problem] or rows
    worst = max(own, key=lambda r: r["ratio_per_step"])
    return worst["ratio_per_step"], worst["problem"]


def note(data: dict, run) -> str | None:
    """The headline's line for a run named in a cost verdict whose family's ratio per step
    exceeds :data:`HARNESS_RATIO` (``"ida-ggl: 2.6x its native yardstick per step on
    pendulum"``), else None."""
    found = ratio(data, run)
    if found is None or not found[0] > HARNESS_RATIO:
        return None
    return (f"{base_name(run['integrator'])}: {found[0]:.1f}x its native yardstick per step "
            f"on {found[1]}")
