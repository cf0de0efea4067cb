"""The columns of ``runs.csv``, each declared once: what it holds and who reads it how.

A :class:`Column` says which part of a :class:`~benchmarks.records.Record` holds it, its
kind (text, whole number, float), whether it is an accuracy column (equal bit for bit
whatever engine ran the run), which way is better, the drift gate's :class:`Tolerance`
(or none: not gated), the floor below which its value is the floor's and not the run's,
and where the report's summary table shows it under which header. :data:`TABLE` holds
them in ``runs.csv`` order; every list the other layers use (:data:`COLUMNS`,
:data:`ACCURACY_COLUMNS`, :data:`TEXT_COLUMNS`, :data:`WHOLE_COLUMNS`,
:data:`TOLERANCES`, the store's columns, the gate's metrics, the report's summary table)
is a view of it, read when used, so that a column declared later (:func:`declare`, with
the function that computes it from a run) reaches all of them.

This module imports neither JAX nor an integrator nor a problem.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Callable

TEXT, WHOLE, FLOAT = "text", "whole", "float"
#: Report formats other than a column kind's own: a JSON map of names to numbers, and free
#: text (blank where missing).
MAP, NOTE = "map", "note"
#: The metrics whose quantiles over an ensemble's lanes :class:`~benchmarks.records.Spread`
#: holds, by the short name of its columns, and the quantiles (in percent).
SPREAD_METRICS = ("pos", "vel", "energy", "final")
QUANTILES = (0, 50, 90, 100)
#: The parts of a record (:data:`benchmarks.records.PARTS`) a column can belong to.
PARTS = ("run", "ending", "timing", "work", "metrics", "spread")


@dataclass(frozen=True)
class Tolerance:
    """How the drift gate compares one metric (:func:`benchmarks.gate.compare_metric`).

    ``lower`` metrics regress when ``current > factor * baseline`` and ``current > floor``;
    ``higher`` metrics (digits, ``scd``) regress when ``min(current, floor)`` falls below
    ``min(baseline, floor) - log10(factor)``, the floor there being the digit count beyond
    which differences are round-off.
    """

    direction: str  # "lower" or "higher" is better
    factor: float
    floor: float


@dataclass(frozen=True)
class Floor:
    """A floor a column's value is judged against: where the value of column ``of`` is at
    or below the (positive) value of column ``column``, the number is the floor's (a
    reference's accuracy, a quadrature's error estimate), not the run's; the report shows
    ``at {label} (≤ floor)`` instead."""

    column: str
    of: str
    label: str


@dataclass(frozen=True)
class Column:
    """One ``runs.csv`` column, declared once.

    Parameters
    ----------
    name : str
        The ``runs.csv`` and store column.
    part : str
        The record part holding it (:data:`PARTS`); a metric declared outside this module
        is of part ``metrics``.
    kind : str
        :data:`TEXT`, :data:`WHOLE` (an integer, stored as such) or :data:`FLOAT`.
    description : str
        What it is, with its unit.
    accuracy : bool
        Whether it depends only on what was computed (equal bit for bit for the same run
        on the same machine, whatever engine or ``jobs`` ran it).
    better : str, optional
        ``"lower"`` or ``"higher"``: which way the value improves.
    gate : (factor, floor), optional
        Gated with ``Tolerance(better, factor, floor)``; ``None``: not gated.
    floor : Floor, optional
        The floor its value is judged against, in the gate and the report.
    header : str, optional
        Its header in each problem's summary table; ``None``: not shown there.
    place : int
        Its position in the summary table (columns sort by it).
    optional : bool
        Shown in the summary table only where some run has a value (a column that applies
        to some problems only).
    note : str
        A sentence added to the summary table's caption where the column is shown.
    format : str, optional
        How the report shows it where not by its kind (3 significant digits for numbers):
        :data:`MAP` or :data:`NOTE`.
    compute : callable, optional
        ``compute(case, trajectory) -> float`` for a metric that
        :func:`benchmarks.metrics.summarize` does not compute itself.
    """

    name: str
    part: str
    kind: str = FLOAT
    description: str = ""
    accuracy: bool = False
    better: str | None = None
    gate: tuple[float, float] | None = None
    floor: Floor | None = None
    header: str | None = None
    place: int = 0
    optional: bool = False
    note: str = ""
    format: str | None = None
    compute: Callable | None = None

    def __post_init__(self):
        if self.part not in PARTS:
            raise ValueError(f"column {self.name}: part {self.part!r} is not one of {PARTS}")
        if self.kind not in (TEXT, WHOLE, FLOAT):
            raise ValueError(f"column {self.name}: kind {self.kind!r} is not text, whole "
                             f"or float")
        if self.gate is not None and self.better not in ("lower", "higher"):
            raise ValueError(f"column {self.name}: a gated column says which way is better")

    @property
    def tolerance(self) -> Tolerance | None:
        """The gate's :class:`Tolerance`, ``None`` where not gated."""
        return None if self.gate is None else Tolerance(self.better, *self.gate)


