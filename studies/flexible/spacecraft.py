r"""Finite-element model of the box-hub spacecraft with two solar panels.

Geometry (FE axes, metres; the hub frame origin is the centre of the box)
-------------------------------------------------------------------------
* Hub: the seed's closed box of 1.5 mm aluminium panels, 2 m (x) by
  3 m (y) by 3 m (z), centred at the origin, with no internal frame: its six
  walls are shells joined along the twelve box edges.
* Solar panels: two flat 1.5 mm aluminium plates in the plane ``z = 0``, one
  on each of the opposite walls ``y = +-1.5 m``, spanning outwards along
  ``+-y``.

Assumption: panel size and attachment
-------------------------------------
The seed's drawing of the panels is not available. A panel is taken as wide
as the wall it leaves (2 m along x) and its root edge is joined to the wall
along the wall's horizontal centre line, from one vertical box edge to the
other. That is where a root fitting would be bolted: the two ends of the line
are the box's corner edges, which the adjacent walls stiffen in their own
plane, so the fitting is supported where the wall is stiffest. The wall
between the ends is left as the seed gives it (1.5 mm, no doubler), so its
local bending flexibility enters the panels' root rotation. The span of the
panel is the one free design parameter; its default, 1.5 m, is the round
value that brings the first elastic frequency of the assembled free-free
spacecraft nearest the seed's finite-element value of 0.55 Hz: when the
choice was made, 1.4 m gave 0.61 Hz and 1.5 m gave 0.533 Hz on the 0.125 m
mesh (0.529 Hz on a 0.0625 m mesh). The value a run gives is the one
:mod:`studies.flexible.study` reports.

Mesh
----
Every wall and panel is a structured grid of triangles
(:mod:`studies.flexible.mesh`) with a target element size; the numbers of
intervals along x, y and z are shared by all parts so that nodes coincide on
the box edges and on the root lines, and the interval count along z is even
so that a grid line runs along each root line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .mesh import ShellMesh, box, merge, rectangle
from .shell import ShellSection, assemble, node_dofs, rigid_body_modes

PANELS = ("panel+y", "panel-y")
"""Names of the two solar panels, by the side of the hub they leave."""


@dataclass(frozen=True)
class SpacecraftDesign:
    """Geometry, material and mesh size of the spacecraft model.

    Attributes
    ----------
    hub_size : tuple of float
        Box edge lengths along x, y, z (m).
    panel_span : float
        Length of each panel from its root line outwards (m); see the module
        notes for why 1.5 m.
    thickness : float
        Wall and panel thickness (m).
    E, nu, rho : float
        Aluminium: Young's modulus (Pa), Poisson's ratio, density (kg/m^3).
    element_size : float
        Target edge length of the grid (m).
    """

    hub_size: tuple[float, float, float] = (2.0, 3.0, 3.0)
    panel_span: float = 1.5
    thickness: float = 1.5e-3
    E: float = 70e9
    nu: float = 0.33
    rho: float = 2700.0
    element_size: float = 0.125

    @property
    def section(self) -> ShellSection:
        """Shell section shared by walls and panels."""
        return ShellSection(self.E, self.nu, self.rho, self.thickness)

    def intervals(self) -> tuple[int, int, int, int]:
        """Grid intervals along x, y, z of the hub and along the panel span."""
        lx, ly, lz = self.hub_size
        size = self.element_size
        nx = max(1, round(lx / size))
        ny = max(1, round(ly / size))
        nz = 2 * max(1, round(lz / (2.0 * size)))
        ns = max(1, round(self.panel_span / size))
        return nx, ny, nz, ns


@dataclass(frozen=True)
class Component:
    """One substructure: its own elements' matrices on the global numbering.

    Attributes
    ----------
    nodes : numpy.ndarray
        Global indices of the component's nodes.
    dofs : numpy.ndarray
        Their global degrees of freedom.
    K, M : scipy.sparse.csr_matrix
        Stiffness and mass of the component alone, restricted to ``dofs``.
    """

    nodes: np.ndarray
    dofs: np.ndarray
    K: sp.csr_matrix
    M: sp.csr_matrix


@dataclass(frozen=True)
class SpacecraftFE:
    """Assembled finite-element model of the spacecraft.

    Attributes
    ----------
    design : SpacecraftDesign
    mesh : ShellMesh
    K, M : scipy.sparse.csr_matrix
        Global stiffness and mass, ``6 n_nodes`` square.
    components : Mapping[str, Component]
        ``"hub"`` and the :data:`PANELS`.
    interface : Mapping[str, numpy.ndarray]
        For each panel, the global indices of its root-line nodes, which it
        shares with the hub.
    origin : numpy.ndarray
        Hub frame origin, the centre of the box.
    """

    design: SpacecraftDesign
    mesh: ShellMesh
    K: sp.csr_matrix
    M: sp.csr_matrix
    components: Mapping[str, Component]
    interface: Mapping[str, np.ndarray]
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def n_dof(self) -> int:
        """Number of degrees of freedom."""
        return self.K.shape[0]

    def rigid_body_modes(self) -> np.ndarray:
        """``(n_dof, 6)`` rigid motions about :attr:`origin` (see :func:`~studies.flexible.shell.rigid_body_modes`)."""
        return rigid_body_modes(self.mesh.nodes, self.origin)

    def interface_dofs(self) -> np.ndarray:
        """All root-line degrees of freedom, panel by panel in :data:`PANELS` order."""
        return np.concatenate([node_dofs(self.interface[p]) for p in PANELS])


def spacecraft_mesh(design: SpacecraftDesign) -> ShellMesh:
    """Mesh of hub walls and panels with groups ``"hub"`` and :data:`PANELS`."""
    lx, ly, lz = design.hub_size
    nx, ny, nz, ns = design.intervals()
    span = design.panel_span
    parts = {"hub": box(lx, ly, lz, nx, ny, nz)}
    for name, side in zip(PANELS, (1.0, -1.0)):
        corner = (-0.5 * lx, side * 0.5 * ly, 0.0)
        parts[name] = [rectangle(corner, (lx, 0.0, 0.0), (0.0, side * span, 0.0), nx, ns)]
    return merge(parts, tol=1e-6 * min(lx, ly, lz))


def build_spacecraft(design: SpacecraftDesign = SpacecraftDesign()) -> SpacecraftFE:
    """Mesh and assemble the spacecraft.

    Parameters
    ----------
    design : SpacecraftDesign

    Returns
    -------
    SpacecraftFE
        The global matrices are the sums of the components' own matrices,
        which are kept for the component-mode syntheses.
    """
    mesh = spacecraft_mesh(design)
    n = 6 * mesh.n_nodes
    K = sp.csr_matrix((n, n))
    M = sp.csr_matrix((n, n))
    components = {}
    for name in ("hub",) + PANELS:
        Kc, Mc = assemble(mesh, design.section, mesh.groups[name])
        K = K + Kc
        M = M + Mc
        nodes = mesh.group_nodes(name)
        dofs = node_dofs(nodes)
        components[name] = Component(nodes, dofs, Kc[dofs][:, dofs].tocsr(), Mc[dofs][:, dofs].tocsr())
    hub_nodes = components["hub"].nodes
    interface = {p: np.intersect1d(components[p].nodes, hub_nodes) for p in PANELS}
    return SpacecraftFE(design, mesh, K.tocsr(), M.tocsr(), components, interface)


def spd_factor(A: sp.spmatrix) -> sla.SuperLU:
    """Sparse LU factors of a symmetric positive definite matrix.

    A symmetric minimum-degree ordering of :math:`A + A^\top` without
    pivoting away from the diagonal (safe for a positive definite matrix)
    keeps the factors of a shell model several times sparser than the default
    column ordering, which is what makes the shift-invert eigen-solutions and
    the static solves fast.
    """
    return sla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True})


def free_vibration(K: sp.spmatrix, M: sp.spmatrix, n_modes: int, shift: float) -> tuple[np.ndarray, np.ndarray]:
    r"""Lowest modes of :math:`\mathbf K \boldsymbol\phi = \omega^2 \mathbf M \boldsymbol\phi` by shift-invert.

    Both paths solve the shifted, inverted problem
    :math:`\mathbf M \boldsymbol\phi = \mu (\mathbf K - \sigma \mathbf M) \boldsymbol\phi`,
    :math:`\omega^2 = \sigma + 1/\mu`, which stays well posed when
    :math:`\mathbf K` is singular (free structure) and when :math:`\mathbf M`
    is (the massless drilling rotations give :math:`\mu = 0`): Lanczos
    (``scipy.sparse.linalg.eigsh``) on the sparse factors for large models,
    a dense solver when a large fraction of the spectrum is asked of a small
    model.

    Parameters
    ----------
    K, M : scipy.sparse matrix
        Symmetric stiffness and (positive semi-definite) mass.
    n_modes : int
        Number of modes wanted (lowest first).
    shift : float
        :math:`\sigma < 0` for a free structure, so that
        :math:`\mathbf K - \sigma \mathbf M` is positive definite although
        ``K`` is singular; of the order of the square of the lowest elastic
        circular frequency or smaller.

    Returns
    -------
    omega2 : numpy.ndarray
        Eigenvalues :math:`\omega^2`, ascending.
    Phi : numpy.ndarray
        Mass-normalised mode shapes, one per column.
    """
    n = K.shape[0]
    A = K - shift * M
    if n <= 600 or n_modes > n // 5:
        mu, Phi = la.eigh(M.toarray(), A.toarray())
        mu, Phi = mu[::-1][:n_modes], Phi[:, ::-1][:, :n_modes]
        if mu[-1] <= 1e-12 * mu[0]:
            raise ValueError(f"{n_modes} modes asked of a model with fewer finite eigenvalues")
        omega2 = shift + 1.0 / mu
    else:
        lu = spd_factor(A)
        op = sla.LinearOperator((n, n), matvec=lu.solve, dtype=float)
        # A fixed start vector: ARPACK's default is random, and on this symmetric structure
        # (pairs of equal frequencies) it made the basis of each pair, and the tables built
        # on it, differ from run to run (modal-convergence frequencies by about 1e-4 Hz).
        start = np.random.default_rng(0).standard_normal(n)
        omega2, Phi = sla.eigsh(K, n_modes, M, sigma=shift, which="LM", OPinv=op, v0=start)
    order = np.argsort(omega2)
    Phi = Phi[:, order]
    Phi = Phi / np.sqrt(np.einsum("ij,ij->j", Phi, M @ Phi))
    return omega2[order], Phi


def frequencies_hz(omega2: np.ndarray) -> np.ndarray:
    r"""Natural frequencies :math:`\operatorname{sign}(\omega^2) \sqrt{|\omega^2|}/2\pi` in Hz.

    The sign is kept so that a negative eigenvalue (round-off for a rigid-body
    mode, or a defect) shows up as a negative frequency instead of being
    hidden.
    """
    return np.sign(omega2) * np.sqrt(np.abs(omega2)) / (2.0 * np.pi)
