"""Suites as declarative TOML files under ``benchmarks/suites/``.

A suite file has a ``description`` and one or more ``[[group]]`` tables; each group runs
every combination of its lists::

    description = "the seed's experiment"

    [[group]]
    problems = ["sps-receiver"]
    integrators = ["lobatto3ab2"]
    h = [0.5]
    t_end = 50.0

``h`` applies to fixed-step integrators, ``rtol`` and ``atol`` to adaptive ones. A file
that is not valid TOML, has an unknown key or a value of the wrong type is refused with a
message that names the file, the line and what is wrong.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

from benchmarks.runner import RunSpec, expand
from problems import suggest

SUITE_DIR = Path(__file__).parent / "suites"

#: Allowed keys and their types: top level, and per group.
TOP_KEYS = {"description": str, "group": list, "repeats": int}
GROUP_KEYS = {"problems": list, "integrators": list, "h": list, "rtol": list, "atol": list,
              "t_end": float}


class SuiteError(ValueError):
    """A suite that does not exist or cannot be read."""


@dataclass(frozen=True)
class Suite:
    name: str
    description: str
    runs: list[RunSpec]
    repeats: int | None = None


def names() -> list[str]:
    """The suites shipped with the project."""
    return sorted(p.stem for p in SUITE_DIR.glob("*.toml"))


def _line_of(text: str, key: str, occurrence: int = 0) -> int:
    hits = [text[: m.start()].count("\n") + 1
            for m in re.finditer(rf"^\s*{re.escape(key)}\s*=", text, re.M)]
    return hits[min(occurrence, len(hits) - 1)] if hits else 0


def load(name: str) -> Suite:
    """Load a suite by name (``benchmarks/suites/NAME.toml``) or by path."""
    path = Path(name)
    if not path.suffix:
        path = SUITE_DIR / f"{name}.toml"
        if not path.exists():
            raise SuiteError(f"unknown suite {name!r}{suggest(name, names())}; "
                             f"known: {', '.join(names())}")
    if not path.exists():
        raise SuiteError(f"suite file {path} does not exist")
    text = path.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SuiteError(f"{path}: invalid TOML: {exc}") from None

    def fail(key: str, what: str, occurrence: int = 0):
        line = _line_of(text, key, occurrence)
        where = f"{path}:{line}" if line else str(path)
        raise SuiteError(f"{where}: {what}")

    for key, value in data.items():
        if key not in TOP_KEYS:
            fail(key, f"unknown key {key!r}{suggest(key, TOP_KEYS)}; allowed: {', '.join(TOP_KEYS)}")
        if not isinstance(value, TOP_KEYS[key]):
            fail(key, f"{key!r} must be a {TOP_KEYS[key].__name__}")
    groups = data.get("group", [])
    if not groups:
        raise SuiteError(f"{path}: no [[group]] table: a suite needs at least one")
    runs: list[RunSpec] = []
    seen: dict[str, int] = {}
    for group in groups:
        for key, value in group.items():
            occurrence = seen.get(key, 0)
            seen[key] = occurrence + 1
            if key not in GROUP_KEYS:
                fail(key, f"unknown key {key!r} in [[group]]{suggest(key, GROUP_KEYS)}; "
                          f"allowed: {', '.join(GROUP_KEYS)}", occurrence)
            want = GROUP_KEYS[key]
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) \
                if want is float else isinstance(value, want)
            if want is list and ok:
                item_types = (str,) if key in ("problems", "integrators") else (int, float)
                ok = all(isinstance(v, item_types) and not isinstance(v, bool) for v in value)
            if not ok:
                fail(key, f"{key!r} has the wrong type: expected "
                          f"{'a number' if want is float else 'a list'}"
                          f"{' of strings' if key in ('problems', 'integrators') else ''}"
                          f"{' of numbers' if key in ('h', 'rtol', 'atol') else ''}", occurrence)
        for required in ("problems", "integrators"):
            if required not in group:
                raise SuiteError(f"{path}: a [[group]] lacks the required key {required!r}")
        runs.extend(expand(group["problems"], group["integrators"],
                           [float(x) for x in group.get("h", [])],
                           [float(x) for x in group.get("rtol", [])],
                           [float(x) for x in group.get("atol", [])],
                           float(group["t_end"]) if "t_end" in group else None))
    return Suite(path.stem, data.get("description", ""), runs, data.get("repeats"))
