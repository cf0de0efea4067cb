"""Lobatto IIIA-IIIB coefficients: the identities that make the method what it is."""

import numpy as np
import pytest

import independent as ind
from integrators.tableau import TABLEAU_TOL, LobattoTableau, combine, lobatto


@pytest.mark.parametrize("s", [2, 3, 4])
def test_tableau_equals_the_exact_one(s):
    """Against the exact tableau of the independent re-derivation (rational arithmetic in
    Q(sqrt 5), each entry rounded once): the double-precision polynomial integration of
    :func:`lobatto` is off by a few ulps at most."""
    t = lobatto(s)
    A, A_hat, b, c = ind.lobatto_tableau(s)
    for mine, exact in ((t.A, A), (t.A_hat, A_hat), (t.b, b), (t.b_hat, b), (t.c, c)):
        assert np.max(np.abs(mine - exact)) <= TABLEAU_TOL
    # Gauss-Lobatto quadrature is exact for polynomials of degree 2s - 3, not 2s - 2.
    assert abs(t.b @ t.c ** (2 * s - 2) - 1 / (2 * s - 1)) > 1e-6


def test_known_three_stage_coefficients():
    # Hairer, Lubich and Wanner (2006), Table II.1.2: Lobatto IIIA and IIIB, s = 3.
    t = lobatto(3)
    A = np.array([[0, 0, 0], [5 / 24, 1 / 3, -1 / 24], [1 / 6, 2 / 3, 1 / 6]])
    Ah = np.array([[1 / 6, -1 / 6, 0], [1 / 6, 1 / 3, 0], [1 / 6, 5 / 6, 0]])
    assert np.allclose(t.A, A, atol=1e-15) and np.allclose(t.A_hat, Ah, atol=1e-15)


def test_seed_equation_12_as_printed_is_not_the_symplecticity_condition():
    # The seed prints b_i ah_ij - b_j a_ij - b_i b_j = 0; the condition that holds (and
    # makes the PRK symplectic) is b_i ah_ij + b_j a_ji - b_i b_j = 0.
    t = lobatto(2)
    printed = t.b[:, None] * t.A_hat - t.b[None, :] * t.A - np.outer(t.b, t.b)
    assert np.max(np.abs(printed)) > 0.1


def test_corrupted_tableau_is_refused():
    t = lobatto(3)
    A_hat = t.A_hat.copy()
    A_hat[1, 0] += 1e-6  # keeps the row sum, breaks symplecticity
    A_hat[1, 1] -= 1e-6
    with pytest.raises(ValueError, match="symplecticity"):
        LobattoTableau(3, t.c, t.b, t.b_hat, t.A, A_hat)


@pytest.mark.parametrize("s", [2, 3, 4])
def test_combine_is_the_tableau_product(s):
    """The sums of scaled stage values that the SPARK step uses equal the matrix products,
    zero rows (Lobatto IIIA's first) and zero columns (IIIB's last) included, for stage
    values of any trailing shape."""
    t = lobatto(s)
    X = np.random.default_rng(s).standard_normal((s, 5, 2))
    for coefficients in (t.A, t.A_hat, t.A[1:], t.b):
        out = np.asarray(combine(coefficients, X))
        exact = np.tensordot(coefficients, X, axes=1)
        assert out.shape == exact.shape
        assert np.max(np.abs(out - exact)) <= 1e-15 * s * np.max(np.abs(X))
    assert not np.any(np.asarray(combine(t.A, X))[0])
