"""Suites as declarative TOML files under ``benchmarks/suites/``.

A suite file has a ``description``, optional ``repeats``, ``timeout`` (seconds per run) and
``budget`` (seconds for the whole suite, report included, on the project's reference
machine of two cores: what ``python -m benchmarks.perf.suite_time`` holds it to), ``[[group]]``
tables of runs and ``studies``; each group runs every combination of its lists::

    description = "the seed's experiment"
    timeout = 600
    budget = 120

    [[group]]
    problems = ["sps-receiver"]
    integrators = ["lobatto3ab2"]
    h = [0.5]
    t_end = 50.0
    timeout = 60          # this group's runs only

``h`` applies to fixed-step integrators, ``rtol`` and ``atol`` to adaptive ones. A group's
``t_end`` (the horizon, overridden by ``--t-end``) is given to the factory of every problem
that takes a ``t_end`` parameter, so its case and reference are built for it
(:func:`problems.at_horizon`). A group's ``timeout`` overrides the suite's, and
``--timeout`` on the command line overrides both.
``ensemble = K`` (and ``seed = S``, default 0) runs each of the group's runs from ``K``
initial states (:mod:`problems.ensemble`), ``device = "auto"`` (or ``"cpu"``, ``"gpu"``)
says where their loops run and ``lanes_per_chunk = L`` how many lanes a chunk of them
holds at least (:func:`benchmarks.plan.lane_ranges`); ``--ensemble``, ``--seed``,
``--device`` and ``--lanes-per-chunk`` on the command line override them for every group.

``studies = ["flexible-modal"]`` names studies that are not integrator runs: each is a
function ``run(out: Path) -> dict[str, DataFrame]`` looked up by name in
:data:`studies.STUDIES` (never taken from the file), run beside the suite's runs.
A suite may hold only studies.

``load = ["models/arm.py", "mypackage.problems"]`` imports user code that registers
problems and integrators (files relative to the suite file, or module names) before the
groups are read; it is the only code a suite file can run, and it is trusted as it is.

``targets = [1e-6, 1e-10]`` sets the accuracy targets of the report's per-problem
target tables (cheapest run reaching each) for this suite's runs.

``cluster = "local:4"`` or ``cluster = "tcp://HOST:PORT"`` runs the suite on a Dask cluster
(:mod:`benchmarks.cluster`) unless the command line names an engine (``--jobs`` or
``--cluster``).

A file that is not valid TOML (nested too deeply included), has an unknown key, a value
of the wrong type or out of range, or names an unknown problem, integrator or study is
refused with one line that names the file, the line and what is wrong.

Entries that repeat a run (the same problem, parameters, method, options and horizon, in
one group or in two) are run once (:func:`benchmarks.plan.pending`).

Reading a suite resolves its specs (:mod:`benchmarks.plan`) and imports no engine.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import integrators
import problems
from benchmarks.plan import DEVICES, cluster_address, expand
from benchmarks.records import InputError, RunSpec
from problems.ensemble import MAX_LANES, MAX_SEED
from problems.spec import SpecError, suggest
from studies import STUDIES

SUITE_DIR = Path(__file__).parent / "suites"

NUMBER, STRINGS, NUMBERS = "a number", "a list of strings", "a list of numbers"
#: Allowed keys and what they hold: top level, and per group.
TOP_KEYS = {"description": "a string", "group": "an array of [[group]] tables",
            "repeats": "a whole number", "timeout": NUMBER, "budget": NUMBER,
            "studies": STRINGS, "cluster": "a string", "load": STRINGS, "targets": NUMBERS}
GROUP_KEYS = {"problems": STRINGS, "integrators": STRINGS, "h": NUMBERS, "rtol": NUMBERS,
              "atol": NUMBERS, "t_end": NUMBER, "timeout": NUMBER,
              "ensemble": "a whole number", "seed": "a whole number", "device": "a string",
              "lanes_per_chunk": "a whole number"}


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _beyond_int64(value) -> bool:
    """Whether ``value`` (or an item of it) is an integer outside TOML's 64-bit range,
    which ``tomllib`` reads all the same (and ``float`` of it may overflow)."""
    items = value if isinstance(value, list) else [value]
    return any(isinstance(x, int) and not -2**63 <= x < 2**63 for x in items)


#: Type checks by the description of what a key holds.
TYPE_CHECKS = {
    "a string": lambda v: isinstance(v, str),
    "an array of [[group]] tables": lambda v: isinstance(v, list)
    and all(isinstance(g, dict) for g in v),
    "a whole number": lambda v: isinstance(v, int) and not isinstance(v, bool),
    NUMBER: _is_number,
    STRINGS: lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
    NUMBERS: lambda v: isinstance(v, list) and all(_is_number(x) for x in v),
}

#: Group keys that say how an ensemble runs, and so need ``ensemble``.
ENSEMBLE_ONLY = ("seed", "device", "lanes_per_chunk")

#: Range checks: key -> (test of one value, what the value must be).
RANGES = {
    "h": (lambda x: math.isfinite(x) and x > 0, "positive and finite"),
    "rtol": (lambda x: 0 < x < 1, "in (0, 1)"),
    "atol": (lambda x: math.isfinite(x) and x > 0, "positive and finite"),
    "t_end": (lambda x: math.isfinite(x) and x > 0, "positive and finite"),
    "timeout": (lambda x: x > 0, "a positive number of seconds (inf for no limit)"),
    "repeats": (lambda x: x >= 1, "at least 1"),
    "budget": (lambda x: math.isfinite(x) and x > 0, "a positive number of seconds"),
    "targets": (lambda x: math.isfinite(x) and x > 0, "positive and finite"),
    "ensemble": (lambda x: 1 <= x <= MAX_LANES, f"a number of lanes from 1 to {MAX_LANES}"),
    "seed": (lambda x: 0 <= x <= MAX_SEED, f"from 0 to {MAX_SEED}"),
    "device": (lambda x: x in DEVICES, f"one of {', '.join(DEVICES)}"),
    "lanes_per_chunk": (lambda x: x >= 2, "at least 2"),
}


class SuiteError(InputError):
    """A suite that does not exist or cannot be read."""


@dataclass(frozen=True)
class Suite:
    """A loaded suite file: its runs, their defaults, its studies and the engine it names.

    ``repeats``, ``timeout``, ``budget`` and ``cluster`` are ``None`` where the file sets
    none; ``load`` holds the user code it loaded (resolved paths and module names);
    ``targets`` the report's accuracy targets (empty: the report's defaults).
    """

    name: str
    description: str
    runs: list[RunSpec]
    repeats: int | None = None
    timeout: float | None = None
    studies: tuple[str, ...] = field(default=())
    budget: float | None = None
    cluster: str | None = None
    load: tuple[str, ...] = field(default=())
    targets: tuple[float, ...] = field(default=())


def names() -> list[str]:
    """The suites shipped with the project."""
    return sorted(p.stem for p in SUITE_DIR.glob("*.toml"))


def _group_spans(text: str) -> list[tuple[int, int]]:
    """First and last line of each ``[[group]]`` block (1-based)."""
    lines = text.splitlines()
    heads = [i + 1 for i, line in enumerate(lines) if re.match(r"\s*\[\[\s*group\s*\]\]", line)]
    ends = []
    for k, head in enumerate(heads):
        stop = heads[k + 1] - 1 if k + 1 < len(heads) else len(lines)
        for j in range(head, stop):  # a later [table] header ends the group too
            if re.match(r"\s*\[", lines[j]):
                stop = j
                break
        ends.append(stop)
    return list(zip(heads, ends))


def _line_of(text: str, key: str, span: tuple[int, int] | None = None) -> int:
    """Line of ``key = ...`` (within ``span`` if given; top level: before any table, or
    the header ``[key]`` of a table)."""
    for i, line in enumerate(text.splitlines(), 1):
        if span is not None and not span[0] <= i <= span[1]:
            continue
        if span is None and re.match(rf"\s*\[\s*{re.escape(key)}\s*\]", line):
            return i
        if span is None and re.match(r"\s*\[", line):
            break
        if re.match(rf"\s*{re.escape(key)}\s*=", line):
            return i
    return span[0] if span else 0


def load(name: str) -> Suite:
    """Load a suite by name (``benchmarks/suites/NAME.toml``) or by path."""
    path = Path(name)
    if not path.suffix:
        path = SUITE_DIR / f"{name}.toml"
        if not path.exists():
            raise SuiteError(f"unknown suite {name!r}{suggest(name, names())}; "
                             f"known: {', '.join(names())}")
    if not path.is_file():
        raise SuiteError(f"suite file {path} does not exist")
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        at = re.search(r"\(at line (\d+), column \d+\)", str(exc))
        raise SuiteError(f"{path}:{at.group(1)}: invalid TOML: {exc}" if at else
                         f"{path}: invalid TOML: {exc}") from None
    except RecursionError:  # the parser recurses once per level of nested arrays and tables
        raise SuiteError(f"{path}: invalid suite file: arrays or tables nested too deeply "
                         f"to read") from None

    def fail(line: int, what: str):
        raise SuiteError(f"{path}:{line}: {what}" if line else f"{path}: {what}")

    def check(table: dict, allowed: dict, where: str, line_of) -> None:
        for key, value in table.items():
            if key not in allowed:
                fail(line_of(key), f"unknown key {key!r}{where}{suggest(key, allowed)}; "
                                   f"allowed: {', '.join(allowed)}")
            if _beyond_int64(value):
                fail(line_of(key), f"{key!r}{where} holds an integer beyond TOML's 64-bit "
                                   f"range")
            if not TYPE_CHECKS[allowed[key]](value):
                fail(line_of(key), f"{key!r}{where} must be {allowed[key]}, "
                                   f"not {type(value).__name__} {value!r}")
            if key in RANGES:
                ok, must = RANGES[key]
                bad = [x for x in (value if isinstance(value, list) else [value]) if not ok(x)]
                if bad:
                    fail(line_of(key), f"{key!r}{where} = {bad[0]!r} must be {must}")
            if key in ("problems", "integrators", "studies") and not value:
                fail(line_of(key), f"{key!r}{where} is an empty list")
            if key in ENSEMBLE_ONLY and "ensemble" not in table:
                fail(line_of(key), f"{key!r}{where} applies to ensembles only: give "
                                   f"'ensemble = K' too")

    check(data, TOP_KEYS, "", lambda key: _line_of(text, key))
    groups = data.get("group", [])
    studies = tuple(data.get("studies", ()))
    for study in studies:
        if study not in STUDIES:
            fail(_line_of(text, "studies"), f"unknown study {study!r}{suggest(study, STUDIES)}; "
                                            f"known: {', '.join(sorted(STUDIES))}")
    loaded = []
    for source in data.get("load", []):
        try:
            loaded.append(problems.load(source, base=path.parent))
        except problems.LoadError as exc:
            fail(_line_of(text, "load"), f"load: {exc}")
    cluster = data.get("cluster")
    if cluster is not None:
        try:
            cluster_address(cluster)
        except InputError as exc:
            fail(_line_of(text, "cluster"), str(exc))
    if not groups and not studies:
        fail(0, "no [[group]] table and no studies: a suite needs at least one")
    spans = _group_spans(text)
    runs: list[RunSpec] = []
    for k, group in enumerate(groups):
        span = spans[k] if k < len(spans) and len(spans) == len(groups) else None
        where = f" in [[group]] {k + 1}"

        def line_of(key, span=span):
            return _line_of(text, key, span) if span else _line_of(text, key)

        check(group, GROUP_KEYS, where, line_of)
        for required in ("problems", "integrators"):
            if required not in group:
                fail(span[0] if span else 0, f"[[group]] {k + 1} lacks the required key "
                                             f"{required!r}")
        origin = f"{path}:{span[0]} ([[group]] {k + 1})" if span else f"{path} ([[group]] {k + 1})"
        resolved = []
        for spec in group["problems"]:
            try:
                resolved.append(problems.resolve(spec, origin))
            except SpecError as exc:
                fail(line_of("problems"), f"{exc}{where}")
        try:
            methods = [integrators.resolve(spec, origin) for spec in group["integrators"]]
            runs.extend(expand(resolved, methods,
                               [float(x) for x in group.get("h", [])],
                               [float(x) for x in group.get("rtol", [])],
                               [float(x) for x in group.get("atol", [])],
                               float(group["t_end"]) if "t_end" in group else None,
                               float(group["timeout"]) if "timeout" in group else None,
                               origin, group.get("ensemble"), group.get("seed"),
                               group.get("device"), group.get("lanes_per_chunk")))
        except SpecError as exc:
            fail(line_of("integrators"), f"[[group]] {k + 1}: {exc}")
    timeout = float(data["timeout"]) if "timeout" in data else None
    if timeout is not None:
        runs = [r if r.timeout is not None else dataclasses.replace(r, timeout=timeout)
                for r in runs]
    return Suite(path.stem, data.get("description", ""), runs, data.get("repeats"),
                 timeout, studies, float(data["budget"]) if "budget" in data else None,
                 cluster, tuple(loaded), tuple(float(x) for x in data.get("targets", ())))
