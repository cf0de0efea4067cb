r"""The four modal sets of the seed, each assembled into a hybrid-coordinate model.

Hybrid coordinates
------------------
The spacecraft's nodal displacements :math:`\mathbf u` (``N`` degrees of
freedom, finite-element model of :mod:`studies.flexible.spacecraft`) are
written as a rigid motion of the hub-fixed frame plus a deformation relative
to it,

.. math::

    \mathbf u = \mathbf R\,\mathbf q_r + \boldsymbol\Phi\,\boldsymbol\eta,
    \qquad \mathbf T = [\mathbf R \;\; \boldsymbol\Phi],

where :math:`\mathbf q_r = (x, y, z, \theta_x, \theta_y, \theta_z)` are the
translation of the frame origin (the centre of the hub box) and its small
rotations, :math:`\mathbf R` moves every node rigidly with the frame, and the
columns of :math:`\boldsymbol\Phi` are the deformation shapes of a modal set.
The reduced model is the Rayleigh-Ritz projection

.. math::

    \mathbf M_r = \mathbf T^\top \mathbf M \mathbf T =
    \begin{bmatrix} \mathbf R^\top \mathbf M \mathbf R & \mathbf R^\top \mathbf M \boldsymbol\Phi \\
    \boldsymbol\Phi^\top \mathbf M \mathbf R & \boldsymbol\Phi^\top \mathbf M \boldsymbol\Phi \end{bmatrix},
    \qquad
    \mathbf K_r = \begin{bmatrix} \mathbf 0 & \mathbf 0 \\
    \mathbf 0 & \boldsymbol\Phi^\top \mathbf K \boldsymbol\Phi \end{bmatrix},

whose rigid block :math:`\mathbf R^\top \mathbf M \mathbf R` holds the total
mass, first moment and inertia about the origin, whose coupling block holds
the modal momentum coefficients, and whose stiffness vanishes on the rigid
block because :math:`\mathbf K \mathbf R = \mathbf 0`. Because
:math:`\mathbf T` is a set of compatible displacement fields of the finite-
element model, the free-free eigenvalues of :math:`(\mathbf K_r, \mathbf M_r)`
bound those of the full model from above, eigenvalue by eigenvalue
(Rayleigh-Ritz / Poincare separation).

The hub-fixed frame is the hub's mean-axis (Tisserand) frame: a deformation
carries no linear or angular momentum of the hub,

.. math::

    \mathbf C \boldsymbol\Phi = \mathbf 0, \qquad
    \mathbf C = \mathbf R_h^\top \mathbf M_h \mathbf P_h,

with :math:`\mathbf P_h` the restriction to the hub's degrees of freedom and
:math:`\mathbf M_h`, :math:`\mathbf R_h` the hub's own mass matrix and rigid
modes. Any shape :math:`\mathbf y` is made relative to that frame by removing
its mean-axis rigid part, :math:`\mathcal D\mathbf y = \mathbf y - \mathbf R
(\mathbf C \mathbf R)^{-1} \mathbf C \mathbf y`; this does not change the span
of :math:`\mathbf T`, hence not the eigenvalues, only the meaning of
:math:`\mathbf q_r`. For the hub's free-interface modes the condition holds by
mass-orthogonality to its rigid modes.

Components and interface
------------------------
Three components: the hub and the two panels, each with its own stiffness
and mass :math:`\mathbf K_c, \mathbf M_c` (its own elements only). The
interface :math:`b` is the set of the six degrees of freedom of every node on
the two root lines, shared by hub and panels; :math:`i` is everything else.

The modal sets (Section 2 of the seed)
--------------------------------------
``component`` -- component elastic normal modes (Section 2.1):
    the hub's free-interface elastic modes (hub alone, free-free,
    :math:`\mathbf K_h \boldsymbol\phi = \omega^2 \mathbf M_h \boldsymbol\phi`,
    rigid modes dropped: they are :math:`\mathbf q_r`), carried into the
    panels by the panels' static extension of the root-line motion
    :math:`\mathbf u_i = -\mathbf K_{ii}^{-1}\mathbf K_{ib}\mathbf u_b` (for a
    single attachment point this is the rigid motion of the seed's
    attachment frame; for a root line it is the static shape the panel takes
    when the root line moves), plus each panel's fixed-interface
    (cantilever) modes :math:`\mathbf K_{p,ii}\boldsymbol\phi =
    \omega^2 \mathbf M_{p,ii}\boldsymbol\phi`. Nothing in this set
    represents the hub's static flexibility at the root line: every hub
    free-interface mode moves the root line, the static extension turns
    that motion into membrane strain of the panel, and a system mode that
    keeps the root line still (a hub-wall mode of the assembled craft) has to
    be built from many hub modes. The set converges slowly for that reason.
``craig-bampton`` -- Craig and Bampton (1968) (Section 2.2):
    fixed-interface normal modes of hub and panels (interface clamped) plus
    the interface constraint modes
    :math:`\boldsymbol\Psi = [\mathbf I;\ -\mathbf K_{ii}^{-1}\mathbf K_{ib}]`,
    one static shape per interface degree of freedom. Their span contains
    the rigid motions; the constraint-mode coordinates are therefore taken
    as an orthonormal basis of the range of the interface projector
    :math:`\mathbf Q = (\mathcal D\boldsymbol\Psi)_b`, of dimension
    :math:`n_b - 6`, and the rest of the motion is :math:`\mathbf q_r`.
``macneal-rubin`` -- MacNeal (1971), Rubin (1975) (Section 2.3):
    each component's free-interface normal modes :math:`\hat{\boldsymbol\Phi}_c`
    (its six rigid-body modes and its lowest elastic ones) plus its residual
    flexibility at the interface, the attachment shapes of the omitted modes,

    .. math::

        \mathbf G_c = \mathbf G_{e,c}\,\mathbf E_b
          - \boldsymbol\Phi_c \boldsymbol\Lambda_c^{-1} \boldsymbol\Phi_{c,b}^\top,

    where :math:`\mathbf G_{e,c}` is the component's inertia-relief
    (elastic) flexibility, computed from the bordered system
    :math:`[\mathbf K_c,\ \mathbf M_c \mathbf R_c;\ \mathbf R_c^\top \mathbf M_c,\ \mathbf 0]`.
    With the interface forces :math:`\mathbf F` on the hub and
    :math:`-\mathbf F` on the panels, a component's motion is
    :math:`\hat{\boldsymbol\Phi}_c \boldsymbol\eta_c \pm \mathbf G_c \mathbf F`;
    interface compatibility
    :math:`\hat{\boldsymbol\Phi}_{h,b}\boldsymbol\eta_h + \mathbf G_{h,bb}\mathbf F
    = \hat{\boldsymbol\Phi}_{P,b}\boldsymbol\eta_P - \mathbf G_{P,bb}\mathbf F`
    eliminates the residual coordinates,
    :math:`\mathbf F = (\mathbf G_{h,bb} + \mathbf G_{P,bb})^{-1}
    (\hat{\boldsymbol\Phi}_{P,b}\boldsymbol\eta_P - \hat{\boldsymbol\Phi}_{h,b}\boldsymbol\eta_h)`,
    so the coordinates are the component modal coordinates only. The
    system's common rigid motion is :math:`\mathbf q_r`; what remains are the
    hub's elastic modes and, per panel, its six rigid-body modes (its motion
    relative to the hub, resisted only through the residual flexibility)
    and its elastic modes. All of them are used as Ritz vectors with the
    full mass and stiffness (Rubin's form, residual inertia kept).
``system`` -- system elastic modes relative to the hub frame (Section 2.4):
    obtained by modal synthesis: the deformation block of a Craig-Bampton
    model with a richer component basis is solved with the frame held
    (:math:`\mathbf q_r = 0`),
    :math:`\boldsymbol\Phi_{CB}^\top \mathbf K \boldsymbol\Phi_{CB}\,\boldsymbol\chi
    = \omega^2 \boldsymbol\Phi_{CB}^\top \mathbf M \boldsymbol\Phi_{CB}\,\boldsymbol\chi`,
    and the lowest ``n`` shapes :math:`\boldsymbol\Phi_{CB}\boldsymbol\chi_j`
    are the deformation basis. They satisfy the mean-axis condition, are
    mass-normalised and diagonalise the deformation block of the stiffness.

Every deformation column is scaled to unit generalised mass
:math:`\boldsymbol\phi^\top \mathbf M \boldsymbol\phi = 1`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp

from .shell import node_dofs
from .spacecraft import PANELS, SpacecraftFE, free_vibration, frequencies_hz, spd_factor

MODAL_SETS = ("component", "craig-bampton", "macneal-rubin", "system")
"""Names of the four modal sets, in the seed's order of Section 2."""

