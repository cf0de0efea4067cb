"""Independent re-derivation of RATTLE, Lobatto IIIA-IIIB and generalized-alpha for constrained
Hamiltonians.

This module is a cross-check of the project's compiled integrators and deliberately shares
nothing with them: plain numpy, no JAX, no automatic differentiation, hand-written
derivatives, a different way of obtaining the coefficients and different nonlinear solvers.

Class of systems (Hairer, Lubich & Wanner, *Geometric Numerical Integration*, 2nd ed.,
section VII.1; Jay, SIAM J. Numer. Anal. 33, 1996)::

    H(q, p) = p^T M^{-1} p / 2 + U(q),   M constant,   g(q) = 0,   G = dg/dq,
    q' = M^{-1} p,   p' = -grad U(q) - G(q)^T lam.

Lobatto IIIA-IIIB, s stages (A = IIIA, Ahat = IIIB, common weights b)::

    Q_i = q0 + h sum_j a_ij M^{-1} P_j
    P_i = p0 + h sum_j ahat_ij F_j,       F_j = -grad U(Q_j) - G(Q_j)^T Lam_j
    q1  = q0 + h sum_j b_j M^{-1} P_j
    p1  = p0 + h sum_j b_j F_j
    g(Q_i) = 0 (i = 2..s),   G(q1) M^{-1} p1 = 0.

Coefficients
------------
All coefficients are computed *exactly* in the number field Q(sqrt 5) (rationals for
s = 2, 3), with no floating-point quadrature:

* nodes: 0, 1 and the roots of d/dt P_{s-1}(2t - 1) (shifted Legendre), found exactly;
* IIIA (collocation): a_ij = int_0^{c_i} l_j, b_j = int_0^1 l_j, Lagrange basis l_j
  integrated term by term with exact coefficients;
* IIIB from its own definition: ahat_i1 = b_1, ahat_is = 0 and the simplifying assumption
  C(s-2), i.e. a small exact linear solve; the symplecticity relation
  b_i ahat_ij + b_j a_ji = b_i b_j is then *checked* (not used to build IIIB).

Each exact entry x + y sqrt 5 is rounded once to the nearest double through 50-digit
decimal arithmetic.

Solvers
-------
* Lobatto: full Newton on all stage unknowns (Q, P, Lam) with the analytic Jacobian
  assembled by hand from grad U, Hess U, g, G and Hess g; quadratic convergence is used
  to stop one iteration after the state increment falls below sqrt(eps), i.e. at the
  round-off floor.
* RATTLE (one constraint, quadratic g): the position-step multiplier is the root nearest
  zero of the exact scalar quadratic g(a - lam d) = 0 (stable formula); the velocity-step
  multiplier is the solution of a scalar linear equation.
* Generalized-alpha (index 3 and stabilised index 2): full Newton on the unscaled
  (q_{n+1}, lam_{n+1}[, mu_{n+1}]) with the hand-built Jacobian, stopped when the
  position increment is at round-off; coefficients from the roots of the amplification
  matrix at infinite frequency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal, localcontext
from fractions import Fraction
from typing import Callable

import numpy as np

__all__ = ["Q5", "lobatto_tableau", "lobatto_tableau_exact", "Problem", "PROBLEMS",
           "rattle_step", "lobatto_step", "NewtonFailure", "integrate", "n_steps", "METHODS",
           "genalpha_coefficients", "genalpha_integrate"]


# ----------------------------------------------------------------------------------------
# Exact arithmetic in Q(sqrt 5)
# ----------------------------------------------------------------------------------------
class Q5:
    """The number x + y sqrt(5) with rational x, y (exact)."""

    __slots__ = ("x", "y")

    def __init__(self, x=0, y=0):
        self.x = Fraction(x)
        self.y = Fraction(y)

    @staticmethod
    def lift(v) -> "Q5":
        return v if isinstance(v, Q5) else Q5(v)

    def __add__(self, o):
        o = Q5.lift(o)
        return Q5(self.x + o.x, self.y + o.y)

    __radd__ = __add__

    def __neg__(self):
        return Q5(-self.x, -self.y)

    def __sub__(self, o):
        return self + (-Q5.lift(o))

    def __rsub__(self, o):
        return Q5.lift(o) - self

    def __mul__(self, o):
        o = Q5.lift(o)
        return Q5(self.x * o.x + 5 * self.y * o.y, self.x * o.y + self.y * o.x)

    __rmul__ = __mul__

    def inverse(self) -> "Q5":
        norm = self.x * self.x - 5 * self.y * self.y  # nonzero unless self == 0 (sqrt5 irrational)
        if norm == 0:
            raise ZeroDivisionError("inverse of zero in Q(sqrt 5)")
        return Q5(self.x / norm, -self.y / norm)

    def __truediv__(self, o):
        return self * Q5.lift(o).inverse()

    def __rtruediv__(self, o):
        return Q5.lift(o) * self.inverse()

    def __pow__(self, k: int):
        out = Q5(1)
        for _ in range(k):
            out = out * self
        return out

    def __eq__(self, o):
        o = Q5.lift(o)
        return self.x == o.x and self.y == o.y

    def __hash__(self):
        return hash((self.x, self.y))

    def is_zero(self) -> bool:
        return self.x == 0 and self.y == 0

    def to_dtype(self, dtype) -> np.floating:
        """Nearest value of ``dtype`` (float64 or the x87 80-bit long double)."""
        with localcontext() as ctx:
            ctx.prec = 50
            val = (Decimal(self.x.numerator) / Decimal(self.x.denominator)
                   + Decimal(self.y.numerator) / Decimal(self.y.denominator) * Decimal(5).sqrt())
            return dtype(float(val)) if dtype is np.float64 else dtype(str(val))

    def to_float(self) -> float:
        return float(self.to_dtype(np.float64))

    def __repr__(self):
        return f"Q5({self.x}, {self.y})"


# Polynomials: lists of Q5 coefficients, lowest degree first.
def _pmul(p, r):
    out = [Q5(0) for _ in range(len(p) + len(r) - 1)]
    for i, a in enumerate(p):
        for j, b in enumerate(r):
            out[i + j] = out[i + j] + a * b
    return out


def _pint(p, upper) -> Q5:
    """int_0^upper p(t) dt, exactly."""
    total = Q5(0)
    for k, a in enumerate(p):
        total = total + a * Fraction(1, k + 1) * (Q5.lift(upper) ** (k + 1))
    return total


def _shifted_legendre(n: int) -> list[Fraction]:
    """Coefficients of P_n(2t - 1), lowest degree first (Rodrigues: d^n/dt^n (t^2 - t)^n / n!)."""
    # (t^2 - t)^n = t^n (t - 1)^n = sum_k C(n, k) (-1)^(n-k) t^(n+k)
    base = [Fraction(0)] * (2 * n + 1)
    for k in range(n + 1):
        base[n + k] = Fraction(math.comb(n, k) * (-1) ** (n - k))
    poly = base
    for _ in range(n):
        poly = [poly[i] * i for i in range(1, len(poly))]
    return [c / math.factorial(n) for c in poly]


def _exact_sqrt_in_q5(d: Fraction) -> Q5:
    """sqrt(d) as an element of Q(sqrt 5), for d = r^2 or d = 5 r^2 with rational r."""

    def rational_sqrt(f: Fraction):
        if f < 0:
            return None
        n, m = math.isqrt(f.numerator), math.isqrt(f.denominator)
        return Fraction(n, m) if n * n == f.numerator and m * m == f.denominator else None

    r = rational_sqrt(d)
    if r is not None:
        return Q5(r)
    r = rational_sqrt(d / 5)
    if r is not None:
        return Q5(0, r)
    raise ValueError(f"sqrt({d}) is not in Q(sqrt 5)")


def lobatto_nodes_exact(s: int) -> list[Q5]:
    """0, 1 and the zeros of the derivative of the shifted Legendre polynomial P_{s-1}."""
    if s < 2:
        raise ValueError("Lobatto needs s >= 2")
    poly = _shifted_legendre(s - 1)
    deriv = [poly[i] * i for i in range(1, len(poly))]  # degree s - 2
    if s == 2:
        interior: list[Q5] = []
    elif s == 3:
        interior = [Q5(-deriv[0] / deriv[1])]
    elif s == 4:
        c0, c1, c2 = deriv
        root = _exact_sqrt_in_q5(c1 * c1 - 4 * c2 * c0)
        interior = sorted([(Q5(-c1) - root) / (2 * c2), (Q5(-c1) + root) / (2 * c2)],
                          key=Q5.to_float)
    else:
        raise NotImplementedError("exact nodes implemented for s = 2, 3, 4")
    return [Q5(0)] + interior + [Q5(1)]


def _solve_exact(A, rhs):
    """Gaussian elimination over Q(sqrt 5) (exact)."""
    n = len(A)
    M = [list(row) + [r] for row, r in zip(A, rhs)]
    for col in range(n):
        piv = next(i for i in range(col, n) if not M[i][col].is_zero())
        M[col], M[piv] = M[piv], M[col]
        inv = M[col][col].inverse()
        M[col] = [v * inv for v in M[col]]
        for i in range(n):
            if i != col and not M[i][col].is_zero():
                f = M[i][col]
                M[i] = [vi - f * vc for vi, vc in zip(M[i], M[col])]
    return [M[i][n] for i in range(n)]


def lobatto_tableau_exact(s: int):
    """Exact (A_IIIA, A_IIIB, b, c) as nested lists of :class:`Q5`."""
    c = lobatto_nodes_exact(s)
    basis = []
    for j in range(s):
        poly = [Q5(1)]
        for k in range(s):
            if k != j:
                den = c[j] - c[k]
                poly = _pmul(poly, [-c[k] / den, Q5(1) / den])
        basis.append(poly)
    b = [_pint(basis[j], Q5(1)) for j in range(s)]
    A = [[_pint(basis[j], c[i]) for j in range(s)] for i in range(s)]

    # IIIB: ahat_i1 = b_1, ahat_is = 0, and C(s-2) for the s-2 interior columns.
    Ahat = []
    for i in range(s):
        row = [b[0]] + [Q5(0)] * (s - 2) + [Q5(0)]
        if s > 2:
            mat = [[c[j] ** (k - 1) for j in range(1, s - 1)] for k in range(1, s - 1)]
            rhs = [c[i] ** k * Fraction(1, k) - (b[0] if k == 1 else 0) for k in range(1, s - 1)]
            row[1:s - 1] = _solve_exact(mat, rhs)
        Ahat.append(row)

    # Symplecticity b_i ahat_ij + b_j a_ji = b_i b_j must hold exactly.
    for i in range(s):
        for j in range(s):
            if not (b[i] * Ahat[i][j] + b[j] * A[j][i] - b[i] * b[j]).is_zero():
                raise AssertionError(f"IIIA/IIIB pair not symplectic at ({i}, {j})")
    return A, Ahat, b, c


def lobatto_tableau(s: int, dtype=np.float64):
    """(A_IIIA, A_IIIB, b, c) as arrays of ``dtype``, each entry rounded once."""
    A, Ahat, b, c = lobatto_tableau_exact(s)

    def conv(x):
        arr = np.array(x, dtype=object)
        flat = [Q5.to_dtype(v, dtype) for v in arr.ravel()]
        return np.array(flat, dtype=dtype).reshape(arr.shape)

    return conv(A), conv(Ahat), conv(b), conv(c)


# ----------------------------------------------------------------------------------------
# Problems, with hand-written derivatives
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Problem:
    """A constrained separable Hamiltonian with constant diagonal mass.

    Every function takes positions of shape (..., n) (a stack of points is allowed) and
    returns: ``U`` (...), ``grad_U`` (..., n), ``hess_U`` (..., n, n), ``g`` (..., m),
    ``G`` (..., m, n), ``hess_g`` (..., m, n, n). ``quadratic_g`` says that g is a quadratic
    polynomial (so its second-order Taylor expansion is exact). All arrays have ``dtype``.
    """

    name: str
    dtype: type
    mass: np.ndarray
    U: Callable[[np.ndarray], np.ndarray]
    grad_U: Callable[[np.ndarray], np.ndarray]
    hess_U: Callable[[np.ndarray], np.ndarray]
    g: Callable[[np.ndarray], np.ndarray]
    G: Callable[[np.ndarray], np.ndarray]
    hess_g: Callable[[np.ndarray], np.ndarray]
    q0: np.ndarray
    p0: np.ndarray
    quadratic_g: bool = True

    @property
    def n(self) -> int:
        return self.mass.size

    @property
    def m(self) -> int:
        return self.g(self.q0).size

    def energy(self, q, p):
        return (p @ (p / self.mass)) / 2 + self.U(q)


def _stack(*parts, shape=None):
    """Stack equally shaped arrays along a new last axis, reshaped to ``shape``."""
    first = np.asarray(parts[0])
    out = np.empty(first.shape + (len(parts),), dtype=first.dtype)
    for i, part in enumerate(parts):
        out[..., i] = part
    return out if shape is None else out.reshape(first.shape + shape)


def _sps_receiver(dtype=np.float64, Mr: float = 0.8, m: float = 1.0, w: float = 1.0,
                  R0: float = 1.0, r0: float = 0.8) -> Problem:
    """q = (R, r); M = diag(6 Mr, 6 m); U = -3 w^2 (Mr R^2 + m r^2);
    g = R^2 + r^2 - 2 R r cos(pi/6) - l^2 with l^2 fixed by (R0, r0)."""
    # The problem data (cos(pi/6), l^2) are double-precision numbers whatever ``dtype``:
    # an extended-precision run then solves the very same problem with less round-off.
    cs = dtype(math.cos(math.pi / 6.0))
    l2 = dtype(R0 * R0 + r0 * r0 - 2.0 * R0 * r0 * math.cos(math.pi / 6.0))
    k = dtype(3.0 * w * w)
    Mr, m, two = dtype(Mr), dtype(m), dtype(2)
    zero = lambda q: np.zeros(np.shape(q)[:-1], dtype=dtype)  # noqa: E731
    R = lambda q: q[..., 0]  # noqa: E731
    r = lambda q: q[..., 1]  # noqa: E731
    return Problem(
        name="sps-receiver",
        dtype=dtype,
        mass=np.array([6 * Mr, 6 * m], dtype=dtype),
        U=lambda q: -k * (Mr * R(q) ** 2 + m * r(q) ** 2),
        grad_U=lambda q: _stack(-two * k * Mr * R(q) + zero(q), -two * k * m * r(q) + zero(q)),
        hess_U=lambda q: _stack(-two * k * Mr + zero(q), zero(q), zero(q),
                                -two * k * m + zero(q), shape=(2, 2)),
        g=lambda q: _stack(R(q) ** 2 + r(q) ** 2 - two * R(q) * r(q) * cs - l2 + zero(q)),
        G=lambda q: _stack(two * R(q) - two * r(q) * cs, two * r(q) - two * R(q) * cs,
                           shape=(1, 2)),
        hess_g=lambda q: _stack(two + zero(q), -two * cs + zero(q), -two * cs + zero(q),
                                two + zero(q), shape=(1, 2, 2)),
        q0=np.array([R0, r0], dtype=dtype),
        p0=np.zeros(2, dtype=dtype),
    )


def _pendulum(dtype=np.float64, gravity: float = 9.81) -> Problem:
    """q = (x, y), unit mass and length; U = gravity y; g = x^2 + y^2 - 1."""
    grav, one, two = dtype(gravity), dtype(1), dtype(2)
    zero = lambda q: np.zeros(np.shape(q)[:-1], dtype=dtype)  # noqa: E731
    return Problem(
        name="pendulum",
        dtype=dtype,
        mass=np.ones(2, dtype=dtype),
        U=lambda q: grav * q[..., 1],
        grad_U=lambda q: _stack(zero(q), grav + zero(q)),
        hess_U=lambda q: np.zeros(np.shape(q) + (2,), dtype=dtype),
        g=lambda q: _stack(q[..., 0] ** 2 + q[..., 1] ** 2 - one + zero(q)),
        G=lambda q: _stack(two * q[..., 0], two * q[..., 1], shape=(1, 2)),
        hess_g=lambda q: _stack(two + zero(q), zero(q), zero(q), two + zero(q), shape=(1, 2, 2)),
        q0=np.array([1, 0], dtype=dtype),
        p0=np.zeros(2, dtype=dtype),
    )


PROBLEMS: dict[str, Callable[..., Problem]] = {
    "sps-receiver": _sps_receiver,
    "pendulum": _pendulum,
}


# ----------------------------------------------------------------------------------------
# Dense linear solve that also works in long double (numpy.linalg does not)
# ----------------------------------------------------------------------------------------
def _solve(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    if J.dtype == np.float64:
        return np.linalg.solve(J, r)
    J = J.copy()
    r = r.copy()
    n = len(r)
    for k in range(n):
        piv = k + int(np.argmax(np.abs(J[k:, k])))
        if J[piv, k] == 0:
            raise np.linalg.LinAlgError("singular Newton matrix")
        if piv != k:
            J[[k, piv]] = J[[piv, k]]
            r[[k, piv]] = r[[piv, k]]
        f = J[k + 1:, k] / J[k, k]
        J[k + 1:, k:] -= np.outer(f, J[k, k:])
        r[k + 1:] -= f * r[k]
    x = np.empty_like(r)
    for k in range(n - 1, -1, -1):
        x[k] = (r[k] - J[k, k + 1:] @ x[k + 1:]) / J[k, k]
    return x


# ----------------------------------------------------------------------------------------
# RATTLE
# ----------------------------------------------------------------------------------------
def _nearest_zero_root(alpha, beta, gamma):
    """Root of alpha x^2 + beta x + gamma nearest zero, without cancellation."""
    disc = beta * beta - 4 * alpha * gamma
    if disc < 0:
        raise FloatingPointError("RATTLE position step: no real multiplier (step too large)")
    big = -(beta + np.copysign(np.sqrt(disc), beta)) / 2
    if big == 0:
        return big
    return gamma / big


def rattle_step(prob: Problem, q0, p0, h):
    """One RATTLE step for one quadratic constraint; returns (q1, p1, lam, mu)."""
    if prob.m != 1 or not prob.quadratic_g:
        raise NotImplementedError("closed-form RATTLE needs one quadratic constraint")
    h = prob.dtype(h)
    Minv = 1 / prob.mass
    G0 = prob.G(q0)[0]
    # q1 = a - lam * d
    a = q0 + h * Minv * (p0 - h / 2 * prob.grad_U(q0))
    d = h * h / 2 * Minv * G0
    # g(a - lam d) = g(a) - lam G(a) d + lam^2 d^T Hg d / 2, exact for quadratic g.
    alpha = (d @ prob.hess_g(a)[0] @ d) / 2
    beta = -(prob.G(a)[0] @ d)
    gamma = prob.g(a)[0]
    lam = _nearest_zero_root(alpha, beta, gamma)
    p_half = p0 - h / 2 * (prob.grad_U(q0) + G0 * lam)
    q1 = q0 + h * Minv * p_half
    # G1 M^{-1} (r - h/2 G1^T mu) = 0 with r = p_half - h/2 grad U(q1): linear in mu.
    G1 = prob.G(q1)[0]
    r = p_half - h / 2 * prob.grad_U(q1)
    mu = (G1 @ (Minv * r)) / (h / 2 * (G1 @ (Minv * G1)))
    p1 = r - h / 2 * G1 * mu
    return q1, p1, lam, mu


# ----------------------------------------------------------------------------------------
# Lobatto IIIA-IIIB
# ----------------------------------------------------------------------------------------
class NewtonFailure(RuntimeError):
    pass


def lobatto_step(prob: Problem, tab, q0, p0, h, guess=None, max_iter: int = 40):
    """One Lobatto IIIA-IIIB step by full Newton with the hand-built Jacobian.

    Unknowns x = (Q_1..Q_s, P_1..P_s, Lam_1..Lam_s), residuals in the same block order
    (Q equations, P equations, g(Q_2..Q_s), G(q1) M^{-1} p1). Returns
    (q1, p1, stages, its) with stages = (Q - q0, P - p0, Lam), a starting guess for the next
    step (``guess``).

    Stopping: on the increments of the state unknowns (Q, P) only. The multipliers are
    determined only to about eps / h^2 (they move Q by h^2 Lam) and the stage momenta to
    about eps / h (they move by h Lam): increments can stagnate there (seen at 1e-12 for
    s = 4 on sps-receiver at h = 0.05, cond(J) ~ 1e7), so a stagnation test is kept as a
    fallback. The end-point values q1, p1 are much less sensitive.
    """
    A, Ah, b, c = tab
    dtype = prob.dtype
    h = dtype(h)
    s, n, m = len(b), prob.n, prob.m
    minv = 1 / prob.mass
    Minv = np.diag(minv)
    sn, sm = s * n, s * m
    N = 2 * sn + sm
    n_state = 2 * sn
    # Constant part of the Jacobian: identity blocks and d(Q eqs)/dP = -h A (x) M^{-1}.
    J0 = np.zeros((N, N), dtype=dtype)
    J0[:2 * sn, :2 * sn] = np.eye(2 * sn, dtype=dtype)
    J0[:sn, sn:2 * sn] = -h * np.kron(A, Minv)
    sel = np.eye(s, dtype=dtype)[1:]       # picks stages 2..s

    def unpack(x):
        return (x[:sn].reshape(s, n), x[sn:2 * sn].reshape(s, n), x[2 * sn:].reshape(s, m))

    def residual_and_jacobian(x):
        Q, P, L = unpack(x)
        GQ = prob.G(Q)                                              # (s, m, n)
        forces = -prob.grad_U(Q) - np.einsum("jln,jl->jn", GQ, L)  # (s, n)
        K = prob.hess_U(Q) + np.einsum("jl,jlab->jab", L, prob.hess_g(Q))  # (s, n, n)
        q1 = q0 + h * minv * (b @ P)
        p1 = p0 + h * (b @ forces)
        G1 = prob.G(q1)                                             # (m, n)
        v1 = minv * p1
        F = np.concatenate([
            (Q - q0 - h * minv * (A @ P)).ravel(),
            (P - p0 - h * (Ah @ forces)).ravel(),
            prob.g(Q[1:]).ravel(),
            G1 @ v1,
        ])
        J_PQ = (h * np.einsum("ij,jab->iajb", Ah, K)).reshape(sn, sn)
        J_PL = (h * np.einsum("ij,jla->iajl", Ah, GQ)).reshape(sn, sm)
        J_gQ = np.einsum("ij,jlb->iljb", sel, GQ).reshape((s - 1) * m, sn)
        dG1v = np.einsum("lab,b->la", prob.hess_g(q1), v1)         # d(G(q) v1)/dq at q1
        G1Minv = G1 * minv
        J_vP = (h * b[None, :, None] * (dG1v * minv)[:, None, :]).reshape(m, sn)
        J_vQ = (-h * np.einsum("j,la,jab->ljb", b, G1Minv, K)).reshape(m, sn)
        J_vL = (-h * np.einsum("j,la,jka->ljk", b, G1Minv, GQ)).reshape(m, sm)
        J = J0.copy()
        J[sn:2 * sn, :sn] = J_PQ
        J[sn:2 * sn, 2 * sn:] = J_PL
        J[2 * sn:N - m, :sn] = J_gQ
        J[N - m:, :sn] = J_vQ
        J[N - m:, sn:2 * sn] = J_vP
        J[N - m:, 2 * sn:] = J_vL
        return F, J, q1, p1

    if guess is None:
        x = np.concatenate([(q0 + np.outer(c * h, minv * p0)).ravel(), np.tile(p0, s),
                            np.zeros(sm, dtype)])
    else:
        # Previous step's stage increments (Q_i - q0, P_i - p0) and multipliers.
        dQ, dP, L = guess
        x = np.concatenate([(q0 + dQ).ravel(), (p0 + dP).ravel(), L.ravel()])
    eps = np.finfo(dtype).eps
    prev = np.inf
    for it in range(1, max_iter + 1):
        F, J, _, _ = residual_and_jacobian(x)
        dx = _solve(J, -F)
        x = x + dx
        size = np.max(np.abs(dx[:n_state]))
        scale = 1 + np.max(np.abs(x[:n_state]))
        # Newton with the exact Jacobian converges quadratically: once an increment was
        # below sqrt(eps), the error after the next one is of the order of eps.
        if size <= 2 * eps * scale or prev <= np.sqrt(eps) * scale:
            break
        # Round-off floor (fallback): small increments that no longer shrink. The floor of
        # the stage momenta is about eps / (h |G|) times the size of the inverse of the
        # h^2 (A Ahat) coupling block, far above eps for s = 4 (1e-12 is seen).
        if size <= 1e-9 * scale and size > prev / 4:
            break
        prev = size
    else:
        raise NewtonFailure(f"Lobatto Newton did not converge in {max_iter} iterations")
    _, _, q1, p1 = residual_and_jacobian(x)
    Q, P, L = unpack(x)
    return q1, p1, (Q - q0, P - p0, L), it


# ----------------------------------------------------------------------------------------
# Driver
# ----------------------------------------------------------------------------------------
METHODS = ("rattle", "lobatto2", "lobatto3", "lobatto4")
_TABLEAUX: dict[tuple, tuple] = {}


def _tab(s: int, dtype):
    if (s, dtype) not in _TABLEAUX:
        _TABLEAUX[s, dtype] = lobatto_tableau(s, dtype)
    return _TABLEAUX[s, dtype]


def n_steps(h: float, t_end: float) -> int:
    """Number of steps of size h over [0, t_end]; h must divide t_end."""
    N = int(round(t_end / h))
    if N < 1 or abs(N * h - t_end) > 1e-9 * max(1.0, t_end):
        raise ValueError(f"h = {h} does not divide t_end = {t_end}")
    return N


def integrate(problem: str, method: str, h: float, t_end: float, *,
              q0=None, p0=None, dtype=np.float64, return_energy: bool = False):
    """Integrate ``problem`` with ``method`` by N = t_end / h steps of size ``h``.

    Returns ``(q_final, p_final, max_abs_g)`` (float64 arrays) with ``max_abs_g`` the
    largest |g(q_n)| over all steps; with ``return_energy`` a fourth entry, the largest
    |H(q_n, p_n) - H_0|. ``q0``/``p0`` override the problem's initial values (they must be
    consistent). ``dtype=np.longdouble`` runs the same arithmetic in x87 extended precision
    (a round-off reference; slow).
    """
    prob = PROBLEMS[problem](dtype)
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; known: {METHODS}")
    q = np.array(prob.q0 if q0 is None else q0, dtype=dtype)
    p = np.array(prob.p0 if p0 is None else p0, dtype=dtype)
    H0 = prob.energy(q, p)
    max_g = np.max(np.abs(prob.g(q)))
    max_dH = dtype(0)
    stages = None
    for _ in range(n_steps(h, t_end)):
        if method == "rattle":
            q, p, _, _ = rattle_step(prob, q, p, h)
        else:
            q, p, stages, _ = lobatto_step(prob, _tab(int(method[-1]), dtype), q, p, h,
                                           guess=stages)
        max_g = max(max_g, np.max(np.abs(prob.g(q))))
        if return_energy:
            max_dH = max(max_dH, abs(prob.energy(q, p) - H0))
    out = (q.astype(np.float64), p.astype(np.float64), float(max_g))
    return out + (float(max_dH),) if return_energy else out


# ----------------------------------------------------------------------------------------
# Generalized-alpha (Chung and Hulbert 1993; Arnold and Bruls 2007)
# ----------------------------------------------------------------------------------------
def genalpha_coefficients(rho: float):
    """(alpha_m, alpha_f, gamma, beta) for the spectral radius ``rho`` at infinite frequency.

    Obtained from the roots of the amplification matrix at infinite frequency rather than
    from the closed formulas: ``alpha_f / (alpha_f - 1) = -rho`` fixes ``alpha_f``; the
    double root ``(s - 2) / s`` of the position-velocity part, ``s = 1 - alpha_m +
    alpha_f``, equals ``-rho`` for ``s = 2 / (1 + rho)``, which fixes ``alpha_m``;
    ``gamma = s - 1/2`` gives second order and ``beta = s^2 / 4`` makes the root double.
    """
    alpha_f = rho / (1.0 + rho)
    s = 2.0 / (1.0 + rho)
    return 1.0 + alpha_f - s, alpha_f, s - 0.5, s * s / 4.0


def genalpha_integrate(problem: str, h: float, t_end: float, rho: float, ggl: bool,
                       record=None):
    """Generalized-alpha on ``problem``: index 3, or stabilised index 2 when ``ggl``.

    Unknowns of the Newton iteration: ``q_{n+1}`` and ``lam_{n+1}`` (and ``mu_{n+1}``),
    unscaled, with the hand-built Jacobian; the acceleration-like variable ``a_{n+1}``
    follows from the Newmark position formula solved for it::

        a1   = (q1 - q0 - h v0 - h^2 (1/2 - beta) a0 - [G(q0)^T mu]) / (beta h^2)
        v1   = v0 + h (1 - gamma) a0 + h gamma a1
        acc1 = ((1 - alpha_m) a1 + alpha_m a0 - alpha_f acc0) / (1 - alpha_f)
        0 = M acc1 + grad U(q1) + G(q1)^T lam,   0 = g(q1)   [, 0 = G(q1) v1]

    Starts from ``a0 = acc0``, the acceleration of the index-1 system. Returns ``(q, v)``
    at ``t_end``; ``record(n, q, v, lam)`` is called after every step if given.
    """
    prob = PROBLEMS[problem](np.float64)
    am, af, gamma, beta = genalpha_coefficients(rho)
    n, m = prob.n, prob.m
    M, minv = np.diag(prob.mass), 1.0 / prob.mass
    q, v = prob.q0.copy(), prob.p0 * minv
    # Index-1 system: M a + G^T lam = -grad U, G a = -v^T Hess g v.
    G = prob.G(q)
    K = np.block([[M, G.T], [G, np.zeros((m, m))]])
    rhs = np.concatenate([-prob.grad_U(q), -np.einsum("lab,a,b->l", prob.hess_g(q), v, v)])
    sol = np.linalg.solve(K, rhs)
    a, acc, lam = sol[:n], sol[:n].copy(), sol[n:]
    c_q = (1 - am) / ((1 - af) * beta * h * h)   # d acc1 / d q1
    for step in range(n_steps(h, t_end)):
        G0 = prob.G(q)
        base = q + h * v + h * h * (0.5 - beta) * a
        x = np.concatenate([base + beta * h * h * a, lam] + ([np.zeros(m)] if ggl else []))
        for _ in range(40):
            q1, lam1 = x[:n], x[n:n + m]
            shift = G0.T @ x[n + m:] if ggl else 0.0
            a1 = (q1 - base - shift) / (beta * h * h)
            v1 = v + h * (1 - gamma) * a + h * gamma * a1
            acc1 = ((1 - am) * a1 + am * a - af * acc) / (1 - af)
            G1, Hg = prob.G(q1), prob.hess_g(q1)
            F = [M @ acc1 + prob.grad_U(q1) + G1.T @ lam1, prob.g(q1)]
            J = [[c_q * M + prob.hess_U(q1) + np.einsum("l,lab->ab", lam1, Hg), G1.T],
                 [G1, np.zeros((m, m))]]
            if ggl:
                F.append(G1 @ v1)
                dv = gamma / (beta * h)   # d v1 / d q1
                J[0].append(-c_q * M @ G0.T)
                J[1].append(np.zeros((m, m)))
                J.append([np.einsum("lab,b->la", Hg, v1) + dv * G1, np.zeros((m, m)),
                          -dv * G1 @ G0.T])
            dx = np.linalg.solve(np.block(J), -np.concatenate(F))
            x = x + dx
            if np.max(np.abs(dx[:n])) <= 4 * np.finfo(float).eps * (1 + np.max(np.abs(x[:n]))):
                break
        else:
            raise NewtonFailure(f"generalized-alpha Newton did not converge at step {step + 1}")
        q1, lam = x[:n], x[n:n + m]
        shift = G0.T @ x[n + m:] if ggl else 0.0
        a1 = (q1 - base - shift) / (beta * h * h)
        v = v + h * (1 - gamma) * a + h * gamma * a1
        acc = ((1 - am) * a1 + am * a - af * acc) / (1 - af)
        q, a = q1, a1
        if record is not None:
            record(step + 1, q, v, lam)
    return q, v
