"""The flexible-spacecraft benchmark problem: mechanics, invariants, linearisation, a short run."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

import problems
from integrators import make as make_integrator
from integrators.base import Grid, Status
from problems import flexible_spacecraft as fs
from studies.flexible.selection import free_free_frequencies_hz

MODELS = ["demo"] + (["fe"] if fs.DATA.exists() else [])


@pytest.fixture(scope="module")
def case():
    return problems.make("flexible-spacecraft:model=demo,t_end=4")


def random_state(k, seed=0, unit=True):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    if unit:
        q /= np.linalg.norm(q)
    omega, eta, eta_dot = rng.normal(size=3) * 0.2, rng.normal(size=k) * 0.1, rng.normal(size=k)
    x = np.concatenate([q, eta])
    v = np.concatenate([np.asarray(fs.quaternion_rate(q, omega)), eta_dot])
    return x, v, omega


def test_mass_matrix_is_positive_definite_off_the_manifold(case):
    k = case.system.n - 4
    for seed in range(5):
        x, _, _ = random_state(k, seed, unit=False)
        Mx = np.asarray(case.mech.mass(jnp.asarray(x)))
        # Symmetric by construction (a sum of congruences): round-off only.
        assert np.allclose(Mx, Mx.T, rtol=0, atol=1e-12 * np.abs(Mx).max())
        assert np.linalg.eigvalsh(Mx).min() > 0


def test_energy_and_momentum_are_the_hybrid_models(case):
    k = case.system.n - 4
    data = fs.load_model("demo")
    S = fs.rotation_elastic_block(data.M, k)
    Kee = data.K[6:6 + k, 6:6 + k]
    x, v, omega = random_state(k, 3)
    w = np.concatenate([omega, v[4:]])
    eta = x[4:]
    energy = 0.5 * w @ S @ w + 0.5 * eta @ Kee @ eta
    h = np.asarray(fs.rotation_matrix(x[:4])) @ (S[:3, :3] @ omega + S[:3, 3:] @ v[4:])
    xj, vj = jnp.asarray(x), jnp.asarray(v)
    # Two algebraically equal expressions on the manifold: round-off only.
    assert float(case.mech.energy(xj, vj)) == pytest.approx(energy, rel=1e-12)
    assert np.allclose(np.asarray(case.mech.invariant_values(xj, vj)), h,
                       rtol=1e-12, atol=1e-12 * np.abs(h).max())
    assert list(case.system.invariants) == ["Lx", "Ly", "Lz"]


def test_initial_state_is_consistent_and_tumbling(case):
    q0, v0 = jnp.asarray(case.q0), jnp.asarray(case.v0)
    assert abs(float(case.mech.g(q0, jnp.asarray(0.0))[0])) <= 1e-15
    assert abs(float(case.mech.vel_residual(q0, v0, jnp.asarray(0.0))[0])) <= 1e-15
    omega = 2.0 * np.asarray(fs.body_rate_matrix(q0[:4])) @ np.asarray(v0[:4])
    J = fs.rotation_elastic_block(fs.load_model("demo").M, 1)[:3, :3]
    # Tumbling: the initial angular momentum is not along the angular velocity.
    h = J @ omega
    assert np.linalg.norm(np.cross(h, omega)) > 0.1 * np.linalg.norm(h) * np.linalg.norm(omega)


@pytest.mark.parametrize("model", MODELS)
def test_linearisation_about_rest_reproduces_the_modal_frequencies(model):
    case = problems.make(f"flexible-spacecraft:model={model},w0x=0,w0y=0,w0z=0,eta0=0")
    k = case.system.n - 4
    data = fs.load_model(model)
    keep = np.r_[0:6 + k]
    expected = free_free_frequencies_hz(data.M[np.ix_(keep, keep)], data.K[np.ix_(keep, keep)])
    mech = case.mech
    x = jnp.asarray(case.q0)
    Mx = np.asarray(mech.mass(x))
    H = np.asarray(jax.hessian(mech.potential)(x))
    # At rest lambda = 0, so the constraint curvature adds nothing to the tangent stiffness.
    T = sla.null_space(np.asarray(mech.G(x, jnp.asarray(0.0))))
    lam = sla.eigh(T.T @ H @ T, T.T @ Mx @ T, eigvals_only=True)
    f = np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)
    # Three rigid rotations (zero to round-off) and the k elastic frequencies, equal to the
    # hybrid model's free-free ones up to round-off of two different eliminations.
    assert np.all(f[:3] < 1e-6 * f[3])
    assert np.allclose(f[3:], expected, rtol=1e-9)


def test_slew_torque_does_the_work_of_the_torque():
    case = problems.make("flexible-spacecraft:model=demo,slew_torque=2.0,slew_time=40,slew_axis=y")
    assert case.system.invariants == {} and not case.mech.has_energy
    x, v, omega = random_state(case.system.n - 4, 5)
    t = 7.0
    Qf = np.asarray(case.mech.external(jnp.asarray(t), jnp.asarray(x), jnp.asarray(v)))
    tau = 2.0 * np.sin(2 * np.pi * t / 40.0) * np.array([0.0, 1.0, 0.0])
    # The generalised force's power equals the torque's, tau . omega (round-off).
    assert Qf @ v == pytest.approx(tau @ omega, rel=1e-12)
    after = np.asarray(case.mech.external(jnp.asarray(41.0), jnp.asarray(x), jnp.asarray(v)))
    assert np.all(after == 0.0)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="n_modes"):
        problems.make("flexible-spacecraft:model=demo,n_modes=99")
    with pytest.raises(ValueError, match="model"):
        problems.make("flexible-spacecraft:model=nope")
    with pytest.raises(ValueError, match="slew_axis"):
        problems.make("flexible-spacecraft:model=demo,slew_axis=w")


def run(case, key, h):
    grid = Grid(case.t0, case.t_end, n_windows=10, n_samples=10)
    traj = make_integrator(key, h=h).prepare(case, grid)()
    assert traj.status == Status.OK, traj.message
    return traj


def test_rattle_conserves_angular_momentum_to_round_off_and_energy_to_order_two(case):
    h0 = case.mech.invariant_values(jnp.asarray(case.q0), jnp.asarray(case.v0))
    h_scale = float(np.max(np.abs(h0)))
    errors = []
    for h in (0.02, 0.01):
        traj = run(case, "rattle", h)
        n = traj.counts["n_steps"]
        # The momentum map is conserved exactly by the method; what is left is round-off
        # accumulated over n steps (about sqrt(n) * 10 eps relative).
        for name in ("inv:Lx", "inv:Ly", "inv:Lz"):
            assert traj.windows[name].max() <= 1e-13 * np.sqrt(n) * h_scale
        # |q| = 1 is enforced by the Newton iteration to its 1e-14 tolerance.
        assert traj.windows["pos"].max() <= 1e-13
        errors.append(traj.windows["energy"].max())
    # Symplectic, order 2: the energy error is O(h^2) and halving h divides it by about 4.
    assert 3.0 < errors[0] / errors[1] < 5.0
    # Its size is that of Stoermer-Verlet on the stiffest retained mode, a fraction of
    # (omega_max h)^2 of the energy.
    f_max = free_free_frequencies_hz(fs.load_model("demo").M, fs.load_model("demo").K).max()
    assert errors[1] < (2 * np.pi * f_max * 0.01) ** 2 * case.energy_scale
