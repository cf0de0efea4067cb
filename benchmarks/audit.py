"""Checks of user-written physics before any run, and errors explained in one sentence.

:func:`audit` evaluates the functions of a loaded problem's :class:`~problems.System` at its
initial values, the way the integrators will (under JAX, with autodiff), and refuses what
would make every run meaningless: a wrong shape, a value that is not finite, a mass matrix
that is not symmetric positive definite, a function that JAX cannot trace, constraints
that read ``t`` in a system declared scleronomic (:func:`check_rheonomic`). The message
names the function, the file and line where it is defined (for a constant mass, those of
the problem's factory), and what is wrong.

:func:`explain` turns any exception met while building or running user code into one line
with the user's ``file:line`` and, for JAX's tracer errors, what they mean.
"""

from __future__ import annotations

import traceback

import jax
from jax.extend.core import Literal
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

import problems
from benchmarks.records import one_line
from problems.source import located

#: JAX's errors of a function that uses a traced value as a concrete one, and what to do.
TRACER_ERRORS = (jax.errors.ConcretizationTypeError, jax.errors.TracerBoolConversionError,
                 jax.errors.TracerArrayConversionError, jax.errors.TracerIntegerConversionError)
TRACER_ADVICE = ("it is not traceable by JAX: it converts a traced value to a Python or "
                 "NumPy one (if/while on q, float(), int(), numpy functions); use jax.numpy "
                 "and jnp.where instead")
#: Relative asymmetry of a mass matrix accepted as round-off.
SYMMETRY_TOL = 1e-12
#: Largest mass given by ``kinetic`` that is formed densely to check it (eigenvalues);
#: above, its blocks are checked by their Cholesky factors. Also the largest system whose
#: sampled states are projected onto ``g = 0`` by dense least squares (:func:`check_rheonomic`).
DENSE_AUDIT_MAX = 2000
#: Random states, besides the initial one, at which :func:`check_rheonomic` evaluates g_t.
TIME_SAMPLES = 4
#: Relative noise on ``q0`` of those states before they are projected onto ``g(q, t) = 0``.
SAMPLE_NOISE = 1e-3
#: Gauss-Newton steps of that projection (quadratic convergence from a nearby state).
SAMPLE_STEPS = 8
#: ``max |g_t| (t_end - t0)`` at or below this fraction of ``g``'s own size over the
#: horizon (``max_i sum_j |G_ij| (|q_j| + (t_end - t0) |v_j|)`` at the initial state) is
#: round-off of terms in ``t`` that cancel, not a time dependence.
RHEONOMIC_TOL = 1e-10


def explain(exc: BaseException) -> str:
    """One line: the user's ``file:line`` where ``exc`` arose (if in user code), the
    exception, and the meaning of a JAX tracer error."""
    where = problems.user_frame(exc, None)
    if isinstance(exc, TRACER_ERRORS):
        detail = f"{type(exc).__name__}: {TRACER_ADVICE}"
    else:
        # The exception itself, without its notes: JAX adds one to every error it raises
        # (that it removed its internal frames), which would stand in for the message.
        shown = traceback.TracebackException.from_exception(exc)
        shown.__notes__ = None
        detail = list(shown.format_exception_only())[-1]
    return one_line(located(detail, where))


class AuditError(ValueError):
    """A user function that returns something the integrators cannot use."""


def _refuse(case, message: str, func=None) -> AuditError:
    """The error ``message`` about ``case``, led by where ``func`` is defined, else where
    the problem's factory is."""
    return AuditError(located(message, func, problems.REGISTRY.get(case.name)))


def _check(case, args, label: str, func, call, shape: tuple[int, ...]) -> np.ndarray:
    """Evaluate ``call(q, v, t)`` (which calls ``func``) at ``args``, traced as the
    integrators' compiled programs trace it and then with values, and check its shape and
    finiteness."""
    what = f"{label} of problem {case.name!r}"
    try:
        # Traced first: autodiff alone runs the function on concrete values, where Python
        # control flow on q works and would pass the audit, then fail every run.
        jax.make_jaxpr(call)(*args)
        value = np.asarray(call(*args), dtype=np.float64)
    except AuditError:
        raise
    except Exception as exc:  # the user's function raised: say where and what
        raise _refuse(case, f"{what} raised {explain(exc)}", func) from None
    if value.shape != shape:
        raise _refuse(case, f"{what} returns shape {value.shape}, not {shape} "
                            f"(System n = {case.system.n}, m = {case.system.m})", func)
    if not np.all(np.isfinite(value)):
        raise _refuse(case, f"{what} is not finite at the initial values", func)
    return value


