"""Ensembles of initial values: many consistent starts of one case, drawn reproducibly.

A method's drift and energy behaviour depend on where in phase space its trajectory runs,
so an ensemble runs it from ``K`` initial states near the case's own. Lane 0 starts from
the case's initial values as they are (the run the suite makes without an ensemble); lane
``i >= 1`` draws ``xi_q, xi_v ~ N(0, I_n)`` from NumPy's generator seeded with
``(seed, i)`` (so any one lane can be drawn again on its own) and starts from

.. math::

    q_i = P_g\\big(q_0 + \\sigma_q\\, D\\, \\xi_q\\big), \\qquad
    v_i = P_{G}\\big(v_0 + \\sigma_v\\, D\\, \\xi_v\\big),

where ``P_g`` is the mass-orthogonal projection onto ``g(q, t_0) = 0`` (Gauss-Newton),
``P_G`` the one onto ``G(q_i) v + g_t = 0`` (:func:`problems.case.project`, in batches of
one width), and ``D`` the 0/1 diagonal of the coordinates that are
perturbed. The sizes come from the case's :class:`~problems.case.Perturbation`:
``sigma_q = position * rms(q_0)`` (``position`` itself where ``q_0 = 0``) and
``sigma_v = sqrt(2 * velocity * energy_scale / tr M(q_0))``, so that the perturbation's
kinetic energy is about ``velocity`` times the case's energy scale whatever the units
(``tr M`` is estimated from a few products with ``M``, :data:`TRACE_PROBES`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from problems.case import CONSISTENT_TOL, Case, project

#: Most lanes of one ensemble (the loop's memory is a few kilobytes per lane).
MAX_LANES = 1 << 20
#: Largest seed: the store keeps it as a signed 64-bit integer.
MAX_SEED = (1 << 63) - 1
#: Probes of the estimate of ``tr M(q0)`` that scales the velocity noise.
TRACE_PROBES = 16


def draw(case: Case, lanes: int, seed: int = 0, first: int = 0
         ) -> tuple[np.ndarray, np.ndarray]:
    """``(q0s, v0s)``, each ``(lanes - first, n)``: the consistent initial states of the
    ensemble's lanes ``first`` to ``lanes - 1`` (a chunk of it: each lane is drawn and
    projected on its own, so it is the same whatever the chunk it is drawn in).

    Raises
    ------
    ValueError
        ``lanes`` out of range, or a perturbed state the projection could not bring within
        :data:`problems.case.CONSISTENT_TOL` of the constraints (a perturbation too large
        for the case: the message says which lane).
    """
    if not 1 <= lanes <= MAX_LANES:
        raise ValueError(f"an ensemble has 1 to {MAX_LANES} lanes, not {lanes}")
    if not 0 <= first < lanes:
        raise ValueError(f"lane {first} is not one of the ensemble's {lanes} lanes")
    n = case.q0.size
    spec = case.perturbation
    mask = np.ones(n)
    mask[list(spec.fixed)] = 0.0
    rms = float(np.sqrt(np.mean(case.q0 ** 2)))
    sigma_q = spec.position * (rms if rms > 0 else 1.0)
    # tr M(q0) by Hutchinson's estimate with Rademacher probes (exact for a diagonal M),
    # without forming M.
    probes = np.random.default_rng(0).choice([-1.0, 1.0], size=(TRACE_PROBES, n))
    trace = float(np.mean(jax.jit(jax.vmap(
        lambda z: z @ case.mech.mass_times(jnp.asarray(case.q0), z)))(probes)))
    sigma_v = float(np.sqrt(2.0 * spec.velocity * case.energy_scale / trace))
    drawn = range(max(first, 1), lanes)
    noise = np.array([np.random.default_rng([seed, i]).standard_normal(2 * n)
                      for i in drawn]).reshape(len(drawn), 2 * n)
    q = case.q0 + sigma_q * mask * noise[:, :n]
    v = case.v0 + sigma_v * mask * noise[:, n:]
    if len(drawn):
        q, v = project(case.mech, q, v, case.t0)
        error = np.maximum(*_residuals(case.mech, q, v, case.t0))
        bad = ~(error <= CONSISTENT_TOL)  # NaN is bad too
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{case.name}: lane {drawn[i]} of the ensemble of seed {seed} "
                             f"is {error[i]:.3g} off the constraints after projection (a "
                             f"perturbation too large for the case?)")
    if first > 0:
        return q, v
    return np.concatenate([case.q0[None], q]), np.concatenate([case.v0[None], v])


def _residuals(mech, q, v, t) -> tuple[np.ndarray, np.ndarray]:
    """Per lane, ``max |g|`` and ``max |G v + g_t|`` of a batch of states."""

    def one(q, v):
        return (jnp.max(jnp.abs(mech.g(q, t)), initial=0.0),
                jnp.max(jnp.abs(mech.vel_residual(q, v, t)), initial=0.0))

    pos, vel = jax.jit(jax.vmap(one))(jnp.asarray(q), jnp.asarray(v))
    return np.asarray(pos), np.asarray(vel)
