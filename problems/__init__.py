"""Problem registry: names map to case factories; ``name:key=value,...`` sets parameters.

A problem module defines a factory whose keyword arguments (with defaults) are the
problem's parameters and registers it with :func:`register`. The parameter types come from
the defaults, so ``chain:N=64`` gives an ``int`` and ``sps-ring:coriolis=false`` a ``bool``.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
from typing import Callable

from problems.case import Case, InconsistentInitialValues, Reference, make_case  # noqa: F401
from problems.mechanics import Mechanics, System  # noqa: F401

REGISTRY: dict[str, Callable[..., Case]] = {}

#: Modules that register problems when imported.
_MODULES = (
    "problems.pendulum", "problems.sps_receiver", "problems.flexible_spacecraft",
    "problems.andrews", "problems.car_axis", "problems.double_pendulum", "problems.chain",
    "problems.four_bar", "problems.sps_ring", "problems.sps_lattice", "problems.rigid_body",
    "problems.bricard",
)


class SpecError(ValueError):
    """A problem or integrator specification that cannot be understood."""


def register(name: str):
    """Decorator: register a case factory under ``name``."""

    def wrap(factory: Callable[..., Case]) -> Callable[..., Case]:
        if name in REGISTRY:
            raise ValueError(f"problem {name!r} registered twice")
        REGISTRY[name] = factory
        return factory

    return wrap


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
            options[key.strip()] = value.strip()
    return name, options


def parameters(name: str) -> dict[str, object]:
    """Parameter names and defaults of a registered problem."""
    _load()
    sig = inspect.signature(REGISTRY[name])
    return {k: p.default for k, p in sig.parameters.items()}


def make(spec: str, **overrides) -> Case:
    """Build the case named by ``spec`` (``name`` or ``name:key=value,...``)."""
    _load()
    name, raw = split_spec(spec)
    if name not in REGISTRY:
        raise SpecError(f"unknown problem {name!r}{suggest(name, REGISTRY)}; "
                        f"known: {', '.join(sorted(REGISTRY))}")
    defaults = parameters(name)
    kwargs = {}
    for key, text in raw.items():
        if key not in defaults:
            raise SpecError(f"problem {name!r} has no parameter {key!r}{suggest(key, defaults)}; "
                            f"parameters: {', '.join(defaults) or 'none'}")
        kwargs[key] = parse_value(text, defaults[key], f"problem {name!r}, parameter {key!r}")
    kwargs.update(overrides)
    return REGISTRY[name](**kwargs)


def names() -> list[str]:
    """Registered problem names, sorted."""
    _load()
    return sorted(REGISTRY)


def _load() -> None:
    for module in _MODULES:
        importlib.import_module(module)
