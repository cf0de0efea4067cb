"""Specification strings, ``name:key=value,...``, shared by the problem and integrator
registries: splitting, typed values, the error and hint they raise and give, and the
resolved values they become (:class:`ProblemSpec`, :class:`IntegratorSpec`).

A spec string is parsed once, where it enters (command line, suite file, Python API):
:func:`problems.resolve` and :func:`integrators.resolve` check the name and every
``key=value`` against the registry and return a resolved spec, which
:func:`problems.make` and :func:`integrators.make` build from without parsing again.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field


class SpecError(ValueError):
    """A problem or integrator specification that cannot be understood."""


def suggest(name: str, valid) -> str:
    """A ' (did you mean ...?)' hint, or an empty string."""
    close = difflib.get_close_matches(name, list(valid), n=3, cutoff=0.5)
    return f" (did you mean {', '.join(close)}?)" if close else ""


def parse_value(text: str, default, where: str):
    """Convert ``text`` to the type of ``default``."""
    try:
        if isinstance(default, bool):
            low = text.strip().lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return low in ("true", "1", "yes")
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            return float(text)
        return text
    except ValueError:
        raise SpecError(f"{where}: {text!r} is not a valid {type(default).__name__}") from None


def split_spec(spec: str) -> tuple[str, dict[str, str]]:
    """Split ``name:key=value,key=value`` into the name and raw option strings."""
    name, _, rest = spec.partition(":")
    name = name.strip()
    options: dict[str, str] = {}
    if rest.strip():
        for item in rest.split(","):
            key, eq, value = item.partition("=")
            if not eq or not key.strip():
                raise SpecError(f"{spec!r}: option {item!r} is not of the form key=value")
            if key.strip() in options:  # the last value winning would hide a typo
                raise SpecError(f"{spec!r}: {key.strip()!r} is given twice")
            options[key.strip()] = value.strip()
    return name, options


@dataclass(frozen=True)
class Spec:
    """A resolved specification: the registry name and its arguments by name.

    ``text`` is the spec as written (what ``runs.csv`` and messages show) and ``origin``
    where it was written (a suite file and line); neither takes part in comparisons, so
    ``pendulum`` and ``pendulum:L=1.0`` are the same spec.
    """

    name: str
    arguments: tuple[tuple[str, object], ...]
    text: str = field(default="", compare=False)
    origin: str = field(default="", compare=False)

    @property
    def kwargs(self) -> dict[str, object]:
        """The arguments as keyword arguments."""
        return dict(self.arguments)

    def __str__(self) -> str:
        return self.text or self.name


@dataclass(frozen=True)
class ProblemSpec(Spec):
    """A problem: its registered name and every parameter of its factory (defaults filled
    in), typed as the defaults are."""


@dataclass(frozen=True)
class IntegratorSpec(Spec):
    """An integrator: its registry key and the options given to it (typed as the class's
    fields); once planned, every option of the integrator that runs."""
