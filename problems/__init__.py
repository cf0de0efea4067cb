"""Problem registry and the public problem-authoring API.

A problem is a factory whose keyword arguments (with defaults) are its parameters and which
returns a :class:`Case`; :func:`register` names it. The parameter types come from the
defaults, so ``chain:N=64`` gives an ``int`` and ``sps-ring:coriolis=false`` a ``bool``.

The public API, exactly what the built-in problems use:

- :class:`System`: the physics, ``mass``, ``potential``, ``constraints`` and optional
  ``forces`` as JAX functions (everything else is derived by autodiff);
- :func:`make_case`: a :class:`Case` from a system, initial values, a horizon, the
  parameters, the energy scale and an optional :class:`Reference`;
- :func:`register`: the decorator that names a factory.

User code registers problems (and integrators, through :func:`integrators.register`) the
same way, from a file or a module given to :func:`load` (``--load`` on the command line,
``load = [...]`` in a suite file) or from an installed package through the entry-point
group ``driftbench.problems``. Loaded code is trusted Python, run as it is.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.util
import inspect
import sys
import sysconfig
import traceback
from collections import OrderedDict
from importlib import metadata
from pathlib import Path
from typing import Callable

from problems.case import (Case, InconsistentInitialValues, Perturbation, Reference,  # noqa: F401
                           make_case)
from problems.mechanics import Mechanics, System  # noqa: F401
from problems.spec import ProblemSpec, SpecError, parse_value, split_spec, suggest

#: The public problem-authoring API.
__all__ = ["System", "make_case", "Reference", "Perturbation", "Case", "register", "load"]

REGISTRY: dict[str, Callable[..., Case]] = {}

#: Modules that register problems when imported.
_MODULES = (
    "problems.pendulum", "problems.sps_receiver", "problems.flexible_spacecraft",
    "problems.andrews", "problems.car_axis", "problems.double_pendulum", "problems.chain",
    "problems.four_bar", "problems.sps_ring", "problems.sps_lattice", "problems.rigid_body",
    "problems.bricard",
    "problems.rigid_chain", "problems.flyball_governor",
)


#: Entry-point group through which installed packages register problems.
ENTRY_POINTS = "driftbench.problems"

#: Where each registered problem comes from: ``built-in``, a file, a module or a package.
ORIGINS: dict[str, str] = {}
#: What :func:`load` is loading now (the origin of what registers meanwhile).
_loading: list[str] = []
#: Loaded sources: resolved file path or module name -> module.
_loaded: dict[str, object] = {}


class LoadError(SpecError):
    """User code that cannot be loaded: the message names the file and what is wrong."""


class SizeError(SpecError):
    """A problem spec above its size limit (see :func:`check_size`)."""


#: Largest product of a problem's size parameters built without ``allow_large``: four
#: times the largest size the scaling study runs (16384), far below sizes whose building
#: alone exhausts memory (``chain:N=1000000000`` asks for 15 GiB).
SIZE_LIMIT = 100_000
#: Whole-number parameters that are not sizes (a seed, a horizon in whole seconds).
NOT_SIZES = frozenset({"seed", "t_end"})
#: Size limits that problems declare (:func:`register`'s ``size_limit``), by name.
SIZE_LIMITS: dict[str, int] = {}
#: How a caller lifts the size limits, as error messages say it.
ALLOW_LARGE = "--allow-large (allow_large=True in Python)"


def register(name: str, origin: str | None = None, size_limit: int | None = None):
    """Decorator: register a case factory under ``name``.

    Parameters
    ----------
    name : str
        The problem's name on the command line and in suites (kebab-case).
    origin : str, optional
        Where the factory comes from, as ``--list`` shows it; default: the file, module or
        package being loaded (:func:`load`), else ``built-in``.
    size_limit : int, optional
        The largest product of the problem's size parameters (its whole-number parameters
        but ``seed``: counts of bodies, rings, modes) that is built without
        ``allow_large``; default :data:`SIZE_LIMIT`. A problem whose memory grows faster
        than its size (a dense matrix) declares a lower one.

    The factory's keyword arguments, all with defaults, are the problem's parameters
    (``name:key=value,...``); it returns a :class:`Case` (build it with
    :func:`make_case`)::

        @register("spherical-pendulum")
        def spherical_pendulum(L: float = 1.0, t_end: float = 100.0) -> Case:
            ...

    A ``t_end`` parameter is the horizon: ``--t-end`` (a suite's ``t_end``, the Python
    API's) sets it (:func:`at_horizon`), so the case and its reference are built for the
    horizon that runs. A reference valid up to some time only (one computed by the
    factory) declares it, :attr:`Reference.span`, and is never scored past it.

    Raises
    ------
    ValueError
        When ``name`` is registered already (the message says by whom).
    """

    def wrap(factory: Callable[..., Case]) -> Callable[..., Case]:
        if name in REGISTRY:
            raise ValueError(f"problem {name!r} registered twice (first by {ORIGINS[name]})")
        REGISTRY[name] = factory
        ORIGINS[name] = origin or (_loading[-1] if _loading else "built-in")
        if size_limit is not None:
            SIZE_LIMITS[name] = size_limit
        return factory

    return wrap


def parameters(name: str) -> dict[str, object]:
    """Parameter names and defaults of a registered problem."""
    _load()
    sig = inspect.signature(REGISTRY[name])
    return {k: p.default for k, p in sig.parameters.items()}


def resolve(spec: str | ProblemSpec, origin: str = "") -> ProblemSpec:
    """The :class:`~problems.spec.ProblemSpec` of ``spec`` (``name`` or
    ``name:key=value,...``): the name checked against the registry, every parameter typed
    as its default, the defaults filled in. A resolved spec is returned as it is.

    Raises
    ------
    SpecError
        An unknown name or parameter, or a value of the wrong type.
    """
    if isinstance(spec, ProblemSpec):
        return spec
    _load()
    name, raw = split_spec(spec)
    if name not in REGISTRY:
        raise SpecError(f"unknown problem {name!r}{suggest(name, REGISTRY)}; "
                        f"known: {', '.join(sorted(REGISTRY))}")
    arguments = parameters(name)
    for key, text in raw.items():
        if key not in arguments:
            raise SpecError(f"problem {name!r} has no parameter {key!r}{suggest(key, arguments)}; "
                            f"parameters: {', '.join(arguments) or 'none'}")
        arguments[key] = parse_value(text, arguments[key], f"problem {name!r}, parameter {key!r}")
    return ProblemSpec(name, tuple(arguments.items()), spec, origin)


#: The factory parameter that is the horizon (:func:`at_horizon`).
HORIZON = "t_end"


def at_horizon(spec: str | ProblemSpec, t_end: float | None) -> ProblemSpec:
    """``spec`` resolved, with its factory's ``t_end`` parameter set to the horizon
    ``t_end`` (``None``: as it is).

    A horizon is a parameter of the case wherever the factory takes one: the factory
    builds the case, the parameters it records and its reference for the horizon that
    runs, so a reference computed up to the factory's own ``t_end`` is never scored past
    it. A factory without a ``t_end`` parameter gets its spec back unchanged; its case is
    cut to the horizon (:meth:`Case.with_t_end`) and scored only within its reference's
    :attr:`~problems.case.Reference.span`.

    Raises
    ------
    SpecError
        A horizon that is not a whole number for a factory whose ``t_end`` is one.
    """
    spec = resolve(spec)
    arguments = spec.kwargs
    if t_end is None or HORIZON not in arguments:
        return spec
    default = parameters(spec.name)[HORIZON]
    if isinstance(default, int) and not isinstance(default, bool):
        if not float(t_end).is_integer():
            raise SpecError(f"problem {spec.name!r}: its {HORIZON} is a whole number, and the "
                            f"horizon {t_end!r} is not")
        value: object = int(t_end)
    else:
        value = float(t_end)
    arguments[HORIZON] = value
    return dataclasses.replace(spec, arguments=tuple(arguments.items()))


#: Cases kept for reuse (:func:`make`), the most recently used last.
KEPT_CASES = 8
_cases: OrderedDict = OrderedDict()


def make(spec: str | ProblemSpec, **overrides) -> Case:
    """The case of ``spec`` (a spec string, or resolved by :func:`resolve`), with the
    factory's parameters ``overrides`` replaced.

    Cases are immutable, so the last :data:`KEPT_CASES` are kept, by factory and
    parameters, and a later call with the same ones returns the same case: with it the
    functions compiled for its :class:`Mechanics` (a step-size sweep, another method's
    run or another test of the same problem traces and compiles nothing again).
    """
    spec = resolve(spec)
    factory = REGISTRY[spec.name]
    arguments = {**spec.kwargs, **overrides}
    key = (factory, tuple(sorted((k, type(v), v) for k, v in arguments.items())))
    try:
        case = _cases.pop(key)
    except KeyError:
        case = factory(**arguments)
    except TypeError:  # an unhashable override: built afresh, not kept
        return factory(**arguments)
    _cases[key] = case
    while len(_cases) > KEPT_CASES:
        _cases.popitem(last=False)
    return case


def forget() -> None:
    """Drop the cases :func:`make` keeps."""
    _cases.clear()


def check_size(spec: str | ProblemSpec) -> None:
    """Refuse ``spec`` when the product of its size parameters passes the problem's limit.

    Only the spec's parameters are read, nothing is built: the check runs before a case is
    made, so a size that would exhaust memory costs nothing. Size parameters are the
    whole-number ones but those in :data:`NOT_SIZES`.

    Raises
    ------
    SizeError
        Naming the parameters, the limit and the option that lifts it.
    SpecError
        A spec that cannot be resolved (:func:`resolve`).
    """
    spec = resolve(spec)
    sizes = {key: value for key, value in spec.arguments
             if isinstance(value, int) and not isinstance(value, bool) and key not in NOT_SIZES}
    product = 1
    for value in sizes.values():
        product *= abs(value)
    limit = SIZE_LIMITS.get(spec.name, SIZE_LIMIT)
    if product > limit:
        what = (f"{' * '.join(sizes)} = {' * '.join(map(str, sizes.values()))} = {product}"
                if len(sizes) > 1 else f"{next(iter(sizes))} = {product}")
        raise SizeError(f"problem {spec.name!r}: {what} is above its size limit of {limit} "
                        f"(the product of its size parameters {', '.join(sizes)}); give "
                        f"{ALLOW_LARGE} to build it anyway")


def names() -> list[str]:
    """Registered problem names, sorted."""
    _load()
    return sorted(REGISTRY)


def origin(name: str) -> str:
    """Where problem ``name`` comes from: ``built-in``, a file, a module or a package."""
    _load()
    return ORIGINS[name]


def _load() -> None:
    """Import the built-in problems, then (once) those of installed packages (entry
    points)."""
    for module in _MODULES:
        importlib.import_module(module)
    if ENTRY_POINTS not in _loaded:  # installed packages are looked up once
        _loaded[ENTRY_POINTS] = None
        for entry in metadata.entry_points(group=ENTRY_POINTS):
            package = entry.dist.name if entry.dist is not None else entry.value
            _run_user(f"package {package} ({entry.value})", entry.value, entry.load)


#: Folders of the library's own code and of installed code: frames there are not the user's.
_NOT_USER = tuple(Path(p).resolve() for p in (
    *(Path(__file__).resolve().parent.parent / pkg
      for pkg in ("problems", "integrators", "linalg", "benchmarks", "reports", "studies")),
    sysconfig.get_paths()["stdlib"], sysconfig.get_paths()["purelib"],
    sysconfig.get_paths()["platlib"]))


def user_frame(exc: BaseException, path: str | None = None) -> str:
    """``file:line`` of the innermost frame of ``exc``'s traceback in the file ``path``,
    or (``path`` None) in any file that is neither the library's nor installed code;
    ``""`` when there is none."""
    where = ""
    for frame in traceback.extract_tb(exc.__traceback__):
        if frame.filename.startswith("<"):
            continue
        file = Path(frame.filename).resolve()
        if (str(file) == path if path else not any(file.is_relative_to(d) for d in _NOT_USER)):
            where = f"{frame.filename}:{frame.lineno}"
    return where


def _run_user(label: str, source: str, run: Callable[[], object]) -> object:
    """Run ``run`` (an import of user code) with ``label`` as the origin of what it
    registers; turn any failure into a :class:`LoadError` naming the user's file:line."""
    if source in _loaded:
        return _loaded[source]
    _loading.append(label)
    try:
        module = run()
    except Exception as exc:
        where = (f"{exc.filename}:{exc.lineno}" if isinstance(exc, SyntaxError) else
                 user_frame(exc, source if source.endswith(".py") else None))
        detail = traceback.format_exception_only(type(exc), exc)[-1].strip()
        raise LoadError(f"{where or label}: {detail} (while loading {label})") from None
    finally:
        _loading.pop()
    _loaded[source] = module
    return module



def import_file(name: str, path: Path):
    """Import the Python file ``path`` as module ``name``; nothing is left in
    ``sys.modules`` if its code raises."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module

def load(source: str, base: Path | None = None) -> str:
    """Import user code that registers problems (and integrators): a file or a module.

    Parameters
    ----------
    source : str
        A path to a Python file (``.py``; relative paths are taken from ``base``) or the
        name of an importable module.
    base : Path, optional
        The folder relative file paths start from (a suite file's); default: the current
        folder.

    Returns
    -------
    str
        What was loaded: the file's resolved path or the module's name (what a worker
        process loads to see the same registrations).

    Raises
    ------
    LoadError
        A file that does not exist, a module that cannot be found, or code that raises
        while it is imported (a name registered twice, an exception): one line with the
        user's ``file:line`` and what went wrong.
    """
    _load()
    if source.endswith(".py") or "/" in source or "\\" in source:
        path = Path(source).expanduser()
        path = (Path(base) / path if base is not None and not path.is_absolute() else path)
        path = path.resolve()
        if not path.is_file():
            raise LoadError(f"{source}: no such Python file ({path})")
        name = f"driftbench_user_{path.stem}_{hashlib.sha256(str(path).encode()).hexdigest()[:8]}"

        _run_user(str(path), str(path), lambda: import_file(name, path))
        return str(path)
    if importlib.util.find_spec(source.split(".")[0]) is None:
        raise LoadError(f"{source}: no such Python file or importable module")
    _run_user(f"module {source}", source, lambda: importlib.import_module(source))
    return source
