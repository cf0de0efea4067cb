"""Checks of user-written physics before any run, and errors explained in one sentence.

:func:`audit` evaluates the functions of a loaded problem's :class:`~problems.System` at its
initial values, the way the integrators will (under JAX, with autodiff), and refuses what
would make every run meaningless: a wrong shape, a value that is not finite, a mass matrix
that is not symmetric positive definite, a function that JAX cannot trace. The message
names the function, the file and line where it is defined (for a constant mass, those of
the problem's factory), and what is wrong.

:func:`explain` turns any exception met while building or running user code into one line
with the user's ``file:line`` and, for JAX's tracer errors, what they mean.
"""

from __future__ import annotations

import traceback

import jax
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
#: above, its blocks are checked by their Cholesky factors.
DENSE_AUDIT_MAX = 2000


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


def audit(case) -> None:
    """Check the functions of ``case.system`` at ``(t0, q0, v0)``.

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
