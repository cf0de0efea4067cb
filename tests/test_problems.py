"""The problem library: autodiff derivatives against finite differences, consistent
initial values, declared invariants, and the references' own consistency."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import problems
from problems.case import project, residuals

#: Every problem of the library, at a size small enough for the checks to be quick.
LIBRARY = [
    "andrews", "car-axis", "double-pendulum", "chain:N=5", "four-bar:N=3", "bricard",
    "rigid-body", "sps-ring:N=5", "sps-ring:N=4,coriolis=true,perturb=0.1,seed=3",
    # The lattices take longer to trace than the rest together: checked by make test only.
    pytest.param("sps-lattice:N=3,K=3", marks=pytest.mark.slow),
    pytest.param("sps-lattice:N=4,K=2,coriolis=true,perturb=0.1,seed=3", marks=pytest.mark.slow),
]


def central(f, x, dx):
    """Central difference of ``f`` at ``x`` along ``dx``."""
    return (f(x + dx) - f(x - dx)) / 2.0


def fd_jacobian(f, x, step):
    """Central-difference Jacobian of ``f`` at ``x`` (columns along the unit vectors)."""
    cols = jax.jit(jax.vmap(lambda e: central(f, x, step * e) / step))(jnp.eye(x.shape[0]))
    return np.asarray(cols).T


def probe(case, seed=0):
    """A state near the initial one, off the manifold, and a time inside the horizon."""
    rng = np.random.default_rng(seed)
    n = case.mech.n
    q = case.q0 + 0.05 * rng.standard_normal(n)
    v = case.v0 + rng.standard_normal(n) * (1.0 + np.max(np.abs(case.v0)))
    t = case.t0 + 0.37 * (case.t_end - case.t0)
    return jnp.asarray(q), jnp.asarray(v), jnp.asarray(t)


@pytest.fixture(scope="module", params=LIBRARY)
def case(request):
    return problems.make(request.param)


def test_every_module_registers_its_problem():
    assert {"andrews", "car-axis", "double-pendulum", "chain", "four-bar", "bricard",
            "rigid-body", "sps-ring", "sps-lattice"} <= set(problems.names())


def test_initial_values_are_consistent_without_projection(case):
    pos, vel = residuals(case.mech, case.q0, case.v0, case.t0)
    # Initial values are built exactly (closed forms, published digits); only round-off
    # of the coordinates themselves may remain.
    assert pos <= 1e-13 and vel <= 1e-13, (pos, vel)
    assert "projected" not in case.notes


def test_constraint_jacobian_matches_finite_differences(case):
    mech = case.mech
    q, _, t = probe(case)
    G = np.asarray(mech.G(q, t))
    step = 1e-6
    fd = fd_jacobian(lambda x: mech.g(x, t), q, step)
    # Central differences with step 1e-6 on O(1) quadratic-to-trigonometric constraints:
    # truncation ~1e-12, cancellation ~1e-10 relative to the entries' scale.
    assert np.allclose(G, fd, rtol=1e-7, atol=1e-8 * (1.0 + np.max(np.abs(G))))


def test_time_derivatives_match_finite_differences(case):
    mech = case.mech
    q, v, t = probe(case, seed=1)
    step = 1e-6
    g_t = np.asarray(mech.g_t(q, t))
    fd_t = np.asarray(central(lambda s: mech.g(q, s), t, step)) / step
    assert np.allclose(g_t, fd_t, rtol=1e-6, atol=1e-8)
    # gamma is the derivative of G v + g_t along (q', t') = (v, 1) at fixed v.
    gamma = np.asarray(mech.gamma(q, v, t))
    fd_gamma = np.asarray(
        central(lambda s: mech.vel_residual(q + s * v, v, t + s), 0.0, step)) / step
    # Same step and error budget as the Jacobian test, scaled by |v|^2.
    scale = 1.0 + np.max(np.abs(gamma))
    assert np.allclose(gamma, fd_gamma, rtol=1e-6, atol=1e-7 * scale)


def test_force_matches_finite_differences_of_the_lagrangian(case):
    """``force = -grad U + f + c`` with ``c = grad_q(v^T M v)/2 - (dM/dq . v) v``."""
    mech = case.mech
    q, v, t = probe(case, seed=2)
    step = 1e-6
    T = lambda x: 0.5 * v @ mech.mass(x) @ v  # noqa: E731
    grad = lambda f: fd_jacobian(f, q, step)  # noqa: E731
    dM_v = np.asarray(central(lambda s: mech.mass(q + s * v), 0.0, step)) / step @ np.asarray(v)
    expected = (-grad(mech.potential) + grad(T) - dM_v
                + np.asarray(mech.external(t, q, v)))
    force = np.asarray(mech.force(t, q, v))
    # First derivatives by central differences (step 1e-6): ~1e-9 relative to the
    # largest term, which for andrews is a 4530 N/m spring.
    assert np.allclose(force, expected, rtol=1e-6, atol=1e-7 * (1.0 + np.max(np.abs(force))))


def test_hamiltonian_gradients_match_finite_differences(case):
    mech = case.mech
    q, v, _ = probe(case, seed=3)
    p = mech.momentum(q, v)
    step = 1e-6
    H_q = np.asarray(mech.H_q(q, p))
    fd = fd_jacobian(lambda x: mech.hamiltonian(x, p), q, step)
    assert np.allclose(H_q, fd, rtol=1e-6, atol=1e-7 * (1.0 + np.max(np.abs(H_q))))
    assert np.allclose(np.asarray(mech.H_p(q, p)), np.asarray(v), rtol=1e-10, atol=1e-10)


def test_mass_matrix_is_symmetric_positive_definite(case):
    q, _, _ = probe(case, seed=4)
    M = np.asarray(case.mech.mass(q))
    assert np.allclose(M, M.T, rtol=0, atol=1e-15 * np.max(np.abs(M)))
    assert np.min(np.linalg.eigvalsh(M)) > 0


#: Problems whose energy is not conserved (written out by hand from their modules: time-
#: dependent constraints, applied forces, or Coriolis forces in the rotating frame).
NOT_CONSERVATIVE = ("car-axis", "coriolis=true")


def test_energy_is_derived_exactly_when_it_is_conserved(case):
    spec = case.name + ":" + ",".join(f"{k}={v}" for k, v in case.params.items())
    expected = not any(mark in spec.lower() for mark in NOT_CONSERVATIVE)
    assert case.mech.has_energy == expected, spec


def test_index1_flow_conserves_declared_invariants(case):
    """The declared invariants (and the energy, where derived) have zero time derivative
    along the exact flow, checked at a consistent state with a random velocity."""
    mech = case.mech
    rng = np.random.default_rng(6)
    scale_v = 1.0 + np.max(np.abs(case.v0))
    q, v = project(mech, case.q0, case.v0 + scale_v * rng.standard_normal(mech.n), case.t0)
    q, v, t = jnp.asarray(q), jnp.asarray(v), jnp.asarray(case.t0)
    a, _ = mech.accelerations(t, q, v)
    funcs = dict(case.system.invariants)
    if mech.has_energy:
        funcs["energy"] = mech.energy
    for name, f in funcs.items():
        rate = float(jax.jvp(f, (q, v), (v, a))[1])
        terms = jax.grad(f, argnums=(0, 1))(q, v)
        scale = float(jnp.abs(terms[0]) @ jnp.abs(v) + jnp.abs(terms[1]) @ jnp.abs(a))
        # dI/dt = I_q v + I_v a cancels exactly on the manifold: what remains is round-off
        # of the two terms, relative 1e-15 for regular constraints and up to 1e-10 where
        # the least-squares multipliers of redundant ones (bricard) amplify it; plus an
        # absolute floor for invariants whose terms vanish at this state.
        assert abs(rate) <= 1e-9 * scale + 1e-13, (name, rate, scale)


def test_redundant_constraints_are_declared_and_solved():
    case = problems.make("bricard")
    G = np.asarray(case.mech.G(jnp.asarray(case.q0), 0.0))
    assert np.linalg.matrix_rank(G) == case.mech.m - 1
    assert "rank" in case.notes["rank_deficient"]
    a, lam = case.mech.accelerations(0.0, jnp.asarray(case.q0), jnp.asarray(case.v0))
    assert np.all(np.isfinite(np.asarray(lam)))
    # The least-squares multipliers give accelerations tangent to the constraints to
    # round-off amplified by the ill-conditioned (rank-deficient) Schur complement.
    assert np.max(np.abs(G @ np.asarray(a))) <= 1e-10
    assert np.max(np.abs(np.asarray(a))) > 1.0  # released from rest: gravity moves it


def test_andrews_coriolis_terms_match_the_test_set():
    from problems.andrews import testset_forces

    case = problems.make("andrews")
    mech = case.mech
    rng = np.random.default_rng(5)
    for _ in range(3):
        q = jnp.asarray(case.q0 + 0.3 * rng.standard_normal(7))
        v = jnp.asarray(100.0 * rng.standard_normal(7))
        ours = np.asarray(mech.force(0.0, q, v))
        # The Test Set's f includes the drive torque, which here is the potential -mom*beta.
        theirs = np.asarray(testset_forces(q, v))
        # Same terms in another order: agreement to a few ulps of the largest one.
        assert np.max(np.abs(ours - theirs)) <= 1e-13 * np.max(np.abs(theirs))


def test_andrews_initial_multipliers_match_the_test_set():
    case = problems.make("andrews")
    a, lam = case.mech.accelerations(0.0, jnp.asarray(case.q0), jnp.asarray(case.v0))
    # Test Set initial values y15, y16 (accelerations) and y22, y23 (multipliers), same
    # sign convention; they are given to 30 digits, we solve in double precision.
    np.testing.assert_allclose(np.asarray(a)[:2], [14222.4439199541138705911625887,
                                                   -10666.8329399655854029433719415],
                               rtol=1e-12)
    np.testing.assert_allclose(np.asarray(lam)[:2], [98.5668703962410896057654982170,
                                                     -6.12268834425566265503114393122],
                               rtol=1e-12)


def test_car_axis_initial_accelerations_match_the_test_set():
    case = problems.make("car-axis")
    a, lam = case.mech.accelerations(0.0, jnp.asarray(case.q0), jnp.asarray(case.v0))
    # Test Set: consistent initial accelerations (0, -1, 0, -1) with lambda(0) = 0.
    np.testing.assert_allclose(np.asarray(a), [0.0, -1.0, 0.0, -1.0], atol=1e-14)
    np.testing.assert_allclose(np.asarray(lam), [0.0, 0.0], atol=1e-14)


def test_four_bar_exact_solution_solves_its_ode_and_stays_on_the_constraints():
    from problems.four_bar import exact_solution

    case = problems.make("four-bar:N=3")
    mech = case.mech
    for t in (0.3, 4.1, 19.7):
        q, v = exact_solution(t, 3, 9.81, np.pi / 2)
        pos, vel = residuals(mech, q, v, t)
        assert pos <= 1e-13 and vel <= 1e-13
        # The closed form's acceleration (central difference, step 1e-5: error ~1e-9)
        # equals the DAE's index-1 acceleration off the singular configurations.
        step = 1e-5
        fd = (exact_solution(t + step, 3, 9.81, np.pi / 2)[1]
              - exact_solution(t - step, 3, 9.81, np.pi / 2)[1]) / (2 * step)
        a, _ = mech.accelerations(t, jnp.asarray(q), jnp.asarray(v))
        assert np.max(np.abs(np.asarray(a) - fd)) <= 1e-7


def test_rigid_body_closed_form_matches_an_independent_integration():
    from scipy.integrate import solve_ivp

    from problems.rigid_body import E_matrix, EulerTop, quat_mul

    J = np.array([1.0, 2.0, 3.0])
    top = EulerTop(J, 1.0, 1.0)

    def rhs(t, y):
        q, w = y[:4], y[4:]
        dw = np.array([(J[1] - J[2]) * w[1] * w[2] / J[0], (J[2] - J[0]) * w[2] * w[0] / J[1],
                       (J[0] - J[1]) * w[0] * w[1] / J[2]])
        return np.concatenate([0.5 * quat_mul(q, np.concatenate([[0.0], w])), dw])

    q0, v0 = top.state(0.0)
    sol = solve_ivp(rhs, (0.0, 20.0), np.concatenate([q0, top.omega(0.0)]), method="DOP853",
                    rtol=2.5e-14, atol=1e-14, t_eval=[3.0, 20.0])
    for i, t in enumerate(sol.t):
        q, v = top.state(t)
        # DOP853 at rtol 2.5e-14 over 20 s of a smooth flow: about 1e-13.
        assert np.max(np.abs(sol.y[:4, i] - q)) <= 1e-12
        assert np.max(np.abs(2 * np.asarray(E_matrix(q)) @ v - sol.y[4:, i])) <= 1e-12