def reads_t(g, q0, t0) -> bool:
    """Whether ``g(q, t)``'s value depends on ``t`` at all: a path from ``t`` to an output
    in its jaxpr (an operation with any input that depends on ``t`` is taken to depend on
    it, nested calls included). Exact where sampling ``g_t`` is not: a ``t`` that acts on
    part of the horizon only (a drive that starts late) has ``g_t = 0`` at most times."""
    closed = jax.make_jaxpr(lambda q, t: jnp.asarray(g(q, t)))(
        jnp.asarray(q0, jnp.float64), jnp.asarray(t0, jnp.float64))
    jaxpr = closed.jaxpr
    marked = {id(jaxpr.invars[1])}
    for eqn in jaxpr.eqns:
        if any(id(v) in marked for v in eqn.invars if not isinstance(v, Literal)):
            marked.update(id(v) for v in eqn.outvars)
    return any(id(v) in marked for v in jaxpr.outvars
               if not isinstance(v, Literal))


def _time_rates(case) -> tuple[np.ndarray, np.ndarray, float]:
    """``max_i |g_t|`` at the initial state and at :data:`TIME_SAMPLES` random states at
    random times of the horizon (a fixed seed: the audit is repeatable), the times, and
    ``g``'s own size over the horizon (:data:`RHEONOMIC_TOL`).

    The random states are ``q0`` with noise, projected onto ``g(q, t) = 0`` by Gauss-Newton
    with the minimum-norm step (dense least squares), all in one compiled call; above
    :data:`DENSE_AUDIT_MAX` coordinates they are left next to the manifold unprojected.
    ``g_t`` is one forward derivative of ``g`` in ``t``; a non-finite one (a state outside
    ``g``'s domain) counts as 0."""
    s = case.system
    g = s.constraints
    rng = np.random.default_rng(0)
    q0 = np.asarray(case.q0, np.float64)
    size = max(float(np.sqrt(np.mean(q0 ** 2))), 1.0)
    q = np.concatenate([q0[None], q0 + SAMPLE_NOISE * size
                        * rng.standard_normal((TIME_SAMPLES, q0.size))])
    t = np.concatenate([[case.t0], case.t0 + (case.t_end - case.t0) * rng.random(TIME_SAMPLES)])
    dense = s.n <= DENSE_AUDIT_MAX

    def settle(x, u):
        def step(_, x):
            return x - jnp.linalg.lstsq(jax.jacfwd(g)(x, u), jnp.asarray(g(x, u)))[0]
        return jax.lax.fori_loop(0, SAMPLE_STEPS, step, x) if dense else x

    def rate(x, u):
        return jnp.max(jnp.abs(jax.jvp(lambda w: jnp.asarray(g(x, w)), (u,),
                                       (jnp.ones_like(u),))[1]))

    def probe(q, t):
        # The initial state is consistent already: only the random ones are projected.
        q = q.at[1:].set(jax.vmap(settle)(q[1:], t[1:]))
        return jax.vmap(rate)(q, t)

    rates = np.asarray(jax.jit(probe)(jnp.asarray(q), jnp.asarray(t)))
    span = case.t_end - case.t0
    args = jnp.asarray(q0), jnp.asarray(case.t0, jnp.float64)
    v0 = jnp.asarray(case.v0, jnp.float64)
    if dense:
        scale = float(jax.jit(lambda q, u, v: jnp.max(jnp.abs(jax.jacfwd(g)(q, u))
                                                      @ (jnp.abs(q) + span * jnp.abs(v))))(
            *args, v0))
    else:
        scale = float(case.mech.rounding(*args)) + span * float(case.mech.rounding(*args, v0))
    return np.where(np.isfinite(rates), rates, 0.0), t, scale


def check_rheonomic(case, notes: list[str] | None = None) -> None:
    """Refuse constraints that depend on ``t`` in a system declared scleronomic.

    A scleronomic system's ``g_t`` is taken as 0 everywhere (:meth:`Mechanics.g_t`): with
    a ``g`` that reads ``t`` the velocities are projected onto the wrong manifold and the
    energy is scored as if conserved, wrong numbers with status ok. ``g_t = dg/dt`` is
    evaluated at the initial state and at random consistent states and times
    (:func:`_time_rates`); it must vanish there, up to :data:`RHEONOMIC_TOL`. The converse,
    ``rheonomic=True`` with ``g_t = 0`` at every sample, costs only the energy error (the
    run is scored by its energy balance instead): a note is appended to ``notes``.

    Raises
    ------
    AuditError
        Led by the ``file:line`` of ``constraints``, with the largest ``g_t`` found and
        where, and what to set.
    """
    s = case.system
    if s.m == 0:
        return
    rates, times, scale = _time_rates(case)
    worst = int(np.argmax(rates))
    reads = reads_t(s.constraints, case.q0, case.t0)
    # Sampled g_t above round-off moves g; so does a g that reads t and whose g_t is zero at
    # every sample (t acts elsewhere on the horizon). A g that reads t in terms that cancel
    # shows g_t at the round-off of those terms, and is scleronomic.
    moving = reads and (rates[worst] == 0.0
                        or rates[worst] * (case.t_end - case.t0) > RHEONOMIC_TOL * scale)
    if moving and not s.rheonomic:
        where = (f"|g_t| = {rates[worst]:.3g} at t = {times[worst]:.6g}" if rates[worst] > 0
                 else f"they read t, though g_t = 0 at the {len(rates)} sampled times")
        raise _refuse(case, f"constraints(q, t) of problem {case.name!r} depend on t "
                            f"({where}) but its "
                            f"System is declared scleronomic: set rheonomic=True in System(...) "
                            f"(without it g_t is taken as 0)", s.constraints)
    if s.rheonomic and not moving and notes is not None:
        notes.append(located(f"note: problem {case.name!r} sets rheonomic=True but g_t = 0 "
                             f"at {len(rates)} sampled states and times: if its constraints "
                             f"do not read t, leave rheonomic out (a rheonomic system gets its "
                             f"energy balance scored, not its energy)", s.constraints))


