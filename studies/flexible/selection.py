r"""Retained-mode selection: modal cost analysis and internal balancing.

The two criteria of the seed's section 3 act on the *system* modes of a flexible
spacecraft model in hybrid coordinates ``x = [r (3), theta (3), eta (k)]`` (translations
and small rotations of the hub frame, then deformation coordinates), given by its constant
mass and stiffness matrices ``M`` and ``K`` with ``K`` zero on the six rigid rows and
columns. Everything here depends on ``(M, K)`` only.

Diagonalised model
------------------
The free-free elastic modes are ``K phi = omega^2 M phi`` with ``phi`` mass-orthogonal to
the six rigid-body motions. Eliminating the rigid coordinates by that orthogonality,
``x_r = -M_rr^{-1} M_re psi``, leaves the ``k x k`` problem

.. math::

    K_{ee} \psi = \omega^2 S \psi, \qquad S = M_{ee} - M_{er} M_{rr}^{-1} M_{re},

so the rigid-body modes are removed exactly (no near-zero eigenvalues to sort out). With
``x = Phi xi`` (``Phi^T M Phi = I``), modal damping ``zeta``, inputs ``u`` acting on the
hybrid coordinates through ``B`` (generalised forces ``B u``) and outputs
``y = C_q x + C_v x'``, the seed's equation (1) reads

.. math::

    \ddot\xi + 2 \zeta \Omega \dot\xi + \Omega^2 \xi = D u, \qquad
    y = C_1 \xi + C_2 \dot\xi, \qquad D = \Phi^T B, \; C_1 = C_q \Phi, \; C_2 = C_v \Phi.

The default is the seed's: the three hub torques in (``B`` selects the rotation
coordinates 3:6, whose generalised forces are the torques by virtual work) and the three
hub rotation angles out (``C_q`` selects 3:6, ``C_v = 0``). The default damping ratio is
``zeta = 0.005`` for every mode, a typical value for bolted aluminium spacecraft structures
and small enough for the weak-damping results below.

Modal cost (seed equations (2)-(3), Skelton)
-------------------------------------------
For white-noise inputs of intensity ``W`` (``E[u(t) u(s)^T] = W delta(t - s)``) the
steady-state cost is ``V = E[y^T Q y]``; for an impulsive disturbance ``u = w delta(t)``
with ``E[w w^T] = W`` (initial modal velocities ``xi'(0) = D w``) it is
``V = E int_0^inf y^T Q y dt``. Both equal ``V = tr(C^T Q C X)`` with ``X`` the solution
of ``A X + X A^T + B W B^T = 0``, so one number serves both readings. In the weak-damping
limit ``V = sum_i V_i`` with (equation (3))

.. math::

    V_i = \frac{(c_{1i}^T Q c_{1i} + \omega_i^2 c_{2i}^T Q c_{2i})\,\sigma_i^2}
               {4 \zeta_i \omega_i^3}, \qquad \sigma_i^2 = d_i^T W d_i .

:func:`modal_costs` gives equation (3); :func:`cost_decomposition` gives the exact total
from the Lyapunov equation and Skelton's exact component costs (the diagonal of
``X C^T Q C`` summed over each mode's two states), which add up to the total exactly and
tend to equation (3) as ``zeta -> 0``.

Internal balancing (seed section 3.2, Moore)
--------------------------------------------
With the state ``chi = [xi; xi']``, ``A = [[0, I], [-Omega^2, -2 zeta Omega]]``,
``B = [0; D]``, ``C = [C_1, C_2]``, the Gramians solve
``A W + W A^T + B B^T = 0`` and ``A^T V + V A + C^T C = 0`` and the Hankel singular
values are ``sigma_i = sqrt(lambda_i(W V))``. The balanced realisation is computed by the
square-root method (SVD of the product of the Gramians' square-root factors), and
truncating it to order ``k`` satisfies

.. math::

    \| G(j\omega) - G_k(j\omega) \|_\infty \le 2 \sum_{i > k} \sigma_i .

Gregory's approximation (equation (4)) for a lightly damped mode with separated frequency
is ``sigma_i ~ sigma_{p+i} ~ sqrt(|d_i|^2 (|c_1i|^2 + omega_i^2 |c_2i|^2)) / (4 zeta_i
omega_i^2)``; equation (5), ``max(zeta_i, zeta_j) max(omega_i, omega_j) / |omega_i -
omega_j| << 1``, says when the frequencies are separated enough for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import pandas as pd
import scipy.linalg as sla
from scipy.optimize import linear_sum_assignment, minimize_scalar

#: Default modal damping ratio of every elastic mode.
ZETA = 0.005
#: Number of rigid-body coordinates leading a hybrid coordinate vector.
N_RIGID = 6
#: Rotation coordinates of the hub frame in hybrid coordinates.
ROTATIONS = slice(3, 6)
#: Equation (5) reads "<< 1" as "below this": modes whose ratio reaches it form a cluster.
SEPARATION_THRESHOLD = 0.1
#: Relative thresholds of the selection rule (see :func:`select_modes`).
COST_TOL = 1e-4
HSV_TOL = 1e-2

#: The seed's Table 2: modal costs and modal influence coefficients of system modes 1-5.
SEED_TABLE2 = pd.DataFrame({
    "mode": [1, 2, 3, 4, 5],
    "modal_cost": [0.124e-7, 0.476e-5, 0.810e-13, 0.486e-11, 0.377e-11],
    "hsv": [0.154e-3, 0.935e-2, 0.391e-6, 0.234e-5, 0.205e-5],
})


# --------------------------------------------------------------------------------------
# The diagonalised model
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModalModel:
    """The elastic part of a hybrid model in modal coordinates (seed equation (1)).

    Attributes
    ----------
    omega : numpy.ndarray
        Free-free elastic circular frequencies (rad/s), ascending, ``(p,)``.
    zeta : numpy.ndarray
        Modal damping ratios, ``(p,)``.
    Phi : numpy.ndarray
        Mass-normalised mode shapes in hybrid coordinates, ``(n, p)``.
    D : numpy.ndarray
        Modal input matrix ``Phi^T B``, ``(p, r)``; row ``i`` is the seed's ``d_i``.
    C1, C2 : numpy.ndarray
        Modal output matrices ``C_q Phi`` and ``C_v Phi``, ``(l, p)``.
    """

    omega: np.ndarray
    zeta: np.ndarray
    Phi: np.ndarray
    D: np.ndarray
    C1: np.ndarray
    C2: np.ndarray

    @property
    def p(self) -> int:
        """Number of elastic modes."""
        return len(self.omega)

    @property
    def f_hz(self) -> np.ndarray:
        """Elastic frequencies in Hz."""
        return self.omega / (2.0 * np.pi)

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(A, B, C)`` of the state ``chi = [xi; xi']`` (seed section 3.2)."""
        p = self.p
        A = np.block([[np.zeros((p, p)), np.eye(p)],
                      [-np.diag(self.omega ** 2), -np.diag(2.0 * self.zeta * self.omega)]])
        B = np.vstack([np.zeros_like(self.D), self.D])
        C = np.hstack([self.C1, self.C2])
        return A, B, C

    def transfer(self, w: np.ndarray) -> np.ndarray:
        """``G(j w)`` as the sum of the modal terms, ``(len(w), l, r)``.

        ``G(s) = sum_i (c_1i + c_2i s) d_i^T / (s^2 + 2 zeta_i omega_i s + omega_i^2)``.
        """
        s = 1j * np.asarray(w, dtype=float)[:, None]
        den = s ** 2 + 2.0 * self.zeta * self.omega * s + self.omega ** 2
        num_c = self.C1[None, :, :] + self.C2[None, :, :] * s[:, None, :]
        return np.einsum("wlp,wp,pr->wlr", num_c, 1.0 / den, self.D)


