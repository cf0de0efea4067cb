"""Lobatto IIIA-IIIB coefficients for any number of stages, validated on construction."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import jax.numpy as jnp
import numpy as np
from numpy.polynomial import Polynomial
from numpy.polynomial import legendre as L

#: Tolerance of the coefficient identities: the coefficients come from polynomial
#: integration in double precision, exact up to a few ulps for s <= 6.
TABLEAU_TOL = 1e-13


@dataclass(frozen=True)
class LobattoTableau:
    """The s-stage Lobatto IIIA (``A``) and IIIB (``A_hat``) pair with weights ``b``.

    Nodes ``c`` are the Gauss-Lobatto points on [0, 1]: 0, 1 and the roots of
    ``P'_{s-1}(2x - 1)``. Lobatto IIIA is the collocation method,
    ``a_ij = int_0^{c_i} l_j``; Lobatto IIIB is its symplectic partner,
    ``b_i a_hat_ij + b_j a_ji - b_i b_j = 0``; both have order ``2s - 2``
    (Hairer, Lubich and Wanner, *Geometric Numerical Integration*, 2006, section II.1.4).
    """

    s: int
    c: np.ndarray
    b: np.ndarray
    b_hat: np.ndarray
    A: np.ndarray
    A_hat: np.ndarray

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Check the defining identities; raise ``ValueError`` on the first that fails."""
        s, c, b, A, Ah = self.s, self.c, self.b, self.A, self.A_hat
        checks = {
            "weights sum to 1": abs(b.sum() - 1.0),
            "b equals b_hat": np.max(np.abs(b - self.b_hat)),
            "IIIA row sums equal c": np.max(np.abs(A.sum(1) - c)),
            # Lobatto IIIB satisfies C(s - 2) only: its row sums equal c from s = 3 on.
            "IIIB row sums equal c (s >= 3)": np.max(np.abs(Ah.sum(1) - c)) if s >= 3 else 0.0,
            "IIIA first row is zero": np.max(np.abs(A[0])),
            "IIIA last row equals b": np.max(np.abs(A[-1] - b)),
            "IIIB last column is zero": np.max(np.abs(Ah[:, -1])),
            "symplecticity b_i ah_ij + b_j a_ji - b_i b_j = 0":
                np.max(np.abs(b[:, None] * Ah + (b[:, None] * A).T - np.outer(b, b))),
            f"quadrature exact to degree {2 * s - 3}":
                max(abs(b @ c ** k - 1.0 / (k + 1)) for k in range(2 * s - 2)),
        }
        for name, err in checks.items():
            if not err <= TABLEAU_TOL:
                raise ValueError(f"Lobatto tableau s={s}: {name} fails (error {err:.2e})")


@lru_cache(maxsize=None)
def lobatto(s: int) -> LobattoTableau:
    """Generate the s-stage Lobatto IIIA-IIIB tableau (s >= 2)."""
    if s < 2:
        raise ValueError(f"Lobatto IIIA-IIIB needs s >= 2 stages, got {s}")
    interior = L.legroots(L.legder([0] * (s - 1) + [1])) if s > 2 else np.array([])
    c = np.concatenate([[0.0], (np.sort(interior) + 1) / 2, [1.0]])
    A = np.zeros((s, s))
    b = np.zeros(s)
    for j in range(s):
        others = np.delete(c, j)
        lj = Polynomial.fromroots(others) / np.prod(c[j] - others)
        integral = lj.integ()
        b[j] = integral(1.0) - integral(0.0)
        A[:, j] = integral(c) - integral(0.0)
    A_hat = b[None, :] - A.T * b[None, :] / b[:, None]
    # The weights of the p-update, computed apart from b (moment equations on the nodes),
    # so that the check b = b_hat compares two independent computations.
    b_hat = np.linalg.solve(np.vander(c, increasing=True).T, 1.0 / np.arange(1, s + 1))
    return LobattoTableau(s, c, b, b_hat, A, A_hat)


def combine(A: np.ndarray, X):
    """``A @ X`` for constant coefficients ``A`` (a tableau's matrix, shape ``(r, s)``, or
    its weights, ``(s,)``) and stage values ``X`` (leading axis the ``s`` stages), written
    as sums of the stage values scaled by the nonzero coefficients.

    Why not ``A @ X``: under ``jax.vmap`` the product becomes one matrix product over all
    lanes, which XLA:CPU hands to its matrix library, and that call keeps the time loop
    from compiling into one native kernel (:mod:`integrators.loop`); sums of scaled
    arrays fuse into it (``python -m benchmarks.perf.ensemble`` measures ensembles).
    """
    A = np.asarray(A)
    if A.ndim == 2:
        return jnp.stack([combine(row, X) for row in A])
    terms = [a * X[j] for j, a in enumerate(A) if a != 0.0]
    return sum(terms[1:], terms[0]) if terms else jnp.zeros_like(X[0])