# The factor of 4 (0.6 digits for scd) leaves room for what a change of round-off alone
# does: residuals accumulate it as a random walk, and an adaptive method's step sequence
# jumps when a rejected step turns accepted, which was seen to move IDA's final error on
# Andrews' mechanism by a factor of 2 after a refactoring of the mechanics; the regressions
# the gate is for move metrics by orders of magnitude. The floors sit a few hundred ulps
# above the round-off of O(1) quantities, low enough that a Newton iteration stopped 1e6
# times too early shows in the residuals.
GATE_FACTOR = 4.0
#: Tolerance of each declared invariant's error (``inv:NAME``, from ``invariant_errors``).
INVARIANT_TOLERANCE = Tolerance("lower", GATE_FACTOR, 1e-12)
REFERENCE = Floor("reference_floor", "final_state_error", "reference floor")
QUADRATURE = Floor("balance_floor", "rel_balance_error", "quadrature floor")
BALANCE_NOTE = ("Energy balance (no conserved energy): max |H - H0 - W| / energy scale over "
                "the sampled states, W the work of the applied and moving-constraint forces "
                "by quadrature over those states; at quadrature floor: within that "
                "quadrature's error estimate.")


def _run(name, kind=FLOAT, description=""):
    return Column(name, "run", kind, description)


def _count(name, description, header=None, place=0):
    return Column(name, "work", WHOLE, description, accuracy=True, better="lower",
                  header=header, place=place)