def rigid_elastic_split(M: np.ndarray, K: np.ndarray, n_rigid: int = N_RIGID):
    """Check the hybrid form and return ``(M_rr, M_re, M_ee, K_ee)``.

    Raises ``ValueError`` when ``M`` is not symmetric or ``K`` couples the rigid
    coordinates (a rigid motion would then store strain energy).
    """
    M = np.asarray(M, dtype=float)
    K = np.asarray(K, dtype=float)
    n = M.shape[0]
    if M.shape != (n, n) or K.shape != (n, n) or n <= n_rigid:
        raise ValueError(f"M {M.shape} and K {K.shape} must be square and larger than {n_rigid}")
    scale_m = np.max(np.abs(M))
    if np.max(np.abs(M - M.T)) > 1e-10 * scale_m:
        raise ValueError("M is not symmetric")
    scale_k = np.max(np.abs(K))
    rigid_rows = max(np.max(np.abs(K[:n_rigid, :])), np.max(np.abs(K[:, :n_rigid])))
    if rigid_rows > 1e-9 * scale_k:
        raise ValueError(f"K is not zero on the first {n_rigid} (rigid) rows and columns")
    r = slice(0, n_rigid)
    e = slice(n_rigid, n)
    return M[r, r], M[r, e], M[e, e], 0.5 * (K[e, e] + K[e, e].T)


