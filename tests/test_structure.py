"""Linear algebra chosen by structure: patterns, solvers, and every family on both paths."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import integrators
import problems
from integrators.base import Grid
from integrators.ida import FORMULATIONS, consistent_values, iteration_pattern
from problems.mechanics import System
from linalg.blocks import Blocks
from linalg import pattern
from linalg.pattern import SparseJacobian
from helpers import solve
from test_spelling import coupled_mass_system

STRUCTURED = ("banded", "superlu")


def random_state(case, scale=1e-2, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(case.q0 + scale * rng.standard_normal(case.q0.shape))


@pytest.mark.parametrize("name", problems.names())
def test_pattern_of_G_holds_every_entry_of_the_dense_jacobian(name):
    # The traced pattern must contain every nonzero of G at a generic point, and the
    # compressed evaluation must reproduce G's values there: the values are the same
    # forward/reverse derivatives in another grouping, so they agree to round-off.
    case = problems.make(name)
    mech = case.mech
    q, t = random_state(case), jnp.asarray(0.3)
    G = np.asarray(mech.G(q, t))
    coloring = mech.G_coloring
    rows, cols = np.asarray(coloring.sparsity.rows), np.asarray(coloring.sparsity.cols)
    compressed = np.zeros_like(G)
    compressed[rows, cols] = np.asarray(jax.jit(mech.G_values)(q, t))
    assert np.max(np.abs(G - compressed)) <= 1e-14 * max(1.0, np.max(np.abs(G)))
    # ... and be no larger than the structure: no column is coloured densely by mistake.
    assert coloring.num_colors <= mech.n


@pytest.mark.parametrize("spec", ["chain:N=16", "sps-ring:N=6", "sps-ring:N=40"])
@pytest.mark.parametrize("kind", STRUCTURED)
def test_structured_schur_solve_equals_dense(spec, kind):
    # sps-ring:N=40 has hub rows (80 entries) that become the banded solver's border.
    case = problems.make(spec)
    mech = case.mech
    q, t = random_state(case), jnp.asarray(0.0)
    rhs = jnp.asarray(np.random.default_rng(1).standard_normal((mech.m, 3)))
    dense, structured = mech.schur("dense"), mech.schur(kind)
    assert structured.name == kind and structured.nnz > 0
    x_dense = jax.jit(lambda q, r: dense.solve(dense.factor(q, t), r))(q, rhs)
    F = jax.jit(structured.factor)(q, t)
    x = jax.jit(structured.solve)(F, rhs)
    assert bool(F.ok)
    # Both are backward stable solves of a system with condition number below 1e3 here.
    assert np.max(np.abs(x - x_dense)) <= 1e-12 * np.max(np.abs(x_dense))
    # The norm that Newton's stall test uses bounds ||S||_inf, and equals it where the
    # band holds all of S (no border rows).
    G = np.asarray(mech.G(q, t))
    S_inf = np.max(np.sum(np.abs(G @ (G.T / np.asarray(mech.mass_diagonal)[:, None])), axis=1))
    assert float(F.norm) >= S_inf * (1 - 1e-14)
    if kind == "banded" and not len(structured.pattern.border):
        assert float(F.norm) == pytest.approx(S_inf, rel=1e-14)


@pytest.mark.parametrize("kind", STRUCTURED)
def test_structured_solve_does_not_depend_on_the_order_of_the_constraints(kind):
    # Reversing the constraints permutes S; the solvers reorder it themselves (reverse
    # Cuthill-McKee, minimum degree), so the multipliers are the same, permuted.
    case = problems.make("sps-ring:N=40")
    system = case.system
    flipped = System(system.n, system.m, system.mass,
                     lambda q, t: system.constraints(q, t)[::-1], system.potential)
    q, t = random_state(case), jnp.asarray(0.0)
    rhs = jnp.asarray(np.random.default_rng(2).standard_normal(system.m))
    solvers = [s.mech.schur(kind) for s in (system, flipped)]
    x, y = (jax.jit(lambda q, r, s=s: s.solve(s.factor(q, t), r))(q, r)
            for s, r in zip(solvers, (rhs, rhs[::-1])))
    assert np.max(np.abs(x - y[::-1])) <= 1e-12 * np.max(np.abs(x))


@pytest.mark.slow
@pytest.mark.parametrize("spec, h, t_end, key", [
    *(("chain:N=16", 1e-3, 0.2, key) for key in ("rattle", "lobatto3ab3", "baumgarte-rk4")),
    ("sps-ring:N=6", 0.01, 1.0, "rattle")])
def test_every_fixed_step_family_gives_the_dense_result_on_the_structured_path(spec, h, t_end, key):
    # The same equations solved to round-off by two linear algebras: the states agree to
    # accumulated round-off (chain:N=16 is chaotic, so the horizon is short). Each family
    # on the chain, and rattle on the ring, whose hub couples every point.
    _, dense = solve(spec, f"{key}:linear_solver=dense", t_end, h=h)
    assert dense.linear_solver == "dense" and dense.pattern_nnz is None
    for kind in STRUCTURED:
        _, traj = solve(spec, f"{key}:linear_solver={kind}", t_end, h=h)
        assert traj.linear_solver == kind and traj.pattern_nnz > 0
        assert np.max(np.abs(traj.q_final - dense.q_final)) <= 1e-11
        assert np.max(np.abs(traj.v_final - dense.v_final)) <= 1e-10
        assert np.max(traj.windows["pos"]) <= 1e-13 or key == "baumgarte-rk4"


def test_blocks_of_a_mass_are_its_connected_components_and_solve_it():
    # Blocks {0, 3}, {1}, {2, 4, 5}, {6, 7}, {8, 9, 10}: sizes 1, 2 and 3, interleaved.
    rng = np.random.default_rng(3)
    n, parts = 11, [[0, 3], [1], [2, 4, 5], [6, 7], [8, 9, 10]]
    M = np.zeros((n, n))
    for b in parts:
        A = rng.standard_normal((len(b), len(b)))
        M[np.ix_(b, b)] = A @ A.T + len(b) * np.eye(len(b))
    blocks = Blocks(*np.nonzero(M), n)
    assert sorted(map(sorted, (c.tolist() for g in blocks.groups for c in g))) == sorted(parts)
    L = blocks.factor(blocks.values(jnp.asarray(M @ blocks.seeds().T).T))
    B = rng.standard_normal((n, 3))
    assert np.max(np.abs(np.asarray(blocks.solve(L, jnp.asarray(B))) - np.linalg.solve(M, B))) \
        <= 1e-14
    # Whitening G's entries: G L^-T on the spread pattern, with (G L^-T)(G L^-T)^T = G M^-1
    # G^T. Row 0 touches two blocks, row 1 one block at two positions, row 2 a hub row on
    # every block, row 3 a block of its own.
    G = np.zeros((4, n))
    G[0, [0, 1]], G[1, [4, 2]], G[2, :] = 1.0, (2.0, -1.0), rng.standard_normal(n)
    G[3, 10] = 3.0
    rows, cols = np.nonzero(G)
    plan = blocks.whitening(rows, cols)
    values = np.asarray(blocks.whiten_rows(L, jnp.asarray(G[rows, cols]), plan))
    W = np.zeros((4, n))
    W[plan.rows, plan.cols] = values
    Linv = np.linalg.inv(np.linalg.cholesky(M))
    assert np.max(np.abs(W - G @ Linv.T)) <= 1e-14
    assert np.max(np.abs(W @ W.T - G @ np.linalg.solve(M, G.T))) <= 1e-13


def test_block_structure_first_found_inside_a_trace_serves_later_traces():
    # mass_blocks is found once, on first use: where that use is inside jax.jit, its
    # arrays must still be concrete, or the next compiled function meets a leaked tracer.
    mech = problems.make("rigid-chain:N=2").mech
    q = jnp.asarray(problems.make("rigid-chain:N=2").q0)
    b = jnp.arange(1.0, mech.n + 1)
    first = jax.jit(lambda q: mech.mass_factor(q))(q)
    x = jax.jit(lambda q, b: mech.mass_solver(q)(b))(q, b)
    assert np.max(np.abs(np.asarray(mech.mass(q)) @ np.asarray(x) - np.asarray(b))) <= 1e-12
    assert len(first) == len(mech.mass_blocks.groups)


@pytest.mark.slow
def test_a_mass_given_by_the_kinetic_energy_is_solved_blockwise_and_whitened():
    # rigid-chain's mass: 3N translational 1 x 1 blocks and N quaternion 4 x 4 blocks,
    # traced from T. The structured Schur complement of G L^-T equals G M^-1 G^T.
    case = problems.make("rigid-chain:N=3")
    mech = case.mech
    assert sorted(g.shape for g in mech.mass_blocks.groups) == [(3, 4), (9, 1)]
    q, t = random_state(case), jnp.asarray(0.0)
    M, G = np.asarray(mech.mass(q)), np.asarray(mech.G(q, t))
    b = np.random.default_rng(1).standard_normal(mech.n)
    assert np.max(np.abs(np.asarray(mech.solve_mass(q, jnp.asarray(b)))
                         - np.linalg.solve(M, b))) <= 1e-13
    # The solver with its factors computed once solves alike, and H_q takes its velocity.
    solve = mech.mass_solver(q)
    assert np.max(np.abs(np.asarray(solve(jnp.asarray(b))) - np.linalg.solve(M, b))) <= 1e-13
    p = jnp.asarray(M @ b)
    assert np.max(np.abs(np.asarray(mech.H_q(q, p, solve(p)) - mech.H_q(q, p)))) <= 1e-13
    # Factors given by the caller (radau5 keeps them across steps) solve alike, and H_q
    # does use the velocity it is given: a wrong one moves it.
    given = mech.mass_solver(q, mech.mass_factor(q))
    assert np.max(np.abs(np.asarray(given(jnp.asarray(b))) - np.linalg.solve(M, b))) <= 1e-13
    assert np.max(np.abs(np.asarray(mech.H_q(q, p, 2.0 * solve(p)) - mech.H_q(q, p)))) > 1e-6
    schur = mech.schur("banded")
    r = np.random.default_rng(2).standard_normal(mech.m)
    x = np.asarray(jax.jit(lambda q, r: schur.solve(schur.factor(q, t), r))(q, jnp.asarray(r)))
    assert np.max(np.abs(G @ np.linalg.solve(M, G.T) @ x - r)) <= 1e-12 * np.max(np.abs(r))


def test_a_hub_row_on_a_block_mass_is_whitened_and_goes_to_the_border():
    # rigid-chain:N=48 with one more constraint on the height of every body's centre: a
    # hub row on 48 coordinates, more than four times a joint row's 10. Whitened, it is a
    # piece on each of 48 blocks, and it goes to the banded solver's border. The solve
    # must still be that of G M^-1 G^T.
    N = 48
    system = problems.make(f"rigid-chain:N={N}").system

    def constraints(q, t):
        heights = q.reshape(N, 7)[:, 2]
        return jnp.concatenate([system.constraints(q, t), jnp.sum(heights)[None]])

    hub = System(system.n, system.m + 1, None, constraints, system.potential,
                 kinetic=system.kinetic)
    mech = hub.mech
    schur = mech.schur("banded")
    assert schur.name == "banded" and list(schur.pattern.border) == [system.m]
    q, t = random_state(problems.make(f"rigid-chain:N={N}")), jnp.asarray(0.0)
    M, G = np.asarray(mech.mass(q)), np.asarray(mech.G(q, t))
    r = np.random.default_rng(4).standard_normal(mech.m)
    x = np.asarray(jax.jit(lambda q, r: schur.solve(schur.factor(q, t), r))(q, jnp.asarray(r)))
    assert np.max(np.abs(G @ np.linalg.solve(M, G.T) @ x - r)) <= 1e-11 * np.max(np.abs(r))


@pytest.mark.slow
@pytest.mark.parametrize("key", ["lobatto3ab3", "genalpha", "baumgarte-rk4"])
def test_a_block_mass_gives_the_dense_result_on_the_structured_path(key):
    # rigid-chain: configuration-dependent 7 x 7 blocks, non-separable H. Measured at
    # N = 4 over t = 0.5: the paths agree to 1.5e-14 (q) and 2.6e-13 (v) or better, with
    # rattle too (on one block in the next test, on this chain against the C yardstick
    # in test_scaling).
    _, dense = solve("rigid-chain:N=2", f"{key}:linear_solver=dense", 0.5, h=0.005)
    _, banded = solve("rigid-chain:N=2", f"{key}:linear_solver=banded", 0.5, h=0.005)
    assert banded.linear_solver == "banded" and banded.pattern_nnz > 0
    assert np.max(np.abs(banded.q_final - dense.q_final)) <= 1e-12
    assert np.max(np.abs(banded.v_final - dense.v_final)) <= 1e-11


@pytest.mark.slow
@pytest.mark.parametrize("spec, h, key", [("rigid-body", 0.01, "rattle"),
                                          ("rigid-body", 0.01, "baumgarte-rk4"),
                                          ("andrews", 1e-5, "genalpha-ggl")])
def test_a_mass_matrix_function_written_as_kinetic_energy_takes_the_block_path(spec, h, key):
    # rigid-body (4 x 4) and andrews (7 x 7) give M(q) as a matrix function. The same
    # mass written as T = v^T M(q) v / 2 has its blocks traced from T, whitened on the
    # banded path: 50 steps there agree with the dense path on the system as given to
    # round-off, the velocities to the positions' divided by h, as generalized-alpha's
    # carry it. The blocks are the mechanism's, whichever method solves with them: a
    # Schur-complement method, the explicit one and generalized-alpha's velocities show
    # it (the previous test runs the families on a chain of blocks). Measured:
    # 1.2e-12 in q and 4.8e-10 relative in v for genalpha-ggl on andrews, 1.4e-14 or less
    # for rattle, lobatto3ab3 and baumgarte-rk4 on both.
    case = problems.make(spec).with_t_end(50 * h)
    given = case.system
    twin = dataclasses.replace(given, mass=None,
                               kinetic=lambda q, v: 0.5 * v @ (given.mass(q) @ v))
    assert twin.mech.mass_blocks is not None
    runs = []
    for system, kind in ((given, "dense"), (twin, "banded")):
        c = dataclasses.replace(case, system=system)
        traj = integrators.make(key, h=h, linear_solver=kind).prepare(
            c, Grid(c.t0, c.t_end))()
        assert traj.status == "ok" and traj.linear_solver == kind
        runs.append(traj)
    dense, banded = runs
    scale = max(1.0, np.max(np.abs(dense.v_final)))
    assert np.max(np.abs(banded.q_final - dense.q_final)) <= 1e-11
    assert np.max(np.abs(banded.v_final - dense.v_final)) <= 1e-13 / h * scale


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["chain:N=16", "sps-ring:N=6", "andrews"])
def test_ida_sparse_iteration_matrix_gives_the_dense_result(spec):
    # andrews has a configuration-dependent mass: the sparse IDA path does not need a
    # constant diagonal one. Same tolerances, same Jacobian values: IDA takes the same
    # steps, so the states agree far below the tolerance.
    case = problems.make(spec)
    t_end = case.t0 + (0.2 if spec != "andrews" else 0.003)
    _, dense = solve(spec, "ida-ggl:linsolver=dense", t_end, rtol=1e-8)
    _, sparse = solve(spec, "ida-ggl:linsolver=sparse", t_end, rtol=1e-8)
    assert sparse.linear_solver == "sparse" and dense.linear_solver == "dense"
    assert sparse.counts["n_steps"] == dense.counts["n_steps"]
    assert np.max(np.abs(sparse.q_final - dense.q_final)) <= 1e-10


@pytest.mark.slow
@pytest.mark.parametrize("spec", ["sps-ring:N=40", "andrews", "bricard"])
@pytest.mark.parametrize("form", sorted(FORMULATIONS))
def test_sparse_jacobian_with_dense_lines_equals_forward_mode(spec, form, monkeypatch):
    # sps-ring:N=40's hub gives the iteration matrix dense rows and dense columns, which
    # are evaluated one by one beside the coloured rest.
    case = problems.make(spec)
    mech = case.mech
    F = FORMULATIONS[form].residual(mech)
    y0, yp0 = consistent_values(mech, FORMULATIONS[form].multiplier_blocks, 0.0, case.q0, case.v0)
    y = jnp.asarray(y0 + 1e-3 * np.random.default_rng(3).standard_normal(len(y0)))

    def f(z):
        return F(jnp.asarray(0.1), z, jnp.asarray(yp0) + 7.0 * (z - y))

    jac = SparseJacobian(f, y)
    if spec == "sps-ring:N=40":
        assert len(jac.dense_rows) > 0 and len(jac.dense_cols) > 0
        assert jac.n_colours + len(jac.dense_rows) + len(jac.dense_cols) < len(y0) // 10
    J = np.asarray(jax.jacfwd(f)(y))
    S = np.zeros_like(J)
    entries = np.asarray(jax.jit(jac.values)(y))
    S[jac.rows, jac.cols] = entries
    assert np.max(np.abs(J - S)) <= 1e-13 * max(1.0, np.max(np.abs(J)))
    # The same entries with the passes one by one (as for a large system; another program,
    # so to round-off), and in another order (as IDA takes them; exactly).
    monkeypatch.setattr(pattern, "BATCH_ENTRIES", 1)
    one_by_one = np.asarray(jax.jit(jac.values)(y))
    np.testing.assert_allclose(one_by_one, entries, rtol=1e-14,
                               atol=1e-15 * max(1.0, np.max(np.abs(J))))
    other = jac.reordered(np.random.default_rng(4).permutation(jac.nnz))
    S[jac.rows, jac.cols] = one_by_one
    moved = np.zeros_like(J)
    moved[other.rows, other.cols] = np.asarray(jax.jit(other.values)(y))
    np.testing.assert_array_equal(moved, S)


@pytest.mark.parametrize("spec", ["four-bar", "rigid-chain:N=4", "sps-ring:N=16"])
@pytest.mark.parametrize("form", sorted(FORMULATIONS))
def test_assembled_iteration_pattern_holds_the_traced_one_and_is_checked(spec, form):
    # The pattern IDA's sparse path assembles from the system's structure, without tracing
    # the residual, holds every entry the traced one has and few more; the random-point
    # check accepts it, and rejects a pattern that lacks one entry.
    mech = problems.make(spec).mech
    F = FORMULATIONS[form].residual(mech)
    size = 2 * mech.n + FORMULATIONS[form].multiplier_blocks * mech.m
    y = jnp.zeros(size)

    def f(z):
        return F(jnp.asarray(0.0), z, z - y)

    traced = SparseJacobian(f, y)
    rows, cols, shape = iteration_pattern(mech, form)
    assembled = SparseJacobian(f, y, (rows, cols, shape))
    got = set(zip(assembled.rows.tolist(), assembled.cols.tolist()))
    assert set(zip(traced.rows.tolist(), traced.cols.tolist())) <= got
    assert assembled.nnz <= 1.1 * traced.nnz
    point = jnp.asarray(np.random.default_rng(5).standard_normal(size))
    assert assembled.agrees(point, np.asarray(jax.jit(assembled.values)(point)))
    J = np.abs(np.asarray(jax.jacfwd(f)(point)))
    drop = np.argmax(J[assembled.rows, assembled.cols])
    keep = np.arange(assembled.nnz) != drop
    lacking = SparseJacobian(f, y, (assembled.rows[keep], assembled.cols[keep], shape))
    assert not lacking.agrees(point, np.asarray(jax.jit(lacking.values)(point)))


def test_no_assembled_pattern_for_a_mass_without_structure():
    # A mass function coupling 13 coordinates has no blocks: its pattern is traced from
    # the residual. andrews' M(q) has blocks, traced from the function.
    assert iteration_pattern(coupled_mass_system().mech, "ggl") is None
    assert iteration_pattern(problems.make("andrews").mech, "ggl") is not None


def redundant_chain():
    """chain:N=12 with its last constraint repeated: G has rank m - 1 everywhere."""
    case = problems.make("chain:N=12")
    system = case.system
    doubled = System(system.n, system.m + 1, system.mass,
                     lambda q, t: jnp.concatenate([system.constraints(q, t),
                                                   system.constraints(q, t)[-1:]]),
                     system.potential)
    return problems.make_case("chain-redundant", doubled, case.q0, case.v0, (0.0, 0.05), {},
                              energy_scale=case.energy_scale)


@pytest.mark.slow
def test_one_policy_for_redundant_constraints(monkeypatch):
    # Every path takes an exact solution of the consistent, singular system (the same
    # constraint force, so the same run to round-off): dense and banded the basic one
    # (banded drops the dependent row in its Cholesky), SuperLU a dense least-squares
    # solve for up to FALLBACK_MAX constraints; above that SuperLU fails the run with
    # the policy's message instead of returning meaningless states.
    import integrators
    import linalg.sparse
    from integrators import Grid

    def run(kind):
        case = redundant_chain()
        return integrators.make(f"rattle:linear_solver={kind}", h=1e-3).prepare(
            case, Grid(case.t0, case.t_end))()

    dense = run("dense")
    assert dense.status == "ok" and np.max(dense.windows["pos"]) <= 1e-13
    for kind in STRUCTURED:
        traj = run(kind)
        assert traj.status == "ok", traj.message
        assert np.max(np.abs(traj.q_final - dense.q_final)) <= 1e-12
    monkeypatch.setattr(linalg.sparse, "FALLBACK_MAX", 0)
    assert run("banded").status == "ok"
    traj = run("superlu")
    assert traj.status == "failed"
    assert "numerically singular" in traj.message
    assert "linear_solver=dense" in traj.message


@pytest.mark.parametrize("lanes", [None, 8])
def test_the_rank_deficient_branch_is_computed_only_where_taken(lanes):
    # The basic solution (QR with column pivoting, a LAPACK call) must stay inside the
    # while loop that runs it only for a deficient system: hoisted out as loop-invariant,
    # it runs at every solve, once per lane in an ensemble.
    from linalg.dense import solve
    rng = np.random.default_rng(0)
    A = jnp.asarray(rng.normal(size=(5, 5)))
    b = jnp.asarray(rng.normal(size=5))
    f = solve if lanes is None else jax.vmap(solve)
    args = (A, b) if lanes is None else (jnp.stack([A] * lanes), jnp.stack([b] * lanes))
    text = jax.jit(f).lower(*args).compile().as_text()
    computations = text.split("\n\n")
    qr = [c for c in computations if "geqp3" in c]
    assert qr and not any(c.lstrip().startswith("ENTRY") for c in qr)
    x = f(*args)
    assert np.allclose(np.asarray(x).reshape(-1, 5)[0], np.linalg.solve(A, b), rtol=1e-12)
    # A deficient system still takes it: the basic solution of a consistent system.
    S = A.at[4].set(A[0] + A[1])
    rhs = S @ jnp.asarray(rng.normal(size=5))
    y = solve(S, rhs)
    assert np.max(np.abs(S @ y - rhs)) <= 1e-12 * np.max(np.abs(rhs))
    assert np.count_nonzero(np.asarray(y) == 0.0) == 1   # the dependent unknown


def test_equilibration_scales_by_exact_powers_of_two():
    # The LU's equilibration must not round the matrix: every scale, as compiled, is an
    # exact power of two, the nearest to 1/x in the logarithm (x s within [2^-1/2, 2^1/2]).
    # exp2(-round(log2 x)) under XLA missed a power of two for about half of these values.
    from linalg.dense import power_of_two_scale
    rng = np.random.default_rng(3)
    x = np.concatenate([10.0 ** rng.uniform(-300, 300, 20000), rng.uniform(0, 4, 20000)])
    s = np.asarray(jax.jit(power_of_two_scale)(jnp.asarray(x)))
    assert np.all(np.frexp(s)[0] == 0.5)
    assert np.all((x * s >= 2 ** -0.5) & (x * s <= 2 ** 0.5))
    assert np.asarray(power_of_two_scale(jnp.zeros(2))).tolist() == [1.0, 1.0]


def test_banded_cholesky_drops_dependent_rows():
    # A singular band matrix (row 3 = row 1 + row 2 of G): the dropped row's unknown is
    # zero and the others solve the consistent system exactly.
    from linalg.banded import band_cholesky, band_solve
    rng = np.random.default_rng(0)
    G = np.zeros((6, 9))
    for i in range(6):
        G[i, i:i + 3] = rng.normal(size=3)
    G[3] = G[1] + G[2]
    S = G @ G.T
    w = 5
    Sb = np.zeros((6, w + 1))
    for i in range(6):
        for k in range(min(i, w) + 1):
            Sb[i, k] = S[i, i - k]
    L = band_cholesky(jnp.asarray(Sb))
    assert float(L[3, 0]) == 0.0 and np.all(np.asarray(L[4:, 0]) > 0)
    rhs = S @ rng.normal(size=6)
    x = np.asarray(band_solve(L, jnp.asarray(rhs)[:, None]))[:, 0]
    assert x[3] == 0.0
    assert np.max(np.abs(S @ x - rhs)) <= 1e-12 * np.max(np.abs(rhs))


def test_structured_solvers_take_a_block_mass_and_refuse_one_without_blocks():
    # andrews' M(q) has blocks of one and two coordinates; four-bar:N=64's constant mass
    # couples its points along the whole chain.
    assert problems.make("andrews").mech.schur("banded").name == "banded"
    with pytest.raises(ValueError, match="diagonal or block-diagonal mass"):
        problems.make("four-bar:N=64").mech.schur("banded")


def test_auto_choice_follows_the_structure():
    assert problems.make("pendulum").mech.schur().name == "dense"
    assert problems.make("chain:N=64").mech.schur().name == "banded"
    # The ring's hub rows form the border; the core stays a narrow band.
    ring = problems.make("sps-ring:N=64").mech.schur()
    assert ring.name == "banded" and len(ring.pattern.border) == 2
    assert ring.pattern.bandwidth <= 4



def test_fixed_step_families_name_their_own_crossover():
    # Newton on a whole stage system is cheaper structured from one constraint up
    # (benchmarks/perf/crossover.py); RATTLE's separable one-constraint Newton is a
    # division and stays dense; the other callers keep linalg.schur.DENSE_MAX.
    import integrators

    def path(key, name):
        return integrators.make(key).linear_algebra(problems.make(name).mech).name

    for key in ("lobatto3ab3", "genalpha", "genalpha-ggl", "hht"):
        assert path(key, "pendulum") == "banded", key
        assert path(key, "rigid-chain:N=1") == "banded", key
    assert path("rattle", "pendulum") == path("rattle", "sps-receiver") == "dense"
    # Two constraints, or forces (car-axis), put RATTLE's Newton on the structured path.
    assert path("rattle", "double-pendulum") == path("rattle", "car-axis") == "banded"
    # Without a Newton iteration (baumgarte-rk4) the default crossover holds, on a single
    # run, an ensemble and a Stepper alike (all three ask linear_algebra).
    assert path("baumgarte-rk4", "chain:N=4") == "dense"
    assert path("baumgarte-rk4", "chain:N=16") == "banded"
    # A mass function in blocks (andrews', flyball-governor's) takes the structured path,
    # as the same mass given by its kinetic energy does; without blocks every family stays
    # dense.
    assert path("lobatto3ab3", "andrews") == path("rattle", "flyball-governor") == "banded"
    assert integrators.make("lobatto3ab3").linear_algebra(coupled_mass_system().mech).name \
        == "dense"
    assert problems.make("car-axis").mech.schur().name == "dense"


def test_the_crossover_benchmark_compares_both_paths():
    from benchmarks.perf import crossover

    line = crossover.pair("lobatto3ab3", "pendulum", 0.01, 0.5, 1)
    assert "dense   ok" in line and "banded  ok" in line and "auto: banded" in line
    apart = float(line.split("apart ")[1].split()[0])
    assert apart <= 1e-13
    # bricard's constant mass in natural coordinates has no structured solver below
    # linalg.schur.DENSE_KKT_MAX constraints.
    assert crossover.pair("rattle", "bricard", 1e-4, 1e-3, 1) is None

@pytest.mark.slow
def test_generalized_alpha_index3_gives_the_dense_result_on_the_structured_path():
    _, dense = solve("chain:N=16", "genalpha:linear_solver=dense", 0.2, h=1e-3)
    for kind in STRUCTURED:
        _, traj = solve("chain:N=16", f"genalpha:linear_solver={kind}", 0.2, h=1e-3)
        assert traj.linear_solver == kind
        assert np.max(np.abs(traj.q_final - dense.q_final)) <= 1e-11
        assert np.max(np.abs(traj.v_final - dense.v_final)) <= 1e-10
        assert np.max(traj.windows["pos"]) <= 1e-13


@pytest.mark.slow
def test_generalized_alpha_ggl_gives_the_dense_result_on_the_structured_path():
    # The GGL form's mu needs solves with G G^T beside G M^-1 G^T (two factors per step).
    # Measured: the paths agree to 1e-14 (q) and 4e-14 (v) here, and to 2e-14 and 6e-14
    # on rigid-chain:N=2 (block mass; left out for its compile time).
    _, dense = solve("sps-ring:N=6", "genalpha-ggl:linear_solver=dense", 1.0, h=0.01)
    for kind in STRUCTURED:
        _, traj = solve("sps-ring:N=6", f"genalpha-ggl:linear_solver={kind}", 1.0, h=0.01)
        assert traj.linear_solver == kind
        assert np.max(np.abs(traj.q_final - dense.q_final)) <= 1e-12
        assert np.max(np.abs(traj.v_final - dense.v_final)) <= 1e-12
        assert np.max(traj.windows["pos"]) <= 1e-13 and np.max(traj.windows["vel"]) <= 1e-12


def test_a_diverged_iterate_fails_the_superlu_solve_as_data():
    # Non-finite G values or right-hand sides (a Newton iterate that diverged) give NaN,
    # which the loop turns into a failed step with its message; nothing raises out of
    # the host callback.
    import jax.numpy as jnp

    case = problems.make("chain:N=16")
    S = case.mech.schur("superlu")
    q = jnp.asarray(case.q0)
    good = S.factor(q, 0.0)
    rhs = jnp.ones(case.mech.m)
    assert np.all(np.isfinite(np.asarray(S.solve(good, rhs))))
    assert np.all(np.isnan(np.asarray(S.solve(good, rhs * jnp.nan))))
    bad = S.factor(q * jnp.nan, 0.0)
    assert not bool(bad.ok)
    assert np.all(np.isnan(np.asarray(S.solve(bad, rhs))))


@pytest.mark.parametrize("spec", ["sps-ring:N=8", "sps-lattice:N=4,K=3,perturb=0.1",
                                  "rigid-chain:N=3"])
def test_superlu_assembles_the_scaled_schur_complement_and_its_norm(spec):
    # The fixed pattern of S (pairs of G's entries in one column, summed into S's columns)
    # against G M^-1 G^T formed densely: a ring's hub rows, a lattice's non-unit masses and
    # a rigid chain's whitened block mass (unit mass, G L^-T).
    case = problems.make(spec)
    mech = case.mech
    schur = mech.schur("superlu")
    q = jnp.asarray(case.q0) * 1.01 + 1e-3      # off the symmetric start: no chance zeros
    values = np.asarray(schur.G_values(q, 0.0))
    G = np.zeros((mech.m, schur.pattern.n))
    np.add.at(G, (np.asarray(schur.pattern.rows), np.asarray(schur.pattern.cols)), values)
    dinv = np.zeros(schur.pattern.n)
    dinv[np.asarray(schur.pattern.cols)] = 1.0 / np.asarray(schur.mass_diagonal)[
        np.asarray(schur.pattern.cols)]
    S = (G * dinv) @ G.T
    Ss, D, norm = schur.assemble(values)
    assert np.allclose(D, 1.0 / np.sqrt(np.diag(S)), rtol=1e-14, atol=0.0)
    assert np.max(np.abs(Ss.toarray() - D[:, None] * S * D[None, :])) <= 1e-14
    assert abs(norm - np.max(np.abs(S).sum(axis=1))) <= 1e-14 * norm
    assert Ss.nnz == np.count_nonzero(Ss.toarray())   # no stored zeros for SuperLU to fill


@pytest.mark.parametrize("spec, kind", [("chain:N=40", "banded"), ("chain:N=40", "superlu"),
                                        ("four-bar:N=40", "kkt"), ("rigid-chain:N=4", "banded")])
def test_a_structured_solver_first_built_inside_a_trace_serves_later_traces(spec, kind):
    # Mechanics.schur builds each solver once, on first use, and keeps it: where that use is
    # inside jax.jit, the solver's arrays must still be concrete, or the next compiled
    # function meets a leaked tracer.
    case = problems.make(spec)
    mech, q, t = case.mech, jnp.asarray(case.q0), jnp.asarray(0.0)
    r = jnp.asarray(np.random.default_rng(3).standard_normal(mech.m))

    def solved(q, r):
        schur = mech.schur(kind)
        return schur.solve(schur.factor(q, t), r)

    first = jax.jit(solved)(q, r)
    again = jax.jit(lambda q, r: solved(q, r) * 2.0)(q, r)
    M, G = np.asarray(mech.mass(q)), np.asarray(mech.G(q, t))
    S = G @ np.linalg.solve(M, G.T)
    assert np.max(np.abs(S @ np.asarray(first) - np.asarray(r))) <= 1e-9 * np.max(np.abs(S))
    assert np.array_equal(np.asarray(again), 2.0 * np.asarray(first))
