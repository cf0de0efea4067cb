"""The Python API: one call runs a sweep and returns its runs as a pandas DataFrame.

::

    from benchmarks.api import sweep

    runs = sweep(["pendulum", my_case], ["rattle", "lobatto3ab3"], h=[0.01, 0.005],
                 t_end=100.0)
    runs[["problem", "integrator", "h", "status", "max_pos_residual"]]

It is the command line's batch (:func:`benchmarks.batch.run_specs`) with the same
isolation, time limits, engines and progress lines; the columns are those of ``runs.csv``
(:data:`benchmarks.records.COLUMNS`), and the accuracy columns equal the command line's
for the same runs, bit for bit. A plain script may call it without an ``if __name__ ==
"__main__"`` guard: neither the runs' worker processes (:mod:`benchmarks.pool`) nor the
report's drawing processes (:class:`reports.figures.Drawing`) import the caller's script.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Iterable, TextIO

import pandas as pd

from benchmarks.batch import run_specs, user_code
from benchmarks.plan import expand
from benchmarks.records import COLUMNS, InputError
from problems import Case
from reports import build as build_report


def sweep(problems: str | Case | Iterable[str | Case], integrators: str | Iterable[str], *,
          h: float | Iterable[float] = (), rtol: float | Iterable[float] = (),
          atol: float | Iterable[float] = (),
          t_end: float | None = None, load: Iterable[str] = (), out: str | Path | None = None,
          report: bool = False, jobs: int | None = None, cluster: str | None = None,
          timeout: float | None = None, repeats: int = 3,
          log: TextIO | None | str = "stderr") -> pd.DataFrame:
    """Run every combination of problems, integrators and settings; return the runs.

    Parameters
    ----------
    problems : str, Case or iterable of them
        Problem specs (``"pendulum"``, ``"chain:N=16"``, a loaded problem's name) or
        :class:`problems.Case` objects built with :func:`problems.make_case` (run under
        their names, which must not be registered problems' names).
    integrators : str or iterable of str
        Integrator specs (``"rattle"``, ``"lobatto3ab3:newton_tol=1e-12"``).
    h, rtol, atol : float or iterable of float
        Step sizes for fixed-step methods; tolerances for adaptive ones. Empty: each
        method's default.
    t_end : float, optional
        The horizon (default: each problem's own): the ``t_end`` parameter of every
        problem whose factory takes one (:func:`problems.at_horizon`); other problems,
        and cases, run to it and are scored only within their reference's span.
    load : iterable of str
        Files or modules that register problems or integrators (``--load``).
    out : str or Path, optional
        Keep ``runs.csv`` and the results store here (default: a temporary folder,
        removed afterwards).
    report : bool
        Also write ``report.md`` and ``report.html`` to ``out`` (which it needs).
    jobs, cluster : optional
        The engine: ``jobs`` local worker processes (default: the usable cores) or a Dask
        cluster (``"local:N"``, ``"tcp://HOST:PORT"``).
    timeout : float, optional
        Time limit of each run in seconds (default: one hour).
    repeats : int
        Timed solves of each run at least, within autorange's cap
        (:func:`benchmarks.execute.more`; ``wall_s`` is their median).
    log : text stream, optional
        Where one line per finished run goes (None: nowhere; default: standard error).

    Returns
    -------
    pandas.DataFrame
        One row per run, in the order of the combinations, with the columns of
        ``runs.csv``. A run that failed is a row with its status and message.

    Raises
    ------
    benchmarks.records.InputError
        Bad input, found before any run starts: unknown names, options out of range,
        user code that does not load or does not check out (the message names the file
        and the function).
    """
    if report and out is None:
        raise InputError("report=True needs out= (the folder the report is written to)")
    problems, integrators = _several(problems), _several(integrators)
    cases = [p for p in problems if isinstance(p, Case)]
    specs = [p.name if isinstance(p, Case) else p for p in problems]
    user_code(load, cases)  # so that expand resolves what the user registered
    settings = {name: _numbers(name, values)
                for name, values in (("h", h), ("rtol", rtol), ("atol", atol))}
    if t_end is not None:
        if not isinstance(t_end, (int, float, str)):
            raise InputError(f"t_end = {t_end!r:.60}: one number, the horizon")
        t_end = _numbers("t_end", t_end)[0]
    try:
        runs = expand(specs, integrators, settings["h"], settings["rtol"], settings["atol"],
                      t_end)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    with tempfile.TemporaryDirectory(prefix="driftbench-sweep-") as tmp:
        folder = Path(out) if out is not None else Path(tmp)
        records = run_specs(runs, folder, jobs, cluster=cluster, suite="python-api",
                            repeats=repeats, timeout=timeout, load=load, cases=cases,
                            log=log, progress=False)
        if report:
            build_report(folder / "driftbench.sqlite", folder)
    return pd.DataFrame([r.row for r in records], columns=list(COLUMNS))


def _several(values) -> list:
    """``values`` as a list: one name or case alone is a list of one, not of characters."""
    return [values] if isinstance(values, (str, Case)) else list(values)


def _numbers(name: str, values) -> list[float]:
    """The floats of a setting given as one number or several, or InputError naming it."""
    try:
        return [float(x) for x in
                ([values] if isinstance(values, (int, float, str)) else values)]
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} = {values!r:.60}: not a number or a list of numbers "
                         f"({exc})") from None
