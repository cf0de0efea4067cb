"""A benchmark case: a system with consistent initial values, a horizon and a reference."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from functools import lru_cache, partial
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from linalg.compiled import compile_lifted
from problems.mechanics import Mechanics, System
from problems.source import ArgumentError, located, refuse

#: Initial residuals at or below this are round-off and accepted as they are.
CONSISTENT_TOL = 1e-12
#: Initial residuals up to this are projected away; larger ones are refused.
PROJECT_TOL = 1e-6


#: What a :class:`Reference` may be.
REFERENCE_KINDS = ("exact", "published", "computed")


class InconsistentInitialValues(ArgumentError):
    """Initial values violate the constraints by more than projection may repair."""


def _number(value, what: str, low: float | None = None) -> float:
    """``value`` as a finite float (at least ``low``), or :class:`ArgumentError` located at
    the user's call."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise refuse(f"{what} = {value!r} must be a number", __file__)
    if not (np.isfinite(value) and (low is None or value >= low)):
        raise refuse(f"{what} = {value!r} must be finite"
                     + ("" if low is None else f" and >= {low:g}"), __file__)
    return float(value)


def _numbers(values, what: str) -> tuple[float, ...]:
    """A sequence of finite numbers as a tuple of floats (:func:`_number`)."""
    if isinstance(values, (str, bytes)) or not np.iterable(values):
        raise refuse(f"{what} = {values!r} must be a sequence of numbers", __file__)
    return tuple(_number(x, what) for x in values)


def _indices(values, what: str) -> tuple[int, ...]:
    """A sequence of indices (whole numbers >= 0, not booleans) as a tuple of ints."""
    if isinstance(values, (str, bytes)) or not np.iterable(values):
        raise refuse(f"{what} = {values!r} must be a sequence of indices (a tuple of int)",
                     __file__)
    for i in values:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) or i < 0:
            raise refuse(f"{what} = {values!r}: {i!r} is not an index (an int >= 0)",
                         __file__)
    return tuple(int(i) for i in values)


@dataclass(frozen=True)
class Reference:
    """A reference solution with its provenance.

    Parameters
    ----------
    kind : {"exact", "published", "computed"}
        Closed form, published values, or a documented tight-tolerance run.
    source : str
        Where it comes from (citation, or the command that regenerates it).
    solution : callable
        ``solution(t) -> (q, v)`` as numpy arrays.
    times : tuple of float, optional
        The only times at which the reference exists; ``None`` for any ``t``.
    scored : tuple of int
        Indices into the stacked state ``(q, v)`` that scores use.
    floor : float, optional
        The reference's own accuracy: a bound on the max-norm error of its scored
        components (published digits, or the stored estimate of a computed reference); 0
        for a closed form evaluated to round-off. A run's final error at or below it says
        only that the run is at least as accurate as the reference, so reports show such
        errors as "at reference floor" and fit no order through them.
    span : (float, float), optional
        The interval ``[t_a, t_b]`` on which ``solution`` is valid (a computed or stored
        reference holds only up to where it was computed, and ``solution`` past it would
        extrapolate); ``None`` for a closed form valid for every ``t``. No error is
        scored against the reference outside it.
    """

    kind: str
    source: str
    solution: Callable[[float], tuple[np.ndarray, np.ndarray]]
    scored: tuple[int, ...]
    times: tuple[float, ...] | None = None
    floor: float = 0.0
    span: tuple[float, float] | None = None

    def __post_init__(self):
        if self.kind not in REFERENCE_KINDS:
            raise refuse(f"Reference kind {self.kind!r} is not one of "
                         f"{', '.join(REFERENCE_KINDS)}", __file__)
        if not (isinstance(self.source, str) and self.source.strip()):
            raise refuse(f"Reference source {self.source!r} must be a non-empty string (a "
                         f"citation, or the command that regenerates it)", __file__)
        if not callable(self.solution):
            raise refuse(f"Reference solution must be callable, solution(t) -> (q, v), not "
                         f"{type(self.solution).__name__}", __file__)
        object.__setattr__(self, "scored", _indices(self.scored, "Reference scored"))
        if not self.scored:
            raise refuse("Reference scored is empty: name the components of (q, v) that "
                         "the final error is taken over", __file__)
        if self.times is not None:
            times = _numbers(self.times, "Reference times")
            if not times:
                raise refuse("Reference times is empty (None: the reference exists at any t)",
                             __file__)
            object.__setattr__(self, "times", times)
        object.__setattr__(self, "floor", _number(self.floor, "Reference floor", 0.0))
        if self.span is not None:
            span = _numbers(self.span, "Reference span")
            if not (len(span) == 2 and span[0] <= span[1]):
                raise refuse(f"Reference span {self.span!r} must be two finite times "
                             f"(t_a, t_b) with t_a <= t_b", __file__)
            object.__setattr__(self, "span", span)

    def available_at(self, t: float) -> bool:
        """Whether the reference exists at time ``t``: within :attr:`span` and, where
        :attr:`times` is given, at one of them (each to a relative 1e-12)."""
        if self.span is not None and not (
                self.span[0] - 1e-12 * max(1.0, abs(self.span[0])) <= t
                <= self.span[1] + 1e-12 * max(1.0, abs(self.span[1]))):
            return False
        if self.times is None:
            return True
        return any(abs(t - s) <= 1e-12 * max(1.0, abs(s)) for s in self.times)


