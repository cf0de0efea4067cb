"""One contract for fixed-step methods: ``start``, ``step``, ``observe``, and one ``prepare``.

A fixed-step method is a :class:`FixedStep`: a frozen dataclass of its options (``h``
among them) and its traits, which supplies three pure functions of arrays,

- ``start(mech, schur, q0, v0, t0) -> carry``: the method's state at ``t0`` (a pytree:
  positions, momenta, warm starts, a factorisation to reuse...);
- ``step(mech, schur, carry, t, h) -> (carry1, code, residual, counts)``: one step from
  ``t`` to ``t + h``; ``code`` is :attr:`Failure.NONE` or why the step failed,
  ``residual`` the last Newton residual (for the message), ``counts`` the increments of
  the work counters (:data:`integrators.base.COUNTERS` but ``n_steps``);
- ``observe(mech, carry) -> (q, v)``.

``mech`` (:class:`problems.mechanics.Mechanics`) and ``schur`` (the solver for
``G M^{-1} G^T`` that :meth:`FixedStep.linear_algebra` picks) are fixed for a run; the
arrays are the only things that change. ``h`` reaches the functions as ``step``'s argument
only (``start`` and ``step`` do not read the option), so the compiled ``start`` and time
loop serve every step size. The one shared :meth:`FixedStep.prepare` checks
the options, picks the linear algebra, compiles ``start`` once and hands ``step`` and
``observe`` to the compiled time loop (:func:`integrators.loop.march`); :class:`Stepper`
drives the same functions by hand.

Nothing in ``step`` branches in Python on the values of its arrays (failures are codes,
selected with ``jnp.where``), so an ensemble of initial states is a leading axis away:
:meth:`FixedStep.prepare_ensemble` maps ``start`` over the lanes' ``(q0, v0)`` and runs one
compiled time loop for every lane, ``step`` mapped over them (``jax.vmap``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache, partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from integrators.base import COUNTERS, Failure, Grid, Integrator
from integrators.loop import CACHE_SIZE, WORK, attempt, march
from linalg.compiled import compile_lifted
from linalg.schur import DENSE_MAX
from problems.case import Case
from problems.mechanics import Mechanics


def newton_failure(converged: jax.Array, solvable: jax.Array | bool = True) -> jax.Array:
    """The code of a step whose equations Newton's method solved: :attr:`Failure.SINGULAR`
    where ``G M^{-1} G^T`` could not be solved with, else :attr:`Failure.NEWTON` where
    Newton did not converge, else :attr:`Failure.NONE`."""
    return jnp.where(solvable, jnp.where(converged, Failure.NONE, Failure.NEWTON),
                     Failure.SINGULAR)


@dataclass(frozen=True)
class FixedStep(Integrator):
    """Base class of the fixed-step methods run by the shared compiled loop.

    Subclasses add their options as dataclass fields (``h`` first: the step size, shrunk
    to divide the horizon evenly) and implement :meth:`start`, :meth:`step` and
    :meth:`observe` (see the module notes). A method with a ``linear_solver`` option gets
    that solver for ``G M^{-1} G^T``; others get the one chosen by structure.
    """

    batched = True

    def dense_max(self, mech: Mechanics) -> int:
        """The most constraints for which ``linear_solver = "auto"`` keeps the dense path
        where a structured one could run (:func:`linalg.schur.choose`):
        :data:`linalg.schur.DENSE_MAX` by default, for methods without a Newton iteration
        (``baumgarte-rk4``: one solve with ``S`` per stage).

        A method that runs Newton on its whole stage system names its own: none for SPARK
        and the generalized-alpha members, one separable constraint for RATTLE. On the
        dense path that Newton has the exact autodiff Jacobian, ``K`` forward derivatives
        and an ``O(K^3)`` LU for ``K`` unknowns at every iteration (once per step from
        :data:`integrators.newton.FROZEN_MIN` unknowns on), through LAPACK, which
        keeps XLA from compiling the time loop into one kernel; the structured path's
        simplified Newton takes two to five times the iterations, each ``O(n)`` and inside
        the one kernel. One trajectory at a time the structured path is the faster on
        every constant-diagonal and block-diagonal mass, from one constraint up, for
        lobatto3ab3 and the generalized-alpha members, with masses given as functions
        ``M(q)`` and as kinetic energies alike (``python -m benchmarks.perf.crossover``
        measures the crossover).
        """
        return DENSE_MAX

    def linear_algebra(self, mech: Mechanics):
        """The solver for ``G M^{-1} G^T`` that the steps use (:meth:`Mechanics.schur`,
        with this family's :meth:`dense_max`)."""
        return mech.schur(getattr(self, "linear_solver", "auto"), self.dense_max(mech))

    def start(self, mech: Mechanics, schur, q0: jax.Array, v0: jax.Array, t0: jax.Array) -> Any:
        """The carry at ``t0`` from consistent ``(q0, v0)``."""
        raise NotImplementedError

    def step(self, mech: Mechanics, schur, carry: Any, t: jax.Array, h: jax.Array
             ) -> tuple[Any, jax.Array, jax.Array, dict[str, jax.Array]]:
        """One step: ``(carry1, code, residual, counts)``."""
        raise NotImplementedError

    def observe(self, mech: Mechanics, carry: Any) -> tuple[jax.Array, jax.Array]:
        """Positions and velocities of a carry."""
        raise NotImplementedError

    def prepare(self, case: Case, grid: Grid):
        self.check()
        mech = case.mech
        schur = self.linear_algebra(mech)
        args = (jnp.asarray(case.q0), jnp.asarray(case.v0), jnp.asarray(grid.t0, jnp.float64))
        like = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args)
        # Keyed as the loop is (march), without h: the step size is an argument of step.
        carry0 = _start(replace(self, h=None), mech, schur, like)(*args)
        return self._march(mech, schur, grid, carry0, lanes=False)

    def prepare_ensemble(self, case: Case, grid: Grid, q0s, v0s):
        """One compiled loop for the whole ensemble: ``start`` mapped over the lanes, then
        the time loop with the step mapped over them (:func:`integrators.loop.march`)."""
        self.check()
        mech = case.mech
        schur = self.linear_algebra(mech)
        carry0 = jax.jit(jax.vmap(partial(self.start, mech, schur), in_axes=(0, 0, None)))(
            jnp.asarray(q0s, jnp.float64), jnp.asarray(v0s, jnp.float64),
            jnp.asarray(grid.t0, jnp.float64))
        return self._march(mech, schur, grid, carry0, lanes=True)

    def _march(self, mech: Mechanics, schur, grid: Grid, carry0, lanes: bool):
        return march(mech, grid, self.h, carry0, partial(self.step, mech, schur),
                     partial(self.observe, mech), key=replace(self, h=None),
                     linear_solver=schur.name, pattern_nnz=schur.nnz, lanes=lanes)


