"""SUNDIALS IDA (variable-order BDF) on index-reduced forms of the equations of motion.

The problem's JAX functions give the residual ``F(t, y, y')`` and its iteration matrix
``dF/dy + cj dF/dy'`` (forward-mode autodiff, no finite differences); both are compiled once
per case in ``prepare``. With the dense linear solver they are compiled to C with IDA's
stepping loop (:mod:`integrators.sundials`), so that IDA runs at the speed of a C program;
otherwise, and where that cannot be built, they are handed to IDA through scikit-sundae's
Python callbacks. Large systems get the
iteration matrix as a sparse matrix, its pattern traced from the residual and its values
from compressed autodiff (:class:`linalg.pattern.SparseJacobian`), factorised by
SUNDIALS' sparse direct solver (SuperLU_MT, with its own fill-reducing column ordering). IDA runs in one-step mode
so that every internal step is measured; the drift bookkeeping is
:class:`integrators.record.Recorder`'s.
"""

from __future__ import annotations

import contextlib
import io
import math
import time
import warnings
from dataclasses import dataclass
from functools import partial
from typing import Callable, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from sksundae.ida import IDA as SundialsIDA

from integrators import sundials
from integrators.base import Grid, Integrator
from integrators.record import Recorder
from linalg.compiled import compile_lifted
from linalg.pattern import SparseJacobian
from linalg.schur import DENSE_MAX
from linalg.sparse import FALLBACK_MAX
from problems.case import Case
from problems.mechanics import Mechanics

Residual = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


def ggl_residual(mech: Mechanics) -> Residual:
    """Stabilised index-2 form of Gear, Gupta and Leimkuhler (1985), ``y = (q, v, lam, mu)``.

    .. math::

        0 = q' - v + G^T \\mu, \\quad 0 = M(q) v' - f(t, q, v) + G^T \\lambda, \\quad
        0 = g(q, t), \\quad 0 = G v + g_t,

    with ``f`` the full right-hand side (:meth:`Mechanics.force`). ``mu`` vanishes on the
    exact solution; it is the multiplier that keeps ``q`` on ``g = 0`` while ``v`` obeys the
    velocity constraint, so both constraint levels hold to the Newton tolerance.
    """
    n, m = mech.n, mech.m

    def F(t, y, yp):
        q, v, lam, mu = y[:n], y[n:2 * n], y[2 * n:2 * n + m], y[2 * n + m:]
        return jnp.concatenate([
            yp[:n] - v + mech.GT(q, t, mu),
            mech.mass_times(q, yp[n:2 * n]) - mech.force(t, q, v) + mech.GT(q, t, lam),
            mech.g(q, t),
            mech.vel_residual(q, v, t),
        ])

    return F


def index1_residual(mech: Mechanics) -> Residual:
    """Acceleration-level index-1 form, ``y = (q, v, lam)``.

    .. math::

        0 = q' - v, \\quad 0 = M(q) v' - f(t, q, v) + G^T \\lambda, \\quad
        0 = G v' + \\gamma(q, v, t),

    with ``gamma`` the curvature and ``g_tt`` terms (:meth:`Mechanics.gamma`), so that the
    last row is ``d^2 g/dt^2 = 0``. Neither ``g = 0`` nor ``G v + g_t = 0`` is enforced: both
    drift.
    """
    n, m = mech.n, mech.m

    def F(t, y, yp):
        q, v, lam = y[:n], y[n:2 * n], y[2 * n:2 * n + m]
        return jnp.concatenate([
            yp[:n] - v,
            mech.mass_times(q, yp[n:2 * n]) - mech.force(t, q, v) + mech.GT(q, t, lam),
            mech.G_times(q, t, yp[n:2 * n]) + mech.gamma(q, v, t),
        ])

    return F


class Formulation(NamedTuple):
    """A DAE form: its residual builder, how many multiplier blocks of size ``m`` it has and
    which constraint levels are among its equations (held to IDA's tolerance)."""

    residual: Callable[[Mechanics], Residual]
    multiplier_blocks: int
    enforces: tuple[str, ...]


#: ``formulation`` option -> DAE form.
FORMULATIONS: dict[str, Formulation] = {
    "ggl": Formulation(ggl_residual, 2, ("position", "velocity")),
    "index1": Formulation(index1_residual, 1, ()),
}

#: Most constraints whose rank is checked densely at set-up on the sparse path.
RANK_CHECK_MAX = 512