@dataclass(frozen=True)
class Perturbation:
    """How a case's initial values are perturbed for an ensemble (:mod:`problems.ensemble`).

    Parameters
    ----------
    position : float
        Standard deviation of the position noise relative to ``rms(q0)``.
    velocity : float
        Expected kinetic energy of the velocity noise relative to the case's energy scale.
    fixed : tuple of int
        Coordinates left as they are (an accumulated quantity such as dissipated work).
    """

    position: float = 1e-3
    velocity: float = 1e-2
    fixed: tuple[int, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "position", _number(self.position, "Perturbation position", 0.0))
        object.__setattr__(self, "velocity", _number(self.velocity, "Perturbation velocity", 0.0))
        object.__setattr__(self, "fixed", _indices(self.fixed, "Perturbation fixed"))


@dataclass(frozen=True, eq=False)
class Case:
    """A system with consistent initial values, a time span, parameters and a reference.

    Use :func:`make_case` to build one: it checks, and where needed projects, the
    initial values.
    """

    name: str
    system: System
    q0: np.ndarray
    v0: np.ndarray
    t0: float
    t_end: float
    params: Mapping[str, object]
    energy_scale: float
    reference: Reference | None = None
    notes: Mapping[str, object] = field(default_factory=dict)
    perturbation: Perturbation = Perturbation()

    @property
    def mech(self) -> Mechanics:
        return self.system.mech

    def with_t_end(self, t_end: float) -> "Case":
        """The same case over ``[t0, t_end]``."""
        if not np.isfinite(t_end) or t_end <= self.t0:
            raise ValueError(f"{self.name}: t_end = {t_end} must be finite and > t0 = {self.t0}")
        return replace(self, t_end=float(t_end))

    def with_initial(self, q0: np.ndarray, v0: np.ndarray) -> "Case":
        """The same system and horizon from other consistent initial values (an ensemble's
        lane, :mod:`problems.ensemble`). The case's reference belongs to its own initial
        values, so the new case has none."""
        return replace(self, q0=np.asarray(q0, np.float64), v0=np.asarray(v0, np.float64),
                       reference=None)


def _residuals(mech: Mechanics, q, v, t):
    return (jnp.max(jnp.abs(mech.g(q, t)), initial=0.0),
            jnp.max(jnp.abs(mech.vel_residual(q, v, t)), initial=0.0))


def residuals(mech: Mechanics, q: np.ndarray, v: np.ndarray, t: float) -> tuple[float, float]:
    """Max-norms of ``g(q, t)`` and ``G v + g_t``."""
    f64 = jnp.float64
    args = (jnp.asarray(q, f64), jnp.asarray(v, f64), jnp.asarray(t, f64))
    pos, vel = _residuals_of(mech, args[0].shape, args[1].shape)(*args)
    return float(pos), float(vel)


@lru_cache(maxsize=16)
def _residuals_of(mech: Mechanics, q_shape: tuple[int, ...], v_shape: tuple[int, ...]):
    # One compiled function, kept for the mechanics' later cases: evaluated eagerly, the
    # autodiff Jacobian in ``vel_residual`` compiles each of its dozens of primitive
    # operations on its own (seconds per case).
    f64 = jnp.float64
    like = (jax.ShapeDtypeStruct(q_shape, f64), jax.ShapeDtypeStruct(v_shape, f64),
            jax.ShapeDtypeStruct((), f64))
    return compile_lifted(partial(_residuals, mech), *like)


