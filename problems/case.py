"""A benchmark case: a system with consistent initial values, a horizon and a reference."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from linalg.compiled import compile_lifted
from problems.mechanics import Mechanics, System
from problems.source import located

#: Initial residuals at or below this are round-off and accepted as they are.
CONSISTENT_TOL = 1e-12
#: Initial residuals up to this are projected away; larger ones are refused.
PROJECT_TOL = 1e-6


class InconsistentInitialValues(ValueError):
    """Initial values violate the constraints by more than projection may repair."""


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
    """

    kind: str
    source: str
    solution: Callable[[float], tuple[np.ndarray, np.ndarray]]
    scored: tuple[int, ...]
    times: tuple[float, ...] | None = None
    floor: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.floor) and self.floor >= 0.0):
            raise ValueError(f"reference floor {self.floor!r} must be finite and >= 0")

    def available_at(self, t: float) -> bool:
        """Whether the reference exists at time ``t``."""
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
        if not (self.position >= 0 and self.velocity >= 0):
            raise ValueError(f"perturbation sizes must be >= 0: {self}")


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
    # One compiled function: evaluated eagerly, the autodiff Jacobian in ``vel_residual``
    # compiles each of its dozens of primitive operations on its own (seconds per case).
    pos, vel = compile_lifted(partial(_residuals, mech), *args)(*args)
    return float(pos), float(vel)


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
    calls at once deadlocked on 2 cores (a batch of 4095 states of ``chain:N=8`` hung in
    half the tries; 512 never did).
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


def _projector(mech: Mechanics, shape: tuple[int, ...], tol: float, max_iter: int):
    """``(q, v, t) -> (q, v)`` projected (:func:`project`), for states of ``shape`` (one
    state, or a batch on the leading axis), compiled once for all calls."""
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
    file and line of the call that made the case.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    v0 = np.asarray(v0, dtype=np.float64)
    if q0.shape != (system.n,) or v0.shape != (system.n,):
        raise InconsistentInitialValues(located(
            f"{name}: q0 {q0.shape} and v0 {v0.shape} must both have shape ({system.n},)",
            sys._getframe(1)))
    if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(v0))):
        raise InconsistentInitialValues(located(f"{name}: initial values are not finite",
                                                sys._getframe(1)))
    t0, t_end = map(float, t_span)
    if not np.isfinite(t_end) or t_end <= t0:
        raise ValueError(located(f"{name}: t_end = {t_end} must be finite and > t0 = {t0}",
                                 sys._getframe(1)))
    # The constraints' shape first: with one too many, the extra one's value at q0 would
    # be reported as inconsistent initial values.
    shape = jax.eval_shape(lambda q, t: jnp.asarray(system.constraints(q, t)),
                           jnp.asarray(q0), jnp.asarray(t0)).shape
    if shape != (system.m,):
        raise ValueError(located(f"{name}: constraints(q, t) returns shape {shape}, not "
                                 f"({system.m},) (System m = {system.m})",
                                 sys._getframe(1)))
    mech = system.mech
    pos, vel = residuals(mech, q0, v0, t0)
    if max(pos, vel) > PROJECT_TOL:
        raise InconsistentInitialValues(located(
            f"{name}: inconsistent initial values: |g(q0)| = {pos:.3e}, "
            f"|G v0 + g_t| = {vel:.3e} (projection is allowed up to {PROJECT_TOL:g})",
            sys._getframe(1)))
    if max(pos, vel) > CONSISTENT_TOL:
        q0, v0 = project(mech, q0, v0, t0)
        notes = {**notes, "projected": f"|g| = {pos:.2e}, |G v + g_t| = {vel:.2e} before projection"}
    return Case(name, system, q0, v0, t0, t_end, dict(params), float(energy_scale),
                reference, notes, perturbation)
