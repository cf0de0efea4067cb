"""Baumgarte-stabilised explicit Runge-Kutta methods (diffrax tableaus, our own step loop).

The constrained equations are replaced by the ODE ``q' = v``, ``M(q) v' = f - G^T lam`` with
``lam`` chosen so that the constraint obeys the damped equation of Baumgarte (1972)

.. math::

    \\ddot g + 2 \\alpha \\dot g + \\beta^2 g = 0, \\qquad
    G M^{-1} (f - G^T \\lambda) + \\gamma = -2 \\alpha (G v + g_t) - \\beta^2 g,

(:meth:`Mechanics.accelerations` with ``stab = 2 alpha (G v + g_t) + beta^2 g``: one
Cholesky factorisation of the m x m matrix ``G M^{-1} G^T`` per evaluation). The exact
solution keeps ``g = 0``; numerical drift off it decays instead of accumulating.

The time loop is ours, compiled with ``lax.while_loop`` around an explicit Runge-Kutta step
with diffrax's Butcher tableaus (:func:`erk_step`) and diffrax's
``PIDController.adapt_step_size`` (the controller of diffrax's own loop), so that every
accepted step is measured without storing the steps: the loop keeps the per-window maxima
and the sampled states of :class:`integrators.record.Recorder`'s layout inside itself
(:func:`integrators.record.tracker`), and a run is one call of it, whatever its length.

An ensemble of the adaptive pairs (:meth:`BaumgarteEmbeddedRK.prepare_ensemble`) runs the
same loop under ``jax.vmap`` (:func:`run_lanes`): each lane has its own time, step size,
controller state, counters, failure code, windows and samples, so memory is bounded per
lane. The vmapped ``while_loop`` runs until the last lane has ended; a lane
that has ended (at ``t_end``, on a failure, at ``max_steps``) is carried unchanged, so a
lane that fails stops only itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache, partial
from typing import Any, ClassVar, NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix

from integrators.base import Failure, Grid, Integrator, Trajectory
from integrators.fixed import FixedStep
from integrators.loop import CACHE_SIZE
from integrators.record import Tally, ended, kept, series, series_names, tracker
from linalg.compiled import compile_lifted, equations
from problems.case import Case
from problems.mechanics import Mechanics


class ClassicalRK4(diffrax.AbstractERK):
    """Kutta's classical four-stage method of order 4, for fixed steps only.

    It has no embedded error estimate (the error weights are zero), so it cannot drive a
    step-size controller.
    """

    tableau: ClassVar[diffrax.ButcherTableau] = diffrax.ButcherTableau(
        c=np.array([0.5, 0.5, 1.0]),
        a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
        b_sol=np.array([1.0, 2.0, 2.0, 1.0]) / 6.0,
        b_error=np.zeros(4),
    )
    interpolation_cls: ClassVar[Any] = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 4


#: ``solver`` option -> diffrax solver class.
SOLVERS: dict[str, type[diffrax.AbstractERK]] = {
    "rk4": ClassicalRK4,
    "tsit5": diffrax.Tsit5,
    "dopri5": diffrax.Dopri5,
    "dopri8": diffrax.Dopri8,
}

def baumgarte_field(mech: Mechanics, alpha: float, beta: float, schur=None):
    """The stabilised first-order ODE ``y' = (v, a)`` for ``y = (q, v)``.

    ``schur`` solves with ``G M^{-1} G^T`` (:meth:`Mechanics.schur`; default dense).
    """
    n = mech.n

    def field(t, y, args):
        q, v = y[:n], y[n:]
        stab = 2.0 * alpha * mech.vel_residual(q, v, t) + beta * beta * mech.g(q, t)
        a, _ = mech.accelerations(t, q, v, stab=stab, schur=schur)
        return jnp.concatenate([v, a])

    return field


#: Equations of the stabilised field (its jaxpr's, nested ones counted) from which
#: :func:`erk_step` evaluates the stages in a loop instead of one after another.
ROLL_EQUATIONS = 800


def erk_step(tableau: diffrax.ButcherTableau, field, t0, t1, y0, f0):
    """One explicit Runge-Kutta step of ``tableau`` from ``(t0, y0)`` to ``t1``.

    With ``dt = t1 - t0`` and ``f_1 = f0``, the stages are
    ``f_i = field(t0 + c_i dt, y0 + dt sum_j a_ij f_j)`` (``t1`` where ``c_i = 1``), the
    solution ``y1 = y0 + sum_i b_i (dt f_i)`` (the last stage's point where the tableau is
    stiffly accurate, ``b = a_s``), the error estimate ``sum_i e_i (dt f_i)``: diffrax's
    ``AbstractERK.step`` for an ODE term, whose stage values are formed the same way.

    The stages are written out one after another for XLA to fuse: diffrax runs them in a
    loop with the stage values in buffers, which is an inner loop per step; straight-line
    stages cost a fraction of that for the small systems, and the same arithmetic. A field
    of :data:`ROLL_EQUATIONS` or more is evaluated in such a loop instead: each written-out
    stage is a copy of the field in the program, and for a large field (dopri8's twelve
    copies of a flexible body's) compiling them costs seconds that the loop saves, while
    the loop's own cost per stage is small beside the field's; below that size the loop
    costs more per step than the fusion of written-out stages saves. The sums are the same
    in either form, term by term in the same order (a zero coefficient adds an exact zero),
    and XLA may round them differently.

    Returns ``(y1, y_error, f_last)``: ``f_last`` is the last stage, ``field(t1, y1)`` for a
    first-same-as-last tableau (the next step's ``f0``).
    """
    dt = t1 - t0
    first = field(t0, y0, None) if f0 is None else f0
    if sum(1 for _ in equations(jax.make_jaxpr(field)(t0, y0, None).jaxpr)) < ROLL_EQUATIONS:
        fs = [first]
        for a_i, c_i in zip(tableau.a_lower, tableau.c):
            # Zero coefficients are left out: each would add an exact zero.
            y = y0 + dt * sum(float(a) * f for a, f in zip(a_i, fs) if a != 0)
            fs.append(field(t1 if c_i == 1 else t0 + float(c_i) * dt, y, None))
    else:
        fs, y = rolled_stages(tableau, field, t0, t1, dt, y0, first)
    ks = [dt * f for f in fs]
    if not tableau.ssal:
        y = y0 + sum(float(b) * k for b, k in zip(tableau.b_sol, ks) if b != 0)
    y_error = sum(float(e) * k for e, k in zip(tableau.b_error, ks) if e != 0)
    if isinstance(y_error, int):
        y_error = jnp.zeros_like(y0)
    return y, y_error, fs[-1]


def rolled_stages(tableau: diffrax.ButcherTableau, field, t0, t1, dt, y0, first):
    """The stages ``f_1 ... f_s`` of :func:`erk_step` and the last stage's point, evaluated
    in a ``lax.fori_loop`` with the stage values in one buffer, the coefficients of each
    stage's row read from a table."""
    s = tableau.num_stages
    a = np.zeros((s, s))
    for i, a_i in enumerate(tableau.a_lower):
        a[i + 1, :i + 1] = a_i
    c = np.concatenate([[0.0], tableau.c])

    def stage(i, carry):
        fs, _ = carry
        row = jnp.asarray(a)[i]
        total = row[0] * fs[0]
        for j in range(1, s - 1):
            total = total + row[j] * fs[j]
        y = y0 + dt * total
        ci = jnp.asarray(c)[i]
        return fs.at[i].set(field(jnp.where(ci == 1, t1, t0 + ci * dt), y, None)), y

    fs = jnp.zeros((s,) + y0.shape, y0.dtype).at[0].set(first)
    fs, y = jax.lax.fori_loop(1, s, stage, (fs, y0))
    return [fs[i] for i in range(s)], y


def first_stage(solver, field, t0, y0):
    """The ``f0`` of the first :func:`erk_step`: ``field(t0, y0)`` for a first-same-as-last
    tableau, whose later steps reuse their last stage; ``None`` otherwise (evaluated in
    every step)."""
    return field(t0, y0, None) if solver.tableau.fsal else None


class LoopState(NamedTuple):
    """State of the step loop between attempts."""

    t: jax.Array
    t_next: jax.Array
    y: jax.Array
    solver_state: Any
    controller_state: Any
    n_accepted: jax.Array
    n_rejected: jax.Array
    n_attempts: jax.Array
    code: jax.Array


class FixedSteps(NamedTuple):
    """Equal steps ``h = (t_end - t0) / N`` on the grid ``t_k = t0 + k h`` (``t_N = t_end``).

    ``N`` comes in ``params["n_steps"]`` (traced), so one compiled loop serves every ``h``.
    """

    t0: float
    t_end: float

    #: Vector-field evaluations before the first step.
    initial_evals: ClassVar[int] = 0

    def init(self, term, solver, y0, params):
        return self.grid_time(params, 1), None

    def grid_time(self, params, k):
        n_steps = params["n_steps"]
        h = (self.t_end - self.t0) / n_steps
        return jnp.where(k >= n_steps, self.t_end, self.t0 + k * h)

    def adapt(self, params, state: LoopState, y1, y_error, error_order):
        return (jnp.asarray(True), state.t_next, self.grid_time(params, state.n_accepted + 2),
                None)


class EmbeddedControl(NamedTuple):
    """diffrax's PID controller on the embedded error estimate, clipped to ``t_end``.

    The controller's settings come in ``params`` (traced), so one compiled loop serves
    every tolerance.
    """

    t0: float
    t_end: float
    automatic_dt0: bool

    @property
    def initial_evals(self) -> int:
        """The automatic initial step (Hairer, Norsett and Wanner's) costs 2 evaluations."""
        return 2 if self.automatic_dt0 else 0

    @staticmethod
    def pid(params) -> diffrax.PIDController:
        return diffrax.PIDController(
            rtol=params["rtol"], atol=params["atol"], norm=optimistix.rms_norm,
            pcoeff=params["pcoeff"], icoeff=params["icoeff"], dcoeff=params["dcoeff"],
            dtmin=None, dtmax=params["dtmax"], force_dtmin=True,
            factormin=params["factormin"], factormax=params["factormax"],
            safety=params["safety"])

    def init(self, term, solver, y0, params):
        dt0 = None if self.automatic_dt0 else params["dt0"]
        t_next, state = self.pid(params).init(term, self.t0, self.t_end, y0, dt0, None,
                                              solver.func, solver.error_order(term))
        return jnp.minimum(t_next, self.t_end), state

    def adapt(self, params, state: LoopState, y1, y_error, error_order):
        # As in diffrax's loop: a NaN error estimate (a non-finite attempt) rejects.
        y_error = jnp.where(jnp.isnan(y_error), jnp.inf, y_error)
        keep, t_new, t_next, _, cstate, _ = self.pid(params).adapt_step_size(
            state.t, state.t_next, state.y, y1, None, y_error, error_order,
            state.controller_state)
        t_new = jnp.minimum(t_new, self.t_end)
        # Also as diffrax: an attempt that would end within 100 ulp of t_end ends at t_end,
        # so that no sliver step is left over; a retry then halves the distance instead.
        floor = self.t_end - 100 * np.spacing(self.t_end)
        t_next = jnp.where(t_next > floor,
                           jnp.where(keep, self.t_end, t_new + 0.5 * (self.t_end - t_new)),
                           t_next)
        return keep, t_new, t_next, cstate


def _term(mech: Mechanics, schur, params) -> diffrax.ODETerm:
    return diffrax.ODETerm(baumgarte_field(mech, params["alpha"], params["beta"], schur))


@partial(jax.jit, static_argnames=("mech", "schur", "solver", "control"))
def initial_state(y0, params, *, mech, schur, solver, control) -> LoopState:
    """The loop state at ``t0``: first attempt's end, first stage and controller state."""
    term = _term(mech, schur, params)
    t_next, cstate = control.init(term, solver, y0, params)
    t0 = jnp.asarray(control.t0, dtype=jnp.float64)
    sstate = first_stage(solver, term.vector_field, t0, y0)
    zero = jnp.zeros((), jnp.int64)
    return LoopState(t0, jnp.asarray(t_next, jnp.float64), y0, sstate, cstate, zero, zero,
                     zero, jnp.zeros((), jnp.int32))


def running(st: LoopState, t_end: float, max_steps) -> jax.Array:
    """Whether a run goes on from ``st``: before ``t_end``, no failure, fewer than
    ``max_steps`` accepted steps."""
    return (st.t < t_end) & (st.code == 0) & (st.n_accepted < max_steps)


def attempt(term, solver, control, params, error_order, st: LoopState
            ) -> tuple[LoopState, jax.Array]:
    """One step attempt (:func:`erk_step`) from ``st``: the next loop state and whether
    the step was accepted (then the state's ``t`` and ``y`` are the new point; otherwise
    they are unchanged and ``code`` says whether the attempt failed)."""
    tiny = 16 * np.finfo(np.float64).eps
    y1, y_error, f_last = erk_step(solver.tableau, term.vector_field, st.t, st.t_next, st.y,
                                   st.solver_state)
    sstate = f_last if solver.tableau.fsal else None
    keep, t_new, t_next, cstate = control.adapt(params, st, y1, y_error, error_order)
    finite = jnp.all(jnp.isfinite(y1))
    underflow = ~keep & (t_next - st.t <= tiny * jnp.maximum(1.0, jnp.abs(st.t)))
    code = jnp.where(keep & ~finite, Failure.NON_FINITE,
                     jnp.where(underflow, Failure.UNDERFLOW, Failure.NONE))
    accept = keep & (code == 0)

    def pick(new, old):
        return jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, old)

    return LoopState(
        # A failed attempt keeps its end time, for the message.
        t=jnp.where(accept, t_new, st.t), t_next=jnp.where(code == 0, t_next, st.t_next),
        y=pick(y1, st.y),
        solver_state=pick(sstate, st.solver_state), controller_state=cstate,
        n_accepted=st.n_accepted + accept, n_rejected=st.n_rejected + ~keep,
        n_attempts=st.n_attempts + 1, code=code.astype(jnp.int32)), accept


def run(state: LoopState, params, *, mech, schur, solver, control, grid):
    """Make step attempts from ``state`` until the run ends, in one compiled loop.

    Returns ``(state, tally)``: the final loop state and the windows and samples
    (:class:`integrators.record.Tally`) of every accepted step, measured inside the loop
    (:func:`integrators.record.tracker`). The run ends at ``t_end``, on a failure code, or
    after ``params["max_steps"]`` accepted steps. Static arguments are hashable (the
    problem's :class:`Mechanics` by identity) and every option is in ``params``, so one
    compilation serves every run of the same system, solver, horizon and grid.
    """
    term = _term(mech, schur, params)
    error_order = solver.error_order(term)
    start, add = tracker(mech, grid)
    n = mech.n

    def cond(carry):
        return running(carry[0], control.t_end, params["max_steps"])

    def body(carry):
        st, tally = carry
        st, accept = attempt(term, solver, control, params, error_order, st)
        return st, add(tally, accept, st.t, st.y[:n], st.y[n:])

    tally = start(state.t, state.y[:n], state.y[n:])
    return jax.lax.while_loop(cond, body, (state, tally))


STATIC = ("mech", "schur", "solver", "control", "grid")

#: One run (:func:`run`), compiled.
run_one = jax.jit(run, static_argnames=STATIC)


@partial(jax.jit, static_argnames=STATIC)
def run_packed(state: LoopState, params, *, mech, schur, solver, control, grid):
    """:func:`run` with its results (some twenty arrays: state, counters, windows,
    samples) stacked into one float64 vector (:func:`unpack` on the host): one transfer to
    the host instead of one per array, each of which has a fixed cost of its own, most of
    a short run's. The counters and flags are exact in float64 (below ``2^53``)."""
    out = run(state, params, mech=mech, schur=schur, solver=solver, control=control,
              grid=grid)
    return jnp.concatenate([jnp.ravel(x).astype(jnp.float64)
                            for x in jax.tree_util.tree_leaves(out)])


def unpack(flat: np.ndarray, like):
    """The results of :func:`run` from :func:`run_packed`'s vector ``flat``, as host
    arrays shaped and typed as ``like`` (their shapes and dtypes)."""
    leaves, tree = jax.tree_util.tree_flatten(like)
    out, start = [], 0
    for x in leaves:
        out.append(flat[start:start + x.size].reshape(x.shape).astype(x.dtype, copy=False))
        start += x.size
    return jax.tree_util.tree_unflatten(tree, out)


@partial(jax.jit, static_argnames=STATIC)
def run_lanes(states: LoopState, params, *, mech, schur, solver, control, grid):
    """:func:`run` for every lane of ``states`` (a :class:`LoopState` with a leading lane
    axis), in one compiled loop under ``jax.vmap``: ``(states, tallies)``."""
    return jax.vmap(partial(run, params=params, mech=mech, schur=schur, solver=solver,
                            control=control, grid=grid))(states)


def _static(mech: Mechanics, params: dict, max_steps: int, solver, control,
            linear_solver: str) -> tuple[dict, dict, dict]:
    """The traced options (``params`` as float64 arrays, ``max_steps`` among them), the
    static arguments of the compiled loops and what the record says of the linear solver."""
    params = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in params.items()}
    params["max_steps"] = jnp.asarray(max_steps, dtype=jnp.int64)
    schur = mech.schur(linear_solver)
    return (params, dict(mech=mech, schur=schur, solver=solver, control=control),
            dict(linear_solver=schur.name, pattern_nnz=schur.nnz))


