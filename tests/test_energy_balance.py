"""The energy balance ``H - H_0 - W`` of damped and driven systems (benchmarks.balance)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from benchmarks.balance import DEGREE, MIN_SAMPLES, balance, cumulative
from benchmarks.metrics import summarize
from integrators import Grid
from problems.case import Reference, make_case
from problems.mechanics import System

#: Mass, radius, damping coefficient and initial angular rate of the damped bead.
M, R, C, OMEGA0 = 1.0, 1.0, 0.3, 2.0


def bead(t):
    """A bead on a fixed circle of radius R in the plane, no gravity, damped by ``-C v``:
    its rate decays as ``omega0 exp(-t C / M)``, so ``theta = omega0 M / C (1 - exp(-t C /
    M))`` from ``theta = 0``."""
    rate = OMEGA0 * np.exp(-C * t / M)
    theta = OMEGA0 * M / C * (1.0 - np.exp(-C * t / M))
    q = R * np.array([np.cos(theta), np.sin(theta)])
    return q, R * rate * np.array([-np.sin(theta), np.cos(theta)])


def damped_bead(t_end=2.0):
    system = System(n=2, m=1, mass=np.full(2, M),
                    constraints=lambda q, t: jnp.array([q @ q - R * R]),
                    forces=lambda t, q, v: -C * v)
    q0, v0 = bead(0.0)
    reference = Reference(kind="exact", source="closed form", solution=bead, scored=(0, 1))
    return make_case("damped-bead", system, q0, v0, (0.0, t_end), {},
                     energy_scale=0.5 * M * (R * OMEGA0) ** 2, reference=reference)


def driven_pendulum(t_end=2.0, a=0.1, rate=3.0, L=1.0, g=9.81):
    """A pendulum whose pivot is driven along x as ``a sin(rate t)`` (a moving constraint:
    the drive's work enters only through the constraint's multiplier)."""
    system = System(n=2, m=1, mass=np.full(2, M), rheonomic=True,
                    potential=lambda q: M * g * q[1],
                    constraints=lambda q, t: jnp.array(
                        [(q[0] - a * jnp.sin(rate * t)) ** 2 + q[1] ** 2 - L * L]))
    q0 = L * np.array([np.sin(0.5), -np.cos(0.5)])
    v0 = np.array([a * rate, 0.0])  # at rest relative to the pivot
    return make_case("driven-pendulum", system, q0, v0, (0.0, t_end), {},
                     energy_scale=M * g * L)


def _run(case, key, h):
    traj = integrators.make(key, h=h).prepare(case, Grid(case.t0, case.t_end))()
    assert traj.status == "ok", traj.message
    return summarize(case, traj), traj


def test_quadrature_order_and_its_error_estimate():
    """The quadrature of the work is of order DEGREE + 1 on uneven nodes, and the floor
    (its difference from the degree DEGREE + 2 rule) is its error to within a factor 2."""
    rng = np.random.default_rng(1)
    errors = []
    for n in (100, 200):
        t = np.linspace(0.0, 10.0, n) + rng.uniform(-0.3, 0.3, n) * 10.0 / n
        t[0], t[-1] = 0.0, 10.0
        work = cumulative(t, np.cos(t))
        error = np.max(np.abs(work - np.sin(t)))
        estimate = np.max(np.abs(work - cumulative(t, np.cos(t), DEGREE + 2)))
        assert 0.5 < estimate / error < 2.0
        errors.append(error)
    assert math.log2(errors[0] / errors[1]) > DEGREE + 0.5
    # Three nodes: the degree drops to what they allow (exact for a parabola).
    t = np.array([0.0, 0.3, 1.0])
    assert cumulative(t, t * t)[-1] == pytest.approx(1.0 / 3.0, rel=1e-14)


@pytest.mark.parametrize("key, order", [("rattle", 2), ("lobatto3ab3", 4)])
def test_damped_balance_converges_at_the_method_order(key, order):
    """On the damped bead (closed form) the balance error falls as h^order, far below the
    energy the damper took, and above its quadrature floor; the final state agrees with
    the closed form at the same order (the balance measures the method, not the
    quadrature)."""
    case = damped_bead()
    (coarse, _), (fine, traj) = (_run(case, key, h) for h in (0.04, 0.02))
    observed = math.log2(coarse["rel_balance_error"] / fine["rel_balance_error"])
    assert abs(observed - order) < 0.3, observed
    taken = abs(case.mech.energy(jnp.asarray(traj.q_final), jnp.asarray(traj.v_final))
                - case.mech.energy(jnp.asarray(case.q0), jnp.asarray(case.v0)))
    assert taken / case.energy_scale > 0.5  # the plain energy error: what was dissipated
    assert fine["rel_balance_error"] < 1e-3 * taken / case.energy_scale
    assert fine["balance_floor"] < 0.1 * fine["rel_balance_error"]
    assert math.isnan(fine["rel_energy_error"])


def test_a_moving_constraint_s_work_is_in_the_balance():
    """The driven pivot feeds energy in through the constraint force alone (no applied
    force): the balance, which counts it as ``lam . g_t``, converges at RATTLE's order 2
    and is far below the change of energy."""
    case = driven_pendulum()
    (coarse, _), (fine, traj) = (_run(case, "rattle", h) for h in (0.04, 0.02))
    assert abs(math.log2(coarse["rel_balance_error"] / fine["rel_balance_error"]) - 2) < 0.3
    energy = np.asarray([case.mech.energy(jnp.asarray(q), jnp.asarray(v))
                         for q, v in zip(traj.samples["q"], traj.samples["v"])])
    change = np.max(np.abs(energy - energy[0])) / case.energy_scale
    assert fine["rel_balance_error"] < 1e-2 * change


def test_balance_of_a_run_that_blew_up_stops_at_its_last_finite_state():
    """States that are not finite end the balance there (the run's status accounts for
    the rest); too few states for the quadrature's error estimate give no balance, not a
    balance without a floor."""
    case = damped_bead()
    t = np.linspace(0.0, 1.0, 21)
    states = [bead(s) for s in t]
    q = np.array([s[0] for s in states])
    v = np.array([s[1] for s in states])
    q[15:] = np.nan
    _, error, floor = balance(case.mech, {"t": t, "q": q, "v": v})
    assert np.isfinite(error[:15]).all() and np.isnan(error[15:]).all()
    assert np.max(error[:15]) < 1e-9 * case.energy_scale  # the exact motion balances
    assert np.isfinite(floor[:15]).all() and np.max(floor[:15]) > 0
    few = {k: x[:MIN_SAMPLES - 1] for k, x in {"t": t, "q": q, "v": v}.items()}
    assert np.isnan(balance(case.mech, few)[1]).all()


def test_a_finished_run_with_states_that_are_not_finite_has_no_balance():
    """The balance of a run that reports success is over all of its states or none: a
    maximum over a finite prefix would be a number for less than the run."""
    from integrators.base import Status, Trajectory

    case = damped_bead()
    t = np.linspace(0.0, 1.0, 21)
    q = np.array([bead(s)[0] for s in t])
    v = np.array([bead(s)[1] for s in t])
    windows = {"t": t[1:], "pos": np.zeros(20), "vel": np.zeros(20), "energy": np.zeros(20)}

    def balance_of(status):
        traj = Trajectory(status, "", 1.0, q[-1], v[-1], windows,
                          {"t": t, "q": q, "v": v}, {"n_steps": 20})
        return summarize(case, traj)["rel_balance_error"]

    assert balance_of(Status.OK) < 1e-9
    q[15:] = np.nan
    assert math.isnan(balance_of(Status.OK))
    assert balance_of(Status.FAILED) < 1e-9


def test_power_is_the_rate_of_energy_of_a_driven_system_with_a_varying_mass():
    """On the flyball governor (its mass depends on the rod angles, its drive is a moving
    constraint, its dampers applied forces): ``P = dH/dt`` along the motion, and the
    balance of a fresh system's samples is computed (the multipliers' solver is built
    outside the compiled measurement)."""
    import jax

    case = problems.make("flyball-governor")
    mech = case.mech
    t = np.linspace(0.0, 0.1, MIN_SAMPLES)
    samples = {"t": t, "q": np.tile(case.q0, (len(t), 1)), "v": np.tile(case.v0, (len(t), 1))}
    assert np.isfinite(balance(mech, samples)[1]).all()
    q = jnp.asarray(case.q0) + jnp.array([0.0, 0.05, 0.1, -0.05, 0.0])
    v = jnp.asarray(case.v0) + jnp.array([0.0, 0.3, 0.5, -0.2, 0.0])  # on G v + g_t = 0
    t0 = jnp.asarray(0.0)
    a, _ = mech.accelerations(t0, q, v)
    rate = (jax.grad(mech.energy, argnums=0)(q, v) @ v
            + jax.grad(mech.energy, argnums=1)(q, v) @ a)
    assert abs(float(rate)) > 1.0
    assert float(mech.power(t0, q, v)) == pytest.approx(float(rate), rel=1e-10)


@pytest.mark.slow
def test_report_shows_the_balance_in_place_of_the_energy_error(tmp_path):
    """A damped system's runs carry the balance columns, not an energy error, and the
    report's summary table and headline give the balance."""
    from benchmarks.api import sweep

    runs = sweep([damped_bead()], ["rattle"], h=[0.04, 0.02], out=tmp_path, report=True,
                 jobs=1, repeats=1, log=None)
    assert (runs["status"] == "ok").all()
    assert runs["rel_energy_error"].isna().all()
    assert (runs["rel_balance_error"] > runs["balance_floor"]).all()
    report = (tmp_path / "report.md").read_text()
    assert "max rel. energy balance error" in report
    assert "(energy balance)" in report
