"""What every layer agrees on about a run: its spec, its record, its identity, its provenance.

- :class:`RunSpec`: one run as asked for (problem spec, integrator spec, setting, horizon);
- :class:`Record`: one run as it ended, complete, in named parts: what ran (:class:`Run`,
  known before it starts), how it ended (:class:`Ending`), its :class:`Timing`,
  :class:`Work` and :class:`Metrics` (and an ensemble's :class:`Spread` and per-lane
  table), its drift series and its sampled states. Everything
  a later stage needs to know about a run (nominal order, sensitivity, energy scale,
  ``t0``, the linear solver, the sampling, the drift classes) is in it, filled where the
  run happens, so that the store and the reports never rebuild a problem or an
  integrator; :attr:`Record.row` is its ``runs.csv`` row (:data:`COLUMNS`), the one
  conversion the store and ``runs.csv`` share;
- :func:`identity`: what names a run across invocations and commits (problem, integrator,
  setting, horizon), the one text that the progress log, the drift gate and the report use;
  :func:`run_key` adds the fully resolved parameters and options and the code version, for
  resuming;
- :func:`provenance`: the commit, whether the working tree differs from it, the code
  version, the machine and the package versions;
- :class:`InputError`: bad input, reported on one line before any run starts;
- the column lists :data:`COLUMNS`, :data:`ACCURACY_COLUMNS`, :data:`TEXT_COLUMNS` and
  :data:`WHOLE_COLUMNS`, views of the columns' declarations (:mod:`benchmarks.columns`).

This module imports neither JAX nor an integrator nor a problem.
"""

from __future__ import annotations

import argparse
import enum
import functools
import hashlib
import json
import math
import os
import platform
import subprocess
from dataclasses import asdict, dataclass, field, replace
from importlib import metadata
from pathlib import Path

import numpy as np

from benchmarks.columns import (ACCURACY_COLUMNS, COLUMNS, QUANTILES, SPREAD_METRICS,
                                TEXT_COLUMNS, WHOLE_COLUMNS, of_part)

#: Environment variable that pins the code version (see :func:`provenance`).
CODE_VERSION_ENV = "DRIFTBENCH_CODE_VERSION"

#: Distributions whose versions are recorded with every invocation.
PACKAGES = ("driftbench", "numpy", "scipy", "jax", "jaxlib", "diffrax", "scikit-sundae",
            "pandas", "matplotlib", "dask", "distributed")


class Status(enum.StrEnum):
    """How a run ended (docs/design.md, section 6): the members of
    :class:`integrators.base.Status`, whose values runs.csv and the store hold.

    Defined here as well because the store and the reports read records without importing
    an integrator (and with it JAX); ``tests/test_store.py`` holds the two equal.
    """

    OK = "ok"
    FAILED = "failed"
    TIMEOUT = "timeout"
    ERROR = "error"
    SKIPPED = "skipped"


class InputError(ValueError):
    """Bad input found before any run starts: the message names what and where, on one line."""


def one_line(text) -> str:
    """``text`` with its line breaks folded, for one-line error messages."""
    return " ".join(str(text).split())


#: Exit status of every command on bad input.
EXIT_INPUT = 2


class CommandParser(argparse.ArgumentParser):
    """The command lines' argument parser: an error is one line (no usage block) that
    points to ``--help``, with exit status :data:`EXIT_INPUT`."""

    def error(self, message):
        self.exit(EXIT_INPUT, f"error: {one_line(message)} (see {self.prog} --help)\n")