SEED_HUB_MODES = 12
"""Hub modes retained in the seed's Table 1."""
SEED_PANEL_MODES = 8
"""Modes retained per panel in the seed's Table 1."""
SEED_SYSTEM_MODES = 20
"""System modes retained in the seed's Table 1."""
SYNTHESIS_MODES = (36, 24)
"""(hub, per-panel) fixed-interface modes of the Craig-Bampton basis from which the
system modes are synthesised: richer than the seed's component counts, since
system modes drawn from the seed's own Craig-Bampton basis could not be more
accurate than that basis."""

RIGID_LABELS = ("x", "y", "z", "theta_x", "theta_y", "theta_z")


@dataclass(frozen=True, eq=False)
class HybridModel:
    """Reduced spacecraft model in hybrid coordinates.

    Coordinates: ``[x, y, z, theta_x, theta_y, theta_z, eta_1 ... eta_k]``,
    the translation of the hub frame origin, its small rotations, and ``k``
    deformation coordinates relative to the hub frame.

    Attributes
    ----------
    modal_set : str
        One of :data:`MODAL_SETS`.
    M, K : numpy.ndarray
        ``(6 + k, 6 + k)`` mass and stiffness; ``K`` is zero on the rigid
        rows and columns.
    labels : list of str
        Name of each coordinate.
    origin : numpy.ndarray
        Hub frame origin in finite-element coordinates (m).
    total_mass : float
        Mass of the structure (kg), from the rigid block of ``M``.
    inertia : numpy.ndarray
        ``3 x 3`` inertia about ``origin`` (kg m^2), from the rigid block.
    f_hz : numpy.ndarray
        The ``k`` free-free elastic frequencies of the reduced model (Hz),
        ascending; the six rigid-body ones are dropped after checking they
        are zero.
    n_modes : dict
        Retained normal modes: ``{"hub": ., "panel": .}`` for the component
        sets, ``{"system": .}`` for the system set.
    """

    modal_set: str
    M: np.ndarray
    K: np.ndarray
    labels: list[str]
    origin: np.ndarray
    total_mass: float
    inertia: np.ndarray
    f_hz: np.ndarray
    n_modes: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class RitzBasis:
    """Ritz basis ``T = [R, Phi]`` of a modal set on the finite-element degrees of freedom.

    Attributes
    ----------
    modal_set : str
    T : numpy.ndarray
        ``(N, 6 + k)``: the frame's rigid motions, then the deformation shapes.
    labels : list of str
    n_modes : dict
        See :class:`HybridModel`.
    """

    modal_set: str
    T: np.ndarray
    labels: list[str]
    n_modes: dict


