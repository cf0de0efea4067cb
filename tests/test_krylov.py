"""BiCGSTAB of the matrix-free Newton corrections (:mod:`linalg.krylov`)."""

import jax.numpy as jnp
import numpy as np
import pytest

from linalg.krylov import bicgstab


def system(n=30, seed=0):
    """A nonsymmetric, well-conditioned system and its solution."""
    rng = np.random.default_rng(seed)
    A = np.eye(n) * 4.0 + rng.normal(size=(n, n)) / np.sqrt(n)
    b = rng.normal(size=n)
    return jnp.asarray(A), jnp.asarray(b), np.linalg.solve(A, b)


@pytest.mark.parametrize("preconditioned", [False, True])
def test_bicgstab_reaches_its_relative_residual(preconditioned):
    A, b, x = system()
    # The diagonal's inverse (Jacobi), or none.
    M = (lambda v: v / jnp.diag(A)) if preconditioned else (lambda v: v)
    got = bicgstab(lambda v: A @ v, b, M, 1e-12, 100)
    assert np.linalg.norm(A @ got - b) <= 1e-12 * np.linalg.norm(b)
    assert np.max(np.abs(got - x)) <= 1e-11


def test_bicgstab_with_the_exact_inverse_is_done_in_one_iteration():
    # M = A^-1: the first half-step already solves the system (the early exit).
    A, b, x = system(seed=1)
    inv = jnp.linalg.inv(A)
    calls = []

    def op(v):
        calls.append(1)  # traced once per application in the loop's body
        return A @ v

    got = bicgstab(op, b, lambda v: inv @ v, 1e-10, 100)
    assert np.max(np.abs(got - x)) <= 1e-12
    # One product in the loop's body (a pass is half an iteration), traced once; none at
    # x = 0: the operator is in the program once.
    assert len(calls) == 1


def test_a_zero_right_hand_side_gives_zero_and_the_limit_stops_it():
    A, b, x = system(seed=2)
    assert np.all(bicgstab(lambda v: A @ v, 0.0 * b, lambda v: v, 1e-12, 100) == 0.0)
    # One iteration is not enough unpreconditioned: the iterate is returned, not solved.
    one = bicgstab(lambda v: A @ v, b, lambda v: v, 1e-14, 1)
    assert np.all(np.isfinite(one))
    assert np.linalg.norm(A @ one - b) > 1e-14 * np.linalg.norm(b)
    assert np.linalg.norm(A @ one - b) < np.linalg.norm(b)
