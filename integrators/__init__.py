"""Integrator registry: kebab-case keys name a formulation and its preset options.

``make("lobatto3ab3:newton_tol=1e-12", h=0.05)`` builds the frozen dataclass of the key with
the preset options, the ``key=value`` options and the keyword overrides, in that order.
:func:`resolve` parses a spec string once into an :class:`~problems.spec.IntegratorSpec`,
which :func:`make` builds from as it is.
"""

from __future__ import annotations

import dataclasses
import importlib

from integrators.base import Grid, Integrator, Trajectory  # noqa: F401
from integrators.fixed import FixedStep, Stepper  # noqa: F401
from problems.source import located
from problems.spec import IntegratorSpec, SpecError, parse_value, split_spec, suggest

#: key -> ("module:Class", preset options)
REGISTRY: dict[str, tuple[str, dict[str, object]]] = {
    "lobatto3ab2": ("integrators.lobatto:LobattoIIIAIIIB", {"stages": 2}),
    "lobatto3ab3": ("integrators.lobatto:LobattoIIIAIIIB", {"stages": 3}),
    "lobatto3ab4": ("integrators.lobatto:LobattoIIIAIIIB", {"stages": 4}),
    "rattle": ("integrators.rattle:Rattle", {}),
    "ida-ggl": ("integrators.ida:IDA", {"formulation": "ggl"}),
    "ida-index1": ("integrators.ida:IDA", {"formulation": "index1"}),
    "baumgarte-rk4": ("integrators.baumgarte:BaumgarteRK", {"solver": "rk4"}),
    "baumgarte-tsit5": ("integrators.baumgarte:BaumgarteEmbeddedRK", {"solver": "tsit5"}),
    "baumgarte-dopri5": ("integrators.baumgarte:BaumgarteEmbeddedRK", {"solver": "dopri5"}),
    "baumgarte-dopri8": ("integrators.baumgarte:BaumgarteEmbeddedRK", {"solver": "dopri8"}),
    "genalpha": ("integrators.genalpha:GeneralizedAlpha", {"formulation": "index3"}),
    "genalpha-ggl": ("integrators.genalpha:GeneralizedAlpha", {"formulation": "ggl"}),
    "hht": ("integrators.genalpha:HHT", {"formulation": "index3"}),
    "radau5": ("integrators.radau:RadauIIA", {"formulation": "index3"}),
    "radau5-ggl": ("integrators.radau:RadauIIA", {"formulation": "ggl"}),
}


def register(key: str, target: str, **preset) -> None:
    """Register ``key`` for the class at ``"module:Class"`` with preset options.

    Raises
    ------
    ValueError
        ``key`` is taken, or ``target`` names no class (checked now, so that the error
        points at the registration, not at the first run).
    """
    if key in REGISTRY:
        raise ValueError(f"integrator {key!r} registered twice")
    module, _, name = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as exc:
        raise ValueError(f"integrator {key!r}: target {target!r} is not a class "
                         f"'module:Class' that can be imported ({exc})") from None
    if not (isinstance(cls, type) and issubclass(cls, Integrator)):
        raise ValueError(f"integrator {key!r}: target {target!r} is not an Integrator class")
    REGISTRY[key] = (target, preset)


def cls_of(key: str) -> type[Integrator]:
    """The class behind a registry key."""
    module, _, name = REGISTRY[key][0].partition(":")
    return getattr(importlib.import_module(module), name)


def resolve(spec: str | IntegratorSpec, origin: str = "") -> IntegratorSpec:
    """The :class:`~problems.spec.IntegratorSpec` of ``spec`` (``key`` or
    ``key:opt=value,...``): the key checked against the registry, every option given
    checked against the class's fields and typed as its default. A resolved spec is
    returned as it is.

    Raises
    ------
    SpecError
        An unknown key or option, or a value of the wrong type.
    """
    if isinstance(spec, IntegratorSpec):
        return spec
    key, raw = split_spec(spec)
    if key not in REGISTRY:
        raise SpecError(f"unknown integrator {key!r}{suggest(key, REGISTRY)}; "
                        f"known: {', '.join(sorted(REGISTRY))}")
    fields = {f.name: f for f in dataclasses.fields(cls_of(key))}
    preset = REGISTRY[key][1]
    options = {}
    for name, text in raw.items():
        if name not in fields:
            raise SpecError(located(f"integrator {key!r} has no option {name!r}"
                                    f"{suggest(name, fields)}; options: {', '.join(fields)}",
                                    cls_of(key)))
        default = preset.get(name, fields[name].default)
        options[name] = parse_value(text, default, f"integrator {key!r}, option {name!r}")
    return IntegratorSpec(key, tuple(options.items()), spec, origin)


def make(spec: str | IntegratorSpec, **overrides) -> Integrator:
    """Build the integrator of ``spec`` (a spec string, or resolved by :func:`resolve`):
    the key's preset options, the spec's options, then ``overrides``.

    Overrides (``h``, ``rtol``, ``atol``) that the class does not have are ignored, so the
    runner can pass ``h`` to every method and only fixed-step ones take it.
    """
    spec = resolve(spec)
    cls = cls_of(spec.name)
    fields = {f.name for f in dataclasses.fields(cls)}
    options = {**REGISTRY[spec.name][1], **spec.kwargs}
    options.update({k: v for k, v in overrides.items() if k in fields and v is not None})
    integrator = cls(**options)
    try:
        integrator.check()
    except ValueError as exc:
        raise SpecError(located(f"integrator {str(spec)!r}: {exc}", cls)) from None
    return integrator


def keys() -> list[str]:
    """Registered keys, in registration order."""
    return list(REGISTRY)