def _trajectory(state: LoopState, tally: Tally, names: list[str], solver, control,
                max_steps: int, grid: Grid, sampling: str, solver_record: dict) -> Trajectory:
    """The :class:`~integrators.base.Trajectory` of a run that ended in ``state`` with the
    record ``tally`` of the series ``names`` (host values): its failure message, if any,
    and its work counters."""
    assert state.y.dtype == np.float64, "the loop must run in float64"
    code, t = int(state.code), float(state.t)
    steps, attempts = int(state.n_accepted), int(state.n_attempts)
    tableau = solver.tableau
    fsal = int(tableau.fsal)
    # Per attempt every stage but an FSAL method's first (reused from the last accepted
    # step) is evaluated; an FSAL method evaluates its first stage once.
    evals = control.initial_evals + fsal + attempts * (tableau.num_stages - fsal)
    counts = {"n_steps": steps, "n_rejected": int(state.n_rejected), "n_f_evals": evals,
              "n_jac_evals": 0, "n_newton": 0, "n_lin_solves": evals}
    if code == 0 and t < grid.t_end:
        code = Failure.MAX_STEPS
    message = ""
    if code:
        what = Failure(code).message.format(max_steps=max_steps, t_end=grid.t_end)
        message = f"{what}; at step {steps + 1} (t = {t:.6g} -> {float(state.t_next):.6g})"
    n = state.y.shape[0] // 2
    return ended(message, t, state.y[:n], state.y[n:], counts, sampling,
                 series(grid, names, tally.wins, tally.hit),
                 kept(tally.samp_t, tally.samp_q, tally.samp_v, tally.filled), **solver_record)