def free_free_modes(M: np.ndarray, K: np.ndarray, n_rigid: int = N_RIGID):
    """Elastic free-free modes of a hybrid model, rigid-body modes removed exactly.

    Returns
    -------
    omega : numpy.ndarray
        Circular frequencies, ascending.
    Phi : numpy.ndarray
        Mode shapes in hybrid coordinates with ``Phi^T M Phi = I`` and
        ``Phi^T K Phi = diag(omega^2)``.
    """
    Mrr, Mre, Mee, Kee = rigid_elastic_split(M, K, n_rigid)
    coupling = np.linalg.solve(Mrr, Mre)
    S = Mee - Mre.T @ coupling
    lam, psi = sla.eigh(Kee, 0.5 * (S + S.T))
    if np.any(lam <= 0.0):
        raise ValueError(f"the elastic block has non-positive eigenvalues {lam[lam <= 0]}")
    return np.sqrt(lam), np.vstack([-coupling @ psi, psi])


def free_free_frequencies_hz(M: np.ndarray, K: np.ndarray, n_rigid: int = N_RIGID) -> np.ndarray:
    """Elastic free-free frequencies (Hz) of a hybrid model."""
    return free_free_modes(M, K, n_rigid)[0] / (2.0 * np.pi)


def selector(n: int, rows: slice) -> np.ndarray:
    """Rows of the ``n x n`` identity picked by ``rows``."""
    return np.eye(n)[rows]


def modal_model(M: np.ndarray, K: np.ndarray, B: np.ndarray | None = None,
                Cq: np.ndarray | None = None, Cv: np.ndarray | None = None,
                zeta: float | np.ndarray = ZETA, n_modes: int | None = None,
                n_rigid: int = N_RIGID) -> ModalModel:
    """Diagonalise a hybrid model (seed equation (1)).

    Parameters
    ----------
    M, K : array_like
        Hybrid mass and stiffness, ``(n, n)``.
    B : array_like, optional
        Input matrix ``(n, r)``: generalised forces ``B u``. Default: the three hub torques.
    Cq, Cv : array_like, optional
        Output matrices ``(l, n)`` on displacements and velocities. Default: the three hub
        rotation angles.
    zeta : float or array_like
        Modal damping ratio(s).
    n_modes : int, optional
        Keep the lowest ``n_modes`` elastic modes (all by default).
    """
    omega, Phi = free_free_modes(M, K, n_rigid)
    if n_modes is not None:
        omega, Phi = omega[:n_modes], Phi[:, :n_modes]
    n = Phi.shape[0]
    B = selector(n, ROTATIONS).T if B is None else np.asarray(B, dtype=float)
    Cq = selector(n, ROTATIONS) if Cq is None else np.asarray(Cq, dtype=float)
    Cv = np.zeros_like(Cq) if Cv is None else np.asarray(Cv, dtype=float)
    zeta = np.broadcast_to(np.asarray(zeta, dtype=float), omega.shape).copy()
    if np.any(zeta <= 0):
        raise ValueError("modal damping must be positive (the Gramians need a stable A)")
    return ModalModel(omega, zeta, Phi, Phi.T @ B, Cq @ Phi, Cv @ Phi)


