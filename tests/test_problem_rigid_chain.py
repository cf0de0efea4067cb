"""The chain of rigid bodies in Euler parameters: its structure, the heavy top it is for
N = 1, an independent Newton-Euler formulation for small N, and a short RATTLE run.

The independent formulations here share nothing with :mod:`problems.rigid_chain` but the
state layout: plain numpy, rotations from scipy, angular velocities and accelerations from
quaternion products, the equations of motion written per body in space axes (Newton and
Euler) rather than derived by autodiff from a mass matrix and constraints.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import problems
from helpers import solve
from problems.case import residuals

E_Z = np.array([0.0, 0.0, 1.0])


@functools.lru_cache(maxsize=None)
def make(spec):
    return problems.make(spec)


@functools.lru_cache(maxsize=None)
def compiled_accelerations(spec):
    # One compilation per case: eagerly, every autodiff operation would compile on its own.
    return jax.jit(make(spec).mech.accelerations)


def qmul(a, b):
    """Quaternion product ``a b`` (scalar first)."""
    a0, av, b0, bv = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[a0 * b0 - av @ bv], a0 * bv + b0 * av + np.cross(av, bv)])


def conj(a):
    return np.concatenate([[a[0]], -a[1:]])


def rot(e):
    """Body-to-space rotation of the unit quaternion ``e`` (scalar first) through scipy."""
    return Rotation.from_quat(np.roll(e, -1)).as_matrix()


def skew(r):
    return np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])


def split(y, N):
    """``(x, e)`` per body from a stacked ``(7N,)`` vector."""
    b = np.asarray(y).reshape(N, 7)
    return b[:, :3], b[:, 3:]


def body_rates(q, v, a, N):
    """Centre-of-mass accelerations, space angular velocities and accelerations from the
    suite's ``(q, v, a)``: ``(0, omega_body) = 2 e* e'`` and, because ``e'* e'`` is real,
    ``omega_body' = vec(2 e* e'')``; both turned to space axes by ``R(e)``."""
    x, e = split(q, N)
    _, ed = split(v, N)
    xdd, edd = split(a, N)
    omega = np.array([rot(e[k]) @ (2.0 * qmul(conj(e[k]), ed[k]))[1:] for k in range(N)])
    alpha = np.array([rot(e[k]) @ (2.0 * qmul(conj(e[k]), edd[k]))[1:] for k in range(N)])
    return xdd, omega, alpha


def consistent_state(e, omega, l):
    """``(q, v)`` of a chain with attitudes ``e`` and space angular velocities ``omega``,
    walked down from the fixed point (independently of the problem's own builder)."""
    N = len(e)
    q, v = np.zeros((N, 7)), np.zeros((N, 7))
    joint, joint_rate = np.zeros(3), np.zeros(3)
    for k in range(N):
        R = rot(e[k])
        up, down = R @ [0.0, 0.0, l], R @ [0.0, 0.0, -l]
        q[k, :3], q[k, 3:] = joint - up, e[k]
        v[k, :3] = joint_rate - np.cross(omega[k], up)
        v[k, 3:] = 0.5 * qmul(np.concatenate([[0.0], omega[k]]), e[k])
        joint, joint_rate = q[k, :3] + down, v[k, :3] + np.cross(omega[k], down)
    return q.ravel(), v.ravel()


def random_states(N, l, count, seed):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        e = rng.standard_normal((N, 4))
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        yield consistent_state(e, 2.0 * rng.standard_normal((N, 3)), l)