def project(mech: Mechanics, q: np.ndarray, v: np.ndarray, t: float,
            tol: float = 1e-15, max_iter: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Mass-orthogonal projection onto ``g = 0`` and then ``G v + g_t = 0``.

    Positions by the Gauss-Newton iteration ``q <- q - M^{-1} G^T (G M^{-1} G^T)^{-1} g``;
    velocities by the one linear projection with the same metric. The solves with
    ``G M^{-1} G^T`` are the integrators' (:meth:`Mechanics.schur`, chosen by structure),
    under their one policy for redundant constraints (:mod:`linalg.dense`).

    ``q`` and ``v`` may hold a batch of states on a leading axis (an ensemble's lanes,
    :mod:`problems.ensemble`). The batch is projected in slices of :data:`PROJECT_WIDTH`
    states (the last one padded with copies of its last state), each in one compiled call
    per iteration, and each state stops iterating once its own ``|g|`` is at most ``tol``:
    a state's projection depends neither on the others nor on the batch's size. The
    slices bound the batch of every LAPACK call: jaxlib splits a large batch across
    XLA's intra-op threads and waits for the pieces on those same threads, and two such
    calls at once can deadlock where there are few threads (a batch of 4095 states of
    ``chain:N=8`` could hang; 512 did not).
    """
    if np.ndim(q) == 2:
        width = PROJECT_WIDTH
        q, v = np.asarray(q, np.float64), np.asarray(v, np.float64)
        k = len(q)
        pad = -k % width
        q = np.concatenate([q, np.repeat(q[-1:], pad, axis=0)])
        v = np.concatenate([v, np.repeat(v[-1:], pad, axis=0)])
        one = _projector(mech, (width, q.shape[1]), tol, max_iter)
        parts = [one(q[i:i + width], v[i:i + width], t) for i in range(0, len(q), width)]
        return (np.concatenate([a for a, _ in parts])[:k],
                np.concatenate([b for _, b in parts])[:k])
    return _projector(mech, np.shape(q), tol, max_iter)(q, v, t)


#: States projected together by :func:`project` (the width of every compiled batch).
PROJECT_WIDTH = 256


@lru_cache(maxsize=16)
def _projector(mech: Mechanics, shape: tuple[int, ...], tol: float, max_iter: int):
    """``(q, v, t) -> (q, v)`` projected (:func:`project`), for states of ``shape`` (one
    state, or a batch on the leading axis), compiled once for all calls and kept for
    later ones (an ensemble's lanes, the cases of one mechanics)."""
    schur = mech.schur("auto")
    step, g = _projection_step(mech, schur), mech.g
    residual = mech.vel_residual
    if len(shape) == 2:
        step, g = jax.vmap(step, in_axes=(0, None, 0)), jax.vmap(g, in_axes=(0, None))
        residual = jax.vmap(residual, in_axes=(0, 0, None))
    g, residual = jax.jit(g), jax.jit(residual)
    like = jnp.zeros(shape, jnp.float64)
    zero = jnp.asarray(0.0, jnp.float64)
    # The solver's index arrays as arguments, not constants (linalg.compiled).
    step = compile_lifted(step, like, zero, g(like, zero))

    def run(q, v, t):
        t = jnp.asarray(t, dtype=jnp.float64)
        q = jnp.asarray(q, dtype=jnp.float64)
        for _ in range(max_iter):
            r = g(q, t)
            active = jnp.max(jnp.abs(r), axis=-1, initial=0.0, keepdims=True) > tol
            if not bool(jnp.any(active)):
                break
            q = jnp.where(active, q - step(q, t, r), q)
        v = jnp.asarray(v, dtype=jnp.float64)
        v = v - step(q, t, residual(q, v, t))
        return np.asarray(q), np.asarray(v)

    return run


def _projection_step(mech: Mechanics, schur):
    """``(q, t, r) -> M^{-1} G^T (G M^{-1} G^T)^{-1} r``."""

    def step(q, t, r):
        lam = schur.solve(schur.factor(q, t), r)
        return mech.solve_mass(q, mech.GT(q, t, lam))

    return step


def make_case(name: str, system: System, q0, v0, t_span: tuple[float, float],
              params: Mapping[str, object], energy_scale: float,
              reference: Reference | None = None,
              perturbation: Perturbation = Perturbation(), **notes) -> Case:
    """Build a :class:`Case`, checking the initial values.

    Parameters
    ----------
    name : str
        The problem's name (as registered).
    system : System
        The physics, ``M(q) q'' = -grad U + f(t, q, q') - G^T lam`` with ``g(q, t) = 0``.
    q0, v0 : array_like, shape (n,)
        Initial positions and velocities; consistent means ``g(q0, t0) = 0`` and
        ``G(q0) v0 + g_t(q0, t0) = 0``.
    t_span : (float, float)
        The horizon ``(t0, t_end)``, ``t_end > t0``.
    params : mapping
        The physical parameters, recorded verbatim with every run.
    energy_scale : float
        The size of the energy, positive: ``rel_energy_error = max |H - H0| / energy_scale``
        (never ``|H0|``, which can be 0).
    reference : Reference, optional
        A reference solution (final errors and scd are n/a without one).
    perturbation : Perturbation, optional
        How an ensemble perturbs the initial values (:mod:`problems.ensemble`).
    **notes
        Anything else worth recording with the case.

    Residuals up to :data:`CONSISTENT_TOL` are accepted; up to :data:`PROJECT_TOL` they are
    projected away (recorded in ``notes['projected']``); larger ones, or non-finite values,
    raise :class:`InconsistentInitialValues` with the residuals. Every error leads with the
    file and line of the call that made the case; so does every argument out of its
    contract (:class:`~problems.source.ArgumentError`).
    """
    where = sys._getframe(1)
    if not (isinstance(name, str) and name.strip()):
        raise ArgumentError(located(f"make_case name {name!r} must be a non-empty string",
                                    where))
    if not isinstance(system, System):
        raise ArgumentError(located(f"{name}: make_case system must be a System, not "
                                    f"{type(system).__name__}", where))
    if not isinstance(params, Mapping):
        raise ArgumentError(located(f"{name}: make_case params must be a mapping (a dict "
                                    f"of the physical parameters), not "
                                    f"{type(params).__name__}", where))
    if isinstance(energy_scale, (bool, np.bool_)) or not isinstance(
            energy_scale, (int, float, np.number)) or not (
            np.isfinite(energy_scale) and energy_scale > 0):
        raise ArgumentError(located(f"{name}: energy_scale = {energy_scale!r} must be a "
                                    f"finite number > 0 (the size of the energy)", where))
    if reference is not None:
        if not isinstance(reference, Reference):
            raise ArgumentError(located(f"{name}: make_case reference must be a Reference "
                                        f"or None, not {type(reference).__name__}", where))
        if max(reference.scored) >= 2 * system.n:
            raise ArgumentError(located(
                f"{name}: Reference scored index {max(reference.scored)} is past the state "
                f"(q, v), which has 2 n = {2 * system.n} components", where))
    if not isinstance(perturbation, Perturbation):
        raise ArgumentError(located(f"{name}: make_case perturbation must be a Perturbation, "
                                    f"not {type(perturbation).__name__}", where))
    if perturbation.fixed and max(perturbation.fixed) >= system.n:
        raise ArgumentError(located(f"{name}: Perturbation fixed index "
                                    f"{max(perturbation.fixed)} is past q, which has n = "
                                    f"{system.n} coordinates", where))
    if isinstance(t_span, (str, bytes)) or not np.iterable(t_span) or len(t_span) != 2:
        raise ArgumentError(located(f"{name}: t_span = {t_span!r} must be (t0, t_end)", where))
    q0 = np.asarray(q0, dtype=np.float64)
    v0 = np.asarray(v0, dtype=np.float64)
    if q0.shape != (system.n,) or v0.shape != (system.n,):
        raise InconsistentInitialValues(located(
            f"{name}: q0 {q0.shape} and v0 {v0.shape} must both have shape ({system.n},)",
            where))
    if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(v0))):
        raise InconsistentInitialValues(located(f"{name}: initial values are not finite",
                                                where))
    t0, t_end = _numbers(t_span, f"{name}: t_span")
    if t_end <= t0:
        raise ArgumentError(located(f"{name}: t_end = {t_end} must be > t0 = {t0}", where))
    # The constraints' shape first: with one too many, the extra one's value at q0 would
    # be reported as inconsistent initial values.
    shape = jax.eval_shape(lambda q, t: jnp.asarray(system.constraints(q, t)),
                           jnp.asarray(q0), jnp.asarray(t0)).shape
    if shape != (system.m,):
        raise ArgumentError(located(f"{name}: constraints(q, t) returns shape {shape}, not "
                                    f"({system.m},) (System m = {system.m})", where))
    mech = system.mech
    pos, vel = residuals(mech, q0, v0, t0)
    if max(pos, vel) > PROJECT_TOL:
        raise InconsistentInitialValues(located(
            f"{name}: inconsistent initial values: |g(q0)| = {pos:.3e}, "
            f"|G v0 + g_t| = {vel:.3e} (projection is allowed up to {PROJECT_TOL:g})",
            where))
    if max(pos, vel) > CONSISTENT_TOL:
        q0, v0 = project(mech, q0, v0, t0)
        notes = {**notes, "projected": f"|g| = {pos:.2e}, |G v + g_t| = {vel:.2e} before projection"}
    return Case(name, system, q0, v0, t0, t_end, dict(params), float(energy_scale),
                reference, notes, perturbation)