#: Every column, in ``runs.csv`` order (docs/design.md, section 6, then the work counters,
#: what the run knew about its case and method, its drift classes and the resume key).
TABLE: dict[str, Column] = {c.name: c for c in (
    _run("problem", TEXT, "problem spec as written"),
    _run("integrator", TEXT, "integrator spec as written"),
    _run("h", description="step size"),
    _run("rtol", description="relative tolerance"),
    _run("atol", description="absolute tolerance"),
    _run("t_end", description="horizon"),
    Column("status", "ending", TEXT, "how the run ended (ok, failed, timeout, error, "
           "skipped)", accuracy=True),
    Column("message", "ending", TEXT, "why it stopped or what it could not score",
           accuracy=True, header="message", place=1000, format=NOTE),
    _count("n_steps", "accepted steps", "steps", 10),
    _count("n_rejected", "rejected steps"),
    _count("n_f_evals", "force/residual evaluations", "evaluations", 20),
    _count("n_jac_evals", "Jacobian evaluations"),
    _count("n_newton", "Newton iterations"),
    _count("n_lin_solves", "linear solves"),
    Column("wall_s", "timing", description="median wall time of the timed solves [s]",
           better="lower", header="wall [s]", place=30),
    Column("setup_s", "timing", description="set-up wall time, compilation included [s]"),
    Column("max_pos_residual", "metrics", description="max over steps of `‖g(q_n, t_n)‖_∞`",
           accuracy=True, better="lower", gate=(GATE_FACTOR, 1e-13), header="max |g|",
           place=70),
    Column("max_vel_residual", "metrics", description="max over steps of "
           "`‖G(q_n, t_n) v_n + g_t(q_n, t_n)‖_∞`", accuracy=True, better="lower",
           gate=(GATE_FACTOR, 1e-13), header="max |G v + g_t|", place=80),
    Column("max_energy_error", "metrics", description="max over steps of `|H_n - H_0|`; "
           "empty where the system has no conserved energy", accuracy=True,
           better="lower"),
    Column("rel_energy_error", "metrics", description="`max_energy_error / energy_scale`, "
           "the case's declared scale",
           accuracy=True, better="lower", gate=(GATE_FACTOR, 1e-13),
           header="max rel. energy error", place=90, optional=True),
    Column("final_state_error", "metrics", description="max-norm error at `t_final` "
           "against the reference, on the components it scores", accuracy=True, better="lower",
           gate=(GATE_FACTOR, 1e-12), floor=REFERENCE, header="final error", place=120),
    Column("scd", "metrics", description="`-log10(max_i |y_i - y_ref,i| / "
           "|y_ref,i|)` on those components (IVP Test Set)",
           accuracy=True, better="higher", gate=(GATE_FACTOR, 11.0), floor=REFERENCE,
           header="scd", place=130),
    Column("t_final", "ending", description="time reached", accuracy=True),
    Column("q_final", "ending", TEXT, "final positions (JSON)", accuracy=True),
    Column("v_final", "ending", TEXT, "final velocities (JSON)", accuracy=True),
    Column("invariant_errors", "metrics", TEXT, "the same maximum for each declared "
           "invariant (JSON)", accuracy=True, better="lower", header="invariant errors",
           place=900, optional=True, format=MAP),
    Column("sampling", "ending", TEXT, "how the metrics were sampled", accuracy=True),
    Column("fail_step", "ending", WHOLE, "step at which the run failed", accuracy=True),
    Column("fail_time", "ending", description="time at which the run failed",
           accuracy=True),
    Column("callback_s", "timing", description="time in recording callbacks [s]"),
    Column("repeats", "timing", WHOLE, "number of timed solves", header="solves", place=60),
    Column("wall_min_s", "timing", description="fastest timed solve [s]",
           header="wall min [s]", place=40),
    Column("wall_max_s", "timing", description="slowest timed solve [s]",
           header="wall max [s]", place=50),
    _run("options", TEXT, "every integrator option (JSON)"),
    _run("params", TEXT, "every physical parameter (JSON)"),
    _run("run_key", TEXT, "resume key (benchmarks.records.run_key)"),
    Column("linear_solver", "work", TEXT, "linear solver that ran", accuracy=True,
           header="linear solver", place=140),
    Column("pattern_nnz", "work", WHOLE, "entries of the factorised pattern",
           accuracy=True),
    _run("t0", description="start time"),
    _run("energy_scale", description="the case's energy scale"),
    _run("nominal_order", WHOLE, "the method's nominal order"),
    _run("sensitive", WHOLE, "1 for a chaotic problem"),
    Column("pos_growth", "metrics", TEXT, "drift class of `|g|` with the fitted "
           "exponent",
           accuracy=True, header="|g| growth", place=100),
    Column("energy_growth", "metrics", TEXT, "drift class of `|H - H0|` with the "
           "fitted exponent",
           accuracy=True, header="energy growth", place=110),
    Column("reference_floor", "metrics", description="the reference's own accuracy",
           accuracy=True),
    _run("family", TEXT, "the method's family"),
    Column("setup_cache", "timing", TEXT, "where the set-up's compilations came from"),
    Column("max_balance_error", "metrics", description="max over the sampled states of "
           "`|H - H_0 - W|`, W the work of the applied and moving-constraint forces; empty "
           "where energy is conserved", accuracy=True, better="lower"),
    Column("rel_balance_error", "metrics", description="`max_balance_error / energy_scale`",
           accuracy=True, better="lower", floor=QUADRATURE,
           header="max rel. energy balance error", place=95, optional=True,
           note=BALANCE_NOTE),
    Column("balance_floor", "metrics", description="error estimate of the quadrature "
           "that gives W, over `energy_scale`", accuracy=True),
    _run("lanes", WHOLE, "ensemble size"),
    _run("seed", WHOLE, "ensemble seed"),
    _run("batched", WHOLE, "1: the lanes ran in one compiled loop"),
    Column("failed_fraction", "spread", description="fraction of lanes that failed",
           accuracy=True, better="lower"),
    *(Column(f"{metric}_q{q}", "spread", description=f"{q}th percentile over the lanes",
             accuracy=True, better="lower") for metric in SPREAD_METRICS for q in QUANTILES),
    _run("chunks", WHOLE, "number of chunks of lanes"),
    Column("device", "work", TEXT, "platform the compiled code ran on"),
)}


