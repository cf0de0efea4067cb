"""Energy balance of damped and driven systems, from a run's sampled states.

Without a conserved energy (applied forces, moving constraints) the energy changes by the
work done on the system: along exact solutions

.. math::

    H(t) - H(t_0) - W(t) = 0, \\qquad W(t) = \\int_{t_0}^{t} P(s)\\,ds,

with ``H = T + U`` and ``P`` the power of the applied and constraint forces
(:meth:`problems.mechanics.Mechanics.power`, derived from the system as written). The
balance error of a run is ``max_j |H_j - H_0 - W_j|`` over its sampled states
``(t_j, q_j, v_j)`` (:attr:`integrators.base.Trajectory.samples`).

``W_j`` is a quadrature of ``P`` at the samples: piecewise interpolating polynomials of
degree :data:`DEGREE` on the nearest ``DEGREE + 1`` samples, exact for such polynomials
on any spacing, of order ``DEGREE + 1`` in the spacing: above the order of every method
here, so where the samples are the steps (up to ``Grid.n_samples`` of them) the
quadrature's error falls faster than the method's. Its error is estimated by the same
quadrature of degree ``DEGREE + 2`` (order ``DEGREE + 3``): their difference is the
lower-order rule's error to leading order (on ``cos`` at 50 to 400 jittered nodes it was
0.98 to 1.0 of it). That estimate, its running maximum, is the run's ``balance_floor``:
below it the balance error says nothing about the method, as a reference's floor bounds a
final error.

Quadrature over the samples rather than a work coordinate integrated with the motion
keeps every method's equations, work and error control those of the user's system; its
price is that motions faster than the sample spacing (stiff transients, more steps than
samples) raise the floor, which then says so.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from problems.mechanics import Mechanics

#: Degree of the interpolating polynomials of the quadrature (order ``DEGREE + 1``).
DEGREE = 6
#: Finite sampled states the balance needs: the error estimate's rule takes ``DEGREE + 3``
#: nodes, and with fewer it would equal the quadrature and estimate nothing (an
#: ensemble's lanes keep three states: no balance).
MIN_SAMPLES = DEGREE + 3


def cumulative(t: np.ndarray, p: np.ndarray, degree: int = DEGREE) -> np.ndarray:
    """``W_j = int_{t_0}^{t_j} p dt`` at every node, ``W_0 = 0``.

    Each interval ``[t_i, t_{i+1}]`` integrates the polynomial of degree ``degree`` through
    the ``degree + 1`` nodes around it (centred where the ends allow), whose weights solve
    the moment equations in the interval's own scaled variable. Fewer nodes lower the
    degree to what they allow.
    """
    t = np.asarray(t, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    n = len(t)
    if n < 2:
        return np.zeros(n)
    d = min(degree, n - 1)
    i = np.arange(n - 1)
    first = np.clip(i - d // 2, 0, n - 1 - d)
    nodes = first[:, None] + np.arange(d + 1)
    # Scaled by the stencil's span, so that the nodes lie in [-1, 1] however unevenly an
    # adaptive method stepped (scaled by the interval, a far node's powers would reach
    # (span / width)^d and the moment equations would lose their digits).
    span = t[nodes[:, -1]] - t[nodes[:, 0]]
    x = (t[nodes] - t[i][:, None]) / span[:, None]
    end = (t[1:] - t[:-1]) / span
    # sum_k w_k x_k^j = int_0^end x^j dx = end^(j+1) / (j+1) for j = 0..d.
    power = np.arange(d + 1)
    vandermonde = x[:, None, :] ** power[None, :, None]
    moments = end[:, None] ** (power + 1) / (power + 1)
    weights = np.linalg.solve(vandermonde, moments[..., None])[..., 0]
    pieces = span * np.sum(weights * p[nodes], axis=1)
    return np.concatenate([[0.0], np.cumsum(pieces)])


@partial(jax.jit, static_argnames="mech")
def _energy_and_power(t, q, v, *, mech: Mechanics):
    """``H`` and ``P`` at a batch of states."""
    return (jax.vmap(mech.energy)(q, v), jax.vmap(mech.power)(t, q, v))


def balance(mech: Mechanics, samples: dict[str, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t_j, |H_j - H_0 - W_j|, floor_j)`` at the sampled states, ``floor_j`` the
    quadrature's error estimate (the module notes); ``nan`` from the first state that is
    not finite on, and everywhere where fewer than :data:`MIN_SAMPLES` finite states were
    kept."""
    t = np.asarray(samples["t"], dtype=np.float64)
    error = np.full(len(t), math.nan)
    floor = np.full(len(t), math.nan)
    if len(t) < MIN_SAMPLES:
        return t, error, floor
    if mech.system.rheonomic:
        # The multipliers' solver (Mechanics.power) is built from structure that is found
        # outside a trace, as an integrator's prepare builds its own.
        mech.schur("dense")
    # Padded to a power of two by repeating the last state: the number of kept samples
    # varies from run to run, and each length would be compiled anew.
    pad = (0, (1 << (len(t) - 1).bit_length()) - len(t))
    q, v = (np.pad(np.asarray(samples[k], dtype=np.float64), (pad, (0, 0)), mode="edge")
            for k in ("q", "v"))
    H, P = (np.asarray(x, dtype=np.float64)[:len(t)] for x in _energy_and_power(
        jnp.asarray(np.pad(t, pad, mode="edge")), jnp.asarray(q), jnp.asarray(v), mech=mech))
    # A run that blew up: the balance is measured up to where its states were finite.
    bad = ~(np.isfinite(H) & np.isfinite(P) & np.isfinite(q[:len(t)]).all(axis=1)
            & np.isfinite(v[:len(t)]).all(axis=1))
    end = int(np.argmax(bad)) if bad.any() else len(t)
    if end >= MIN_SAMPLES:
        work = cumulative(t[:end], P[:end])
        finer = cumulative(t[:end], P[:end], DEGREE + 2)
        error[:end] = np.abs(H[:end] - H[0] - work)
        floor[:end] = np.maximum.accumulate(np.abs(work - finer))
    return t, error, floor