#: ``multiplier_atol`` that keeps the multipliers out of the error test.
EXCLUDED = 1e30

#: IDA's direct linear solvers: ``auto`` picks ``sparse`` for more than
#: :data:`linalg.schur.DENSE_MAX` constraints and ``dense`` otherwise.
LINEAR_SOLVERS = ("auto", "dense", "lapackdense", "sparse")

#: What a native run records as its sampling.
NATIVE_SAMPLING = "every internal step (IDA one-step mode, native driver)"

#: ``driver`` option values: who calls IDA (:class:`IDA`).
DRIVERS = ("auto", "native", "scikit-sundae")

#: ``jacobian`` option -> whether our autodiff iteration matrix is handed to IDA (else IDA
#: forms it by difference quotients of the residual).
JACOBIANS = {"autodiff": True, "difference-quotient": False}


@partial(jax.jit, static_argnames=("mech", "formulation"))
def dae_residual(t, y, yp, *, mech: Mechanics, formulation: str):
    """``F(t, y, y')`` of a formulation (compiled once per system and formulation)."""
    return FORMULATIONS[formulation].residual(mech)(t, y, yp)


@partial(jax.jit, static_argnames=("mech", "formulation"))
def iteration_matrix(t, y, yp, cj, *, mech: Mechanics, formulation: str):
    """``dF/dy + cj dF/dy'``, in one forward-mode pass: along ``z``, ``y'`` moves as
    ``cj (z - y)``, so the derivative in ``z`` is the iteration matrix."""
    F = FORMULATIONS[formulation].residual(mech)
    return jax.jacfwd(lambda z: F(t, z, yp + cj * (z - y)))(y)


def iteration_pattern(mech: Mechanics, formulation: str):
    """A structural superset of the iteration matrix's pattern, ``(rows, cols, shape)``,
    assembled from the blocks of the formulation (``None`` where
    :attr:`~problems.mechanics.Mechanics.dynamics_pattern` has none).

    With ``y = (q, v, lam[, mu])`` the blocks are: identities where ``q'`` and ``v`` enter;
    ``G`` and ``G^T`` where the constraints and multipliers do; the Hessian pattern of
    ``sum g`` (:attr:`~problems.mechanics.Mechanics.curvature_pattern`) for the ``q``
    derivatives of ``G^T lam`` and ``G^T mu``; ``M``'s pattern and the dynamics' for the
    momentum rows. The ``q`` and ``v`` derivatives of ``G v + g_t`` (GGL) and of
    ``G v' + gamma`` (index 1) lie within ``G``'s pattern: each of their entries ``(i, k)``
    is a derivative of ``dg_i / dq_k``, which is identically zero off ``G``'s pattern.
    """
    dynamics = mech.dynamics_pattern
    mass = mech.mass_pattern()
    if dynamics is None or mass is None:
        return None
    n, m = mech.n, mech.m
    G = mech.G_pattern()
    GT = G[::-1]
    H = mech.curvature_pattern
    eye = (np.arange(n), np.arange(n))
    q, v, lam, mu = 0, n, 2 * n, 2 * n + m
    # (first row, first column, pattern); the dynamics' spans the q and the v columns.
    blocks = [(q, q, eye), (q, v, eye),
              (v, q, H), (v, q, dynamics), (v, v, mass), (v, lam, GT),
              (lam, q, G)]
    if formulation == "ggl":
        blocks += [(q, q, H), (q, mu, GT), (mu, q, G), (mu, v, G)]
        size = 2 * n + 2 * m
    else:
        blocks += [(lam, v, G)]
        size = 2 * n + m
    rows = np.concatenate([np.asarray(r, dtype=np.int64) + row for row, _, (r, _) in blocks])
    cols = np.concatenate([np.asarray(c, dtype=np.int64) + col for _, col, (_, c) in blocks])
    return rows, cols, (size, size)


