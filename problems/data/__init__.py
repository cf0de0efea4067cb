"""Stored reference solutions computed by documented tight-tolerance runs.

Each ``NAME.json`` here holds the command that regenerates it (``python -m
problems.data.generate NAME``), the method, and a list of entries: the problem parameters,
the time, the reference ``q`` and ``v`` and an estimate of their error (the max-norm
difference between two runs at different tolerances). :func:`reference` turns the entries
for a case's parameters into its :class:`~problems.case.Reference`; a case without stored
entries has no reference.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from problems.case import Reference

DATA_DIR = Path(__file__).parent


@lru_cache(maxsize=None)
def load(name: str) -> dict:
    """The stored file ``NAME.json`` as a dictionary (empty entries if it does not exist)."""
    path = DATA_DIR / f"{name}.json"
    if not path.exists():
        return {"entries": []}
    return json.loads(path.read_text())


def state(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(q, v)`` of an entry as float64 arrays."""
    return np.array(entry["q"], dtype=np.float64), np.array(entry["v"], dtype=np.float64)


def reference(name: str, params: dict) -> Reference | None:
    """The stored computed reference of ``NAME.json`` for ``params`` (None if not stored).

    Scored on every component of ``(q, v)``, at the stored times only, and valid on the
    span from ``t = 0``, where every stored integration starts (:mod:`problems.data.generate`),
    to the last stored time; its floor is the largest stored error estimate.
    """
    stored = load(name)
    entries = [e for e in stored["entries"] if e["params"] == params]
    if not entries:
        return None
    by_time = {float(e["t"]): state(e) for e in entries}
    worst = max(float(e["error_estimate"]) for e in entries)
    n = len(entries[0]["q"])
    return Reference(
        kind="computed",
        source=(f"{stored['method']}; stored in problems/data/{name}.json (estimated error "
                f"<= {worst:.1e}); regenerate with: {stored['command']}"),
        solution=lambda t: by_time[min(by_time, key=lambda s: abs(s - t))],
        scored=tuple(range(2 * n)),
        times=tuple(sorted(by_time)),
        floor=worst,
        span=(0.0, max(by_time)),
    )
