"""The generalized-alpha method on the index-3 and the stabilised index-2 equations of motion."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from integrators.fixed import FixedStep, newton_failure
from integrators.newton import max_norm, newton
from problems.mechanics import Mechanics

#: ``formulation`` option -> whether the velocity constraint is enforced as well.
FORMULATIONS = {"index3": False, "ggl": True}


class Coefficients(NamedTuple):
    """``alpha_m, alpha_f, gamma, beta`` of the method."""

    alpha_m: float
    alpha_f: float
    gamma: float
    beta: float

    @classmethod
    def from_rho_inf(cls, rho: float) -> "Coefficients":
        """Chung and Hulbert's (1993) choice for the spectral radius ``rho`` at infinity.

        Second order (``gamma = 1/2 - alpha_m + alpha_f``), unconditionally stable for
        linear problems, and the least low-frequency damping for the high-frequency
        damping that ``rho`` sets.
        """
        alpha_m = (2 * rho - 1) / (rho + 1)
        alpha_f = rho / (rho + 1)
        gamma = 0.5 - alpha_m + alpha_f
        return cls(alpha_m, alpha_f, gamma, 0.25 * (gamma + 0.5) ** 2)

    @classmethod
    def hht(cls, alpha: float) -> "Coefficients":
        """Hilber, Hughes and Taylor's (1977) method for its ``alpha`` in [-1/3, 0].

        The member ``alpha_m = 0``, ``alpha_f = -alpha`` of the family, with their
        ``gamma = 1/2 - alpha`` and ``beta = (1 - alpha)^2 / 4``: Chung and Hulbert's
        second-order condition ``gamma = 1/2 - alpha_m + alpha_f`` and their
        ``beta = (gamma + 1/2)^2 / 4`` hold, and the spectral radius at infinity is
        ``(1 + alpha) / (1 - alpha)``, from 1 (``alpha = 0``) down to 1/2.
        """
        return cls(0.0, -alpha, 0.5 - alpha, 0.25 * (1.0 - alpha) ** 2)


def velocity_scale(c: Coefficients, h) -> jax.Array:
    """``gamma / (beta h)``: the change of ``v_{n+1}`` per unit change of the unknown
    ``x = beta h^2 a_{n+1}`` (``v_{n+1} = v_hat + gamma x / (beta h)``), which moves
    ``q_{n+1}`` by one unit.

    The step's equations of motion are taken times ``gamma h`` (``beta h^2`` times this),
    and its velocity constraint unscaled, so that their residuals, like the position
    constraint's, are in the units of the state they leave unsolved: of ``v`` for the
    former, of ``q`` for the latter. A Newton stop on them (:func:`integrators.newton.newton`)
    then brings ``v`` to the discrete solution at every ``h``. On equations of motion
    taken times ``beta h^2``, their residual is in the units of ``q``; ``v``'s error is
    ``gamma / (beta h)`` times it, and a tolerance fixed in those units leaves ``v`` ever
    further from the discrete solution as ``h`` falls.
    """
    return c.gamma / (c.beta * h)


class State(NamedTuple):
    """The state the method carries from step to step.

    ``a`` is the acceleration-like variable, ``acc`` the acceleration that satisfies the
    equations of motion with the multipliers ``lam``.
    """

    q: jax.Array
    v: jax.Array
    a: jax.Array
    acc: jax.Array
    lam: jax.Array


@dataclass(frozen=True)
class AlphaMethod(FixedStep):
    """The step of the generalized-alpha family for the coefficients a member chooses.

    The equations, their scaling and their solution are those of :class:`GeneralizedAlpha`;
    a member supplies :meth:`coefficients` and declares the options ``h``, its parameter,
    ``formulation``, ``newton_tol``, ``newton_max_iter`` and ``linear_solver`` as fields.
    """

    family: ClassVar[str] = "generalized-alpha"
    nominal_order: ClassVar[int] = 2

    def coefficients(self) -> Coefficients:
        """``alpha_m, alpha_f, gamma, beta`` of the member."""
        raise NotImplementedError

    @property
    def enforces(self) -> tuple[str, ...]:
        return ("position", "velocity") if FORMULATIONS[self.formulation] else ("position",)

    def check(self) -> None:
        super().check()
        self.check_choice("formulation", FORMULATIONS)

    def equations(self, mech: Mechanics, state: State, t, h):
        """The scaled step equations from ``state`` at ``t`` (their scaling:
        :func:`velocity_scale`).

        Returns ``residual(z)``, the warm start ``z0`` (the previous acceleration-like
        variable and multipliers, ``mu = 0``) and ``advance(z) -> State`` at ``t + h``.
        """
        c = self.coefficients()
        ggl = FORMULATIONS[self.formulation]
        m = mech.m
        q, v, a, acc, lam = state
        t1, bh2 = t + h, c.beta * h * h
        w = velocity_scale(c, h)
        q_hat = q + h * v + h * h * (0.5 - c.beta) * a
        v_hat = v + h * (1 - c.gamma) * a
        # beta h^2 times the part of acc_{n+1} that the previous step fixes.
        acc_hat = bh2 * (c.alpha_m * a - c.alpha_f * acc)

        def kinematics(z):
            x = z[0]
            q1 = q_hat + x + (mech.GT(q, t, z[2]) if ggl else 0.0)
            v1 = v_hat + (c.gamma / (c.beta * h)) * x
            acc1 = ((1 - c.alpha_m) * x + acc_hat) / (1 - c.alpha_f)  # beta h^2 acc_{n+1}
            return q1, v1, acc1

        def residual(z):
            q1, v1, acc1 = kinematics(z)
            rows = (w * (mech.mass_times(q1, acc1) - bh2 * mech.force(t1, q1, v1)
                         + mech.GT(q1, t1, z[1])), mech.g(q1, t1))
            if ggl:
                rows += (mech.vel_residual(q1, v1, t1),)
            return rows

        def advance(z):
            q1, v1, acc1 = kinematics(z)
            return State(q1, v1, z[0] / bh2, acc1 / bh2, z[1] / bh2)

        # The unknowns (x, Lambda[, mu]) and the residual's rows stay separate arrays
        # (:func:`integrators.newton.newton`).
        z0 = (bh2 * a, bh2 * lam) + ((jnp.zeros(m),) if ggl else ())
        return residual, z0, advance

    def simplified(self, mech: Mechanics, schur, state: State, t, h):
        """Simplified Newton's correction on the structured path.

        The iteration matrix frozen at ``q_n`` without the force Jacobian and the
        derivatives of ``M``, ``G^T Lambda`` and ``G v``, with ``c = (1 - alpha_m) / (1 -
        alpha_f)``. Index 3, ``[c M, G_0^T; G_0, 0]``, eliminated through ``S_0 = G_0
        M^{-1} G_0^T``: ``S_0 dLambda = c R_g - G_0 M^{-1} R_M`` and ``dx = -M^{-1} (R_M +
        G_0^T dLambda) / c``. GGL, ``[c M, G_0^T, 0; G_0, 0, P_0; G_0, 0, 0]`` with the
        Gram matrix ``P_0 = G_0 G_0^T`` (``mu`` moves ``q`` along ``G_0^T`` without
        ``M^{-1}``): the last row fixes ``G_0 dx = -R_v``, so ``S_0 dLambda = c R_v - G_0
        M^{-1} R_M``, ``dx`` as before and ``P_0 dmu = R_v - R_g``. One factorisation of
        ``S_0`` (and of ``P_0``) per step. ``R_M`` and ``R_v`` are the residual's rows
        divided by :func:`velocity_scale`: the equations of motion times ``beta h^2`` and
        the velocity constraint times ``beta h / gamma``, the rows of this matrix.

        The matrix leaves out the geometric stiffness ``sum_k Lambda_k nabla^2 g_k`` of
        ``G(q_{n+1})^T Lambda``; relative to ``c M`` it is of the size ``beta h^2 omega^2
        / c``, ``omega`` the frequency that the constraint forces give the fastest motion
        (a chain's transverse waves, ``omega ~ N``), and each correction leaves about that
        fraction of the error, a fraction that grows like ``(N h)^2`` on a chain.
        :func:`integrators.newton.newton`'s Anderson mixing (``anderson``, on in
        :meth:`step`) removes much of what each correction leaves; the stop is unchanged,
        and the solution the same to round-off.
        """
        coef = self.coefficients()
        cm = (1 - coef.alpha_m) / (1 - coef.alpha_f)
        w = velocity_scale(coef, h)
        q = state.q
        ggl = FORMULATIONS[self.formulation]
        S0 = schur.factor(q, t)
        gram = mech.gram(schur.name) if ggl else None
        P0 = gram.factor(q, t) if ggl else None

        # The scaled unknowns are small (beta h^2 a); the constraint rows are computed from
        # q and v, whose rounding reaches them as |G||q| and |G||v| (Mechanics.rounding): a
        # long chain's coordinates put that far above eps |z|. The equations of motion's
        # terms are gamma / (beta h) times the unknowns'.
        data = mech.rounding(q, t)
        if ggl:
            data = jnp.maximum(data, mech.rounding(q, t, state.v))

        solve = mech.mass_solver(q)   # factorised once per step, not per iteration

        def linear(z, r):
            # The rows as the iteration matrix above has them: the equations of motion
            # and the velocity constraint times beta h / gamma.
            r_M, r_g = r[0] / w, r[1]
            r_v = r[2] / w if ggl else r_g
            MinvR = solve(r_M)
            dLam = schur.solve(S0, cm * r_v - mech.G_times(q, t, MinvR))
            dx = -(MinvR + solve(mech.GT(q, t, dLam))) / cm
            parts = (dx, dLam) + ((gram.solve(P0, r_v - r_g),) if ggl else ())
            return parts, jnp.maximum(w * max_norm(z), data)

        return linear, S0.ok & P0.ok if ggl else S0.ok

    def dense_max(self, mech: Mechanics) -> int:
        """None: Newton on the step equations is cheaper on the structured path from one
        constraint up (:meth:`integrators.fixed.FixedStep.dense_max`)."""
        return 0

    def linear_algebra(self, mech: Mechanics):
        """The solver for ``S`` (:meth:`integrators.fixed.FixedStep.linear_algebra`) and,
        for the GGL form on a structured path, its Gram solver of the same kind, built
        here: inside the traced step its index arrays would be made under the trace and
        kept, cached, by a later run's trace."""
        schur = super().linear_algebra(mech)
        if FORMULATIONS[self.formulation] and schur.name != "dense":
            mech.gram(schur.name)
        return schur

    def start(self, mech: Mechanics, schur, q0, v0, t0) -> State:
        """Consistent starting values: ``a_0`` and ``\\ddot q_0`` from the index-1 system."""
        acc, lam = mech.accelerations(t0, q0, v0, schur=schur)
        return State(q0, v0, acc, acc, lam)

    def step(self, mech: Mechanics, schur, state: State, t, h):
        """One step (:class:`integrators.fixed.FixedStep`)."""
        residual, z0, advance = self.equations(mech, state, t, h)
        linear, ok = (None, True) if schur.name == "dense" else self.simplified(
            mech, schur, state, t, h)
        # The dense path solves with the rows of Bottasso's scaling (the equations of
        # motion and the velocity constraint divided back by velocity_scale), whose
        # conditioning does not grow as h falls; the stop reads the residual as it is.
        w = velocity_scale(self.coefficients(), h)
        rows = (w, 1.0) + ((w,) if FORMULATIONS[self.formulation] else ())
        # Simplified Newton's matrix leaves out the geometric stiffness (see simplified),
        # so its contraction is not small on stiff chains: Anderson mixing.
        sol = newton(residual, z0, self.newton_tol, self.newton_max_iter, linear,
                     rows=rows, anderson=True)
        it = sol.iterations
        # One force evaluation per residual; the ggl form evaluates G(q_n) once more.
        extra_G = int(FORMULATIONS[self.formulation])
        counts = {"n_f_evals": it + 1, "n_jac_evals": it + extra_G, "n_newton": it,
                  "n_lin_solves": it}
        return advance(sol.z), newton_failure(sol.converged, ok), sol.residual, counts

    def observe(self, mech: Mechanics, state: State):
        """``(q, v)``."""
        return state.q, state.v