def newton_euler(q, v, m_b, J, l, gravity):
    """Accelerations, angular accelerations (space axes) and joint forces by Newton-Euler.

    Unknowns per body ``k``: ``a_k``, ``alpha_k`` and the force ``F_k`` that body ``k - 1``
    (the ground for ``k = 1``) exerts on body ``k`` at its upper joint, so that body ``k``
    receives ``-F_{k+1}`` at its lower joint. With ``r^+-`` the
    arms from the centre of mass to the joint points and ``I = R J R^T``:

    ``m a_k = F_k - F_{k+1} - m g e_z``,
    ``I alpha_k + omega_k x I omega_k = r^+_k x F_k - r^-_k x F_{k+1}``,
    ``a_k + alpha_k x r^+_k + omega_k x (omega_k x r^+_k) =`` the same of body ``k - 1``
    at ``r^-_{k-1}`` (zero for the fixed point): one linear system of size ``9N``.
    """
    N = len(q) // 7
    x, e = split(q, N)
    _, ed = split(v, N)
    A = np.zeros((9 * N, 9 * N))
    b = np.zeros(9 * N)
    acc, ang, force = (lambda k: slice(3 * k, 3 * k + 3)), \
        (lambda k: slice(3 * N + 3 * k, 3 * N + 3 * k + 3)), \
        (lambda k: slice(6 * N + 3 * k, 6 * N + 3 * k + 3))
    omega, up, down = [], [], []
    for k in range(N):
        R = rot(e[k])
        omega.append(R @ (2.0 * qmul(conj(e[k]), ed[k]))[1:])
        up.append(R @ [0.0, 0.0, l])
        down.append(R @ [0.0, 0.0, -l])
    for k in range(N):
        R = rot(e[k])
        I = R @ np.diag(J) @ R.T
        w = omega[k]
        rows = slice(3 * k, 3 * k + 3)  # Newton
        A[rows, acc(k)] = m_b * np.eye(3)
        A[rows, force(k)] = -np.eye(3)
        if k + 1 < N:
            A[rows, force(k + 1)] = np.eye(3)
        b[rows] = -m_b * gravity * E_Z
        rows = slice(3 * N + 3 * k, 3 * N + 3 * k + 3)  # Euler
        A[rows, ang(k)] = I
        A[rows, force(k)] = -skew(up[k])
        if k + 1 < N:
            A[rows, force(k + 1)] = skew(down[k])
        b[rows] = -np.cross(w, I @ w)
        rows = slice(6 * N + 3 * k, 6 * N + 3 * k + 3)  # joint k, acceleration level
        A[rows, acc(k)] = np.eye(3)
        A[rows, ang(k)] = -skew(up[k])
        b[rows] = -np.cross(w, np.cross(w, up[k]))
        if k > 0:
            wp = omega[k - 1]
            A[rows, acc(k - 1)] = -np.eye(3)
            A[rows, ang(k - 1)] = skew(down[k - 1])
            b[rows] += np.cross(wp, np.cross(wp, down[k - 1]))
    sol = np.linalg.solve(A, b)
    return (sol[:3 * N].reshape(N, 3), sol[3 * N:6 * N].reshape(N, 3),
            sol[6 * N:].reshape(N, 3))


def parameters(case):
    p = case.params
    return p["mass"], np.array([p["J1"], p["J2"], p["J3"]]), p["half_length"], p["gravity"]


@pytest.mark.parametrize("N", [1, 3])
def test_structure_and_consistent_initial_values(N):
    case = make(f"rigid-chain:N={N}")
    mech = case.mech
    assert (mech.n, mech.m) == (7 * N, 4 * N)
    assert not mech.constant_mass and mech.has_energy
    assert set(case.system.invariants) == {"L_z"}
    # Measured regular from the default start below N = 3, chaotic from N = 3 (module doc).
    assert case.system.sensitive == (N >= 3)
    # Built exactly (a walk down the chain from unit quaternions): only the round-off of
    # the coordinates remains, and nothing was projected.
    pos, vel = residuals(mech, case.q0, case.v0, case.t0)
    assert pos <= 1e-14 and vel <= 1e-14, (pos, vel)
    assert "projected" not in case.notes
    M = np.asarray(mech.mass(jnp.asarray(case.q0)))
    assert M.shape == (7 * N, 7 * N)
    # 4 E^T J E is formed as a product, symmetric up to the round-off of its entries.
    assert np.max(np.abs(M - M.T)) <= 1e-15 * np.max(np.abs(M))
    blocks = np.kron(np.eye(N), np.ones((7, 7))).astype(bool)
    assert not np.any(M[~blocks])
    J = np.array([case.params[k] for k in ("J1", "J2", "J3")])
    for k in range(N):
        block = M[7 * k:7 * k + 7, 7 * k:7 * k + 7]
        np.testing.assert_array_equal(block[:3, :3], case.params["mass"] * np.eye(3))
        assert not np.any(block[:3, 3:])
        # On |e| = 1 the rows of (e^T; E(e)) are orthonormal, so the quaternion block has
        # the eigenvalues 4 j0 and 4 J_i (to the round-off of the eigensolver).
        np.testing.assert_allclose(np.linalg.eigvalsh(block[3:, 3:]),
                                   np.sort(4.0 * np.r_[J, J.mean()]), rtol=1e-13)
    assert np.linalg.eigvalsh(M).min() > 0