def sparse_iteration_matrix(mech: Mechanics, formulation: str, t0: float, y0, yp0):
    """The iteration matrix's CSC pattern and ``(t, y, y', cj) -> CSC data``, compiled for
    arguments of the types of ``(t0, y0, yp0, 1.0)``.

    The pattern is assembled from the system's structure (:func:`iteration_pattern`) and
    checked at a random point (:meth:`~linalg.pattern.SparseJacobian.agrees`); where it
    cannot be assembled or fails the check, it is traced from the whole residual. Tracing
    takes more memory than the rest of a run: on ``rigid-chain:N=4096`` the set-up peaked
    at 1.24 GiB with the traced pattern and 0.94 GiB with the assembled one, and at
    ``N = 16384`` a whole run (27 steps) at 1.7 GiB, where tracing alone had reached
    4.2 GiB (a run of 42 steps now peaks at 1.4 GiB: the Jacobian's directions go one by
    one there, :meth:`~linalg.pattern.SparseJacobian.values`).
    """
    F = FORMULATIONS[formulation].residual(mech)
    t, y, yp = jnp.asarray(0.0), jnp.asarray(y0), jnp.asarray(yp0)

    def residual(z):
        return F(t, z, yp + (z - y))

    def build(jac):
        # IDA takes the entries in CSC order: the Jacobian gathers them in that order.
        pattern = sp.csc_matrix((np.arange(1, jac.nnz + 1, dtype=np.float64),
                                 (jac.rows, jac.cols)), shape=(len(y0), len(y0)))
        jac = jac.reordered(pattern.data.astype(np.int64) - 1)

        def data(t, y, yp, cj):
            return jac.values(y, lambda z: F(t, z, yp + cj * (z - y)))

        return jac, pattern, compile_lifted(data, t0, y0, yp0, 1.0)

    assembled = iteration_pattern(mech, formulation)
    if assembled is not None:
        jac, pattern, matrix = build(SparseJacobian(residual, y, assembled))
        point = np.random.default_rng(1).standard_normal(len(y0))
        entries = np.asarray(matrix(0.0, point, yp0 + (point - y0), 1.0))
        if jac.agrees(jnp.asarray(point), entries):
            return pattern, matrix, jac.nnz
    jac, pattern, matrix = build(SparseJacobian(residual, y))
    return pattern, matrix, jac.nnz


@partial(jax.jit, static_argnames=("mech", "blocks", "schur"))
def _consistent(t, q, v, *, mech: Mechanics, blocks: int, schur):
    a, lam = mech.accelerations(t, q, v, schur=schur)
    lam_dot = jax.jvp(lambda s, x, u: mech.accelerations(s, x, u, schur=schur)[1],
                      (t, q, v), (jnp.ones_like(t), v, a))[1]
    zeros = jnp.zeros((blocks - 1) * mech.m)
    return jnp.concatenate([q, v, lam, zeros]), jnp.concatenate([v, a, lam_dot, zeros])


def consistent_values(mech: Mechanics, blocks: int, t0: float, q0: np.ndarray,
                      v0: np.ndarray, schur=None) -> tuple[np.ndarray, np.ndarray]:
    """``(y0, y0')`` of either formulation from a consistent ``(q0, v0)``.

    Accelerations and multipliers come from the index-1 system
    (:meth:`Mechanics.accelerations`); ``lam'`` is its derivative along the flow,
    ``(q', v', t') = (v, a, 1)``, so that IDA's first predictor is right in every
    component; ``mu = mu' = 0``. ``schur`` solves with ``G M^{-1} G^T`` (default: dense).

    Raises
    ------
    ValueError
        When ``schur`` is SuperLU on more than ``FALLBACK_MAX`` constraints: ``lam'`` is a
        derivative of the multipliers and the SuperLU callback has none, so such a system
        takes the dense solve here, which is refused at that size.
    """
    if schur is not None and schur.name == "superlu":
        if mech.m > FALLBACK_MAX:
            raise ValueError(f"the initial multiplier derivative of this system ({mech.m} "
                             "constraints, no narrow band) needs a differentiable solve with "
                             f"G M^-1 G^T; only up to {FALLBACK_MAX} is supported")
        schur = mech.schur("dense")
    args = (jnp.asarray(t0, dtype=jnp.float64), jnp.asarray(q0), jnp.asarray(v0))
    y0, yp0 = compile_lifted(_consistent, *args, mech=mech, blocks=blocks,
                             schur=mech.schur("dense") if schur is None else schur)(*args)
    return np.asarray(y0, dtype=np.float64), np.asarray(yp0, dtype=np.float64)