@dataclass(frozen=True)
class GeneralizedAlpha(AlphaMethod):
    """Generalized-alpha (Chung and Hulbert 1993) for constrained systems (Arnold and Bruls 2007).

    One step from ``(q_n, v_n, a_n, \\ddot q_n)`` to ``t_{n+1} = t_n + h``:

    .. math::

        q_{n+1} &= q_n + h v_n + h^2 (\\tfrac12 - \\beta) a_n + h^2 \\beta a_{n+1}
                   \\; [+\\, G(q_n, t_n)^T \\mu_{n+1}], \\\\
        v_{n+1} &= v_n + h (1 - \\gamma) a_n + h \\gamma a_{n+1}, \\\\
        (1 - \\alpha_m) a_{n+1} + \\alpha_m a_n &= (1 - \\alpha_f) \\ddot q_{n+1}
                   + \\alpha_f \\ddot q_n, \\\\
        M(q_{n+1}) \\ddot q_{n+1} &= f(t_{n+1}, q_{n+1}, v_{n+1})
                   - G(q_{n+1}, t_{n+1})^T \\lambda_{n+1}, \\\\
        0 &= g(q_{n+1}, t_{n+1}) \\; [,\\quad 0 = G(q_{n+1}, t_{n+1}) v_{n+1}
                   + g_t(q_{n+1}, t_{n+1})],

    with ``f`` the full right-hand side (:meth:`Mechanics.force`) and ``a`` the
    acceleration-like variable. ``formulation = "index3"`` omits the bracketed terms: the
    index-3 form of Arnold and Bruls, which enforces ``g = 0`` at every step end but not
    ``G v + g_t = 0``. ``formulation = "ggl"`` is the stabilised index-2 form of Arnold,
    Bruls and Cardona (2015, Numer. Math. 129:149-179) in the manner of Gear, Gupta and
    Leimkuhler: a second multiplier ``mu`` corrects the positions so that ``g = 0`` and
    ``G v + g_t = 0`` both hold at every step end. ``mu`` is O(h^3) on a smooth solution,
    so evaluating its direction at ``q_n`` (which keeps ``q_{n+1}`` explicit in the
    unknowns) changes the step by O(h^4). The starting values ``a_0 = \\ddot q_0`` and
    ``lambda_0`` solve the index-1 system at ``t_0``.

    The parameters follow from the spectral radius at infinity ``rho_inf`` in [0, 1] as in
    Chung and Hulbert (1993): ``alpha_m = (2 rho - 1)/(rho + 1)``,
    ``alpha_f = rho/(rho + 1)``, ``gamma = 1/2 - alpha_m + alpha_f``,
    ``beta = (gamma + 1/2)^2 / 4``. ``rho_inf = 1`` is the trapezoidal rule (Newmark's
    average acceleration), without numerical damping; ``rho_inf < 1`` damps the
    frequencies the step does not resolve and the resolved ones by O((omega h)^3) per
    period, so that the energy of a conservative system decays. The method is not
    symplectic. Order 2 in ``q`` and ``v``. Hilber, Hughes and Taylor's method is the
    family's member with ``alpha_m = 0`` (:class:`HHT`).

    In the index-3 form the constraint directions behave as infinitely stiff modes: their
    errors propagate with the double eigenvalue ``-rho_inf`` of the method at infinite
    frequency (Arnold and Bruls 2007). For ``rho_inf = 1`` that is a Jordan block on the
    unit circle, and on a curved constraint the errors grow until the run breaks down, as
    Cardona and Geradin (1989, Comput. Struct. 33:801-820) found for the trapezoidal rule
    on index-3 equations. On the pendulum A01 the growth is exponential at a rate per unit
    time that a smaller step does not reduce: at h = 0.01 the run fails at t = 84.7 s
    (its energy is already wrong by 1e7 at t = 8 s), at h = 1e-3 at t = 8.9 s. Close to 1
    the step must be small: on the pendulum at h = 0.01, ``rho_inf = 0.99`` does not fail
    but its energy error reaches 2e6 by t = 200 s; on sps-receiver ``rho_inf = 0.9`` fails
    at h = 0.05 and 0.8 diverges at h = 0.1, while 0.5 stays stable up to h = 0.2. The
    index-2 form is stable on the same runs for every ``rho_inf`` tried (0, 0.5, 0.9, 0.99
    and 1).

    The position constraint also makes the index-3 accelerations and multipliers absorb
    the O(h^3) position error of each step: they are off by O(h) in the first steps, with
    alternating signs, until the ``-rho_inf`` mode has decayed (on the pendulum started
    in motion, by 0.10, 0.19, 0.28 and 0.36 in the first four steps for a multiplier near
    2.9, at h = 0.01 and ``rho_inf = 0.9``). The index-2 form determines the accelerations
    through the velocity constraint instead and has no such transient (Arnold, Bruls and
    Cardona 2015); what remains at its start is the O((alpha_m - alpha_f) h) error of
    ``a_0 = \\ddot q_0``, 0.0035 in the same run.

    The step equations are solved by Newton's method with the autodiff Jacobian for
    ``x = beta h^2 a_{n+1}``, ``Lambda = beta h^2 lambda_{n+1}`` (and ``mu``), of which
    ``q_{n+1}``, ``v_{n+1}`` and ``\\ddot q_{n+1}`` are affine functions. With the
    equations of motion multiplied by ``beta h^2`` and the velocity constraint by
    ``beta h / gamma`` (the scalings of Bottasso, Bauchau and Cardona 2007, SIAM J. Sci.
    Comput. 29:397-414) the iteration matrix tends to ``[c M, G^T; G, 0]`` (index 3) or
    ``[c M, G^T, 0; G, 0, G G^T; G, 0, 0]`` (index 2), ``c = (1 - alpha_m)/(1 -
    alpha_f)``, as ``h -> 0`` instead of growing like ``1/h^2``, and its blocks are ``M``,
    ``G`` and the force Jacobians; the structured path solves with that matrix. The
    residual that Newton's stop measures has those two rows multiplied by ``gamma / (beta
    h)`` more, into the units of ``v`` (:func:`velocity_scale`), which leaves the
    correction unchanged (the dense path's LU solves the row-scaled system). With the
    increment-like unknown ``x``, not ``q_{n+1}``, the velocities do not inherit the
    round-off of ``q`` magnified by ``1/h``.

    Parameters
    ----------
    h : float
        Step size (shrunk to divide the horizon evenly).
    rho_inf : float
        Spectral radius at infinity, in [0, 1]. The default 0.5 keeps the index-3 form
        stable on every problem and step of the suites (see above); both forms share it
        so that they differ in the formulation alone.
    formulation : {"index3", "ggl"}
        Index-3 form, or the stabilised index-2 form.
    newton_tol : float
        Max-norm tolerance of the scaled residual: it bounds ``|g|``, ``gamma h`` times
        the residual of the equations of motion (about ``M`` times the change of ``v``
        that it leaves) and, for ``ggl``, ``|G v + g_t|``. The default 1e-16 iterates to
        round-off at every ``h`` (see :func:`integrators.newton.newton`).
    newton_max_iter : int
        Newton iteration limit per step; exceeding it fails the run.
    linear_solver : {"auto", "dense", "banded", "superlu", "kkt"}
        Linear algebra (:func:`linalg.schur.choose`): large sparse systems use simplified
        Newton through ``G M^{-1} G^T`` and, for ``ggl``, ``G G^T`` (:meth:`simplified`).
    """

    h: float = 0.01
    rho_inf: float = 0.5
    formulation: str = "index3"
    newton_tol: float = 1e-16
    newton_max_iter: int = 20
    linear_solver: str = "auto"

    def coefficients(self) -> Coefficients:
        return Coefficients.from_rho_inf(self.rho_inf)

    def check(self) -> None:
        super().check()
        if not 0.0 <= self.rho_inf <= 1.0:
            raise ValueError(f"GeneralizedAlpha: rho_inf = {self.rho_inf} must lie in [0, 1]")


