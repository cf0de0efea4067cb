"""The stacked lattice of receiver rings against the reduced model and the single ring, its
degrees of freedom and hub, and its invariants."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import problems
from benchmarks.drift import classify
from helpers import embed, solve
from problems.case import project


def points(traj, case):
    """Sampled positions and velocities as ``(samples, K, 2N, 3)`` arrays."""
    shape = (len(traj.samples["t"]), case.params["K"], 2 * case.params["N"], 3)
    return traj.samples["q"].reshape(shape), traj.samples["v"].reshape(shape)


def random_configuration(case, seed):
    """A consistent configuration a random 0.05 away from the symmetric one (projected)."""
    mech = case.mech
    noise = 0.05 * np.random.default_rng(seed).standard_normal(mech.n)
    q, _ = project(mech, case.q0 + noise, np.zeros(mech.n), 0.0)
    # The Gauss-Newton projection stops at |g| <= 1e-15 (or at its round-off floor).
    assert np.max(np.abs(np.asarray(mech.g(jnp.asarray(q), 0.0)))) <= 1e-13
    return jnp.asarray(q)


def rigid_motions(q):
    """Velocity fields of the six rigid motions at the points ``q`` (``(P, 3)``):
    translations along and rotations about ``x``, ``y``, ``z``, each as an ``(n,)`` vector."""
    axes = np.eye(3)
    return {**{f"translation {a}": np.tile(e, len(q)) for a, e in zip("xyz", axes)},
            **{f"rotation {a}": np.cross(e, q).ravel() for a, e in zip("xyz", axes)}}


@pytest.mark.slow
def test_symmetric_lattice_rings_follow_the_reduced_model():
    _, reduced = solve("sps-receiver", "rattle", t_end=8.0, h=0.05)
    case, lattice = solve("sps-lattice:N=6,K=3", "rattle", t_end=8.0, h=0.05)
    assert np.array_equal(lattice.samples["t"], reduced.samples["t"])
    q, v = points(lattice, case)
    q_red, v_red = embed(reduced.samples, 6)
    z0 = case.q0.reshape(3, 12, 3)[..., 2]
    # Every ring moves as the reduced model and no point leaves its height: same method,
    # same step, same equations restricted to the symmetric states, so they agree to
    # accumulated round-off (measured: 1.5e-13 in the plane, 5e-14 along z; 2.6e-13 in
    # the plane with lobatto3ab3). As for the single ring, the round-off asymmetry,
    # amplified by the instability of the symmetric motion, passes 1e-12 near t = 10.
    assert np.max(np.abs(q[..., :2] - q_red[:, None])) <= 1e-12
    assert np.max(np.abs(v[..., :2] - v_red[:, None])) <= 1e-12
    assert np.max(np.abs(q[..., 2] - z0)) <= 1e-12
    assert np.max(np.abs(v[..., 2])) <= 1e-12


def test_symmetric_lattice_carries_the_ring_multipliers_and_nothing_else():
    reduced, lattice = problems.make("sps-receiver"), problems.make("sps-lattice:N=6,K=3")
    # Compiled: run eagerly, each autodiff operation would compile on its own.
    _, lam_red = jax.jit(reduced.mech.accelerations)(0.0, reduced.q0, reduced.v0)
    a, lam = jax.jit(lattice.mech.accelerations)(0.0, lattice.q0, lattice.v0)
    lam = np.asarray(lam)
    # Row order: ring 0's 12 bars and 3 hub rows; per link 12 axial bars, 6 braces and the
    # next ring's 12 bars; ring 2's 2 hub rows.
    ring_rows = np.r_[0:12, 15 + 18:15 + 30, 45 + 18:45 + 30]
    others = np.setdiff1d(np.arange(lattice.mech.m), ring_rows)
    # Each ring's bars carry the single ring's share, 1/12 of the reduced multiplier; the
    # axial bars, braces and hub carry nothing, and no point accelerates along z. The
    # multipliers come from one Cholesky solve with O(1) entries: round-off level.
    np.testing.assert_allclose(lam[ring_rows], float(lam_red[0]) / 12.0, rtol=1e-12)
    np.testing.assert_allclose(lam[others], 0.0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(a).reshape(-1, 3)[:, 2], 0.0, atol=1e-14)


@pytest.mark.slow
@pytest.mark.parametrize("coriolis", [False, True])
def test_single_ring_lattice_is_the_ring(coriolis):
    # The same equations, so one method shows it.
    spec = f"N=6,coriolis={str(coriolis).lower()}"
    ring_case, ring = solve(f"sps-ring:{spec}", "rattle", t_end=8.0, h=0.05)
    case, lattice = solve(f"sps-lattice:{spec},K=1", "rattle", t_end=8.0, h=0.05)
    assert case.mech.n == 36 and case.mech.m == 15  # the ring's 24 and 14, plus z and its row
    # The planar coordinates and the ring's constraint rows come first in the same order.
    np.testing.assert_array_equal(case.q0.reshape(-1, 3)[:, :2].ravel(), ring_case.q0)
    q, v = points(lattice, case)
    n = len(ring.samples["t"])
    # The same equations in x, y, with z exactly decoupled: agreement to accumulated
    # round-off (measured at most 1.7e-13 to t = 8), before the instability amplifies it.
    assert np.max(np.abs(q[:, 0, :, :2] - ring.samples["q"].reshape(n, 12, 2))) <= 1e-12
    assert np.max(np.abs(v[:, 0, :, :2] - ring.samples["v"].reshape(n, 12, 2))) <= 1e-12
    # Nothing pushes out of the plane: z stays exactly zero.
    assert np.max(np.abs(q[..., 2])) == 0.0 and np.max(np.abs(v[..., 2])) == 0.0


@pytest.mark.parametrize("N, K", [(5, 1), (5, 2), (4, 4)])
def test_degrees_of_freedom_match_the_rank_of_the_constraint_jacobian(N, K):
    case = problems.make(f"sps-lattice:N={N},K={K}")
    mech = case.mech
    G = np.asarray(jax.jit(mech.G)(random_configuration(case, seed=N + 10 * K), 0.0))
    s = np.linalg.svd(G, compute_uv=False)
    # Full row rank: the smallest singular value is far above round-off (1e-16 of the
    # largest), so the count below is not a matter of a threshold.
    assert s[-1] > 1e-6 * s[0]
    assert mech.n - mech.m == N * K + 3 * N - 3 - 2 * (K > 1)


@pytest.mark.parametrize("N, K", [(5, 1), (4, 3)])
def test_hub_removes_every_rigid_motion_but_the_spin(N, K):
    case = problems.make(f"sps-lattice:N={N},K={K}")
    mech = case.mech
    q = random_configuration(case, seed=1)
    G = np.asarray(jax.jit(mech.G)(q, 0.0))
    hub = np.r_[2 * N:2 * N + 3, mech.m - 2 * (K > 1):mech.m]
    bars = np.setdiff1d(np.arange(mech.m), hub)
    # The bars alone leave all six rigid motions free (G u = 0 to round-off of O(1)
    # entries); the hub removes all but the rotation about the spin axis (K = 1: the
    # tilts of a flat ring also stay free, as the problem states).
    free = {"rotation z"} | ({"rotation x", "rotation y"} if K == 1 else set())
    for name, u in rigid_motions(np.asarray(q).reshape(-1, 3)).items():
        assert np.max(np.abs(G[bars] @ u)) <= 1e-13, name
        blocked = np.max(np.abs(G[hub] @ u))
        assert (blocked <= 1e-13) if name in free else (blocked >= 1e-2), (name, blocked)


@pytest.mark.slow
def test_perturbed_lattice_keeps_constraints_energy_and_angular_momentum():
    # h = 0.004, not 0.01: with the seed's radii at N = 16 the constraint ellipse of
    # (R, r) is thin (axes 1.9 and 0.19), and every half period the rings swing round its
    # tip, where the zig-zag flips through flat and the bar forces peak at about 400
    # times their initial value for about 0.1 s, and by t = 11 the perturbation has grown
    # into a crumpled lattice. At h = 0.01 RATTLE's position step from t = 11.22 has no
    # solution (the least-squares minimum of |g| over lambda is 5.6e-5; see the module
    # docstring). Steps of 0.0048 to 0.0055 each meet a step, between t = 3.9 and 17.7,
    # where the position step's Newton fails, and at 0.005 that depended on the last
    # digits of the Krylov solves (XLA's options and the loop's form decided it). Where
    # the rings pass a configuration where G M^-1 G^T is numerically singular, the
    # structured path's simplified Newton (SuperLU here) diverges and Newton with the
    # exact Jacobian takes over, as the dense path's full Newton does
    # (benchmarks/perf/robustness.py runs both side by side).
    case, traj = solve("sps-lattice:N=16,K=8,perturb=0.01", "rattle", t_end=20.0, h=0.004)
    assert case.mech.n == 768 and case.mech.m == 597
    w = traj.windows
    # g = 0 and G v = 0 are solved to round-off at every step (newton_tol 1e-16; O(1)
    # coordinates; measured 2.0e-15 and 7.7e-15 to t = 20).
    assert np.max(w["pos"]) <= 1e-12
    assert np.max(w["vel"]) <= 1e-12
    # RATTLE is symplectic: the energy error stays bounded, without secular growth; its
    # largest excursion is at the first flip (measured 1.0 % of the scale, 0.4 % after
    # t = 10).
    assert np.max(w["energy"]) <= 3e-2 * case.energy_scale
    assert classify(w["t"], w["energy"]).kind == "bounded"
    # The angular momentum is a quadratic invariant of the rotation symmetry, which
    # RATTLE keeps exactly: only round-off accumulates (measured 5.9e-14).
    assert np.max(w["inv:angular_momentum"]) <= 1e-12


@functools.cache
def small_perturbed_run(coriolis):
    """RATTLE on a small perturbed lattice over t = 10 (shared by two tests)."""
    return solve(f"sps-lattice:N=4,K=3,perturb=0.1,seed=2,coriolis={str(coriolis).lower()}",
                 "rattle", t_end=10.0, h=0.01)


@pytest.mark.slow
@pytest.mark.parametrize("coriolis", [False, True])
def test_lattice_keeps_its_invariants_with_and_without_coriolis(coriolis):
    case, traj = small_perturbed_run(coriolis)
    # Applied (gyroscopic) forces switch the derived energy off; the Jacobi integral is
    # then declared.
    assert case.mech.has_energy != coriolis
    assert set(case.system.invariants) == {"angular_momentum"} | ({"jacobi"} if coriolis
                                                                  else set())
    energy = traj.windows["inv:jacobi" if coriolis else "energy"]
    # As for the ring: the Jacobi integral (the energy) oscillates at O(h^2) without drift
    # (measured 1e-5 of its scale either way), the angular momentum is kept to round-off
    # (measured 1e-14).
    assert np.max(energy) <= 1e-4 * case.energy_scale
    assert np.max(traj.windows["inv:angular_momentum"]) <= 1e-12


@pytest.mark.slow
def test_coriolis_force_changes_the_motion():
    (_, plain), (_, spun) = small_perturbed_run(False), small_perturbed_run(True)
    # Measured 0.36 apart at t = 10, against O(1) coordinates.
    assert np.max(np.abs(spun.q_final - plain.q_final)) > 1e-2


@pytest.mark.parametrize("spec, word", [
    ("K=0", "K = 0"), ("N=1", "N = 1"), ("H=0", "H = 0.0"), ("H=nan", "H = nan"),
    ("r0=-1", "r0 = -1.0"), ("M=0", "M = 0.0"), ("w=inf", "w = inf"),
    ("perturb=-0.1", "perturb = -0.1"),
])
def test_bad_parameters_are_refused_by_name(spec, word):
    with pytest.raises(ValueError, match=word):
        problems.make(f"sps-lattice:{spec}")