class Callbacks:
    """The residual and Jacobian callbacks IDA calls, with their times and trial count.

    ``trials`` counts step attempts as the distinct times at which IDA evaluates the
    residual: every attempt (the first try of a step and each retry after an error-test or
    a convergence failure, which always changes ``h``) evaluates it at its own new time;
    IDA's difference-quotient Jacobian, when used, evaluates it at the attempt's time too.
    """

    def __init__(self, F, J):
        self._F, self._J = F, J
        self.reset()

    def reset(self) -> None:
        self.residual_s = 0.0
        self.jacobian_s = 0.0
        self.calls = 0
        self.trials = 0
        self._t_trial = math.nan

    def residual(self, t, y, yp, res):
        start = time.perf_counter()
        self.calls += 1
        if t != self._t_trial:
            self.trials += 1
            self._t_trial = t
        res[:] = self._F(t, y, yp)
        self.residual_s += time.perf_counter() - start

    def jacobian(self, t, y, yp, res, cj, JJ):
        start = time.perf_counter()
        JJ[...] = self._J(t, y, yp, cj)
        self.jacobian_s += time.perf_counter() - start


@dataclass(frozen=True)
class IDA(Integrator):
    """SUNDIALS IDA (variable-order, variable-step BDF; Hindmarsh et al. 2005) on an
    index-reduced DAE form.

    ``formulation = "ggl"`` integrates the stabilised index-2 system of Gear, Gupta and
    Leimkuhler (1985) (:func:`ggl_residual`) and enforces ``g = 0`` and
    ``G v + g_t = 0`` at every step to the Newton tolerance; ``formulation = "index1"``
    integrates the acceleration-level index-1 system (:func:`index1_residual`), which
    enforces only ``d^2 g/dt^2 = 0``, so ``g`` and ``G v + g_t`` drift (reported, not
    corrected). Order 1 to ``max_order`` (at most 5), chosen by IDA; not symplectic.

    **Multipliers out of the error test.** IDA's error test and its Newton convergence test
    use the weights ``1 / (rtol |y_i| + atol_i)``. The multipliers get
    ``atol_i = multiplier_atol = 1e30`` by default, which makes their weights so small that
    they never decide a step (scikit-sundae has no switch for IDA's own option of excluding
    algebraic variables, and the native driver makes the same calls).

    - ``ggl``: BDF's local error estimate for the index-2 variables ``lam, mu`` does not
      shrink like that of ``q, v`` and forces step-size reductions that buy no accuracy in
      ``(q, v)``. Verified on ``pendulum``: at rtol = 1e-8 over 20 s, ``multiplier_atol``
      = 1e20, 1e30 and 1e40 give the same 8585 steps, 14122 residual evaluations and the
      same final state bit for bit, so the multipliers' contribution to the weighted norms
      is nil; with the multipliers in the test (``multiplier_atol = atol``, rtol = 1e-6,
      2 s) IDA takes 20000 steps (19725 rejected) to reach t = 0.078, where 417 steps cover
      the whole 2 s with them out.
    - ``index1``: ``lam`` is an index-1 variable, which SUNDIALS' guide would keep in the
      test; but it is determined through ``v'``, whose round-off grows like ``eps / h``, so
      at tight tolerances its error estimate sits at that floor and drives the step down.
      On ``pendulum`` over 2 s: at rtol = 1e-6 keeping it costs 467 steps instead of 277
      (final error 2.9e-5 instead of 7.9e-5), but at rtol = 1e-9 it costs 24589 steps
      instead of 708 and the final error is worse (6.2e-6 instead of 3.0e-7).

    ``tests/test_ida.py`` checks both cases.

    **Work counts**, the same for both drivers. IDA's counts of Newton-residual and Jacobian
    evaluations are read from it; the rest are derived exactly: ``n_steps`` counts the one-step returns,
    ``n_rejected`` the step attempts (distinct residual times, see :class:`Callbacks`)
    minus the steps, i.e. error-test plus convergence failures, and ``n_f_evals`` the
    residual calls we serve. IDA's Newton solver (SUNNonlinSol_Newton) evaluates the
    residual once per iteration and does one back-substitution per iteration, so
    ``n_newton = n_lin_solves`` = IDA's residual count, which equals ``n_f_evals`` with our
    Jacobian (a difference-quotient Jacobian adds one call per component of ``y`` per
    evaluation);
    ``n_jac_evals`` counts evaluations (and LU factorisations) of the iteration matrix.
    With scikit-sundae, ``extra["callback_s"]`` is the time spent in our Python residual
    and Jacobian callbacks (``residual_s`` and ``jacobian_s`` apart); the native driver has
    none. ``extra["initial_residual"]`` is ``max |F(t0, y0, y0')|`` of the computed initial
    values.

    Initial values ``(y0, y0')`` are computed from the case (:func:`consistent_values`);
    IDA's own initial-condition calculation is not used. IDA settings that the binding
    does not expose keep SUNDIALS' values: at most 10 error-test failures per step and a
    Newton convergence coefficient of 0.33.

    Parameters
    ----------
    formulation : {"ggl", "index1"}
        The DAE form (:data:`FORMULATIONS`).
    rtol : float
        Relative tolerance (all components).
    atol : float
        Absolute tolerance on ``q`` and ``v``; NaN (the default) sets it equal to ``rtol``
        at construction, so that a tolerance sweep scales both (the problems are O(1)).
    multiplier_atol : float
        Absolute tolerance on the multipliers; the default :data:`EXCLUDED` keeps them out
        of the error test.
    max_order : int
        Maximum BDF order, 1..5.
    max_steps : int
        Internal steps allowed over the whole run; reaching it fails the run.
    max_nonlin_iters : int
        Newton iterations per step attempt.
    max_conv_fails : int
        Newton convergence failures allowed in one step.
    first_step : float
        Initial step; 0 lets IDA choose it from ``||y0'||``.
    min_step, max_step : float
        Step size bounds; 0 means none.
    linsolver : {"auto", "dense", "lapackdense", "sparse"}
        IDA's direct linear solver: dense (SUNDIALS' own or LAPACK's) or sparse
        (SuperLU_MT, one thread, on the compressed autodiff Jacobian); ``auto`` takes
        ``sparse`` above :data:`linalg.schur.DENSE_MAX` constraints.
    jacobian : {"autodiff", "difference-quotient"}
        The iteration matrix: ours (forward-mode autodiff, the default) or IDA's
        difference quotients of the residual (for comparison).
    driver : {"auto", "native", "scikit-sundae"}
        Who calls IDA. ``native`` (:mod:`integrators.sundials`) compiles the residual and
        the iteration matrix to C with the stepping loop, so that IDA runs at the speed of
        a C program; it takes the dense linear solver only. ``scikit-sundae`` calls back
        into the compiled JAX functions from Python at every residual. ``auto`` takes
        ``native`` where it can be built (a C compiler, a system the code generator
        knows, ``linsolver`` dense) and says in the run's ``sampling`` which ran. Both
        drivers make the same IDA calls and take the same steps until round-off in the
        residuals (C against XLA's code) changes a step-size decision; from there they part
        by the method's own error, not more.
    """

    adaptive: ClassVar[bool] = True

    formulation: str = "ggl"
    rtol: float = 1e-6
    atol: float = math.nan
    multiplier_atol: float = EXCLUDED
    max_order: int = 5
    max_steps: int = 5_000_000
    max_nonlin_iters: int = 4
    max_conv_fails: int = 10
    first_step: float = 0.0
    min_step: float = 0.0
    max_step: float = 0.0
    linsolver: str = "auto"
    jacobian: str = "autodiff"
    driver: str = "auto"

    family: ClassVar[str] = "BDF (SUNDIALS IDA)"
    # nominal_order stays None: variable-order BDF (orders 1 to max_order, chosen per step).

    @property
    def enforces(self) -> tuple[str, ...]:
        return FORMULATIONS[self.formulation].enforces

    def check(self) -> None:
        super().check()
        name = type(self).__name__
        self.check_choice("formulation", FORMULATIONS)
        self.check_choice("jacobian", JACOBIANS)
        if self.jacobian != "autodiff" and self.linsolver == "sparse":
            raise ValueError(f"{name}: linsolver = 'sparse' needs jacobian = 'autodiff'")
        self.check_choice("linsolver", LINEAR_SOLVERS)
        self.check_choice("driver", DRIVERS)
        if self.driver == "native" and self.linsolver not in ("auto", "dense"):
            raise ValueError(f"{name}: driver = 'native' takes linsolver = 'dense' only")
        if not 1 <= self.max_order <= 5:
            raise ValueError(f"{name}: max_order = {self.max_order} must lie in 1..5")
        for option in ("max_steps", "max_nonlin_iters", "max_conv_fails"):
            if getattr(self, option) < 1:
                raise ValueError(f"{name}: {option} = {getattr(self, option)} must be >= 1")
        if not self.multiplier_atol > 0:
            raise ValueError(f"{name}: multiplier_atol = {self.multiplier_atol} must be > 0")
        for option in ("first_step", "min_step", "max_step"):
            if not getattr(self, option) >= 0:
                raise ValueError(f"{name}: {option} = {getattr(self, option)} must be >= 0")

    def prepare(self, case: Case, grid: Grid):
        self.check()
        mech = case.mech
        n, m = mech.n, mech.m
        form = FORMULATIONS[self.formulation]
        t0, t_end = float(grid.t0), float(grid.t_end)
        linsolver = self.linsolver
        if linsolver == "auto":
            linsolver = "sparse" if m > DENSE_MAX and self.jacobian == "autodiff" else "dense"
        schur = mech.schur("dense" if linsolver != "sparse" else "auto")
        y0, yp0 = consistent_values(mech, form.multiplier_blocks, t0, case.q0, case.v0, schur)
        redundant = ""
        if linsolver != "sparse" or m <= RANK_CHECK_MAX:
            # Redundant constraints make the iteration matrix singular. SUNDIALS' dense LU
            # does not notice, and the run would return meaningless states as a success;
            # SuperLU_MT does not stop either: on bricard it cuts the step to 1e-30 over
            # more than a million steps before failing. Above RANK_CHECK_MAX constraints
            # (sparse only) the dense rank would cost more than the run.
            rank = int(np.linalg.matrix_rank(np.asarray(mech.G(jnp.asarray(case.q0),
                                                               jnp.asarray(t0)))))
            redundant = (f"G(q0) has rank {rank} < m = {m} (redundant constraints): the "
                         "iteration matrix is singular, which IDA's linear solvers cannot "
                         "solve" if rank < m else "")
        static = dict(mech=mech, formulation=self.formulation)
        residual = compile_lifted(dae_residual, t0, y0, yp0, **static)
        sparse = {}
        if linsolver == "sparse":
            pattern, matrix, nnz = sparse_iteration_matrix(mech, self.formulation, t0, y0, yp0)
            sparse = dict(sparsity=pattern, nthreads=1)
        else:
            matrix = compile_lifted(iteration_matrix, t0, y0, yp0, 1.0, **static)
        r0 = np.asarray(residual(t0, y0, yp0))
        J0 = np.asarray(matrix(t0, y0, yp0, 1.0))
        assert r0.dtype == np.float64 and J0.dtype == np.float64, "IDA must run in float64"
        initial_residual = float(np.max(np.abs(r0)))
        n_mult = form.multiplier_blocks * m
        atol = np.concatenate([np.full(2 * n, self.atol), np.full(n_mult, self.multiplier_atol)])
        algebraic = range(2 * n, 2 * n + n_mult)
        native, why = None, ""
        if self.driver == "native" and linsolver != "dense":
            raise ValueError(f"IDA: driver = 'native' takes the dense linear solver, and "
                             f"linsolver = {self.linsolver!r} gives {linsolver!r} here "
                             f"({m} constraints): set linsolver=dense")
        if self.driver != "scikit-sundae" and linsolver == "dense":
            try:
                native = sundials.build(FORMULATIONS[self.formulation].residual(mech),
                                        len(y0), JACOBIANS[self.jacobian])
            except sundials.NotNative as exc:
                if self.driver == "native":
                    raise
                why = f"; native driver not built: {exc}"
        # The run records IDA's linear solver and the size of G's pattern (the iteration
        # matrix's is larger: it holds G, G^T and the derivatives of G^T lambda).
        solver_record = dict(linear_solver=linsolver,
                             pattern_nnz=mech.schur("auto").nnz if sparse else None)
        recorder = Recorder(mech, grid)
        if native is not None:
            settings = dict(t0=t0, y0=y0, yp0=yp0, rtol=self.rtol, atol=atol,
                            algebraic=algebraic, jacobian=JACOBIANS[self.jacobian],
                            max_order=self.max_order, max_steps=self.max_steps,
                            max_nonlin_iters=self.max_nonlin_iters,
                            max_conv_fails=self.max_conv_fails, first_step=self.first_step,
                            min_step=self.min_step, max_step=self.max_step, tstop=t_end)

            def solve_native():
                if redundant:
                    recorder.start(t0, y0[:n], y0[n:2 * n])
                    return recorder.trajectory(redundant, t0, y0[:n], y0[n:2 * n],
                                               {"n_steps": 0}, NATIVE_SAMPLING, **solver_record)
                solver = native.solver(**settings)
                recorder.start(t0, y0[:n], y0[n:2 * n])
                t, y, steps, failure = t0, y0, 0, ""
                while t < t_end:
                    if steps >= self.max_steps:
                        failure = (f"IDA: max_steps = {self.max_steps} internal steps reached "
                                   f"at t = {t:.6g} before t_end = {t_end:.6g}")
                        break
                    ts, ys, flag, t_now = solver.steps(self.max_steps - steps)
                    if len(ts):
                        recorder.extend(ts, ys[:, :n], ys[:, n:2 * n])
                        steps += len(ts)
                        t, y = float(ts[-1]), ys[-1].copy()
                    if flag < 0:
                        failure = (f"IDA failed at t = {t_now:.6g} after {steps} steps: "
                                   f"{solver.failure(flag)}")
                        t, y = t_now, solver.state()
                        break
                work = solver.counts()
                solver.close()
                counts = {"n_steps": steps, "n_rejected": work["trials"] - steps,
                          "n_f_evals": work["calls"], "n_jac_evals": work["jacobians"],
                          "n_newton": work["residuals"], "n_lin_solves": work["residuals"]}
                return recorder.trajectory(failure, t, y[:n], y[n:2 * n], counts,
                                           NATIVE_SAMPLING, extra={"initial_residual":
                                                                   initial_residual},
                                           **solver_record)

            return solve_native
        callbacks = Callbacks(residual, matrix)
        with warnings.catch_warnings():
            # The binding warns that the pattern is not used for difference quotients:
            # ours is the Jacobian's own pattern, filled by jacfn.
            warnings.filterwarnings("ignore", "Custom sparse Jacobian", UserWarning)
            ida = SundialsIDA(
                callbacks.residual,
                jacfn=callbacks.jacobian if JACOBIANS[self.jacobian] else None,
                rtol=self.rtol, atol=atol, algebraic_idx=list(algebraic),
                calc_initcond=None, first_step=self.first_step, min_step=self.min_step,
                max_step=self.max_step, linsolver=linsolver, max_order=self.max_order,
                max_num_steps=self.max_steps, max_nonlin_iters=self.max_nonlin_iters,
                max_conv_fails=self.max_conv_fails, **sparse)
        sampling = f"every internal step (IDA one-step mode, scikit-sundae{why})"

        def solve():
            if redundant:
                recorder.start(t0, y0[:n], y0[n:2 * n])
                return recorder.trajectory(redundant, t0, y0[:n], y0[n:2 * n], {"n_steps": 0},
                                           sampling, **solver_record)
            callbacks.reset()
            start = ida.init_step(t0, y0, yp0)
            if not start.success:
                raise RuntimeError(f"IDA did not initialise: {start.message}")
            recorder.start(t0, y0[:n], y0[n:2 * n])
            t, y, steps, failure = t0, y0, 0, ""
            nfev = njev = 0
            # The binding prints SUNDIALS' own error text (which says where and with what
            # step size IDA gave up); it is captured for the failure message.
            printed = io.StringIO()
            with contextlib.redirect_stdout(printed):
                while t < t_end:
                    if steps >= self.max_steps:
                        failure = (f"IDA: max_steps = {self.max_steps} internal steps reached "
                                   f"at t = {t:.6g} before t_end = {t_end:.6g}")
                        break
                    out = ida.step(t_end, "onestep", t_end)
                    nfev, njev = out.nfev, out.njev
                    if not out.success:
                        detail = " ".join(printed.getvalue().split())
                        failure = (f"IDA failed at t = {float(out.t):.6g} after {steps} steps: "
                                   f"{out.message} (flag {out.status})"
                                   + (f"; SUNDIALS: {detail}" if detail else ""))
                        t, y = float(out.t), out.y
                        break
                    steps += 1
                    t, y = float(out.t), out.y
                    recorder.add(t, y[:n], y[n:2 * n])
            counts = {"n_steps": steps, "n_rejected": callbacks.trials - steps,
                      "n_f_evals": callbacks.calls, "n_jac_evals": njev, "n_newton": nfev,
                      "n_lin_solves": nfev}
            extra = {"callback_s": callbacks.residual_s + callbacks.jacobian_s,
                     "residual_s": callbacks.residual_s, "jacobian_s": callbacks.jacobian_s,
                     "initial_residual": initial_residual}
            return recorder.trajectory(failure, t, y[:n], y[n:2 * n], counts, sampling,
                                       extra=extra, **solver_record)

        return solve