def number(x) -> str:
    """A setting as text: exact (the shortest text that reads back as the same float), and
    without a trailing ``.0``, so ``0.01``, ``1e-08`` and ``20`` read as they were written."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def _missing(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def setting(h=None, rtol=None, atol=None) -> str:
    """The swept setting of a run: its step size, or its tolerances, or ``defaults``."""
    if not _missing(h):
        return f"h={number(h)}"
    parts = [f"{k}={number(v)}" for k, v in (("rtol", rtol), ("atol", atol)) if not _missing(v)]
    return " ".join(parts) or "defaults"


def identity(row) -> str:
    """The identity of a run: ``problem / integrator / setting / t_end=...``.

    ``row`` is anything with ``get`` (a ``runs.csv`` row, a stored row as pandas gives it,
    where a missing value is NaN) or a :class:`RunSpec`. Runs of the same identity are the
    same experiment, whatever commit or engine ran them: the drift gate matches runs to its
    baseline by it and the report shows the latest run of each. An ensemble's identity ends
    with its size and seed.
    """
    get = row.get if hasattr(row, "get") else lambda k: getattr(row, k, None)
    t_end = get("t_end")
    horizon = "t_end=default" if _missing(t_end) else f"t_end={number(t_end)}"
    lanes = get("lanes")
    ensemble = "" if _missing(lanes) else f" / ensemble={int(lanes)},seed={int(get('seed'))}"
    return (f"{get('problem')} / {get('integrator')} / "
            f"{setting(get('h'), get('rtol'), get('atol'))} / {horizon}{ensemble}")


@dataclass(frozen=True)
class RunSpec:
    """One run as asked for: a problem, an integrator, the settings that vary in sweeps.

    ``problem`` and ``integrator`` are spec strings or, where the input was read
    (:func:`benchmarks.plan.expand`), the resolved
    :class:`~problems.spec.ProblemSpec` and :class:`~problems.spec.IntegratorSpec`.
    ``timeout`` is the run's time limit in seconds (``None``: the batch default); ``origin``
    says where the run was asked for (a suite file and line), for error messages. Neither
    takes part in comparisons. ``lanes`` (``None``: a single run) and ``seed`` ask for an
    ensemble of that many initial states (:mod:`problems.ensemble`), ``device`` where it
    runs (``auto``, ``cpu`` or ``gpu``; ``None``: ``auto``) and ``lanes_per_chunk`` the
    size of its chunks (``None``: :data:`benchmarks.plan.LANES_PER_CHUNK`).
    """

    problem: object
    integrator: object
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    t_end: float | None = None
    timeout: float | None = field(default=None, compare=False)
    origin: str = field(default="", compare=False)
    lanes: int | None = None
    seed: int | None = None
    device: str | None = None
    lanes_per_chunk: int | None = None

    def label(self) -> str:
        """The run's :func:`identity`, for progress lines and messages."""
        return identity(self)


@dataclass(frozen=True)
class Run:
    """What ran: everything fixed before the run starts (:mod:`benchmarks.plan` fills it).

    ``problem`` and ``integrator`` are the specs as written; ``h``, ``rtol``, ``atol`` the
    integrator's resolved options (``None`` where it has none) and ``t_end`` the resolved
    horizon; ``options`` and ``params`` JSON of every option and physical parameter; then
    what the case and the method declare, and the ``run_key`` (:func:`run_key`); for an
    ensemble its number of ``lanes``, its ``seed``, whether they ran in one compiled loop
    (``batched`` 1) or one after another (0), and the number of ``chunks`` of lanes it ran
    in, each a task of its own (:func:`benchmarks.plan.lane_ranges`).
    """

    problem: str
    integrator: str
    h: float | None = None
    rtol: float | None = None
    atol: float | None = None
    t_end: float | None = None
    options: str | None = None
    params: str | None = None
    run_key: str | None = None
    t0: float | None = None
    energy_scale: float | None = None
    nominal_order: int | None = None
    sensitive: int | None = None
    family: str | None = None
    lanes: int | None = None
    seed: int | None = None
    batched: int | None = None
    chunks: int | None = None


@dataclass(frozen=True)
class Ending:
    """How a run ended: its :class:`Status` and message, where it stopped (``fail_step``,
    ``fail_time``), its final state (``q_final``, ``v_final``: JSON lists) and how its
    metrics were sampled."""

    status: Status
    message: str | None = None
    t_final: float | None = None
    q_final: str | None = None
    v_final: str | None = None
    fail_step: int | None = None
    fail_time: float | None = None
    sampling: str | None = None


@dataclass(frozen=True)
class Timing:
    """Wall times in seconds: set-up (and whether its compilations came from the persistent
    cache), the median of the timed solves (``wall_s``), their spread and number, and the
    time spent in recording callbacks."""

    wall_s: float | None = None
    setup_s: float | None = None
    #: Where the set-up's compilations came from (:class:`benchmarks.compilation.Watch`).
    setup_cache: str | None = None
    repeats: int | None = None
    wall_min_s: float | None = None
    wall_max_s: float | None = None
    callback_s: float | None = None