@dataclass(frozen=True)
class HHT(AlphaMethod):
    """Hilber, Hughes and Taylor's alpha method (HHT-alpha, 1977, Earthquake Eng. Struct.
    Dyn. 5:283-292) as the member of the generalized-alpha family with ``alpha_m = 0``.

    For a linear system ``M \\ddot q + K q = F`` HHT's step is Newmark's with
    ``gamma = 1/2 - alpha`` and ``beta = (1 - alpha)^2 / 4`` and the equation of motion

    .. math::

        M a_{n+1} + (1 + \\alpha) K q_{n+1} - \\alpha K q_n = F(t_{n+1 + \\alpha}),
        \\qquad \\alpha \\in [-1/3, 0],

    which is :class:`GeneralizedAlpha`'s step with

    .. math::

        \\alpha_m = 0, \\quad \\alpha_f = -\\alpha, \\quad \\gamma = \\tfrac12 - \\alpha,
        \\quad \\beta = \\tfrac14 (1 - \\alpha)^2

    (Chung and Hulbert 1993; :meth:`Coefficients.hht`). For constrained and nonlinear
    systems the step is Arnold and Bruls's (2007, Multibody Syst. Dyn. 18:185-202) form of
    the family, which averages accelerations, ``a_{n+1} = (1 + alpha) \\ddot q_{n+1} -
    alpha \\ddot q_n``, and imposes the equations of motion and the constraints at
    ``t_{n+1}``; for the linear system above it is HHT's method exactly. Order 2 in ``q``
    and ``v`` for every ``alpha`` (the second-order condition ``gamma = 1/2 - alpha_m +
    alpha_f`` holds); not symplectic. The spectral radius at infinity is ``rho_inf =
    (1 + alpha) / (1 - alpha)``, from 1 at ``alpha = 0`` down to 1/2 at ``alpha = -1/3``.

    Two members coincide with members of Chung and Hulbert's one-parameter choice:
    ``alpha = 0`` is the trapezoidal rule (Newmark's average acceleration), the method of
    ``GeneralizedAlpha`` with ``rho_inf = 1`` (whose ``alpha_m = alpha_f = 1/2`` make
    ``a = \\ddot q`` at every step), and ``alpha = -1/3`` is ``rho_inf = 1/2``
    (``alpha_m = 0``, ``alpha_f = 1/3`` there too). In between, HHT damps the resolved
    frequencies more than Chung and Hulbert's choice for the same ``rho_inf``.

    The registry key ``hht`` is the index-3 form, as in multibody codes (Negrut, Rampalli,
    Ottarsson and Sajdak 2007, J. Comput. Nonlinear Dyn. 2:73-85, the HHT integrator of
    Adams Solver): ``g = 0`` at every step end, ``G v + g_t = 0`` not enforced. Its
    constraint errors propagate with the method's eigenvalues at infinite frequency, so
    the index-3 form inherits the instability that :class:`GeneralizedAlpha` describes
    for ``rho_inf`` near 1 as ``alpha`` approaches 0; ``formulation = "ggl"`` gives the
    stabilised index-2 form.

    Parameters
    ----------
    h : float
        Step size (shrunk to divide the horizon evenly).
    alpha : float
        HHT's parameter, in [-1/3, 0]. The default -0.3 is Adams Solver's default for its
        index-3 HHT integrator; its ``rho_inf`` = 0.54 is close to the 0.5 that keeps
        :class:`GeneralizedAlpha`'s index-3 form stable on every problem of the suites.
    formulation, newton_tol, newton_max_iter, linear_solver
        As for :class:`GeneralizedAlpha`.
    """

    h: float = 0.01
    alpha: float = -0.3
    formulation: str = "index3"
    newton_tol: float = 1e-16
    newton_max_iter: int = 20
    linear_solver: str = "auto"

    def coefficients(self) -> Coefficients:
        return Coefficients.hht(self.alpha)

    def check(self) -> None:
        super().check()
        if not -1.0 / 3.0 <= self.alpha <= 0.0:
            raise ValueError(f"HHT: alpha = {self.alpha} must lie in [-1/3, 0]")