# --------------------------------------------------------------------------------------
# Modal cost analysis
# --------------------------------------------------------------------------------------
def _weights(mm: ModalModel, Q, W):
    Q = np.eye(mm.C1.shape[0]) if Q is None else np.asarray(Q, dtype=float)
    W = np.eye(mm.D.shape[1]) if W is None else np.asarray(W, dtype=float)
    return Q, W


def modal_costs(mm: ModalModel, Q: np.ndarray | None = None,
                W: np.ndarray | None = None) -> np.ndarray:
    """Modal costs ``V_i`` of seed equation (3) (weak-damping approximation).

    ``sigma_i^2 = d_i^T W d_i`` is the intensity of the i-th modal force (or the mean
    square of the i-th initial modal velocity). Defaults: ``Q = I``, ``W = I``.
    """
    Q, W = _weights(mm, Q, W)
    sigma2 = np.einsum("pr,rs,ps->p", mm.D, W, mm.D)
    out = (np.einsum("lp,lm,mp->p", mm.C1, Q, mm.C1)
           + mm.omega ** 2 * np.einsum("lp,lm,mp->p", mm.C2, Q, mm.C2))
    return out * sigma2 / (4.0 * mm.zeta * mm.omega ** 3)


def cost_decomposition(mm: ModalModel, Q: np.ndarray | None = None,
                       W: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Total cost from the state covariance and Skelton's exact component costs.

    ``X`` solves ``A X + X A^T + B W B^T = 0``; ``V = tr(X C^T Q C)``; the component cost
    of mode ``i`` is the sum of the diagonal entries ``i`` and ``p + i`` of ``X C^T Q C``,
    so the components add up to ``V`` exactly.

    Returns
    -------
    V : float
    components : numpy.ndarray, ``(p,)``
    """
    Q, W = _weights(mm, Q, W)
    A, B, C = mm.state_space()
    X = sla.solve_continuous_lyapunov(A, -B @ W @ B.T)
    diag = np.einsum("ij,ji->i", X, C.T @ Q @ C)
    return float(np.sum(diag)), diag[:mm.p] + diag[mm.p:]


# --------------------------------------------------------------------------------------
# Internal balancing
# --------------------------------------------------------------------------------------
def gramians(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Controllability and observability Gramians from their Lyapunov equations.

    ``A W + W A^T + B B^T = 0`` and ``A^T V + V A + C^T C = 0`` (``A`` stable).
    """
    Wc = sla.solve_continuous_lyapunov(A, -B @ B.T)
    Wo = sla.solve_continuous_lyapunov(A.T, -C.T @ C)
    return 0.5 * (Wc + Wc.T), 0.5 * (Wo + Wo.T)


def _psd_factor(X: np.ndarray) -> np.ndarray:
    """``L`` with ``X = L L^T`` for a symmetric positive semi-definite ``X``.

    From the eigendecomposition rather than Cholesky: a Gramian of a model with
    uncontrollable or unobservable modes is singular, and round-off makes its smallest
    eigenvalues slightly negative; those are set to zero.
    """
    lam, U = np.linalg.eigh(X)
    return U * np.sqrt(np.clip(lam, 0.0, None))


def hankel_singular_values(Wc: np.ndarray, Wo: np.ndarray) -> np.ndarray:
    """``sigma_i = sqrt(lambda_i(W V))``, descending.

    Computed as the singular values of ``L_o^T L_c``, whose squares are the eigenvalues of
    ``W V`` without forming the product.
    """
    return sla.svdvals(_psd_factor(Wo).T @ _psd_factor(Wc))


@dataclass(frozen=True)
class Balanced:
    """A balanced realisation ``(A, B, C)`` with ``W = V = diag(hsv)``.

    ``T`` maps balanced to original states (``x = T z``) and ``Tinv`` back
    (``z = Tinv x``). States with ``sigma_i <= rel_tol * sigma_1`` (uncontrollable or
    unobservable to round-off) are left out, so ``hsv`` may be shorter than the order of
    the original model; ``hsv_all`` keeps every value.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    hsv: np.ndarray
    hsv_all: np.ndarray
    T: np.ndarray
    Tinv: np.ndarray

    def truncate(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The balanced truncation of order ``k``: the leading ``k`` balanced states."""
        return self.A[:k, :k], self.B[:k], self.C[:, :k]

    def bound(self, k: int) -> float:
        """The H-infinity error bound ``2 sum_{i > k} sigma_i`` of the order-``k`` truncation."""
        return 2.0 * float(np.sum(self.hsv_all[k:]))


def balanced_realisation(A: np.ndarray, B: np.ndarray, C: np.ndarray,
                         rel_tol: float = 1e-12) -> Balanced:
    """Balance a stable realisation by the square-root method.

    With ``W = L_c L_c^T``, ``V = L_o L_o^T`` and ``L_o^T L_c = U Sigma Z^T``,
    ``T = L_c Z Sigma^{-1/2}`` and ``T^{-1} = Sigma^{-1/2} U^T L_o^T`` give
    ``T^{-1} W T^{-T} = T^T V T = Sigma``.
    """
    Wc, Wo = gramians(A, B, C)
    Lc, Lo = _psd_factor(Wc), _psd_factor(Wo)
    U, s, Zt = sla.svd(Lo.T @ Lc)
    keep = s > rel_tol * s[0]
    r = np.sqrt(s[keep])
    T = Lc @ Zt[keep].T / r
    Tinv = (U[:, keep] / r).T @ Lo.T
    return Balanced(Tinv @ A @ T, Tinv @ B, C @ T, s[keep], s, T, Tinv)


def gregory_hsv(mm: ModalModel) -> np.ndarray:
    """Gregory's approximate modal influence coefficients (seed equation (4)), ``(p,)``.

    ``sigma_i ~ sqrt(|d_i|^2 (|c_1i|^2 + omega_i^2 |c_2i|^2)) / (4 zeta_i omega_i^2)``; each
    mode carries two nearly equal Hankel singular values, ``sigma_i`` and ``sigma_{p+i}``.
    """
    d2 = np.sum(mm.D ** 2, axis=1)
    c2 = np.sum(mm.C1 ** 2, axis=0) + mm.omega ** 2 * np.sum(mm.C2 ** 2, axis=0)
    return np.sqrt(d2 * c2) / (4.0 * mm.zeta * mm.omega ** 2)


def modal_hsv(mm: ModalModel, bal: Balanced) -> tuple[np.ndarray, np.ndarray]:
    """Exact Hankel singular values attributed to modes.

    Balanced state ``j`` is ``x = T[:, j]`` in modal states; its share in mode ``i`` is
    measured in the energy metric, ``omega_i^2 T[i, j]^2 + T[p + i, j]^2``, normalised over
    the modes. Each mode owns two states, so the balanced states are assigned to the
    ``2p`` slots (every mode twice) to maximise the total share (Hungarian method). A mode
    receives the larger of its two values (zero when the balanced realisation holds no
    state of it: the mode is uncontrollable or unobservable).

    Returns
    -------
    hsv : numpy.ndarray, ``(p,)``
    purity : numpy.ndarray, ``(p,)``
        The smaller share of the mode in its assigned states (1 for a mode that is its
        own balanced pair, about 1/2 or less inside a cluster of close modes; NaN when the
        mode holds no balanced state).
    """
    p = mm.p
    share = mm.omega[:, None] ** 2 * bal.T[:p] ** 2 + bal.T[p:] ** 2
    share = share / np.sum(share, axis=0, keepdims=True)
    slots = np.vstack([share, share])
    rows, cols = linear_sum_assignment(-slots.T)
    hsv = np.zeros(p)
    purity = np.full(p, np.nan)
    for j, slot in zip(rows, cols):
        i = slot % p
        hsv[i] = max(hsv[i], bal.hsv[j])
        purity[i] = share[i, j] if np.isnan(purity[i]) else min(purity[i], share[i, j])
    return hsv, purity


def separation_ratios(mm: ModalModel) -> np.ndarray:
    """Seed equation (5) for every pair: ``max(zeta_i, zeta_j) max(w_i, w_j) / |w_i - w_j|``.

    ``(p, p)`` with NaN on the diagonal (and ``inf`` for coincident frequencies).
    """
    z = np.maximum.outer(mm.zeta, mm.zeta)
    w = np.maximum.outer(mm.omega, mm.omega)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = z * w / np.abs(np.subtract.outer(mm.omega, mm.omega))
    np.fill_diagonal(r, np.nan)
    return r


def separation_pairs(mm: ModalModel, threshold: float = SEPARATION_THRESHOLD) -> pd.DataFrame:
    """Equation (5) for every pair of modes, one row per pair ``i < j``.

    Columns ``mode_i, mode_j`` (1-based), ``f_i_hz, f_j_hz``, ``ratio`` and ``separated``
    (``ratio < threshold``).
    """
    ratio = separation_ratios(mm)
    i, j = np.triu_indices(mm.p, k=1)
    return pd.DataFrame({"mode_i": i + 1, "mode_j": j + 1, "f_i_hz": mm.f_hz[i],
                         "f_j_hz": mm.f_hz[j], "ratio": ratio[i, j],
                         "separated": ratio[i, j] < threshold})


def clusters(mm: ModalModel, threshold: float = SEPARATION_THRESHOLD) -> np.ndarray:
    """Cluster label of every mode: modes joined by a pair failing equation (5).

    Two modes whose ratio reaches ``threshold`` are close; clusters are the connected
    components of that relation. Labels are 1-based and numbered by the cluster's lowest
    mode; a separated mode is a cluster of its own.
    """
    close = np.nan_to_num(separation_ratios(mm), nan=0.0, posinf=np.inf) >= threshold
    label = -np.ones(mm.p, dtype=int)
    current = 0
    for i in range(mm.p):
        if label[i] >= 0:
            continue
        current += 1
        stack = [i]
        while stack:
            j = stack.pop()
            if label[j] < 0:
                label[j] = current
                stack.extend(np.flatnonzero(close[j] & (label < 0)))
    return label


# --------------------------------------------------------------------------------------
# Frequency-domain error of a truncation
# --------------------------------------------------------------------------------------
def frequency_grid(omega: np.ndarray, zeta: np.ndarray, n_log: int = 600,
                   n_peak: int = 81, width: float = 8.0) -> np.ndarray:
    """Frequencies (rad/s) for peak searches: log-spaced plus dense points at resonances.

    ``n_log`` points log-spaced over ``[omega_min / 100, 100 omega_max]`` and, for every
    mode, ``n_peak`` points over ``omega_i (1 + zeta_i s)``, ``|s| <= width`` (the
    half-power band is ``|s| <= 1``).
    """
    base = np.geomspace(omega.min() / 100.0, omega.max() * 100.0, n_log)
    s = np.linspace(-width, width, n_peak)
    dense = (omega[:, None] * (1.0 + zeta[:, None] * s[None, :])).ravel()
    w = np.concatenate([base, dense, omega * np.sqrt(np.clip(1.0 - 2.0 * zeta ** 2, 0, None))])
    return np.unique(w[w > 0])


def state_space_transfer(A: np.ndarray, B: np.ndarray, C: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``C (j w I - A)^{-1} B`` for every ``w``, ``(len(w), l, r)``."""
    n = A.shape[0]
    if n == 0:
        return np.zeros((len(w), C.shape[0], B.shape[1]), dtype=complex)
    lhs = 1j * np.asarray(w)[:, None, None] * np.eye(n) - A[None]
    return C[None] @ np.linalg.solve(lhs, np.broadcast_to(B, (len(w),) + B.shape))


def hinf_norm(response: Callable[[np.ndarray], np.ndarray], grid: np.ndarray,
              n_refine: int = 8) -> float:
    """Largest singular value of ``response(w)`` over ``w``: grid search, then refinement.

    The grid maximum is refined around its ``n_refine`` largest local maxima by a bounded
    scalar search between the neighbouring grid points, so a peak that falls between grid
    points is not under-estimated by more than the search tolerance.
    """
    sv = np.linalg.svd(response(grid), compute_uv=False)[:, 0]
    peaks = [i for i in range(len(grid))
             if (i == 0 or sv[i] >= sv[i - 1]) and (i == len(grid) - 1 or sv[i] >= sv[i + 1])]
    best = float(sv.max())
    for i in sorted(peaks, key=lambda i: -sv[i])[:n_refine]:
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        if hi <= lo:
            continue
        res = minimize_scalar(
            lambda x: -np.linalg.svd(response(np.array([x])), compute_uv=False)[0, 0],
            bounds=(lo, hi), method="bounded", options={"xatol": 1e-10 * hi})
        best = max(best, -float(res.fun))
    return best


def truncation_errors(mm: ModalModel, orders: Sequence[int] | None = None,
                      bal: Balanced | None = None) -> pd.DataFrame:
    """Actual H-infinity error of balanced truncations against the bound.

    The error ``|| G - G_k ||_inf`` of the order-``k`` truncation is measured against the
    full modal transfer matrix on :func:`frequency_grid` (with peak refinement) for every
    ``k`` in ``orders`` (default: every order from 1 to one less than the number of
    balanced states).

    Returns
    -------
    pandas.DataFrame
        Columns ``order, error_hinf, bound, holds`` (``holds``: error <= bound, with a
        relative slack of 1e-9 for the round-off of the balancing transformation).
    """
    bal = balanced_realisation(*mm.state_space()) if bal is None else bal
    orders = range(1, len(bal.hsv)) if orders is None else orders
    grid = frequency_grid(mm.omega, mm.zeta)
    rows = []
    for k in orders:
        Ak, Bk, Ck = bal.truncate(k)
        err = hinf_norm(lambda w: mm.transfer(w) - state_space_transfer(Ak, Bk, Ck, w), grid)
        bound = bal.bound(k)
        rows.append((k, err, bound, err <= bound * (1.0 + 1e-9)))
    return pd.DataFrame(rows, columns=["order", "error_hinf", "bound", "holds"])


# --------------------------------------------------------------------------------------
# Selection and the Table 2 analogue
# --------------------------------------------------------------------------------------
def select_modes(costs: np.ndarray, hsv: np.ndarray, cost_tol: float = COST_TOL,
                 hsv_tol: float = HSV_TOL) -> tuple[np.ndarray, np.ndarray]:
    """The selection rule: keep a mode whose cost or influence is not negligible.

    Mode ``i`` is kept by modal cost when ``V_i >= cost_tol * max V`` and by internal
    balancing when ``sigma_i >= hsv_tol * max sigma``. For a lightly damped separated mode
    equations (3) and (4) give ``V_i = 4 zeta_i omega_i sigma_i^2`` (unit weights), so the
    two thresholds are paired as ``hsv_tol = sqrt(cost_tol)``: by default a mode is
    dropped when its output variance is below 1e-4 of the largest mode's (1 % in rms
    amplitude) and when its influence coefficient is below 1 % of the largest. Applied to
    the seed's own Table 2 values (:data:`SEED_TABLE2`) each criterion keeps exactly the
    seed's choice, modes 1 and 2 (mode 1 sits at 2.6e-3 of the largest cost and 1.6e-2 of
    the largest coefficient, the next mode at 1.0e-6 and 2.5e-4).

    Returns
    -------
    by_cost, by_hsv : numpy.ndarray of bool
    """
    costs, hsv = np.asarray(costs, float), np.asarray(hsv, float)
    return costs >= cost_tol * costs.max(), hsv >= hsv_tol * hsv.max()


def analyse(M: np.ndarray, K: np.ndarray, zeta: float = ZETA, n_modes: int | None = None,
            B=None, Cq=None, Cv=None, Q=None, W=None, cost_tol: float = COST_TOL,
            hsv_tol: float = HSV_TOL) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Modal cost analysis and internal balancing of a hybrid model ``(M, K)``.

    See :func:`table2` for the returned tables; this is the same on bare matrices.
    """
    mm = modal_model(M, K, B, Cq, Cv, zeta, n_modes)
    costs = modal_costs(mm, Q, W)
    total, components = cost_decomposition(mm, Q, W)
    bal = balanced_realisation(*mm.state_space())
    hsv_exact, purity = modal_hsv(mm, bal)
    hsv_greg = gregory_hsv(mm)
    by_cost, by_hsv = select_modes(costs, hsv_exact, cost_tol, hsv_tol)
    sep = separation_ratios(mm)
    table = pd.DataFrame({
        "mode": np.arange(1, mm.p + 1),
        "f_hz": mm.f_hz,
        "modal_cost": costs,
        "hsv_exact": hsv_exact,
        "hsv_gregory": hsv_greg,
        "retained": by_cost | by_hsv,
        "modal_cost_exact": components,
        "cost_rank": (-costs).argsort().argsort() + 1,
        "hsv_rank": (-hsv_exact).argsort().argsort() + 1,
        "retained_cost": by_cost,
        "retained_hsv": by_hsv,
        "purity": purity,
        "cluster": clusters(mm),
        "max_separation_ratio": np.nanmax(sep, axis=1) if mm.p > 1 else np.full(mm.p, np.nan),
    })
    table.attrs.update(total_cost_lyapunov=total, sum_modal_costs=float(costs.sum()),
                       zeta=float(np.max(mm.zeta)), hsv_all=bal.hsv_all.tolist())
    return table, truncation_errors(mm, bal=bal)