def test_quaternion_block_is_the_rigid_body_mass():
    # One convention with rigid-body (whose closed form needs J1 < J2 < J3, hence its
    # default inertia here): the same quaternion gives the same 4 x 4 block, to the
    # round-off of the two ways of evaluating it (the chain's kinetic energy does not form
    # the block).
    chain = make("rigid-chain:N=2,J1=1,J2=2,J3=3")
    body = make("rigid-body")
    M = np.asarray(chain.mech.mass(jnp.asarray(chain.q0)))
    for k in range(2):
        e = chain.q0[7 * k + 3:7 * k + 7]
        block = np.asarray(body.mech.mass(jnp.asarray(e)))
        np.testing.assert_allclose(M[7 * k + 3:7 * k + 7, 7 * k + 3:7 * k + 7], block, rtol=0,
                                   atol=4 * np.finfo(float).eps * np.max(np.abs(block)))


def test_initial_motion_is_three_dimensional_with_angular_momentum():
    case = make("rigid-chain:N=3")
    x, _ = split(case.q0, 3)
    xd, _ = split(case.v0, 3)
    L_z = float(case.mech.invariant_values(jnp.asarray(case.q0), jnp.asarray(case.v0))[0])
    assert L_z > 0.1
    # Bodies off the vertical, in different azimuths, all moving.
    assert np.all(np.hypot(x[:, 0], x[:, 1]) > 0.1)
    assert np.ptp(np.arctan2(x[:, 1], x[:, 0])) > 0.5
    assert np.all(np.linalg.norm(xd, axis=1) > 0.1)


def test_large_chains_take_the_general_size_limit():
    # The mass is given by the kinetic energy and never formed, so cost grows linearly in N
    # and the chain takes the limit every problem has.
    problems.check_size("rigid-chain:N=16384")
    with pytest.raises(problems.SizeError, match="rigid-chain"):
        problems.check_size(f"rigid-chain:N={problems.SIZE_LIMIT + 1}")


def test_single_body_is_the_heavy_top_of_euler():
    """N = 1 is a heavy top about the fixed point: Euler's equations in body axes with the
    inertia shifted to that point (Landau and Lifshitz, Mechanics, sections 32 and 36),

    ``J_O omega' + omega x J_O omega = d x R^T (-m g e_z)``,
    ``J_O = J + m (|d|^2 I - d d^T)``, ``d = (0, 0, -l)`` (from the fixed point to the
    centre of mass), and the centre's acceleration ``R (omega' x d + omega x (omega x d))``.
    """
    spec = "rigid-chain:N=1"
    case = make(spec)
    m_b, J, l, gravity = parameters(case)
    d = np.array([0.0, 0.0, -l])
    J_O = np.diag(J) + m_b * (l * l * np.eye(3) - np.outer(d, d))
    accelerations = compiled_accelerations(spec)
    states = [(case.q0, case.v0), *random_states(1, l, 4, seed=11)]
    worst = 0.0
    for q, v in states:
        a, _ = accelerations(0.0, q, v)
        xdd, _, _ = body_rates(q, v, np.asarray(a), 1)
        e, ed, edd = q[3:], v[3:], np.asarray(a)[3:]
        R = rot(e)
        omega = (2.0 * qmul(conj(e), ed))[1:]  # body axes
        omega_dot = (2.0 * qmul(conj(e), edd))[1:]
        torque = np.cross(d, R.T @ (-m_b * gravity * E_Z))
        expected = np.linalg.solve(J_O, torque - np.cross(omega, J_O @ omega))
        centre = R @ (np.cross(expected, d) + np.cross(omega, np.cross(omega, d)))
        scale = max(1.0, np.max(np.abs(expected)))
        worst = max(worst, np.max(np.abs(omega_dot - expected)) / scale,
                    np.max(np.abs(xdd[0] - centre)) / max(1.0, np.max(np.abs(centre))))
    # Two direct solves of small well-conditioned systems with O(10) entries: they agree
    # to round-off (measured: 3e-15 at worst over the five states).
    assert worst <= 1e-12, worst


