"""The augmented-system (``kkt``) solver for a constant mass that is not diagonal."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import problems
from helpers import solve
from test_spelling import coupled_mass_system
from linalg.kkt import BandedMass, band_ldl, band_ldl_solve


def horizontal(N, angle):
    """four-bar's tips with every crank at ``angle`` from the ground line."""
    return jnp.asarray(np.stack([np.arange(N + 1) + np.cos(angle),
                                 np.full(N + 1, np.sin(angle))], axis=1).ravel())


def schur_and_solution(mech, q, r):
    """Dense ``S = G M^-1 G^T`` and the kkt solver's ``S^-1 r``."""
    t = jnp.asarray(0.0)
    G, M = np.asarray(mech.G(q, t)), np.asarray(mech.mass(q))
    kkt = mech.schur("kkt")
    assert kkt.name == "kkt" and kkt.nnz > 0
    F = jax.jit(kkt.factor)(q, t)
    assert bool(F.ok)
    return G, G @ np.linalg.solve(M, G.T), np.asarray(jax.jit(kkt.solve)(F, jnp.asarray(r))), F


def test_kkt_solve_equals_the_dense_schur_solve():
    # four-bar away from its singular configurations: S has condition number about 3e3
    # here, so two backward stable solves agree to a few hundred eps relative.
    case = problems.make("four-bar:N=5")
    mech = case.mech
    q = jnp.asarray(case.q0 + 1e-2 * np.random.default_rng(0).standard_normal(mech.n))
    r = np.random.default_rng(1).standard_normal((mech.m, 3))
    _, S, y, F = schur_and_solution(mech, q, r)
    assert np.max(np.abs(y - np.linalg.solve(S, r))) <= 1e-12 * np.max(np.abs(y))
    # The bound on ||S||_inf that Newton's convergence test uses is one.
    assert float(F.norm) >= np.max(np.sum(np.abs(S), axis=1))


@pytest.mark.parametrize("spec", ["bricard", "four-bar:N=5"])
def test_kkt_solve_drops_dependent_constraints(spec):
    # bricard's G has rank 23 of 24 everywhere; four-bar's has rank N + 1 of 2N + 1 with
    # the cranks horizontal. For a consistent right-hand side the dropped rows' multipliers
    # are zero and the rest solve exactly: the constraint force G^T y is the dense path's
    # (unique) one, to round-off (bricard's S spans five decades, its axes' inertia being
    # a^2/12 of the points': measured 1.8e-13 relative).
    case = problems.make(spec)
    mech = case.mech
    q = jnp.asarray(case.q0) if spec == "bricard" else horizontal(5, 0.0)
    G = np.asarray(mech.G(q, jnp.asarray(0.0)))
    r = G @ np.random.default_rng(2).standard_normal(mech.n)
    G, S, y, F = schur_and_solution(mech, q, r)
    dependent = mech.m - np.linalg.matrix_rank(G, tol=1e-10)
    assert int(np.sum(np.asarray(F.data[1]) == 0)) == dependent > 0
    assert np.max(np.abs(S @ y - r)) <= 1e-12 * np.max(np.abs(r))
    force = G.T @ np.linalg.lstsq(S, r, rcond=None)[0]
    assert np.max(np.abs(G.T @ y - force)) <= 1e-12 * np.max(np.abs(force))


@pytest.mark.slow
def test_kkt_solve_near_a_singular_configuration_is_as_accurate_as_dense():
    # Cranks 1e-3 rad from horizontal: S has condition number 1e8, the residuals of both
    # solves are at that times eps, and the kkt one is no worse than 4x the dense one.
    mech = problems.make("four-bar:N=40").mech
    r = np.random.default_rng(3).standard_normal(mech.m)
    _, S, y, _ = schur_and_solution(mech, horizontal(40, 1e-3), r)
    dense = np.linalg.solve(S, r)
    assert np.max(np.abs(S @ y - r)) <= 4 * max(np.max(np.abs(S @ dense - r)), 1e-15)