def split_modes(n_modes: int | tuple[int, int] | None) -> tuple[int, int]:
    """Hub and per-panel mode counts of a component-based set.

    Parameters
    ----------
    n_modes : int, (int, int) or None
        ``None``: the seed's 12 hub and 8 per-panel modes. A pair: (hub,
        per panel). An integer: the total number of retained component
        modes, shared between hub and panels in the seed's proportion
        12 : 8 : 8 (so 28 gives the seed's counts).
    """
    if n_modes is None:
        return SEED_HUB_MODES, SEED_PANEL_MODES
    if isinstance(n_modes, tuple):
        n_hub, n_panel = n_modes
    else:
        n_panel = round(n_modes * SEED_PANEL_MODES / (SEED_HUB_MODES + 2 * SEED_PANEL_MODES))
        n_hub = n_modes - 2 * n_panel
    if n_hub < 0 or n_panel < 0:
        raise ValueError(f"mode counts must be non-negative, got hub {n_hub}, panel {n_panel}")
    return int(n_hub), int(n_panel)


class Substructures:
    """Component modes, constraint modes and flexibilities of one spacecraft model.

    Eigen-solutions and factorisations are computed on first use and kept,
    so that the four sets and the mode-count sweeps share them.

    Parameters
    ----------
    fe : SpacecraftFE
        The assembled model.
    shift_hz : float
        Spectral shift magnitude for the shift-invert eigen-solutions of free
        components, well below their first elastic frequency.
    min_modes : int
        Fewest modes computed per component eigen-solution, so that later
        requests for a few more reuse the same solution.
    """

    def __init__(self, fe: SpacecraftFE, shift_hz: float = 0.05, min_modes: int = 40):
        self.fe = fe
        self.shift = -(2.0 * np.pi * shift_hz) ** 2
        self.min_modes = min_modes
        self.R = fe.rigid_body_modes()
        self.b = fe.interface_dofs()
        self.n = fe.n_dof
        self.hub_dofs = fe.components["hub"].dofs
        Mh = fe.components["hub"].M
        self._C = (Mh @ self.R[self.hub_dofs]).T
        self._CR = self._C @ self.R[self.hub_dofs]
        self._eig: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._psi: np.ndarray | None = None
        self._psi_frame: np.ndarray | None = None
        self._flex: dict[str, np.ndarray] = {}
        self._system: dict[tuple[int, int], np.ndarray] = {}

    def hub_momentum(self, Y: np.ndarray) -> np.ndarray:
        r"""Hub linear and angular momentum coefficients :math:`\mathbf C \mathbf Y` of shapes ``Y`` (``6 x k``)."""
        return self._C @ Y[self.hub_dofs]

    def to_frame(self, Y: np.ndarray) -> np.ndarray:
        r"""Remove the hub mean-axis rigid part, :math:`\mathcal D\mathbf Y`."""
        return Y - self.R @ np.linalg.solve(self._CR, self.hub_momentum(Y))

    def _scatter(self, dofs: np.ndarray, Y: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n, Y.shape[1]))
        out[dofs] = Y
        return out

    def _local_interface(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Component-local positions of its interface dofs, and the global ones."""
        dofs = self.fe.components[name].dofs
        b = self.b if name == "hub" else node_dofs(self.fe.interface[name])
        return np.searchsorted(dofs, b), b

    def _modes(self, key: str, K, M, n: int) -> tuple[np.ndarray, np.ndarray]:
        cached = self._eig.get(key)
        if cached is None or cached[0].size < n:
            # Half the dofs is below the count of finite eigenvalues (only the
            # drilling rotations, a sixth of the dofs, are massless).
            cached = free_vibration(K, M, max(n, min(self.min_modes, K.shape[0] // 2)), self.shift)
            self._eig[key] = cached
        return cached[0][:n], cached[1][:, :n]

    def free_modes(self, name: str, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Lowest ``n`` elastic free-interface modes of a component (its own dofs).

        The six rigid-body modes are checked to be numerically zero and
        dropped.
        """
        comp = self.fe.components[name]
        omega2, Phi = self._modes("free " + name, comp.K, comp.M, n + 6)
        if not np.all(np.abs(omega2[:6]) < 1e-6 * omega2[6]):
            raise RuntimeError(f"{name}: the six lowest free-free eigenvalues are not rigid-body zeros: {omega2[:7]}")
        return omega2[6:], Phi[:, 6:]

    def fixed_modes(self, name: str, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Lowest ``n`` fixed-interface modes of a component, on the global dofs."""
        comp = self.fe.components[name]
        local_b, _ = self._local_interface(name)
        interior = np.setdiff1d(np.arange(comp.dofs.size), local_b)
        Kii = comp.K[interior][:, interior]
        Mii = comp.M[interior][:, interior]
        omega2, Phi = self._modes("fixed " + name, Kii, Mii, n)
        return omega2, self._scatter(comp.dofs[interior], Phi)

    def constraint_modes(self) -> np.ndarray:
        r"""Interface constraint modes :math:`\boldsymbol\Psi` of the assembled structure, ``(N, n_b)``."""
        if self._psi is None:
            K = self.fe.K
            interior = np.setdiff1d(np.arange(self.n), self.b)
            lu = spd_factor(K[interior][:, interior])
            psi = np.zeros((self.n, self.b.size))
            psi[self.b] = np.eye(self.b.size)
            psi[interior] = -lu.solve(K[interior][:, self.b].toarray())
            self._psi = psi
        return self._psi

    def constraint_deformation(self) -> np.ndarray:
        r"""The constraint modes' deformation relative to the hub frame, ``(N, n_b - 6)``.

        :math:`\mathcal D\boldsymbol\Psi` spans the constraint modes less the
        rigid motions; its interface rows form the projector
        :math:`\mathbf Q`, and the columns returned are
        :math:`\mathcal D\boldsymbol\Psi\,\mathbf U`, with :math:`\mathbf U`
        an orthonormal basis of the range of :math:`\mathbf Q`.
        """
        if self._psi_frame is None:
            psi = self.to_frame(self.constraint_modes())
            U, s, _ = la.svd(psi[self.b], full_matrices=False)
            # Q is a projector: its singular values are 1 on its range and 0
            # on the six rigid interface motions it removes.
            keep = s > 0.5
            if keep.sum() != self.b.size - 6:
                raise RuntimeError(f"constraint-mode projector has rank {keep.sum()}, expected {self.b.size - 6}")
            self._psi_frame = psi @ U[:, keep]
        return self._psi_frame

    def system_modes(self, synthesis_modes: tuple[int, int]) -> np.ndarray:
        """All system modes relative to the hub frame synthesised from one Craig-Bampton basis, ``(N, k_CB)``.

        Ascending in frequency, mass-normalised; see :func:`system_basis`.
        """
        key = tuple(synthesis_modes)
        if key not in self._system:
            Phi_cb = craig_bampton_basis(self, key).T[:, 6:]
            K_cb = Phi_cb.T @ (self.fe.K @ Phi_cb)
            M_cb = Phi_cb.T @ (self.fe.M @ Phi_cb)
            _, chi = la.eigh(0.5 * (K_cb + K_cb.T), 0.5 * (M_cb + M_cb.T))
            self._system[key] = Phi_cb @ chi
        return self._system[key]

    def elastic_flexibility(self, name: str) -> np.ndarray:
        r"""Inertia-relief flexibility columns :math:`\mathbf G_{e,c}\mathbf E_b` of a component (its own dofs).

        The unit interface loads are balanced by the component's rigid-body
        inertia forces, :math:`\mathbf P = \mathbf I - \mathbf M_c\mathbf R_c
        (\mathbf R_c^\top\mathbf M_c\mathbf R_c)^{-1}\mathbf R_c^\top`; the
        self-equilibrated load :math:`\mathbf P\mathbf E_b` is applied to the
        component clamped at one node away from the interface (a statically
        determinate support, whose reactions then vanish), and the response is
        measured from the component's mean axes,
        :math:`\mathbf G_{e,c}\mathbf E_b = \mathbf P^\top \mathbf K_s^{-1} \mathbf P \mathbf E_b`,
        which does not depend on the node chosen.
        """
        if name not in self._flex:
            comp = self.fe.components[name]
            local_b, _ = self._local_interface(name)
            Rc = self.R[comp.dofs]
            MR = comp.M @ Rc
            mass6 = Rc.T @ MR
            load = -MR @ np.linalg.solve(mass6, Rc[local_b].T)
            load[local_b, np.arange(local_b.size)] += 1.0
            support_node = np.setdiff1d(np.arange(comp.nodes.size), local_b // 6)[0]
            free = np.setdiff1d(np.arange(comp.dofs.size), node_dofs([support_node]))
            x = np.zeros_like(load)
            x[free] = spd_factor(comp.K[free][:, free]).solve(load[free])
            self._flex[name] = x - Rc @ np.linalg.solve(mass6, MR.T @ x)
        return self._flex[name]

    def residual_flexibility(self, name: str, n: int) -> np.ndarray:
        r"""Residual attachment shapes :math:`\mathbf G_c` of a component keeping ``n`` elastic modes."""
        omega2, Phi = self.free_modes(name, n)
        local_b, _ = self._local_interface(name)
        return self.elastic_flexibility(name) - (Phi / omega2) @ Phi[local_b].T


def _unit_mass(Y: np.ndarray, M: sp.spmatrix) -> np.ndarray:
    return Y / np.sqrt(np.einsum("ij,ij->j", Y, M @ Y))


def component_basis(sub: Substructures, n_modes=None) -> RitzBasis:
    """Component elastic normal modes: hub free-interface, panel fixed-interface (see module notes).

    Parameters
    ----------
    sub : Substructures
    n_modes : int, (int, int) or None
        Retained modes, see :func:`split_modes`.

    Returns
    -------
    RitzBasis
    """
    n_hub, n_panel = split_modes(n_modes)
    _, Phi_h = sub.free_modes("hub", n_hub)
    hub = sub._scatter(sub.hub_dofs, Phi_h)
    outside = np.setdiff1d(np.arange(sub.n), sub.hub_dofs)
    hub[outside] = (sub.constraint_modes() @ hub[sub.b])[outside]
    cols = [hub]
    labels = [f"hub free {j + 1}" for j in range(n_hub)]
    for p in PANELS:
        cols.append(sub.fixed_modes(p, n_panel)[1])
        labels += [f"{p} fixed {j + 1}" for j in range(n_panel)]
    return _basis(sub, "component", np.hstack(cols), labels, {"hub": n_hub, "panel": n_panel})


def craig_bampton_basis(sub: Substructures, n_modes=None) -> RitzBasis:
    """Craig-Bampton: fixed-interface normal modes plus interface constraint modes.

    Parameters
    ----------
    sub : Substructures
    n_modes : int, (int, int) or None
        Retained modes, see :func:`split_modes`.

    Returns
    -------
    RitzBasis
    """
    n_hub, n_panel = split_modes(n_modes)
    cols = [sub.constraint_deformation()]
    labels = [f"constraint {j + 1}" for j in range(cols[0].shape[1])]
    for name, n in (("hub", n_hub),) + tuple((p, n_panel) for p in PANELS):
        cols.append(sub.fixed_modes(name, n)[1])
        labels += [f"{name} fixed {j + 1}" for j in range(n)]
    return _basis(sub, "craig-bampton", np.hstack(cols), labels, {"hub": n_hub, "panel": n_panel})


def macneal_rubin_basis(sub: Substructures, n_modes=None) -> RitzBasis:
    """MacNeal-Rubin: free-interface normal modes plus residual flexibility, interface-compatible.

    Parameters
    ----------
    sub : Substructures
    n_modes : int, (int, int) or None
        Retained modes, see :func:`split_modes`.

    Returns
    -------
    RitzBasis
    """
    n_hub, n_panel = split_modes(n_modes)
    fe = sub.fe
    hub = fe.components["hub"]
    hub_b, b = sub._local_interface("hub")
    # Free-interface modes of each component, rigid-body ones first.
    Rh = sub.R[hub.dofs]
    Phat_h = np.hstack([Rh, sub.free_modes("hub", n_hub)[1]])
    G_h = sub.residual_flexibility("hub", n_hub)
    S = G_h[hub_b].copy()
    A_h = Phat_h[hub_b]
    panel_blocks = []
    offset = 0
    for p in PANELS:
        comp = fe.components[p]
        pb, gb = sub._local_interface(p)
        Phat_p = np.hstack([sub.R[comp.dofs], sub.free_modes(p, n_panel)[1]])
        G_p = sub.residual_flexibility(p, n_panel)
        rows = slice(offset, offset + gb.size)
        S[rows, rows] += G_p[pb]
        panel_blocks.append((comp, Phat_p, G_p, pb, rows))
        offset += gb.size
    m_p = 6 + n_panel
    A_P = np.zeros((b.size, 2 * m_p))
    for k, (_, Phat_p, _, pb, rows) in enumerate(panel_blocks):
        A_P[rows, k * m_p:(k + 1) * m_p] = Phat_p[pb]
    # Interface forces per unit modal coordinate: F = S^-1 (A_P eta_P - A_h eta_h).
    cho = la.cho_factor(0.5 * (S + S.T))
    F_h = -la.cho_solve(cho, A_h)
    F_P = la.cho_solve(cho, A_P)
    n_cols = Phat_h.shape[1] + 2 * m_p
    T = np.zeros((sub.n, n_cols))
    F = np.hstack([F_h, F_P])
    T[hub.dofs] = G_h @ F
    T[hub.dofs, :Phat_h.shape[1]] += Phat_h
    for k, (comp, Phat_p, G_p, pb, rows) in enumerate(panel_blocks):
        panel_only = np.setdiff1d(np.arange(comp.dofs.size), pb)
        motion = -G_p @ F[rows]
        motion[:, Phat_h.shape[1] + k * m_p:Phat_h.shape[1] + (k + 1) * m_p] += Phat_p
        T[comp.dofs[panel_only]] = motion[panel_only]
        # The root-line values are taken from the hub side, so the field is
        # single-valued whatever the round-off; the check catches a wrong
        # elimination (an O(1) mismatch), not the ~1e-7 left by solving with
        # residual flexibilities whose condition number is ~1e7.
        mismatch = np.abs(motion[pb] - T[comp.dofs[pb]]).max()
        if mismatch > 1e-5 * np.abs(motion).max():
            raise RuntimeError(f"{p}: interface compatibility violated by {mismatch:.3e}")
    # The hub's rigid-body coordinates together with the panels' are the frame's
    # rigid motion q_r; the remaining coordinates are the deformation.
    labels = [f"hub free {j + 1}" for j in range(n_hub)]
    for p in PANELS:
        labels += [f"{p} rigid {r}" for r in RIGID_LABELS] + [f"{p} free {j + 1}" for j in range(n_panel)]
    return _basis(sub, "macneal-rubin", T[:, 6:], labels, {"hub": n_hub, "panel": n_panel})


def system_basis(sub: Substructures, n_modes: int | None = None,
                 synthesis_modes: tuple[int, int] = SYNTHESIS_MODES) -> RitzBasis:
    """System elastic modes relative to the hub frame, synthesised from a Craig-Bampton basis.

    Parameters
    ----------
    sub : Substructures
    n_modes : int or None
        Retained system modes (default 20, the seed's).
    synthesis_modes : (int, int)
        (hub, per-panel) fixed-interface modes of the Craig-Bampton basis.

    Returns
    -------
    RitzBasis
    """
    n = SEED_SYSTEM_MODES if n_modes is None else int(n_modes)
    Phi = sub.system_modes(synthesis_modes)
    if n > Phi.shape[1]:
        raise ValueError(f"{n} system modes asked of a {Phi.shape[1]}-shape synthesis basis")
    labels = [f"system {j + 1}" for j in range(n)]
    return _basis(sub, "system", Phi[:, :n], labels, {"system": n})


def _basis(sub: Substructures, modal_set: str, Phi: np.ndarray, labels: list[str], n_modes: dict) -> RitzBasis:
    Phi = _unit_mass(sub.to_frame(Phi), sub.fe.M)
    return RitzBasis(modal_set, np.hstack([sub.R, Phi]), list(RIGID_LABELS) + labels, n_modes)


BASES = {
    "component": component_basis,
    "craig-bampton": craig_bampton_basis,
    "macneal-rubin": macneal_rubin_basis,
    "system": system_basis,
}
"""Registry: modal-set name to the function that builds its Ritz basis."""


def hybrid_model(sub: Substructures, basis: RitzBasis) -> HybridModel:
    r"""Project the finite-element model on a Ritz basis and solve the free-free reduced problem.

    Parameters
    ----------
    sub : Substructures
    basis : RitzBasis

    Returns
    -------
    HybridModel
        With :math:`\mathbf K_r` set to zero on the rigid rows and columns,
        which :math:`\mathbf K\mathbf R = \mathbf 0` makes exact up to
        round-off.
    """
    fe = sub.fe
    T = basis.T
    Phi = T[:, 6:]
    M = T.T @ (fe.M @ T)
    M = 0.5 * (M + M.T)
    K = np.zeros_like(M)
    K_dd = Phi.T @ (fe.K @ Phi)
    K[6:, 6:] = 0.5 * (K_dd + K_dd.T)
    omega2 = la.eigh(K, M, eigvals_only=True)
    f = frequencies_hz(omega2)
    rigid, elastic = f[:6], f[6:]
    if elastic.size and np.abs(rigid).max() > 1e-6 * elastic[0]:
        raise RuntimeError(f"{basis.modal_set}: reduced model's rigid-body frequencies are not zero: {rigid}")
    origin = np.array(fe.origin, dtype=float)
    for array in (M, K, elastic, origin):
        array.flags.writeable = False
    return HybridModel(
        modal_set=basis.modal_set,
        M=M,
        K=K,
        labels=basis.labels,
        origin=origin,
        total_mass=float(np.trace(M[:3, :3]) / 3.0),
        inertia=M[3:6, 3:6],
        f_hz=elastic,
        n_modes=basis.n_modes,
    )


def reduce(sub: Substructures, modal_set: str, n_modes=None, **options) -> HybridModel:
    """Build the Ritz basis of a modal set and its hybrid model.

    Parameters
    ----------
    sub : Substructures
    modal_set : str
        One of :data:`MODAL_SETS`.
    n_modes : int, (int, int) or None
        See :func:`split_modes` for the component sets; the number of system
        modes for ``"system"`` (default 20).
    **options
        ``synthesis_modes`` for ``"system"``.
    """
    if modal_set not in BASES:
        raise ValueError(f"unknown modal set {modal_set!r}; choose from {MODAL_SETS}")
    return hybrid_model(sub, BASES[modal_set](sub, n_modes, **options))