def _aval(a: jax.Array) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(a.shape, a.dtype)


@lru_cache(maxsize=CACHE_SIZE)
def _compiled(grid: Grid, static: tuple, y0: jax.ShapeDtypeStruct, params: tuple):
    """:func:`initial_state` and :func:`run_packed` compiled for the static arguments
    ``static`` (as items) and arguments of the types ``y0`` and ``params`` (as items), and
    the shapes of the loop's outputs; kept for the last :data:`CACHE_SIZE` of them, so that
    a tolerance sweep, or another run of the same method, traces nothing again."""
    static, params = dict(static), dict(params)
    begin = compile_lifted(initial_state, y0, params, **static)
    state0 = jax.eval_shape(partial(initial_state, **static), y0, params)
    loop = compile_lifted(run_packed, state0, params, grid=grid, **static)
    return begin, loop, jax.eval_shape(partial(run_one, grid=grid, **static), state0, params)


def drive(mech: Mechanics, grid: Grid, y0: np.ndarray, solver, control, params: dict,
          max_steps: int, sampling: str, linear_solver: str = "auto"):
    """Compile the loop (:func:`run`) and return ``solve()``, which runs it from ``y0``
    and returns the :class:`~integrators.base.Trajectory`."""
    params, static, solver_record = _static(mech, params, max_steps, solver, control,
                                            linear_solver)
    y0_device = jnp.asarray(y0)
    begin, compiled, like = _compiled(grid, tuple(static.items()), _aval(y0_device),
                                      tuple((k, _aval(v)) for k, v in params.items()))
    state0 = begin(y0_device, params)
    names = series_names(mech)

    def solve():
        state, tally = unpack(np.asarray(compiled(state0, params)), like)
        return _trajectory(state, tally, names, solver, control, max_steps, grid, sampling,
                           solver_record)

    return solve