def table2(model, zeta: float = ZETA, n_modes: int | None = None,
           **options) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The analogue of the seed's Table 2 for a hybrid model.

    Parameters
    ----------
    model
        Anything with hybrid ``M`` and ``K`` attributes (``studies.flexible.HybridModel``).
    zeta : float
        Modal damping ratio of every mode.
    n_modes : int, optional
        Analyse only the lowest ``n_modes`` system modes.
    **options
        ``B, Cq, Cv, Q, W, cost_tol, hsv_tol`` as in :func:`analyse`.

    Returns
    -------
    table2 : pandas.DataFrame
        One row per elastic system mode: ``mode`` (1-based), ``f_hz``, ``modal_cost``
        (equation (3)), ``hsv_exact`` (the Hankel singular value attributed to the mode,
        :func:`modal_hsv`), ``hsv_gregory`` (equation (4)), ``retained``; then
        ``modal_cost_exact`` (Skelton's component cost), the two ranks, which criterion
        keeps the mode, the assignment ``purity``, the equation-(5) ``cluster`` and the
        mode's largest separation ratio. ``attrs`` holds the Lyapunov total cost, the sum
        of the modal costs and every Hankel singular value.
    truncation : pandas.DataFrame
        ``order, error_hinf, bound, holds`` for every balanced truncation order.
    """
    return analyse(model.M, model.K, zeta=zeta, n_modes=n_modes, **options)


def structural_mode_count(build: Callable[[int], object], retained: Sequence[int],
                          reference_hz: Sequence[float], tol: float = 0.01,
                          n_max: int = 20) -> tuple[int | None, pd.DataFrame]:
    """The seed's section 4, step 3: fewest structural modes that get the retained modes right.

    For ``k = 1, ..., n_max`` the hybrid model ``build(k)`` (``k`` structural elastic
    modes) is solved for its free-free system frequencies, and the system modes listed in
    ``retained`` (1-based indices) are compared by index with ``reference_hz`` (the
    frequencies of those same system modes from the reference model). The answer is the
    smallest ``k`` for which every retained frequency is within the relative ``tol``.

    Returns
    -------
    k : int or None
        ``None`` when no ``k <= n_max`` passes.
    trials : pandas.DataFrame
        ``n_structural, max_rel_error, passes`` and one ``f{i}_hz`` column per retained
        mode (NaN where the model has fewer modes).
    """
    retained = list(retained)
    ref = np.asarray(reference_hz, dtype=float)
    if len(ref) != len(retained):
        raise ValueError("reference_hz needs one frequency per retained mode")
    rows, found = [], None
    for k in range(1, n_max + 1):
        model = build(k)
        f = free_free_frequencies_hz(model.M, model.K)
        got = np.array([f[i - 1] if i <= len(f) else np.nan for i in retained])
        err = np.abs(got - ref) / ref
        worst = float(np.max(err)) if np.all(np.isfinite(err)) else np.inf
        ok = worst <= tol
        rows.append({"n_structural": k, "max_rel_error": worst, "passes": ok,
                     **{f"f{i}_hz": g for i, g in zip(retained, got)}})
        if ok and found is None:
            found = k
            break
    return found, pd.DataFrame(rows)