def declare(column: Column) -> Column:
    """Add ``column`` to :data:`TABLE` (after the others in ``runs.csv``); it then reaches
    ``runs.csv``, the store, the gate (where ``gate`` is set) and the report (where
    ``header`` is). A store of earlier runs gets the column, empty, when next opened."""
    if column.name in TABLE:
        raise ValueError(f"column {column.name} is declared already")
    # The other parts are filled by the code that runs a run, field by field.
    if column.part != "metrics":
        raise ValueError(f"column {column.name}: a column declared outside this module is a "
                         f"metric (part 'metrics'), not of part {column.part!r}")
    TABLE[column.name] = column
    return column


def withdraw(name: str) -> None:
    """Remove the column ``name`` that :func:`declare` added."""
    del TABLE[name]


class Names(Sequence):
    """The names of the declared columns that ``pick`` selects, in :data:`TABLE` order,
    read from the table whenever used."""

    def __init__(self, pick: Callable[[Column], bool]):
        self._pick = pick

    def _names(self) -> tuple[str, ...]:
        return tuple(name for name, c in TABLE.items() if self._pick(c))

    def __getitem__(self, i):
        return self._names()[i]

    def __len__(self) -> int:
        return len(self._names())

    def __iter__(self):
        return iter(self._names())

    def __contains__(self, name) -> bool:
        c = TABLE.get(name)
        return c is not None and self._pick(c)

    def __repr__(self) -> str:
        return repr(self._names())


class Tolerances(Mapping):
    """Gated metric -> its :class:`Tolerance`, in :data:`TABLE` order, read from the table
    whenever used."""

    def __getitem__(self, name) -> Tolerance:
        c = TABLE.get(name)
        if c is None or c.gate is None:
            raise KeyError(name)
        return c.tolerance

    def __iter__(self):
        return (name for name, c in TABLE.items() if c.gate is not None)

    def __len__(self) -> int:
        return sum(c.gate is not None for c in TABLE.values())


#: Columns of runs.csv, in order.
COLUMNS = Names(lambda c: True)
#: The columns that depend on what was computed and not on how long it took.
ACCURACY_COLUMNS = Names(lambda c: c.accuracy)
#: Columns that hold text; every other column holds a number or nothing.
TEXT_COLUMNS = Names(lambda c: c.kind == TEXT)
#: Columns that hold whole numbers (pandas reads them as floats where some are empty).
WHOLE_COLUMNS = Names(lambda c: c.kind == WHOLE)
#: The gated metrics and their tolerances.
TOLERANCES = Tolerances()


def of_part(part: str) -> tuple[str, ...]:
    """The columns a record part holds, in order."""
    return tuple(name for name, c in TABLE.items() if c.part == part)


def computed() -> tuple[Column, ...]:
    """The declared columns that bring their own ``compute``."""
    return tuple(c for c in TABLE.values() if c.compute is not None)


def summary() -> tuple[Column, ...]:
    """The columns of each problem's summary table, in their order."""
    return tuple(sorted((c for c in TABLE.values() if c.header), key=lambda c: c.place))