def audit(case, notes: list[str] | None = None) -> None:
    """Check the functions of ``case.system`` at ``(t0, q0, v0)``, and that they depend on
    ``t`` as declared (:func:`check_rheonomic`, whose notes go to ``notes``).

    Raises
    ------
    AuditError
        With the function's ``file:line``, the problem and what is wrong, on one line.
    """
    s = case.system
    n, m = s.n, s.m
    f64 = jnp.float64
    args = q, v, t = (jnp.asarray(case.q0, f64), jnp.asarray(case.v0, f64),
                      jnp.asarray(case.t0, f64))
    if s.kinetic is not None:
        _check(case, args, "kinetic(q, v)", s.kinetic, lambda q, v, t: s.kinetic(q, v), ())
        _check(case, args, "d kinetic / dq (autodiff)", s.kinetic,
               lambda q, v, t: jax.grad(s.kinetic, argnums=0)(q, v), (n,))
        M = None
        if n <= DENSE_AUDIT_MAX:
            M = _check(case, args, "mass from kinetic (autodiff)", s.kinetic,
                       lambda q, v, t: case.mech.mass(q), (n, n))
        elif case.mech.mass_blocks is not None:
            # Too large to form: the blocks' Cholesky factors are finite exactly where
            # every block is positive definite.
            for L in case.mech.mass_factor(q):
                if not all(np.all(np.isfinite(np.asarray(L[i][i]))) for i in range(len(L))):
                    raise _refuse(case, f"mass of problem {case.name!r} (from kinetic) is "
                                        f"not positive definite at q0", s.kinetic)
    elif callable(s.mass):
        M = _check(case, args, "mass(q)", s.mass, lambda q, v, t: s.mass(q), (n, n))
        _check(case, args, "d mass / dq (autodiff)", s.mass,
               lambda q, v, t: jax.jacfwd(s.mass)(q), (n, n, n))
    elif sp.issparse(s.mass):
        if s.mass.shape != (n, n) or not np.all(np.isfinite(s.mass.data)):
            raise _refuse(case, f"mass of problem {case.name!r} has shape {s.mass.shape}, not "
                                f"({n}, {n}), or is not finite")
        M = s.mass.toarray() if n <= DENSE_AUDIT_MAX else None
    else:
        M = np.asarray(s.mass, dtype=np.float64)
        M = np.diag(M) if M.ndim == 1 else M
        if M.shape != (n, n) or not np.all(np.isfinite(M)):
            raise _refuse(case, f"mass of problem {case.name!r} has shape {M.shape}, not "
                                f"({n}, {n}) or ({n},), or is not finite")
    mass = s.kinetic if s.kinetic is not None else s.mass if callable(s.mass) else None
    if M is not None and np.max(np.abs(M - M.T)) > SYMMETRY_TOL * max(np.max(np.abs(M)), 1.0):
        raise _refuse(case, f"mass of problem {case.name!r} is not symmetric at q0", mass)
    if M is not None and np.min(np.linalg.eigvalsh(0.5 * (M + M.T))) <= 0.0:
        raise _refuse(case, f"mass of problem {case.name!r} is not positive definite at q0 "
                            f"(smallest eigenvalue {np.min(np.linalg.eigvalsh(M)):.3g})", mass)
    if s.potential is not None:
        _check(case, args, "potential(q)", s.potential, lambda q, v, t: s.potential(q), ())
        _check(case, args, "grad potential (autodiff)", s.potential,
               lambda q, v, t: jax.grad(s.potential)(q), (n,))
    _check(case, args, "constraints(q, t)", s.constraints,
           lambda q, v, t: s.constraints(q, t), (m,))
    _check(case, args, "d constraints / dq (autodiff)", s.constraints,
           lambda q, v, t: jax.jacfwd(s.constraints, argnums=0)(q, t), (m, n))
    if s.forces is not None:
        _check(case, args, "forces(t, q, v)", s.forces,
               lambda q, v, t: s.forces(t, q, v), (n,))
    for name, func in s.invariants.items():
        _check(case, args, f"invariant {name!r}(q, v)", func, lambda q, v, t: func(q, v), ())
    check_rheonomic(case, notes)