def drive_lanes(mech: Mechanics, grid: Grid, y0s: np.ndarray, solver, control,
                params: dict, max_steps: int, sampling: str, linear_solver: str = "auto"):
    """Compile the loop of an ensemble from the initial states ``y0s`` (one row per lane)
    and return ``solve()``, which runs it (:func:`run_lanes`) and returns one
    :class:`~integrators.base.Trajectory` per lane, as :func:`drive` would for that lane."""
    params, static, solver_record = _static(mech, params, max_steps, solver, control,
                                            linear_solver)
    states0 = jax.vmap(partial(initial_state, **static), in_axes=(0, None))(
        jnp.asarray(y0s, jnp.float64), params)
    compiled = run_lanes.lower(states0, params, grid=grid, **static).compile()
    names = series_names(mech)

    def solve():
        states, tallies = jax.device_get(compiled(states0, params))
        return [_trajectory(*jax.tree_util.tree_map(lambda a: a[i], (states, tallies)),
                            names, solver, control, max_steps, grid, sampling, solver_record)
                for i in range(len(states.t))]

    return solve


@dataclass(frozen=True)
class BaumgarteBase(Integrator):
    """Options shared by the fixed-step and the adaptive Baumgarte methods."""

    solver: str = "rk4"
    alpha: float = 3.0
    beta: float = 3.0
    linear_solver: str = "auto"

    family: ClassVar[str] = "Baumgarte explicit RK"

    @property
    def nominal_order(self) -> int:
        return SOLVERS[self.solver]().order(None)

    def check(self) -> None:
        super().check()
        name = type(self).__name__
        self.check_choice("solver", SOLVERS)
        for option in ("alpha", "beta"):
            value = getattr(self, option)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: {option} = {value} must be finite and >= 0")


