"""The compiled fixed-step time loop that every one-step method of ours shares.

The loop owns the bookkeeping so that methods only supply a pure ``step``: it measures
``|g|``, ``|G v + g_t|``, ``|H - H0|`` and the declared invariants at every step, keeps
their per-window maxima and a bounded set of sampled states, counts work and stops at the
first failed step. Everything runs inside compiled ``lax.while_loop``\\ s: no Python per
step, and memory independent of the number of steps. The metrics themselves
(:mod:`benchmarks.metrics`) are computed from these records after the solve; taking the
per-step values inside the loop is what keeps memory bounded (keeping every state for
later would not), and its cost is part of the timed solve, a noticeable share only for
the cheapest steps (RATTLE on the pendulum).

Speed
-----
Under :data:`KERNEL_FLAG` XLA:CPU compiles the whole time loop, the methods' Newton loops
included, into one native kernel. Without it XLA's runtime dispatches every fused
operation of the loop body on its own, tens of nanoseconds each, which is most of a small
problem's step (``benchmarks/perf/throughput.py`` measures it, with ``--xla-default``
without the flag). The
flag is read once, when JAX creates its CPU client, so it has to be in ``XLA_FLAGS``
before the process first uses JAX (:func:`kernel_environment`; the benchmark workers
start with it). Results agree to round-off with and without it (bit for bit on the
seed-sps and quick suites and for 1e6 RATTLE steps; 1e6 steps of lobatto3ab3 differ in
the last bits). Scatter, sort and custom calls (LAPACK, which
:func:`integrators.newton.solve` calls for systems larger than 1 x 1) inside the loop
keep XLA from forming the kernel; such loops run op by op.

The steps run in *segments*: an inner loop takes the steps up to the next window end or
sample step, whichever comes first, carrying only the method's state, the running maxima
of the segment and the work counters; an outer loop (one iteration per segment, at most
``n_windows + n_samples`` of them) folds the segment's maxima into its window and writes
the sample. The per-step work thus never touches the window and sample arrays, which
updating them at every step would cost on small problems.

Ensembles
---------
An ensemble (:meth:`integrators.fixed.FixedStep.prepare_ensemble`) runs the same loop with
a leading axis of lanes on the carry: the step, the observation and the measures are
mapped over the lanes (``jax.vmap``), the loops' control is one scalar for all of them.
Every live lane is at the same step, a loop goes on while some lane is live, and a lane
that has failed keeps its last good state, step count, maxima and samples. It is still
computed, since the lanes run in step, and its result dropped; from its own state it
would fail again, its Newton loop running to the iteration limit, and a mapped Newton
loop runs until its slowest lane is done: every lane would pay that limit at every later
step. So a failed lane steps from a live lane's state instead, which leaves every lane's
result the same bit for bit. A lane keeps its state where its step failed by one select
over the lanes, skipped while every lane's step is good, which is cheaper than mapping
the whole loop over the lanes.

Reuse
-----
The step size, the step count, the window count and the sample stride are arguments of
the compiled loop, not constants in it (the window and sample arrays have the grid's
fixed sizes), so one compilation serves every ``h``: :func:`march` keeps the compiled
loops of the last :data:`CACHE_SIZE` methods (keyed by the method's options other than
``h``, the :class:`Mechanics` object, ``t0`` and the grid's sizes) and a step-size sweep,
or a run over another horizon, compiles once.

What a solve pays whatever its number of steps is kept to what the run uses. The sample
buffers (``n_samples`` states of ``q`` and of ``v``, most of the loop's memory for a large
system) are made once, when the solve is prepared, and handed from each solve to the next
(donated to the compiled programs, which write into them in place): a solve neither clears
them nor copies them, and reads back only rows that it wrote. Only the windows and samples
the plan uses, rounded up to a power of two (:func:`rows_copied`) so that a few small
programs serve every plan (:func:`handover`), reach the host, in one copy, which is the
solve's one wait for the device unless a step has to be taken again with the fallback.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections import OrderedDict
from functools import lru_cache, partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from integrators.base import COUNTERS, Failure, Grid, Status, Trajectory
from integrators.record import measurer, series_names
from integrators.newton import deferred_fallback
from linalg.compiled import compile_lifted
from problems.mechanics import Mechanics

#: XLA:CPU option: emit any run of operations (while loops included) whose cost model
#: reads and writes at most this many bytes per pass as one native kernel. The default,
#: 1 kB, is below what one step of the smallest problem touches; the value here puts no
#: practical limit on it.
KERNEL_FLAG = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000000"

#: XLA:CPU option: emit fusions with XLA's LLVM IR emitters instead of its newer MLIR
#: fusion emitters. Compiling is most of a suite's set-up, and this takes about a third
#: less CPU time to compile (``benchmarks/perf/compile_profile.py``), with kernels as fast
#: and the same Newton iterations and residuals.
COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"
#: The last jaxlib release whose XLA knows :data:`COMPILE_FLAG`: jaxlib 0.11 removed the
#: option, and XLA aborts a process whose ``XLA_FLAGS`` names an option it does not know
#: ("Unknown flag in XLA_FLAGS", seen with jaxlib 0.11.2).
COMPILE_FLAG_UNTIL = (0, 10)

#: XLA:GPU options: record while loops and conditionals into CUDA graphs (command buffers)
#: with their predicates evaluated on the device, so that a Newton loop's test does not go
#: back to the host at every iteration; results stay within round-off of single runs on
#: the CPU (``benchmarks/perf/ensemble.py`` measures the gain). XLA:CPU ignores these
#: options.
COMMAND_BUFFER_FLAGS = ("--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL",
                        "--xla_gpu_graph_min_graph_size=1")


#: Compiled loops kept for reuse (each holds its executable; a sweep needs one), and the
#: functions that move an ensemble's retaken lanes in and out of theirs (:func:`march`).
CACHE_SIZE = 8
_LOOPS: OrderedDict = OrderedDict()

#: The work counters a step increments (the loop counts the steps itself).
WORK = tuple(key for key in COUNTERS if key != "n_steps")

Step = Callable[[Any, jax.Array, jax.Array], tuple[Any, jax.Array, jax.Array, dict]]


def xla_options(kernel: bool = True) -> tuple[str, ...]:
    """The XLA options our processes start with: :data:`KERNEL_FLAG` (with ``kernel``),
    :data:`COMPILE_FLAG` where the installed XLA knows it (:data:`COMPILE_FLAG_UNTIL`), and
    :data:`COMMAND_BUFFER_FLAGS`."""
    from jaxlib.version import __version_info__ as version
    known = tuple(version[:2]) <= COMPILE_FLAG_UNTIL
    return ((KERNEL_FLAG,) * kernel + (COMPILE_FLAG,) * known + COMMAND_BUFFER_FLAGS)


def kernel_environment(environ: dict[str, str] | None = None,
                       options: tuple[str, ...] | None = None) -> dict[str, str]:
    """``XLA_FLAGS`` of ``environ`` (default: this process's) with ``options`` added
    (default :func:`xla_options`).

    Returns a one-entry dict to merge into the environment of a process that is yet to
    start, or into ``os.environ`` before this process first uses JAX.
    """
    flags = (os.environ if environ is None else environ).get("XLA_FLAGS", "")
    for option in xla_options() if options is None else options:
        if option not in flags.split():
            flags = f"{flags} {option}".strip()
    return {"XLA_FLAGS": flags}


class Plan(NamedTuple):
    """Step count and recording layout for a horizon and a requested step."""

    n_steps: int
    h: float
    n_windows: int
    stride: int
    n_samples: int

    @classmethod
    def make(cls, grid: Grid, h: float) -> "Plan":
        """Shrink ``h`` to divide ``[t0, t_end]`` into a whole number of steps."""
        span = grid.t_end - grid.t0
        n = max(1, math.ceil(span / h * (1 - 1e-12)))
        stride = max(1, math.ceil(n / max(1, grid.n_samples - 1)))
        return cls(n, span / n, min(n, grid.n_windows), stride, n // stride + 1)

    def window_end_steps(self) -> np.ndarray:
        """Index of the last step of each window (step k lies in ``(k-1) W // N``)."""
        w = np.arange(self.n_windows, dtype=np.int64)
        return ((w + 1) * self.n_steps + self.n_windows - 1) // self.n_windows


def put(rows: jax.Array, i: jax.Array, row: jax.Array, axis: int = 0) -> jax.Array:
    """``rows`` with row ``i`` along ``axis`` replaced, as an in-place dynamic update (not a
    scatter)."""
    return jax.lax.dynamic_update_index_in_dim(rows, row, i, axis)


def take(rows: jax.Array, i: jax.Array, axis: int = 0) -> jax.Array:
    """Row ``i`` of ``rows`` along ``axis``."""
    return jax.lax.dynamic_index_in_dim(rows, i, axis, keepdims=False)


def trial(step: Step, observe: Callable[[Any], tuple[jax.Array, jax.Array]], carry: Any,
          t: jax.Array, h: jax.Array):
    """One step from ``carry`` at ``t``, judged by the loop's rule for failures.

    Returns ``(new, code, residual, work, (q, v))``: ``code`` is the step's own, or
    :attr:`Failure.NON_FINITE` for a non-finite ``(q, v)``; ``work`` holds the increments of
    :data:`WORK` in that order, and ``(q, v)`` is ``new`` observed (meaningful where
    ``code`` is 0). A failed step's ``new`` is to be dropped (:func:`attempt`).
    """
    new, code, resid, inc = step(carry, t, h)
    q, v = observe(new)
    finite = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(v))
    code = jnp.where(code != 0, code, jnp.where(finite, 0, Failure.NON_FINITE)).astype(jnp.int32)
    work = jnp.stack([jnp.asarray(inc.get(key, 0), jnp.int64) for key in WORK])
    return new, code, resid, work, (q, v)


def attempt(step: Step, observe: Callable[[Any], tuple[jax.Array, jax.Array]], carry: Any,
            t: jax.Array, h: jax.Array):
    """:func:`trial` with its verdict applied: a step that fails leaves ``carry1 = carry``.

    Returns ``(carry1, code, residual, work, (q, v))``.
    """
    new, code, resid, work, seen = trial(step, observe, carry, t, h)
    carry = jax.tree_util.tree_map(lambda a, b: jnp.where(code == 0, a, b), new, carry)
    return carry, code, resid, work, seen


def take_lanes(state, E0, I0, pick):
    """The arguments of an ensemble loop's ``run`` (:func:`_loop`) for the lanes ``pick`` of
    ``state``, cleared of their failures, at the first of their steps."""
    _, lane, carry, code, resid, *rest = state
    sub = jax.tree_util.tree_map(lambda a: a[pick], (lane, carry, jnp.zeros_like(code),
                                                     jnp.zeros_like(resid), *rest))
    return (jnp.min(sub[0]), *sub), E0[pick], I0[pick]


def put_lanes(state, qv, sub, sub_qv, pick):
    """``(state, qv)`` with the lanes ``pick`` replaced by the results ``(sub, sub_qv)`` of
    :func:`take_lanes`' lanes (in the same order; a lane picked twice gets the same result
    twice)."""
    k, lane, carry, code, resid, *rest = state
    new = [jax.tree_util.tree_map(lambda a, b: a.at[pick].set(b), x, y)
           for x, y in zip((lane, carry, code, resid, *rest, *qv), (*sub[1:], *sub_qv))]
    lane, carry, code, resid, *rest, q, v = new
    return (k, lane, carry, code, resid, *rest), (q, v)


def sample_buffers(mech: Mechanics, grid: Grid, width: int | None = None
                   ) -> tuple[jax.ShapeDtypeStruct, jax.ShapeDtypeStruct]:
    """The shapes of the loop's sample buffers of ``q`` and ``v``: ``grid.n_samples`` rows of
    ``mech.n`` values, after a leading axis of ``width`` lanes for an ensemble."""
    lead = () if width is None else (width,)
    buffer = jax.ShapeDtypeStruct(lead + (grid.n_samples, mech.n), jnp.float64)
    return buffer, buffer


def rows_copied(used: int, size: int) -> int:
    """Rows of a record of ``size`` rows that reach the host when the plan uses the first
    ``used``: the next power of two, at most ``size``, so that a few :func:`handover`
    programs serve every plan."""
    return min(size, 1 << max(0, used - 1).bit_length())


@partial(jax.jit, static_argnames=("n_windows", "n_samples"))
def handed(lane, code, resid, q, v, wins, samp_q, samp_v, counts, *, n_windows: int,
           n_samples: int):
    """The loop's outputs with the first ``n_windows`` rows of its windows and the first
    ``n_samples`` of its sample buffers (after the lanes' axis, as ``code`` has one)."""
    def first(a, rows):
        return jax.lax.slice_in_dim(a, 0, rows, axis=code.ndim)
    return (lane, code, resid, q, v, first(wins, n_windows), first(samp_q, n_samples),
            first(samp_v, n_samples), counts)


@lru_cache(maxsize=4 * CACHE_SIZE)
def handover(parts: tuple[jax.ShapeDtypeStruct, ...], n_windows: int, n_samples: int,
             device: str):
    """:func:`handed` compiled for arguments of the shapes ``parts`` on ``device`` (the
    default device, which it is compiled for): a solve's copy to the host is that of the
    rows the plan uses, not of the grid's whole buffers, in one small program kept for
    every loop with outputs of these shapes."""
    return compile_lifted(handed, *parts, n_windows=n_windows, n_samples=n_samples)


def _loop(mech: Mechanics, grid: Grid, step: Step,
          observe: Callable[[Any], tuple[jax.Array, jax.Array]], lanes: bool,
          retaken: bool = False) -> tuple[Callable, Callable]:
    """The loop as two functions: ``begin(carry0, samp_q, samp_v) -> (state, E0, I0)``,
    its state before the first step with the sample buffers given (:func:`sample_buffers`;
    rows other than the first are left as they are), and
    ``run(state, E0, I0, h, N, W, stride) -> (state, (q, v))``, which
    takes steps of size ``h`` from the state's step ``k`` to ``N`` (or the first failure),
    with maxima over ``W`` windows and a sample every ``stride`` steps (in arrays of the
    grid's sizes, of which the first ``W`` and ``N // stride + 1`` rows are used). The
    state is ``(k, lane, carry, code, resid, wins, samp_q, samp_v, counts)``; ``run`` may
    continue from a state that another ``run`` left (:func:`march`). The work of a step
    that fails is counted, unless ``retaken``: then another loop takes that step again and
    counts it.

    With ``lanes`` the carry has a leading axis of lanes; the step, the observation and
    the measures are mapped over it (``jax.vmap``), while the loops' control stays one
    scalar for all of them: every live lane is at the same step ``k``, a loop goes on while
    some lane is live, and a lane that has failed is carried unchanged (its own step count,
    ``lane``, stops there). A failed lane is still computed, from a live lane's state
    (module notes). A lane whose own count is ahead of ``k`` waits, unchanged too, until
    ``k`` reaches it, and where no lane is at ``k`` the loop goes to the first one ahead:
    the lanes retaken by :func:`march` go on from the steps they failed at, which differ.
    """
    t0, n_inv = grid.t0, len(mech.system.invariants)
    lift = jax.vmap if lanes else (lambda f, **_: f)
    live = jnp.any if lanes else (lambda x: x)
    measure = lift(measurer(mech), in_axes=(None, 0, 0, 0, 0))
    see = lift(observe)
    tried = lift(partial(trial, step, observe), in_axes=(0, None, None))

    def select(mask, new, old):
        # Lane by lane; where every lane's step is good (the common case) no select at all.
        if not lanes:
            return jax.tree_util.tree_map(lambda a, b: jnp.where(mask, a, b), new, old)
        return jax.lax.cond(jnp.all(mask), lambda: new, lambda: jax.tree_util.tree_map(
            lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b),
            new, old))

    def at(k, lane, code):
        # The lanes live at step k: neither failed nor waiting (docstring). One trajectory
        # is never waiting, and its loop tests its code alone.
        return (code == 0) & (lane == k) if lanes else code == 0

    def stand_in(active, carry):
        # A failed lane is still computed (the lanes run in step) and its result dropped.
        # From its own last state it would fail again, Newton running to its iteration
        # limit and holding every lane there at every later step; it steps from a live
        # lane's state instead, at that lane's cost.
        if not lanes:
            return carry
        live_state = jax.tree_util.tree_map(lambda a: a[jnp.argmax(active)][None], carry)
        return select(active, carry, live_state)

    def segment(k, lane, carry, code, resid, counts, stop, h, E0, I0):
        """Steps ``k .. stop - 1``, each lane up to its first failure; the maxima of
        their measures.

        A failed step leaves a lane's ``carry`` and ``lane`` (its step count) at its last
        good step; without lanes it stops the loop.
        """

        def cond(state):
            k, lane, _, code, *_ = state
            return (k < stop) & live(at(k, lane, code))

        def body(state):
            k, lane, carry, code, resid, peak, counts = state
            active = at(k, lane, code)
            t = t0 + k * h
            new, code1, resid1, inc, (q, v) = tried(stand_in(active, carry), t, h)
            good = active & (code1 == 0)
            # Measured at t + h, the time every method imposes its end conditions at (its
            # last stage's time), not at t0 + (k + 1) h: the two differ by an ulp of t,
            # and a rheonomic |g| read at the other time is |g_t| times that ulp, far
            # above g's round-off where t is large.
            m = measure(t + h, q, v, E0, I0)
            # A lane keeps its state where it was not live or its step failed.
            return (k + 1, lane + good.astype(lane.dtype), select(good, new, carry),
                    jnp.where(active, code1, code), jnp.where(active, resid1, resid),
                    jnp.maximum(peak, jnp.where(good[..., None], m, 0.0)),
                    counts + jnp.where((good if retaken else active)[..., None], inc, 0))

        peak = jnp.zeros(code.shape + (3 + n_inv,))
        return jax.lax.while_loop(cond, body, (k, lane, carry, code, resid, peak, counts))

    def begin(carry0, samp_q, samp_v):
        # The loop's state before the first step, and the energy and invariants at t0.
        # The sample buffers are the caller's, as the last solve left them: a run reads
        # back only rows it wrote, so they are not cleared. The windows are, since a
        # segment folds its maxima into its window's.
        q0, v0 = see(carry0)
        tz = jnp.asarray(t0, dtype=jnp.float64)
        E0, I0 = lift(mech.energy)(q0, v0), lift(mech.invariant_values)(q0, v0)
        shape, axis = E0.shape, E0.ndim
        first = measure(tz, q0, v0, E0, I0)
        wins = jnp.zeros(shape + (grid.n_windows, 3 + n_inv))
        wins, samp_q, samp_v = (put(a, 0, row, axis)
                                for a, row in ((wins, first), (samp_q, q0), (samp_v, v0)))
        state = (jnp.asarray(0, jnp.int64), jnp.zeros(shape, jnp.int64), carry0,
                 jnp.zeros(shape, jnp.int32), jnp.zeros(shape), wins, samp_q, samp_v,
                 jnp.zeros(shape + (len(WORK),), jnp.int64))
        return state, E0, I0

    def run(state, E0, I0, h, N, W, stride):
        axis = E0.ndim

        def cond(state):
            k, lane, _, code, *_ = state
            return (k < N) & live((code == 0) & (lane < N) if lanes else code == 0)

        def body(state):
            k, lane, carry, code, resid, wins, samp_q, samp_v, counts = state
            if lanes:
                # On to the first step that a lane neither failed nor done is at: k itself
                # but where every lane at k has failed and others wait further on.
                k = jnp.maximum(k, jnp.min(jnp.where((code == 0) & (lane < N), lane, N)))
            # Step k lies in window w = k W // N, which ends before step ((w + 1) N + W - 1)
            # // W; the segment also ends where the next sample is due.
            w = k * W // N
            stop = jnp.minimum(((w + 1) * N + W - 1) // W, (k // stride + 1) * stride)
            k, lane, carry, code, resid, peak, counts = segment(
                k, lane, carry, code, resid, counts, stop, h, E0, I0)
            wins = put(wins, w, jnp.maximum(take(wins, w, axis), peak), axis)
            # The state after k steps goes to slot k // stride when k is a multiple of the
            # stride, where segments end, from the lanes that reached step k.
            q, v = see(carry)
            due, slot = ((k % stride == 0) & (lane == k))[..., None], k // stride
            samp_q = put(samp_q, slot, jnp.where(due, q, take(samp_q, slot, axis)), axis)
            samp_v = put(samp_v, slot, jnp.where(due, v, take(samp_v, slot, axis)), axis)
            return k, lane, carry, code, resid, wins, samp_q, samp_v, counts

        state = jax.lax.while_loop(cond, body, state)
        return state, see(state[2])

    return begin, run


def march(mech: Mechanics, grid: Grid, h: float, carry0: Any, step: Step,
          observe: Callable[[Any], tuple[jax.Array, jax.Array]],
          key: tuple | None = None, linear_solver: str = "dense",
          pattern_nnz: int | None = None, lanes: bool = False) -> Callable:
    """Compile the time loop (or reuse it) and return ``solve()``.

    One trajectory's loop is compiled with the exact-Jacobian fallback of simplified
    Newton left out (:func:`integrators.newton.deferred_fallback`), which is up to most of
    its program and rarely needed. Where a step's Newton fails to converge in that loop,
    the loop with the fallback is compiled (once, then reused like the other) and
    continues from that step, so the run's result is that of the loop with the fallback
    throughout: the same steps up to the one that failed, which it takes again, and the
    same work counted (the failed attempt's is not). An ensemble's loop is compiled
    without the fallback too, and the lanes whose Newton failed in it go on with it from
    the steps they failed at, as an ensemble of their own (its loop starts at the first of
    those steps, and each lane waits until the loop reaches its own: :func:`_loop`). An
    ensemble compiled with the fallback would pay for it in set-up and per step where no
    lane takes it.

    Parameters
    ----------
    carry0 : pytree
        The method's state at ``t0`` (positions, momenta, warm starts...); with ``lanes``,
        the states of an ensemble, stacked on a leading axis.
    step : callable
        ``step(carry, t, h) -> (carry1, code, residual, counts)``: one step from ``t``;
        ``code`` is 0 on success or a :class:`Failure`; ``residual`` the final Newton
        residual (for the message); ``counts`` increments of the work counters.
    observe : callable
        ``observe(carry) -> (q, v)``.
    key : tuple, optional
        What ``step`` and ``observe`` depend on besides ``mech`` and ``h`` (the method and
        its other options). With a key, the compiled loop is reused by later calls with
        the same key, ``mech``, ``t0`` and grid sizes; without one it is compiled afresh.
    linear_solver, pattern_nnz
        What the step's linear algebra is, recorded in the trajectory.
    lanes : bool
        Run the ensemble of ``carry0`` in one compiled loop, the step mapped over the
        lanes (module notes). Each lane keeps its own step count, failure, counters,
        maxima and samples; the loop runs until the last lane is done or has failed, and
        a lane that has stopped is carried unchanged (a failed lane stops only itself).

    Returns
    -------
    solve : callable
        ``solve() -> Trajectory`` (with ``lanes``, a list of them, one per lane), which
        holds the grid's sample buffers from one call to the next (module notes; one call
        at a time); its attribute ``compiled`` is the compiled loop (for diagnostics such as whether XLA
        made it one kernel), its large constants passed as arguments
        (:mod:`linalg.compiled`), and ``late_setup_s`` the seconds its calls have spent
        compiling the loop with the fallback (set-up, not solving: the harness moves them).
    """
    plan = Plan.make(grid, h)
    # t_end is not in the loop (N is an argument): other horizons share it. A loop is
    # compiled for the device it runs on (jax.default_device), which the key holds too.
    width = jax.tree_util.tree_leaves(carry0)[0].shape[0] if lanes else None
    device = str(jax.config.jax_default_device)
    cache_key = None if key is None else (key, mech, grid.t0, grid.n_windows, grid.n_samples,
                                          width, device)
    args = (jnp.float64(plan.h), jnp.int64(plan.n_steps), jnp.int64(plan.n_windows),
            jnp.int64(plan.stride))

    def compiled_loop(fallback: bool, width: int | None = width):
        # (begin, run, the shape of run's state), compiled or from the cache; an
        # ensemble's for `width` lanes. Both hand their state on: the solve does not read
        # the arrays it gives them again, and so no sample buffer is copied.
        tag = None if cache_key is None else (cache_key, fallback, width)
        loop = _LOOPS.get(tag) if tag is not None else None
        if loop is None:
            begin, run = _loop(mech, grid, step, observe, lanes, retaken=not fallback)
            carry = carry0 if width is None else jax.tree_util.tree_map(
                lambda a: jax.ShapeDtypeStruct((width,) + a.shape[1:], a.dtype), carry0)
            buffers = sample_buffers(mech, grid, width)
            first = compile_lifted(begin, carry, *buffers, donate=(1, 2))
            state, E0, I0 = jax.eval_shape(begin, carry, *buffers)
            with deferred_fallback() if not fallback else contextlib.nullcontext():
                loop = (first, compile_lifted(run, state, E0, I0, *args, donate=(0,),
                                              name="with fallback" if fallback else ""),
                        state)
            if tag is not None:
                _LOOPS[tag] = loop
                while len(_LOOPS) > CACHE_SIZE:
                    _LOOPS.popitem(last=False)
        else:
            _LOOPS.move_to_end(tag)
        return loop

    # Every path's loop is compiled without the fallback first: the structured paths'
    # simplified Newton has one, and the dense path's from FROZEN_MIN unknowns on
    # (integrators.newton). Decided here, not by the trace, since a loop kept on disk is
    # loaded untraced (linalg.compiled). Only a step whose Newton did not converge is
    # taken again: the fallback changes no other failure.
    begin, run, shape = compiled_loop(fallback=False)
    names = series_names(mech)
    solver = dict(linear_solver=linear_solver, pattern_nnz=pattern_nnz)
    # The rows the plan uses, and only those (to the next power of two), reach the host.
    _, lane, _, code, resid, wins, samp_q, samp_v, counts = shape
    final = jax.ShapeDtypeStruct(lane.shape + (mech.n,), jnp.float64)
    hand = handover((lane, code, resid, final, final, wins, samp_q, samp_v, counts),
                    rows_copied(plan.n_windows, grid.n_windows),
                    rows_copied(plan.n_samples, grid.n_samples), device)
    # The sample buffers, made here and handed from one solve to the next (begin). A solve
    # that raised has lost them, and the next makes new ones.
    blank = sample_buffers(mech, grid, width)
    home = jax.config.jax_default_device or jax.devices()[0]
    if isinstance(home, str):  # a platform's name
        home = jax.devices(home)[0]

    def fresh():
        # New buffers on the device the loop is compiled for (the default one now), even
        # when a later solve is called under another default device.
        return tuple(jax.device_put(jnp.zeros(b.shape, b.dtype), home) for b in blank)

    spare = [fresh()]

    def exact_loop(w=None):
        # The loop with the fallback, its compilation counted as set-up.
        start = time.perf_counter()
        loop = compiled_loop(True, w)
        solve.late_setup_s += time.perf_counter() - start
        return loop

    def regroup(w, state, qv, E0, I0, pick):
        # The compiled functions that take the lanes `pick` (w of them) out of the state
        # and put their results back, compiled as set-up like the loop they serve: run
        # op by op, their compiling and dispatch would be charged to the method's timing.
        tag = None if cache_key is None else (cache_key, "regroup", w)
        pair = _LOOPS.get(tag) if tag is not None else None
        if pair is None:
            start = time.perf_counter()
            gather = jax.jit(take_lanes).lower(state, E0, I0, pick).compile()
            sub_state = jax.eval_shape(take_lanes, state, E0, I0, pick)[0]
            sub_qv = jax.tree_util.tree_map(
                lambda a: jax.ShapeDtypeStruct((w,) + a.shape[1:], a.dtype), qv)
            scatter = jax.jit(put_lanes, donate_argnums=(0, 1)).lower(
                state, qv, sub_state, sub_qv, pick).compile()
            solve.late_setup_s += time.perf_counter() - start
            pair = (gather, scatter)
            if tag is not None:
                _LOOPS[tag] = pair
        return pair

    def retake(state, qv, E0, I0, codes):
        # A step's Newton failed without the fallback: the loop with it takes that step
        # again, from the state before it. `codes`: the lanes' failure codes, on the host.
        _, lane, carry, code, resid, *rest = state
        if not lanes:
            # The step count is handed over twice: as the loop's and as the lane's.
            return exact_loop()[1]((jnp.copy(lane), lane, carry, jnp.zeros_like(code),
                                    jnp.zeros_like(resid), *rest), E0, I0, *args)
        # The lanes whose Newton failed go on from those steps, together, with the
        # fallback (one more compiled loop, of a power-of-two width so that few widths
        # are compiled; padded with repeats of the first, which compute alike and write
        # alike), and their results replace theirs: only the steps from each lane's
        # failure on are taken again.
        failed = np.flatnonzero(codes == Failure.NEWTON)
        w = 1 << int(len(failed) - 1).bit_length()
        pick = jnp.asarray(np.concatenate([failed, np.full(w - len(failed), failed[0])]))
        loop = exact_loop(w)[1]
        gather, scatter = regroup(w, state, qv, E0, I0, pick)
        return scatter(state, qv, *loop(*gather(state, E0, I0, pick), *args), pick)

    def fetch(state, qv):
        # The run's outputs on the host: the one synchronisation of a solve that does not
        # fail.
        _, lane, _, code, resid, wins, samp_q, samp_v, counts = state
        return jax.device_get(hand(lane, code, resid, *qv, wins, samp_q, samp_v, counts))

    def solve():
        buffers = spare.pop() if spare else fresh()
        state, E0, I0 = begin(carry0, *buffers)
        state, qv = run(state, E0, I0, *args)
        out = fetch(state, qv)
        if np.any(out[1] == Failure.NEWTON):
            state, qv = retake(state, qv, E0, I0, out[1])
            out = fetch(state, qv)
        spare.append(state[6:8])
        assert out[3].dtype == np.float64, "the loop must run in float64"
        if not lanes:
            return trajectory(plan, grid.t0, names, *out, **solver)
        return [trajectory(plan, grid.t0, names, *(a[i] for a in out), **solver)
                for i in range(len(out[0]))]

    solve.compiled = run
    solve.late_setup_s = 0.0
    return solve


def trajectory(plan: Plan, t0: float, names: list[str], k, code, resid, q, v, wins, samp_q,
               samp_v, counts, **solver) -> Trajectory:
    """The :class:`Trajectory` of one run of the loop from its outputs (host arrays, of
    which ``wins``, ``samp_q`` and ``samp_v`` hold at least the rows the plan uses): the
    windows and samples it reached, its counters, and its failure if it had one."""
    k, code = int(k), int(code)
    wins = wins[:plan.n_windows]
    t_final = t0 + k * plan.h
    ends = plan.window_end_steps()
    # A run that fails mid-window keeps that partial window (ending at its last good
    # step): the maxima of what was computed are part of the record.
    last = (max(k, 1) - 1) * plan.n_windows // plan.n_steps
    reached = np.arange(plan.n_windows) <= last
    windows = {"t": t0 + np.minimum(ends[reached], k) * plan.h}
    windows.update({name: wins[reached, i] for i, name in enumerate(names)})
    n_samp = k // plan.stride + 1
    samples = {"t": t0 + np.arange(n_samp) * plan.stride * plan.h,
               "q": samp_q[:n_samp], "v": samp_v[:n_samp]}
    counts = {"n_steps": k, **{key: int(val) for key, val in zip(WORK, counts)}}
    if code == 0:
        return Trajectory(Status.OK, "", t_final, q, v, windows, samples, counts, **solver)
    message = (f"{Failure(code).message} at step {k + 1} (t = {t_final:.6g} -> "
               f"{t_final + plan.h:.6g}); last Newton residual {float(resid):.3e}")
    return Trajectory(Status.FAILED, message, t_final, q, v, windows, samples, counts,
                      fail_step=k + 1, fail_time=t_final, **solver)
