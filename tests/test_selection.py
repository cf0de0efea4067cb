"""Retained-mode selection: modal costs, Gramians, balanced truncation, Table 2 machinery.

Everything runs on small synthetic hybrid models built here: a rigid hub carrying two
"panels", each a chain of point masses on springs that move relative to the hub frame,
reduced on the chains' own (hub-fixed) modes exactly as a system modal set is.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from studies.flexible import selection as sel
from problems.flexible_spacecraft import hybrid_spring_mass, skew


def panel_spacecraft(n_nodes: int = 4, asym: float = 0.07):
    """Full physical hybrid model of a hub with two spring-mass chains along +-y.

    Each chain node moves in x and z relative to the hub frame; consecutive nodes (and the
    root node and the hub) are joined by springs. ``asym`` makes the -y panel stiffer so
    that the symmetric and antisymmetric panel modes do not coincide.

    Returns ``(M, K, Phi_full)``: physical hybrid matrices and the chain's hub-fixed modes.
    """
    hub_mass, J = 170.0, np.diag([620.0, 300.0, 520.0]) + 15.0 * np.ones((3, 3))
    positions, masses, dirs = [], [], []
    for side in (1.0, -1.0):
        for j in range(n_nodes):
            for d in ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)):
                positions.append((0.1 * side, side * (1.6 + 1.4 * (j + 0.5) / n_nodes), 0.05))
                masses.append(11.3 / n_nodes)
                dirs.append(d)
    apps = [(m, p, d, 0.0) for m, p, d in zip(masses, positions, dirs)]
    M, _ = hybrid_spring_mass(hub_mass, J, apps)
    n_u = len(apps)
    Ku = np.zeros((n_u, n_u))
    for s_idx, side_k in enumerate((1.0, 1.0 + asym)):
        for comp, k0 in enumerate((60.0, 900.0)):  # out-of-plane soft, in-plane stiff
            idx = [s_idx * 2 * n_nodes + 2 * j + (1 - comp) for j in range(n_nodes)]
            k = k0 * side_k * n_nodes
            for a, b in zip([None] + idx[:-1], idx):
                if a is None:
                    Ku[b, b] += k
                else:
                    Ku[np.ix_([a, b], [a, b])] += k * np.array([[1.0, -1.0], [-1.0, 1.0]])
    K = np.zeros_like(M)
    K[6:, 6:] = Ku
    _, Phi = sla.eigh(Ku, M[6:, 6:])
    return M, K, Phi


def reduce_on_modes(M, K, Phi, k):
    """Hybrid model on the first ``k`` hub-fixed modes (the system modal set)."""
    T = sla.block_diag(np.eye(6), Phi[:, :k])
    return T.T @ M @ T, T.T @ K @ T


class Model:
    def __init__(self, M, K):
        self.M, self.K = M, K


@pytest.fixture(scope="module")
def spacecraft():
    M, K, Phi = panel_spacecraft()
    return reduce_on_modes(M, K, Phi, 8)


def gramian_quadrature(A, B, t_max, dt=0.05):
    """``int_0^t_max e^{At} B B^T e^{A^T t} dt`` by 5-point Gauss-Legendre on panels."""
    x, w = np.polynomial.legendre.leggauss(5)
    nodes = 0.5 * dt * (x + 1.0)
    at_nodes = [sla.expm(A * t) @ B for t in nodes]
    step = sla.expm(A * dt)
    total = np.zeros((A.shape[0], A.shape[0]))
    Phi = np.eye(A.shape[0])
    for _ in range(int(round(t_max / dt))):
        for wk, Ek in zip(w, at_nodes):
            X = Phi @ Ek
            total += 0.5 * dt * wk * X @ X.T
        Phi = step @ Phi
    return total


def test_free_free_modes_are_the_full_eigenproblem(spacecraft):
    M, K = spacecraft
    omega, Phi = sel.free_free_modes(M, K)
    lam = sla.eigh(K, M, eigvals_only=True)
    # The full problem has six zero eigenvalues (round-off about 1e-12 of the largest); the
    # elastic ones must agree with the rigid-eliminated problem to round-off.
    assert np.allclose(np.sort(lam)[6:], omega ** 2, rtol=1e-10)
    assert np.allclose(Phi.T @ M @ Phi, np.eye(len(omega)), atol=1e-12)
    assert np.allclose(Phi.T @ K @ Phi, np.diag(omega ** 2), rtol=1e-10, atol=1e-9)


def test_gramians_match_their_integral_definitions(spacecraft):
    M, K = spacecraft
    mm = sel.modal_model(M, K, zeta=0.05, n_modes=3)
    A, B, C = mm.state_space()
    Wc, Wo = sel.gramians(A, B, C)
    # The integrand decays like exp(-2 zeta omega_min t): at t_max it is below 1e-16.
    t_max = np.ceil(40.0 / (2 * 0.05 * mm.omega.min()))
    Wq = gramian_quadrature(A, B, t_max)
    Vq = gramian_quadrature(A.T, C.T, t_max)
    # Gauss-Legendre with 5 nodes on 0.05 s panels is exact to ~1e-14 for these smooth,
    # slowly oscillating integrands; 1e-9 relative leaves room for the 1e5 accumulated panels.
    assert np.max(np.abs(Wq - Wc)) <= 1e-9 * np.max(np.abs(Wc))
    assert np.max(np.abs(Vq - Wo)) <= 1e-9 * np.max(np.abs(Wo))


def test_hankel_singular_values_and_balanced_gramians(spacecraft):
    M, K = spacecraft
    mm = sel.modal_model(M, K)
    A, B, C = mm.state_space()
    Wc, Wo = sel.gramians(A, B, C)
    hsv = sel.hankel_singular_values(Wc, Wo)
    direct = np.sort(np.sqrt(np.abs(np.linalg.eigvals(Wc @ Wo))))[::-1]
    # The eigenvalues of the unsymmetric product are accurate to about cond * eps relative
    # to the largest; the values below 1e-6 sigma_1 are not compared.
    big = hsv > 1e-6 * hsv[0]
    assert np.allclose(hsv[big], direct[big], rtol=1e-6)
    bal = sel.balanced_realisation(A, B, C)
    Wb, Vb = sel.gramians(bal.A, bal.B, bal.C)
    # Balanced means both Gramians equal diag(sigma); round-off of the square-root method
    # is about eps * sigma_1 / sigma_min.
    s1 = bal.hsv[0]
    assert np.max(np.abs(Wb - np.diag(bal.hsv))) <= 1e-8 * s1
    assert np.max(np.abs(Vb - np.diag(bal.hsv))) <= 1e-8 * s1


def test_balanced_truncation_error_within_bound_at_every_order(spacecraft):
    M, K = spacecraft
    mm = sel.modal_model(M, K)
    bal = sel.balanced_realisation(*mm.state_space())
    table = sel.truncation_errors(mm, bal=bal)
    assert len(table) == len(bal.hsv) - 1
    assert table["holds"].all(), table
    # The error of a truncation is also at least the first discarded Hankel singular value
    # (a lower bound of any order-k approximation); 1e-6 relative slack for the peak search.
    lower = bal.hsv_all[table["order"].to_numpy()]
    assert np.all(table["error_hinf"] >= lower * (1 - 1e-6))
    # Dropping only the smallest (simple) Hankel singular value attains the bound exactly,
    # ||G - G_{n-1}||_inf = 2 sigma_n: a check of the H-infinity evaluation itself.
    last = table.iloc[-1]
    assert last["error_hinf"] == pytest.approx(2 * bal.hsv[-1], rel=1e-6)


def test_full_transfer_matches_state_space(spacecraft):
    M, K = spacecraft
    mm = sel.modal_model(M, K)
    w = sel.frequency_grid(mm.omega, mm.zeta)[::7]
    # Two evaluations of the same rational function: round-off only.
    G1 = mm.transfer(w)
    G2 = sel.state_space_transfer(*mm.state_space(), w)
    assert np.max(np.abs(G1 - G2)) <= 1e-10 * np.max(np.abs(G1))


def test_modal_costs_sum_to_the_lyapunov_total(spacecraft):
    M, K = spacecraft
    rel = []
    for zeta in (1e-2, 1e-3, 1e-4):
        mm = sel.modal_model(M, K, zeta=zeta)
        total, components = sel.cost_decomposition(mm)
        # Skelton's component costs add up to the total by construction (round-off).
        assert components.sum() == pytest.approx(total, rel=1e-12)
        rel.append(abs(sel.modal_costs(mm).sum() - total) / total)
    # Equation (3) is the weak-damping limit: the error of its sum falls like zeta.
    assert rel[-1] < 1e-4
    assert rel[0] / rel[1] > 5 and rel[1] / rel[2] > 5


def test_modal_cost_weights_and_velocity_outputs(spacecraft):
    M, K = spacecraft
    n = M.shape[0]
    rng = np.random.default_rng(3)
    Q = np.diag([1.0, 2.0, 0.5])
    W = np.diag([0.3, 1.0, 4.0])
    Cv = rng.normal(size=(3, n)) * 1e-2
    mm = sel.modal_model(M, K, Cv=Cv, zeta=1e-4)
    total, components = sel.cost_decomposition(mm, Q, W)
    V = sel.modal_costs(mm, Q, W)
    # At zeta = 1e-4 the cross-mode covariances are O(zeta) of the modal ones (separated
    # modes), so each modal cost matches its exact component to ~1e-3 relative at worst.
    big = components > 1e-6 * components.max()
    assert np.allclose(V[big], components[big], rtol=2e-3)


def test_gregory_approximation_for_separated_modes(spacecraft):
    M, K = spacecraft
    mm = sel.modal_model(M, K, zeta=1e-3)
    bal = sel.balanced_realisation(*mm.state_space())
    exact, purity = sel.modal_hsv(mm, bal)
    greg = sel.gregory_hsv(mm)
    ratios = sel.separation_ratios(mm)
    sep = np.nanmax(ratios, axis=1)
    ok = (exact > 1e-6 * exact.max()) & (sep < 0.05)
    assert ok.sum() >= 4
    # Equation (4) is exact as zeta -> 0 for separated modes; with every separation ratio
    # below 0.05 the modal coupling it neglects changes sigma by a few percent at most.
    assert np.allclose(exact[ok], greg[ok], rtol=0.05)
    assert np.all(purity[ok] > 0.9)


def test_close_modes_form_a_cluster():
    # Two light appendages on a heavy hub (so the hub barely shifts their frequencies) at
    # stiffnesses 0.2 % apart: their modes fail equation (5) at zeta = 0.005.
    apps = [(5.0, (0.0, 2.0, 0.0), (1.0, 0.0, 0.0), 5.0 * (2 * np.pi) ** 2),
            (5.0, (0.0, -2.0, 0.0), (1.0, 0.0, 0.0), 5.0 * (2 * np.pi * 1.002) ** 2),
            (3.0, (1.0, 0.0, 1.0), (0.0, 1.0, 0.0), 3.0 * (2 * np.pi * 3.0) ** 2)]
    M, K = hybrid_spring_mass(1e4, np.diag([5e4, 6e4, 7e4]), apps)
    mm = sel.modal_model(M, K)
    labels = sel.clusters(mm)
    assert labels[0] == labels[1] != labels[2]
    pairs = sel.separation_pairs(mm)
    assert len(pairs) == 3
    assert list(pairs["separated"]) == [False, True, True]
    table, trunc = sel.analyse(M, K)
    assert trunc["holds"].all()
    assert (table["cluster"].to_numpy() == labels).all()


def test_selection_rule_reproduces_the_seed_choice_on_the_seed_table():
    by_cost, by_hsv = sel.select_modes(sel.SEED_TABLE2["modal_cost"], sel.SEED_TABLE2["hsv"])
    assert list(sel.SEED_TABLE2["mode"][by_cost]) == [1, 2]
    assert list(sel.SEED_TABLE2["mode"][by_hsv]) == [1, 2]


def test_table2_columns_and_consistency(spacecraft):
    M, K = spacecraft
    table, trunc = sel.table2(Model(M, K))
    assert list(table.columns[:6]) == ["mode", "f_hz", "modal_cost", "hsv_exact",
                                       "hsv_gregory", "retained"]
    assert list(trunc.columns[:3]) == ["order", "error_hinf", "bound"]
    assert np.all(np.diff(table["f_hz"]) > 0)
    assert table["retained"].any()
    # The retained modes are the ones ranked first by one criterion or the other.
    top = table.loc[table["retained"], ["cost_rank", "hsv_rank"]].min(axis=1)
    assert top.max() <= table["retained"].sum()
    assert table.attrs["total_cost_lyapunov"] == pytest.approx(
        table.attrs["sum_modal_costs"], rel=0.05)


def test_rigid_coupled_stiffness_is_refused(spacecraft):
    M, K = spacecraft
    K = K.copy()
    K[3, 7] = K[7, 3] = 1.0
    with pytest.raises(ValueError, match="rigid"):
        sel.modal_model(M, K)


def test_structural_mode_count_finds_the_smallest_model():
    M, K, Phi = panel_spacecraft()
    reference = sel.free_free_frequencies_hz(M, K)
    retained = [1, 2]

    def build(k):
        return Model(*reduce_on_modes(M, K, Phi, k))

    k, trials = sel.structural_mode_count(build, retained, reference[:2], tol=0.01, n_max=16)
    assert k is not None and trials["passes"].iloc[-1]
    assert not trials["passes"].iloc[:-1].any()
    # Rayleigh-Ritz: adding modes can only lower the system frequencies toward the full
    # model's, so the trial frequencies decrease with k and stay above the reference.
    f1 = trials["f1_hz"].dropna().to_numpy()
    assert np.all(np.diff(f1) <= 1e-12) and np.all(f1 >= reference[0] * (1 - 1e-12))


def test_skew_matches_cross_product():
    p, y = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.1, -4.0])
    assert np.allclose(skew(p) @ y, np.cross(p, y))
