"""One physics, one path: a mass written as ``mass=M(q)`` or as ``kinetic=T(q, v)``."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from integrators import Grid
from mechanisms import heavy_top
from problems import System


# One key per implementation (lobatto3ab3 stands for its family's other tableaux).
@pytest.mark.parametrize("key", [
    "rattle",
    pytest.param("lobatto3ab3", marks=pytest.mark.slow),
    pytest.param("genalpha-ggl", marks=pytest.mark.slow)])
def test_the_heavy_top_spelt_both_ways_takes_one_path_to_one_state(key):
    # Both spellings give one 4 x 4 block of M(q) (Euler parameters), so both take the
    # whitened structured path; 40 steps end within round-off of each other.
    runs = {}
    for spelling in ("mass", "kinetic"):
        case = heavy_top(spelling, t_end=0.2)
        assert [g.shape for g in case.mech.mass_blocks.groups] == [(1, 4)]
        runs[spelling] = integrators.make(key, h=0.005).prepare(case, Grid(case.t0, case.t_end))()
    given, kinetic = runs["mass"], runs["kinetic"]
    assert given.status == kinetic.status == "ok"
    assert given.linear_solver == kinetic.linear_solver != "dense"
    assert given.counts == kinetic.counts
    assert np.max(np.abs(given.q_final - kinetic.q_final)) <= 1e-12
    assert np.max(np.abs(given.v_final - kinetic.v_final)) <= 1e-10


def test_a_mass_function_has_its_blocks_traced_and_is_solved_on_them():
    # andrews' M(q): theta couples the first two bodies, phi the next two, omega the last
    # two, and M33 is constant. The blocks come from which entries depend on q and which
    # constant ones are nonzero; the whitened banded solve is that of G M^-1 G^T.
    case = problems.make("andrews")
    mech = case.mech
    groups = mech.mass_blocks.groups
    assert [g.tolist() for g in groups] == [[[2]], [[0, 1], [3, 4], [5, 6]]]
    schur = mech.schur("banded")
    assert schur.name == "banded" and mech.schur(dense_max=0).name == "banded"
    q, t = jnp.asarray(case.q0) + 0.1, jnp.asarray(0.0)
    M, G = np.asarray(mech.mass(q)), np.asarray(mech.G(q, t))
    r = np.random.default_rng(2).standard_normal(mech.m)
    x = np.asarray(schur.solve(schur.factor(q, t), jnp.asarray(r)))
    assert np.max(np.abs(G @ np.linalg.solve(M, G.T) @ x - r)) <= 1e-10 * np.max(np.abs(r))
    # H_q of the varying mass from T(q, v) = v^T M(q) v / 2, against the derivative of
    # H(q, p) = p^T M(q)^-1 p / 2 + U(q) through the solve.
    p = jnp.asarray(np.random.default_rng(3).standard_normal(mech.n))
    through = jax.grad(lambda x: 0.5 * p @ jnp.linalg.solve(mech.mass(x), p)
                       + mech.potential(x))(q)
    assert np.max(np.abs(np.asarray(mech.H_q(q, p)) - np.asarray(through))) \
        <= 1e-12 * np.max(np.abs(np.asarray(through)))


def coupled_mass_system(n: int = 13) -> System:
    """A sphere in ``n`` coordinates whose ``M(q)`` couples all of them through ``q_0``: for
    ``n = 13`` one block above :data:`linalg.blocks.BLOCK_MAX`, so no block structure."""

    def mass(q):
        return jnp.eye(n) * 2.0 + 0.1 * jnp.cos(q[0]) * jnp.ones((n, n))

    return System(n=n, m=1, mass=mass, constraints=lambda q, t: jnp.array([q @ q - 1.0]))


def test_a_mass_function_without_small_blocks_stays_dense_and_banded_is_refused():
    system = coupled_mass_system()
    assert system.mech.mass_blocks is None
    assert system.mech.schur().name == "dense"
    with pytest.raises(ValueError, match="needs a diagonal or block-diagonal mass"):
        system.mech.schur("banded")


def test_linear_solver_options_mean_the_same_for_either_spelling():
    # banded on the heavy top runs, spelt either way; so does dense.
    for spelling in ("mass", "kinetic"):
        mech = heavy_top(spelling, t_end=0.1).mech
        assert mech.schur("banded").name == "banded"
        assert mech.schur("dense").name == "dense"


def test_andrews_spelt_with_its_kinetic_energy_takes_the_structured_path_too():
    case = problems.make("andrews")
    given = case.system
    twin = dataclasses.replace(given, mass=None,
                               kinetic=lambda q, v: 0.5 * v @ (given.mass(q) @ v))
    for system in (given, twin):
        assert system.mech.schur(dense_max=0).name == "banded"
        assert integrators.make("rattle").linear_algebra(system.mech).name == "banded"


def test_the_blocks_of_a_mass_function_first_found_inside_a_trace_are_concrete():
    # The constant entries are read off M(0): inside jax.jit that evaluation must still
    # give numbers, not tracers.
    case = problems.make("andrews")
    mech, q = case.mech, jnp.asarray(case.q0)
    b = jnp.arange(1.0, mech.n + 1)
    x = jax.jit(lambda q, b: mech.mass_solver(q)(b))(q, b)
    assert np.max(np.abs(np.asarray(mech.mass(q)) @ np.asarray(x) - np.asarray(b))) <= 1e-12