@dataclass(frozen=True)
class BaumgarteRK(BaumgarteBase, FixedStep):
    """Baumgarte-stabilised explicit Runge-Kutta method with a fixed step.

    Integrates ``q' = v``, ``v' = a(t, q, v)`` with the accelerations of the module
    docstring, ``G a + gamma = -2 alpha (G v + g_t) - beta^2 g``. Order of the Runge-Kutta
    method (4 for ``rk4``, Kutta's classical method); not symplectic. Enforces no
    constraint level exactly: drift off ``g = 0`` and ``G v + g_t = 0`` is damped at the
    rate of ``ddot g + 2 alpha dot g + beta^2 g = 0``. ``alpha = beta = 0`` is the
    unstabilised index-1 ODE, whose drift grows without bound.

    **Defaults** ``alpha = beta = 3`` (1/s): critically damped (double root ``-3``), so
    drift decays without overshoot with time constant 1/3 s, on the scale of the fastest
    motion of the suite's problems (pendulum ``sqrt(g0/L) = 3.13``/s). Larger values do not
    pay: the stabilised field's derivatives grow like powers of ``beta``, and with them the
    methods' error constants. Measured over ``alpha = beta`` in {0, 1, 2, 3, 5, 10, 20} on
    ``pendulum`` (100 s) and ``sps-receiver`` (50 s), with rk4 at h = 0.01, tsit5 at
    rtol = 1e-8, dopri5 at 1e-6 and dopri8 at 1e-10: 3 lowered max ``|g|`` by 3.5 to 4.8
    orders of magnitude against ``alpha = beta = 0`` for every method, at 8-27 % more steps
    for the adaptive ones. Larger values lowered ``|g|`` further only for the adaptive
    methods, and at a price in steps (10 needed 1.6x (dopri8) and 1.5x (tsit5) the steps of
    3 on ``pendulum``); for rk4 they made ``|g|`` and the final error larger (7x and 17x
    at 10). RK4's real stability interval (2.78) allows ``h < 0.9`` for ``beta = 3``.

    Counts: ``n_f_evals`` vector-field evaluations (the stages: 4 per step for rk4), each
    one factorisation and solve of ``G M^{-1} G^T`` (``n_lin_solves``; dense Cholesky, or
    the structured solver chosen by ``linear_solver``, :mod:`linalg`); no
    Newton iterations.
    Measured at every step.

    Parameters
    ----------
    h : float
        Step size (shrunk to divide the horizon evenly).
    solver : str
        Key of :data:`SOLVERS` (the embedded error estimate, if any, is unused).
    alpha, beta : float
        Baumgarte damping and stiffness (1/s).
    linear_solver : {"auto", "dense", "banded", "superlu", "kkt"}
        How ``G M^{-1} G^T`` is solved (:func:`linalg.schur.choose`).
    """

    h: float = 0.01

    def term(self, mech: Mechanics, schur) -> diffrax.ODETerm:
        """The stabilised field as diffrax's term."""
        return diffrax.ODETerm(baumgarte_field(mech, self.alpha, self.beta, schur))

    def start(self, mech: Mechanics, schur, q0, v0, t0):
        """``(y, f0)`` with ``y = (q, v)`` (``f0`` is ``None`` but for an FSAL tableau,
        whose first stage it holds: :func:`first_stage`)."""
        y0 = jnp.concatenate([q0, v0])
        solver = SOLVERS[self.solver]()
        return y0, first_stage(solver, self.term(mech, schur).vector_field, t0, y0)

    def step(self, mech: Mechanics, schur, carry, t, h):
        """One :func:`erk_step` (:class:`integrators.fixed.FixedStep`); an explicit step
        cannot fail, a non-finite state is the loop's to find."""
        y, f0 = carry
        tableau = SOLVERS[self.solver].tableau
        y1, _, f_last = erk_step(tableau, self.term(mech, schur).vector_field, t, t + h, y, f0)
        stages = tableau.num_stages - int(tableau.fsal)
        return ((y1, f_last if tableau.fsal else None), jnp.asarray(Failure.NONE),
                jnp.asarray(0.0), {"n_f_evals": stages, "n_lin_solves": stages})

    def observe(self, mech: Mechanics, carry):
        """``(q, v)``."""
        return carry[0][:mech.n], carry[0][mech.n:]

    def prepare(self, case: Case, grid: Grid):
        # The diffrax-driven loop that the adaptive pairs share, not the fixed-step loop
        # (integrators.loop), which the same start/step/observe would run too: this one
        # steps with dt = t_{k+1} - t_k and ends at t_end exactly, so the fixed-step loop
        # changes its results at round-off (q after 200 steps on the pendulum by 5e-15)
        # and lays its windows out by step count instead of by time.
        self.check()
        n_steps = max(1, math.ceil((grid.t_end - grid.t0) / self.h * (1 - 1e-12)))
        control = FixedSteps(float(grid.t0), float(grid.t_end))
        y0 = np.concatenate([case.q0, case.v0])
        params = {"alpha": self.alpha, "beta": self.beta, "n_steps": n_steps}
        return drive(case.mech, grid, y0, SOLVERS[self.solver](), control, params, n_steps,
                     "every step", self.linear_solver)


