"""The compiled fixed-step time loop that every one-step method of ours shares.

The loop owns the bookkeeping so that methods only supply a pure ``step``: it measures
``|g|``, ``|G v + g_t|``, ``|H - H0|`` and the declared invariants at every step, keeps
their per-window maxima and a bounded set of sampled states, counts work and stops at the
first failed step. Everything runs inside one ``lax.while_loop``: no Python per step, and
memory independent of the number of steps.
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from integrators.base import COUNTERS, FAILED, OK, Grid, Trajectory
from problems.mechanics import Mechanics

#: Failure codes a step can return (0 is success).
CODES = {1: "the stage equations did not converge (Newton)", 2: "the state became non-finite"}

Step = Callable[[Any, jax.Array, jax.Array], tuple[Any, jax.Array, jax.Array, dict]]


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


def march(mech: Mechanics, grid: Grid, h: float, carry0: Any, step: Step,
          observe: Callable[[Any], tuple[jax.Array, jax.Array]]) -> Callable[[], Trajectory]:
    """Compile the time loop and return ``solve()``.

    Parameters
    ----------
    carry0 : pytree
        The method's state at ``t0`` (positions, momenta, warm starts...).
    step : callable
        ``step(carry, t, h) -> (carry1, code, residual, counts)``: one step from ``t``;
        ``code`` is 0 on success or a key of :data:`CODES`; ``residual`` the final Newton
        residual (for the message); ``counts`` increments of the work counters.
    observe : callable
        ``observe(carry) -> (q, v)``.
    """
    plan = Plan.make(grid, h)
    t0 = grid.t0
    n_inv = len(mech.system.invariants)

    def measure(q, v, t, E0, I0):
        return jnp.concatenate([
            jnp.stack([
                jnp.max(jnp.abs(mech.g(q, t)), initial=0.0),
                jnp.max(jnp.abs(mech.vel_residual(q, v, t)), initial=0.0),
                jnp.abs(mech.energy(q, v) - E0),
            ]),
            jnp.abs(mech.invariant_values(q, v) - I0),
        ])

    def run(carry0):
        q0, v0 = observe(carry0)
        tz = jnp.asarray(t0, dtype=jnp.float64)
        E0, I0 = mech.energy(q0, v0), mech.invariant_values(q0, v0)
        wins = jnp.zeros((plan.n_windows, 3 + n_inv)).at[0].set(measure(q0, v0, tz, E0, I0))
        samp_q = jnp.zeros((plan.n_samples, mech.n)).at[0].set(q0)
        samp_v = jnp.zeros((plan.n_samples, mech.n)).at[0].set(v0)
        counts = {k: jnp.zeros((), jnp.int64) for k in COUNTERS if k != "n_steps"}

        def cond(state):
            k, _, code, *_ = state
            return (k < plan.n_steps) & (code == 0)

        def body(state):
            k, carry, _, _, wins, samp_q, samp_v, counts = state
            t = t0 + k * plan.h
            new, code, resid, inc = step(carry, t, jnp.asarray(plan.h))
            q, v = observe(new)
            finite = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(v))
            code = jnp.where(code != 0, code, jnp.where(finite, 0, 2)).astype(jnp.int32)
            good = code == 0
            carry = jax.tree_util.tree_map(lambda a, b: jnp.where(good, a, b), new, carry)
            k1 = k + good.astype(k.dtype)
            m = measure(q, v, t0 + k1 * plan.h, E0, I0)
            wins = wins.at[k * plan.n_windows // plan.n_steps].max(jnp.where(good, m, 0.0))
            slot = jnp.where(good & (k1 % plan.stride == 0), k1 // plan.stride, plan.n_samples)
            samp_q = samp_q.at[slot].set(q, mode="drop")
            samp_v = samp_v.at[slot].set(v, mode="drop")
            counts = {key: counts[key] + inc.get(key, 0) for key in counts}
            return k1, carry, code, resid, wins, samp_q, samp_v, counts

        state = (jnp.asarray(0, jnp.int64), carry0, jnp.asarray(0, jnp.int32),
                 jnp.asarray(0.0), wins, samp_q, samp_v, counts)
        k, carry, code, resid, wins, samp_q, samp_v, counts = jax.lax.while_loop(cond, body, state)
        q, v = observe(carry)
        return k, code, resid, q, v, wins, samp_q, samp_v, counts

    compiled = jax.jit(run).lower(carry0).compile()

    def solve() -> Trajectory:
        out = jax.block_until_ready(compiled(carry0))
        k, code, resid, q, v, wins, samp_q, samp_v, counts = jax.device_get(out)
        k, code = int(k), int(code)
        assert q.dtype == np.float64, "the loop must run in float64"
        t_final = t0 + k * plan.h
        ends = plan.window_end_steps()
        reached = ends <= max(k, 1)
        names = ["pos", "vel", "energy"] + [f"inv:{s}" for s in mech.system.invariants]
        windows = {"t": t0 + ends[reached] * plan.h}
        windows.update({name: wins[reached, i] for i, name in enumerate(names)})
        n_samp = k // plan.stride + 1
        samples = {"t": t0 + np.arange(n_samp) * plan.stride * plan.h,
                   "q": samp_q[:n_samp], "v": samp_v[:n_samp]}
        counts = {"n_steps": k, **{key: int(val) for key, val in counts.items()}}
        if code == 0:
            return Trajectory(OK, "", t_final, q, v, windows, samples, counts)
        message = (f"{CODES[code]} at step {k + 1} (t = {t_final:.6g} -> "
                   f"{t_final + plan.h:.6g}); last Newton residual {float(resid):.3e}")
        return Trajectory(FAILED, message, t_final, q, v, windows, samples, counts,
                          fail_step=k + 1, fail_time=t_final)

    return solve