@dataclass(frozen=True)
class Work:
    """The work counters (:data:`integrators.base.COUNTERS`), the linear solver that ran,
    the number of entries of the pattern it factorised, and the JAX platform the run's
    compiled code ran on (``cpu``, ``gpu``; an ensemble whose chunks ran on both, ``cpu+gpu``)."""

    n_steps: int | None = None
    n_rejected: int | None = None
    n_f_evals: int | None = None
    n_jac_evals: int | None = None
    n_newton: int | None = None
    n_lin_solves: int | None = None
    linear_solver: str | None = None
    pattern_nnz: int | None = None
    device: str | None = None


class Metrics:
    """The metrics (docs/design.md, section 5; :mod:`benchmarks.metrics`), the errors of the
    declared invariants (JSON), the drift classes (:mod:`benchmarks.drift`), the
    accuracy of the reference the final error was measured against and, without a
    conserved energy, the energy balance's error and its quadrature's floor
    (:mod:`benchmarks.balance`): one value per column of part ``metrics``
    (:mod:`benchmarks.columns`), ``None`` where not measured.

    Not a dataclass: its fields are the declared columns, so that a metric declared later
    has one too. Read a value as an attribute; :meth:`replace` gives a changed copy.
    """

    __slots__ = ("_values",)

    def __init__(self, **values):
        names = of_part("metrics")
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise TypeError(f"Metrics: no metric column named {', '.join(unknown)}")
        object.__setattr__(self, "_values", {n: values.get(n) for n in names})

    def as_dict(self) -> dict:
        """Every declared metric column -> its value (``None``: not measured)."""
        return {n: self._values.get(n) for n in of_part("metrics")}

    def replace(self, **changes) -> "Metrics":
        """A copy with ``changes``."""
        return Metrics(**{**self.as_dict(), **changes})

    def __getattr__(self, name):
        if name.startswith("_") or name not in of_part("metrics"):
            raise AttributeError(name)
        return self._values.get(name)

    def __setattr__(self, name, value):
        raise AttributeError("Metrics is immutable: use replace()")

    def __eq__(self, other):
        return isinstance(other, Metrics) and self.as_dict() == other.as_dict()

    def __hash__(self):
        return hash(tuple(self.as_dict().items()))

    def __repr__(self):
        given = ", ".join(f"{k}={v!r}" for k, v in self.as_dict().items() if v is not None)
        return f"Metrics({given})"

    def __reduce__(self):
        return (_metrics, (self._values,))


def _metrics(values: dict) -> Metrics:
    """A :class:`Metrics` of ``values`` as pickled (names the unpickling side does not
    declare are dropped)."""
    names = set(of_part("metrics"))
    return Metrics(**{k: v for k, v in values.items() if k in names})


@dataclass(frozen=True)
class Spread:
    """An ensemble's distributions over its lanes: the fraction of lanes that failed and the
    quantiles :data:`QUANTILES` of each lane's ``max |g|`` (``pos_q...``), ``max |G v +
    g_t|`` (``vel_q...``), relative energy error (``energy_q...``) and final error against
    its own reference (``final_q...``, :func:`problems.ensemble.references`), over the
    lanes that finished (all ``None`` for a single run). The per-lane values are the
    record's :attr:`Record.lanes`."""

    failed_fraction: float | None = None
    pos_q0: float | None = None
    pos_q50: float | None = None
    pos_q90: float | None = None
    pos_q100: float | None = None
    vel_q0: float | None = None
    vel_q50: float | None = None
    vel_q90: float | None = None
    vel_q100: float | None = None
    energy_q0: float | None = None
    energy_q50: float | None = None
    energy_q90: float | None = None
    energy_q100: float | None = None
    final_q0: float | None = None
    final_q50: float | None = None
    final_q90: float | None = None
    final_q100: float | None = None


#: The parts of a record, by field name of :class:`Record`: each column of :data:`COLUMNS`
#: is a field of the part its declaration names (``tests/test_store.py`` holds the two
#: equal).
PARTS = {"run": Run, "ending": Ending, "timing": Timing, "work": Work, "metrics": Metrics,
         "spread": Spread}