@dataclass(frozen=True)
class BaumgarteEmbeddedRK(BaumgarteBase):
    """Baumgarte-stabilised embedded explicit Runge-Kutta pair with PID step control.

    The stabilised ODE of :class:`BaumgarteRK` (same ``alpha``, ``beta`` and their
    defaults' justification) integrated by a diffrax embedded pair: ``tsit5``
    (Tsitouras 5(4)), ``dopri5`` (Dormand-Prince 5(4)) or ``dopri8`` (Dormand-Prince
    8(7)); order 5, 5 and 8, not symplectic, no constraint level enforced exactly.

    Step control is diffrax's ``PIDController`` with every setting given here: the error
    ``||err_i / (atol + rtol max(|y0_i|, |y1_i|))||_RMS`` over ``y = (q, v)`` decides
    acceptance (``< 1``) and the next step ``h * safety * err^{-(icoeff + pcoeff +
    dcoeff)/k} * ...`` clipped to ``[factormin, factormax]`` (``k`` the solver's error
    order). Defaults ``pcoeff = dcoeff = 0, icoeff = 1`` are the classical I-controller
    (diffrax's recommendation for non-stiff problems). Every accepted step is measured.

    Counts: ``n_steps`` accepted and ``n_rejected`` rejected steps; ``n_f_evals``
    vector-field evaluations (stages per attempt, less the reused first stage of an FSAL
    pair, plus 2 for the automatic initial step, which is computed once in ``prepare``),
    each one Cholesky solve (``n_lin_solves``).

    Parameters
    ----------
    rtol : float
        Relative tolerance.
    atol : float
        Absolute tolerance; NaN (the default) sets it equal to ``rtol`` at construction.
    solver : str
        Key of :data:`SOLVERS` with an embedded error estimate.
    alpha, beta : float
        Baumgarte damping and stiffness (1/s).
    pcoeff, icoeff, dcoeff : float
        PID coefficients.
    safety, factormin, factormax : float
        Safety factor and bounds on the step-size ratio.
    dt0 : float
        Initial step; 0 selects it automatically (Hairer, Norsett and Wanner's algorithm).
    dtmax : float
        Largest step; ``inf`` for none.
    max_steps : int
        Accepted steps allowed over the run; reaching it fails the run.
    linear_solver : {"auto", "dense", "banded", "superlu", "kkt"}
        How ``G M^{-1} G^T`` is solved (:func:`linalg.schur.choose`).
    """

    adaptive: ClassVar[bool] = True

    solver: str = "dopri5"
    rtol: float = 1e-6
    atol: float = math.nan
    pcoeff: float = 0.0
    icoeff: float = 1.0
    dcoeff: float = 0.0
    safety: float = 0.9
    factormin: float = 0.2
    factormax: float = 10.0
    dt0: float = 0.0
    dtmax: float = math.inf
    max_steps: int = 10_000_000

    def check(self) -> None:
        super().check()
        name = type(self).__name__
        if not np.any(SOLVERS[self.solver].tableau.b_error):
            raise ValueError(f"{name}: solver {self.solver!r} has no embedded error estimate")
        if not 0 < self.safety <= 1:
            raise ValueError(f"{name}: safety = {self.safety} must lie in (0, 1]")
        if not 0 < self.factormin < 1 < self.factormax:
            raise ValueError(f"{name}: need 0 < factormin < 1 < factormax, got "
                             f"{self.factormin}, {self.factormax}")
        if not (self.dt0 >= 0 and self.dtmax > 0 and self.max_steps >= 1):
            raise ValueError(f"{name}: need dt0 >= 0, dtmax > 0 and max_steps >= 1")

    #: The lanes of an ensemble run in one compiled loop (:func:`drive_lanes`).
    batched: ClassVar[bool] = True

    #: Where the residuals and the energy are measured.
    SAMPLING: ClassVar[str] = "every internal step (accepted steps)"

    def _loop(self, grid: Grid) -> tuple[EmbeddedControl, dict]:
        """The step control and the traced options of the loop over ``grid``'s horizon."""
        control = EmbeddedControl(float(grid.t0), float(grid.t_end), self.dt0 == 0.0)
        params = {name: getattr(self, name) for name in (
            "alpha", "beta", "rtol", "atol", "pcoeff", "icoeff", "dcoeff", "safety",
            "factormin", "factormax", "dt0", "dtmax")}
        return control, params

    def prepare(self, case: Case, grid: Grid):
        self.check()
        control, params = self._loop(grid)
        y0 = np.concatenate([case.q0, case.v0])
        return drive(case.mech, grid, y0, SOLVERS[self.solver](), control, params,
                     self.max_steps, self.SAMPLING, self.linear_solver)

    def prepare_ensemble(self, case: Case, grid: Grid, q0s, v0s):
        """One compiled loop for the whole ensemble (:func:`drive_lanes`): each lane takes
        its own steps, and the loop runs until the slowest lane has ended."""
        self.check()
        control, params = self._loop(grid)
        y0s = np.concatenate([np.asarray(q0s), np.asarray(v0s)], axis=1)
        return drive_lanes(case.mech, grid, y0s, SOLVERS[self.solver](), control, params,
                           self.max_steps, self.SAMPLING, self.linear_solver)