@lru_cache(maxsize=CACHE_SIZE)
def _start(method: FixedStep, mech: Mechanics, schur, like: tuple[jax.ShapeDtypeStruct, ...]):
    """``method.start`` compiled for arguments of the types ``like``, kept for the last
    :data:`~integrators.loop.CACHE_SIZE` methods: run eagerly, each autodiff operation
    would compile on its own."""
    return compile_lifted(partial(method.start, mech, schur), *like)


class State(NamedTuple):
    """A manually stepped run: the time, the method's carry and the work so far
    (:data:`integrators.base.COUNTERS`)."""

    t: jax.Array
    carry: Any
    counts: dict[str, jax.Array]


class Stepper:
    """Drive a fixed-step method by hand: :meth:`init`, then :meth:`step` as often as wanted.

    The same ``start``, ``step`` and ``observe`` as the compiled loop of
    :meth:`FixedStep.prepare`, each compiled once, with the loop's rule for failures: a
    step that fails (its code, or a non-finite state) leaves the state as it was and
    returns the code. The step size may change from call to call; the time advances by
    ``t + h`` (the compiled loop takes ``t0 + k h``, which differs at round-off, and only
    for problems whose equations depend on ``t``). :meth:`step` is a pure function of
    arrays, so ``jax.vmap(stepper.step)`` steps a batch of states.

    Parameters
    ----------
    method : FixedStep
        The method and its options (checked here).
    case : problems.Case
        The problem and its initial values.

    Examples
    --------
    RATTLE on the pendulum for 100 steps of its default ``h``:

    >>> import integrators, problems
    >>> from integrators.base import Failure
    >>> stepper = integrators.Stepper(integrators.make("rattle"), problems.make("pendulum"))
    >>> state = stepper.init()
    >>> for _ in range(100):
    ...     state, code = stepper.step(state)
    ...     assert code == Failure.NONE, Failure(int(code)).message
    >>> q, v = stepper.observe(state)
    >>> round(float(state.t), 12), int(state.counts["n_steps"])
    (1.0, 100)
    """

    def __init__(self, method: FixedStep, case: Case):
        if not isinstance(method, FixedStep):
            raise TypeError(f"{type(method).__name__} is not a fixed-step method (FixedStep)")
        method.check()
        self.method, self.case = method, case
        mech = case.mech
        self.schur = method.linear_algebra(mech)
        self._start = jax.jit(partial(method.start, mech, self.schur))
        self._observe = partial(method.observe, mech)
        self._step = jax.jit(self._advance)

    def init(self, q0=None, v0=None, t0=None) -> State:
        """The state at ``t0`` (default: the case's initial values and time)."""
        case = self.case
        t0 = jnp.asarray(case.t0 if t0 is None else t0, jnp.float64)
        carry = self._start(jnp.asarray(case.q0 if q0 is None else q0, jnp.float64),
                            jnp.asarray(case.v0 if v0 is None else v0, jnp.float64), t0)
        return State(t0, carry, {key: jnp.zeros((), jnp.int64) for key in COUNTERS})

    def step(self, state: State, h=None) -> tuple[State, jax.Array]:
        """One step of size ``h`` (default: the method's): ``(state1, code)``.

        ``code`` is a :class:`Failure` code (0 where the step succeeded); on failure
        ``state1`` is ``state`` with the work of the attempt counted.
        """
        return self._step(state, jnp.asarray(self.method.h if h is None else h, jnp.float64))

    def _advance(self, state: State, h: jax.Array) -> tuple[State, jax.Array]:
        step = partial(self.method.step, self.case.mech, self.schur)
        carry, code, _, work, _ = attempt(step, self._observe, state.carry, state.t, h)
        good = code == 0
        counts = {"n_steps": state.counts["n_steps"] + good,
                  **{key: state.counts[key] + inc for key, inc in zip(WORK, work)}}
        return State(jnp.where(good, state.t + h, state.t), carry, counts), code

    def observe(self, state: State) -> tuple[jax.Array, jax.Array]:
        """Positions and velocities of ``state``."""
        return self._observe(state.carry)