@dataclass(frozen=True)
class Record:
    """A finished run, complete: what ran, how it ended, its timing, work and metrics, its
    drift series and its sampled states; for an ensemble, its :class:`Spread` and the
    per-lane table ``lanes`` (name -> one value per lane: the lane's ``seed`` index,
    ``status`` code, metrics and counters). Missing values are ``None``.

    :attr:`row` is its ``runs.csv`` row, the one conversion that the store and
    ``runs.csv`` both use; :meth:`from_row` reads a stored row back.
    """

    run: Run
    ending: Ending
    timing: Timing = Timing()
    work: Work = Work()
    metrics: Metrics = Metrics()
    spread: Spread = Spread()
    windows: dict[str, np.ndarray] = field(default_factory=dict, compare=False)
    samples: dict[str, np.ndarray] = field(default_factory=dict, compare=False)
    lanes: dict[str, np.ndarray] = field(default_factory=dict, compare=False)

    @property
    def row(self) -> dict:
        """The ``runs.csv`` row: every column of :data:`COLUMNS`, in order."""
        values = {}
        for name in PARTS:
            part = getattr(self, name)
            values.update(part.as_dict() if isinstance(part, Metrics) else asdict(part))
        return {c: values.get(c) for c in COLUMNS}

    @classmethod
    def from_row(cls, row, windows=None, samples=None, lanes=None) -> "Record":
        """The record of a ``runs.csv`` or stored row (a mapping; absent columns are
        ``None``)."""
        parts = {name: part(**{c: row.get(c) for c in of_part(name)})
                 for name, part in PARTS.items()}
        status = parts["ending"].status
        parts["ending"] = replace(parts["ending"],
                                  status=None if status is None else Status(status))
        return cls(**parts, windows=dict(windows or {}), samples=dict(samples or {}),
                   lanes=dict(lanes or {}))


def _plain(value):
    """A JSON-able form of a parameter or option value (exact for floats)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return repr(value)


def run_key(resolved: dict, version: str) -> str:
    """A stable hash of everything that determines a run's results.

    ``resolved`` holds the problem's name and fully resolved parameters, the integrator's
    registry key and every option, ``t_end`` and the recording grid; ``version`` is the
    code version (:func:`provenance`). Floats enter by their shortest round-trip text, so
    equal values give equal keys.
    """
    text = json.dumps({**resolved, "code": version}, sort_keys=True, default=_plain,
                      allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _git(*args) -> bytes:
    root = Path(__file__).resolve().parent.parent
    try:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return b""


def versions(names) -> dict[str, str | None]:
    """The installed version of each distribution in ``names`` (``None``: not installed)."""
    found = {}
    for name in names:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = None
    return found


@functools.lru_cache(maxsize=1)
def _machine() -> dict[str, str]:
    machine = " ".join(x for x in (platform.node(), platform.system(), platform.machine(),
                                   f"{os.cpu_count()} CPUs") if x)
    return {"machine": machine, "python": platform.python_version(),
            "versions": json.dumps(versions(PACKAGES))}


def provenance() -> dict[str, object]:
    """What code runs, and where.

    ``commit`` (``None`` outside a git checkout); ``dirty``: whether the tracked files
    differ from that commit; ``code_version``: the commit, plus a hash of the difference
    when dirty, so two edits of the same commit have different versions (run keys include
    it: a resumed sweep never mixes results of different code). :data:`CODE_VERSION_ENV`
    overrides the code version: to resume a sweep across an edit known not to change
    results, or to give a test a version that concurrent edits do not change. Then
    ``machine``, ``python`` and ``versions`` (JSON of :data:`PACKAGES`).
    """
    commit = _git("rev-parse", "HEAD").decode().strip() or None
    diff = _git("diff", "HEAD", "--no-ext-diff", "--binary")
    version = commit or "unknown"
    if diff:
        version = f"{version}+{hashlib.sha256(diff).hexdigest()[:12]}"
    return {"commit": commit, "dirty": bool(diff),
            "code_version": os.environ.get(CODE_VERSION_ENV) or version, **_machine()}