def test_band_ldl_factorises_an_indefinite_band_and_drops_dependent_rows():
    # K = [[M, G^T], [G, 0]] interleaved so that every constraint follows its coordinates;
    # the last constraint repeats the second: its pivot vanishes and its unknown is zero.
    rng = np.random.default_rng(4)
    n = 6
    A = rng.standard_normal((n, n))
    M = np.triu(np.tril(A @ A.T + n * np.eye(n), 1), -1)
    G = np.zeros((3, n))
    G[0, 0:2], G[1, 2:4] = rng.standard_normal(2), rng.standard_normal(2)
    G[2] = G[1]
    K = np.block([[M, G.T], [G, np.zeros((3, 3))]])
    order = [0, 1, 6, 2, 3, 7, 8, 4, 5]
    K = K[np.ix_(order, order)]
    w = 4
    Kb = np.zeros((len(K), w + 1))
    for i in range(len(K)):
        for k in range(min(i, w) + 1):
            Kb[i, k] = K[i, i - k]
    assert np.all(K[np.abs(np.subtract.outer(range(9), range(9))) > w] == 0)
    X, D = band_ldl(jnp.asarray(Kb))
    assert float(D[6]) == 0.0 and np.sum(np.asarray(D) == 0) == 1
    rhs = K @ rng.standard_normal(len(K))
    x = np.asarray(band_ldl_solve(X, D, jnp.asarray(rhs)[:, None]))[:, 0]
    assert x[6] == 0.0
    assert np.max(np.abs(K @ x - rhs)) <= 1e-13 * np.max(np.abs(rhs))


def test_banded_mass_multiplies_and_solves_like_the_dense_one():
    M = sp.csr_matrix(np.asarray(problems.make("bricard").mech.mass(jnp.zeros(24))))
    band = BandedMass(M)
    x = np.random.default_rng(5).standard_normal((24, 2))
    dense = M.toarray()
    assert np.max(np.abs(np.asarray(band.times(jnp.asarray(x))) - dense @ x)) <= 1e-15
    assert np.max(np.abs(np.asarray(band.solve(jnp.asarray(x[:, 0]))) - np.linalg.solve(dense, x[:, 0]))) \
        <= 1e-12 * np.max(np.abs(np.linalg.solve(dense, x[:, 0])))
    with pytest.raises(ValueError, match="not positive definite"):
        BandedMass(sp.csr_matrix(-dense))


def test_auto_choice_takes_the_augmented_system_for_a_large_banded_mass():
    mech = problems.make("four-bar:N=64").mech
    kkt = mech.schur()
    assert kkt.name == "kkt" and kkt.bandwidth == 7
    # M is never formed: its products and solves are banded.
    assert mech.mass_band is not None and not hasattr(mech, "_Minv")
    assert problems.make("four-bar:N=2").mech.schur().name == "dense"
    # A configuration-dependent mass in blocks (andrews') is whitened onto a unit mass.
    assert problems.make("andrews").mech.schur("kkt").name == "kkt"
    with pytest.raises(ValueError, match="needs a constant or block-diagonal mass"):
        coupled_mass_system().mech.schur("kkt")
    # Its mass is one band of coupled points, not small blocks.
    with pytest.raises(ValueError, match="diagonal or block-diagonal mass.*or kkt"):
        mech.schur("banded")


#: One key per implementation: the other Lobatto IIIA-IIIB members differ from
#: lobatto3ab3 in their tableau alone, and hht is generalized-alpha's index-3 step with
#: other coefficients; the linear algebra they call is the same.
FAMILIES = ["rattle", "lobatto3ab3", "genalpha", "genalpha-ggl", "baumgarte-rk4"]


# Each family on bricard, whose redundant constraint every kkt solve must drop, but for
# index-3 generalized-alpha, whose Newton diverges on bricard on the dense path too (the
# library suite's expected failure): it is compared on four-bar. The kkt solve itself is
# compared with the dense one on both problems above.
@pytest.mark.slow
@pytest.mark.parametrize("spec, key", [
    ("four-bar:N=4" if family == "genalpha" else "bricard", family) for family in FAMILIES])
def test_every_fixed_step_family_gives_the_dense_result_on_the_kkt_path(spec, key):
    # The same equations solved to round-off by two linear algebras (bricard with its
    # redundant constraint on both), over 50 steps of h = 1e-3. Measured: q agree to 2e-15,
    # v to 2e-14 but for index-3 genalpha (3.7e-12: its velocities carry the positions'
    # round-off divided by h).
    _, dense = solve(spec, f"{key}:linear_solver=dense", 0.05, h=1e-3)
    _, kkt = solve(spec, f"{key}:linear_solver=kkt", 0.05, h=1e-3)
    assert dense.linear_solver == "dense" and kkt.linear_solver == "kkt"
    assert kkt.pattern_nnz > 0
    assert np.max(np.abs(kkt.q_final - dense.q_final)) <= 1e-12
    assert np.max(np.abs(kkt.v_final - dense.v_final)) <= 1e-11