@pytest.mark.parametrize("N", [2, 3])
def test_small_chains_agree_with_newton_euler(N):
    spec = f"rigid-chain:N={N}"
    case = make(spec)
    m_b, J, l, gravity = parameters(case)
    accelerations = compiled_accelerations(spec)
    states = [(case.q0, case.v0), *random_states(N, l, 3, seed=N)]
    worst = 0.0
    for q, v in states:
        a, lam = accelerations(0.0, q, v)
        xdd, _, alpha = body_rates(q, v, np.asarray(a), N)
        ne_acc, ne_alpha, ne_force = newton_euler(q, v, m_b, J, l, gravity)
        # The joint rows of body k are u_k - w_{k-1}: their force on x_k is -lambda.
        joint_forces = -np.asarray(lam).reshape(N, 4)[:, 1:]
        for ours, theirs in ((xdd, ne_acc), (alpha, ne_alpha), (joint_forces, ne_force)):
            worst = max(worst, np.max(np.abs(ours - theirs)) / np.max(np.abs(theirs)))
    # The same motion from two linear solves (a Schur complement of the Euler-parameter
    # DAE, and a 9N x 9N Newton-Euler system): they agree to round-off (measured: 5e-15
    # at worst over the four states); the bound leaves room for other platforms' BLAS.
    assert worst <= 1e-10, worst


@pytest.mark.slow
def test_rattle_keeps_the_constraints_and_the_angular_momentum():
    case, traj = solve("rigid-chain:N=3", "rattle", 1.0, h=1e-2)
    L_z = float(case.mech.invariant_values(jnp.asarray(case.q0), jnp.asarray(case.v0))[0])
    # RATTLE enforces g = 0 and G v = 0 at every step to its Newton tolerance (measured:
    # 4e-16 and 2e-15).
    assert np.max(traj.windows["pos"]) <= 1e-10
    assert np.max(traj.windows["vel"]) <= 1e-10
    # Second order: the energy error is O(h^2) relative to the scale (measured 1.1e-4).
    assert np.max(traj.windows["energy"]) <= 1e-3 * case.energy_scale
    # L_z is the momentum map of a linear symmetry (rotations about the vertical act
    # linearly on x and e and leave M, U and g invariant), which RATTLE conserves up to
    # its Newton tolerance and round-off (measured: 4e-16 relative).
    assert np.max(traj.windows["inv:L_z"]) <= 1e-10 * abs(L_z)


@pytest.mark.slow
def test_rattle_energy_error_is_second_order_and_bounded():
    (case, coarse), (_, fine) = (solve("rigid-chain:N=3", "rattle", 1.0, h=h)
                                 for h in (1e-2, 5e-3))
    # Halving h divides the largest energy error by 2^2 (measured: 4.003).
    ratio = np.max(coarse.windows["energy"]) / np.max(fine.windows["energy"])
    assert 3.8 <= ratio <= 4.2, ratio
    # Over 20 s of chaotic motion the error stays at its first second's level: no drift
    # (measured: at most 1.6e-4 of the scale against 1.1e-4 in the first second).
    case, traj = solve("rigid-chain:N=3", "rattle", 20.0, h=1e-2)
    energy = traj.windows["energy"] / case.energy_scale
    assert np.max(energy) <= 2.0 * np.max(energy[traj.windows["t"] <= 1.0])
    assert np.max(traj.windows["pos"]) <= 1e-10
