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

References of the lanes
-----------------------
Where the case has a reference at ``t`` (lane 0's), each lane gets one of its own
(:func:`references`): the index-1 ODE ``q' = v``, ``v' = a(t, q, v)`` of the case's
:class:`~problems.mechanics.Mechanics` (``a`` from
:meth:`~problems.mechanics.Mechanics.accelerations`), integrated by scipy's DOP853 at
``rtol = atol =`` :data:`REFERENCE_RTOL` for :data:`REFERENCE_LANES` lanes at a time, its
end states projected onto ``g = 0`` and ``G v + g_t = 0``. Lane ``i`` is integrated in
block ``i //`` :data:`REFERENCE_LANES`, always whole, so its reference, like its initial
state, depends neither on the size of the ensemble nor on its chunks. Its floor
(:attr:`~problems.case.Reference.floor`) is the lane's max-norm difference, on the scored
components, to the same integration at :data:`ESTIMATE_RTOL`, which estimates the error
of that looser run and so, conservatively, of the reference: the way the stored references
of :mod:`problems.data.generate` are made. This reference shares the model with the
benchmarked runs and checks their integration, as the ``bricard`` one does.
"""

from __future__ import annotations

import json
from collections import OrderedDict

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

from problems.case import CONSISTENT_TOL, PROJECT_WIDTH, Case, Reference, project
from problems.data.generate import TIGHT_RTOL

#: Most lanes of one ensemble (the loop's memory is a few kilobytes per lane).
MAX_LANES = 1 << 20
#: Largest seed: the store keeps it as a signed 64-bit integer.
MAX_SEED = (1 << 63) - 1
#: Probes of the estimate of ``tr M(q0)`` that scales the velocity noise.
TRACE_PROBES = 16
#: Lanes whose references are integrated as one ODE (one compiled right-hand side for all
#: of them, with one step sequence: a fraction of the cost per lane of integrating them one
#: by one). Bounded like the projection's batches
#: (:data:`problems.case.PROJECT_WIDTH`). DOP853 controls one error norm over the whole
#: block, so what tells a lane's accuracy is its own floor, measured lane by lane.
REFERENCE_LANES = PROJECT_WIDTH
#: Tolerance of the lanes' references: that of the stored references.
REFERENCE_RTOL = TIGHT_RTOL
#: Tolerance of the integration that estimates their error. On the pendulum over 100 s lane
#: 0's reference was 3.3e-9 from the closed form, and its estimate 1.0e-8 at 1e-13 (1.3e-7
#: at 1e-12, the stored references' looser tolerance).
ESTIMATE_RTOL = 1e-13
#: Most right-hand sides one integration of a block of references may evaluate; the lanes
#: of a block that needs more get no reference. The pendulum over 100 s takes 6.8e4 at
#: :data:`REFERENCE_RTOL`; the stiff flyball governor over 10 s 8e5 (16 lanes).
MAX_REFERENCE_EVALS = 200_000
#: Bytes of references a process keeps, least recently used block first out (always the
#: latest block): 256 bytes a lane on the pendulum, 2 MiB a lane on ``chain:N=16384``.
#: Bounded in bytes, not blocks, so that a sweep over the runs of one large ensemble does
#: not drop each block before its next run takes it.
KEPT_BYTES = 256 << 20
_BLOCKS: OrderedDict = OrderedDict()


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


def references(case: Case, seed: int, first: int, stop: int, t: float
               ) -> tuple[list[Reference | None], tuple[str, ...]]:
    """The references at ``t`` of the lanes ``first`` to ``stop - 1`` of the ensembles
    drawn with ``seed`` (see the module's notes), each ``None`` where the case has no
    reference at ``t`` or its block got none, and why each block that got none did not
    (empty where every block got its references).

    A block is computed once per process, so the runs of the ensembles of one case and
    seed, whatever their methods, steps and sizes, share it as long as it is kept (the
    latest :data:`KEPT_BYTES`); :func:`forget` drops them.
    """
    own = case.reference
    if own is None or not own.available_at(t):
        return [None] * (stop - first), ()
    key = (case.name, json.dumps(case.params, sort_keys=True, default=repr), case.t0,
           case.q0.tobytes(), case.v0.tobytes(), case.energy_scale, case.perturbation,
           seed, t)
    out, why = [], []
    for block in range(first // REFERENCE_LANES, (stop - 1) // REFERENCE_LANES + 1):
        if (key, block) not in _BLOCKS:
            _BLOCKS[key, block] = _block(case, seed, block, t)
            while len(_BLOCKS) > 1 and sum(
                    states.nbytes + floors.nbytes for states, floors, _ in _BLOCKS.values()
            ) > KEPT_BYTES:
                _BLOCKS.popitem(last=False)
        _BLOCKS.move_to_end((key, block))
        start = block * REFERENCE_LANES
        states, floors, failure = _BLOCKS[key, block]
        if failure:
            why.append(f"lanes {start} to {start + REFERENCE_LANES - 1}: {failure}")
        for i in range(max(first, start), min(stop, start + REFERENCE_LANES)):
            y, floor = states[i - start], floors[i - start]
            out.append(None if failure else Reference(
                kind="computed",
                source=(f"lane {i} of the ensemble of seed {seed}: index-1 ODE by scipy "
                        f"DOP853 at rtol = atol = {REFERENCE_RTOL:g}, projected; floor = "
                        f"difference to rtol = {ESTIMATE_RTOL:g}"),
                solution=lambda _t, y=y: (y[:case.q0.size], y[case.q0.size:]),
                scored=own.scored, times=(t,), floor=float(floor), span=(case.t0, t)))
    return out, tuple(why)


def forget() -> None:
    """Drop the references this process keeps (a problem's definition was replaced)."""
    _BLOCKS.clear()


class _OutOfEvaluations(Exception):
    pass


def _block(case: Case, seed: int, block: int, t: float
           ) -> tuple[np.ndarray, np.ndarray, str]:
    """The projected states ``(q, v)`` at ``t`` (one row per lane) and floors of the lanes
    of ``block``, and ``""``; or, where a lane of the block could not be drawn, the
    integration failed or raised, or a state is not finite, NaN and why."""
    first = block * REFERENCE_LANES
    k, n = REFERENCE_LANES, case.q0.size
    mech = case.mech

    @jax.jit
    def rhs(s, y):
        q, v = y.reshape(2, k, n)
        a = jax.vmap(lambda q, v: mech.accelerations(s, q, v)[0])(q, v)
        return jnp.concatenate([v.ravel(), a.ravel()])

    def failed(why: str):
        return np.full((k, 2 * n), np.nan), np.full(k, np.nan), why

    try:
        q0, v0 = draw(case, first + k, seed, first)
        ends = []
        for rtol in (REFERENCE_RTOL, ESTIMATE_RTOL):
            calls = [0]

            def f(s, y):
                calls[0] += 1
                if calls[0] > MAX_REFERENCE_EVALS:
                    raise _OutOfEvaluations
                return np.asarray(rhs(s, y))

            sol = solve_ivp(f, (case.t0, t), np.concatenate([q0.ravel(), v0.ravel()]),
                            method="DOP853", rtol=rtol, atol=rtol)
            if sol.status != 0:
                return failed(f"DOP853 at rtol {rtol:g} stopped at t = {sol.t[-1]:.6g}: "
                              f"{sol.message}")
            q, v = sol.y[:, -1].reshape(2, k, n)
            ends.append(np.concatenate(project(mech, q, v, t), axis=1))
    except _OutOfEvaluations:
        return failed(f"DOP853 needed more than {MAX_REFERENCE_EVALS:,} right-hand sides "
                      f"(problems.ensemble.MAX_REFERENCE_EVALS)")
    except Exception as exc:  # the reference is not the run: its failure is a note
        what = str(exc).strip().splitlines()
        return failed(f"{type(exc).__name__}" + (f": {what[0]}" if what else ""))
    floors = np.max(np.abs(ends[0] - ends[1])[:, list(case.reference.scored)], axis=1)
    if not (np.isfinite(floors).all() and np.isfinite(ends[0]).all()):
        return failed("a lane's reference is not finite")
    return ends[0], floors, ""
