r"""Flat-shell finite elements: sparse stiffness and mass matrices.

Element
-------
Each facet is the three-node flat shell ``Tria3DSG`` of the ``pyfe3d``
library, with six degrees of freedom per node, in global axes
:math:`(u, v, w, r_x, r_y, r_z)`. In the element's own axes
:math:`(x, y)` in the facet and :math:`z` normal to it, the displacement
through the thickness is :math:`(u + z r_y, v - z r_x, w)` (first-order shear
deformation theory) and the strain energy of one element of area :math:`A` is

.. math::

    U_e = \frac12 \int_A \left( \boldsymbol\varepsilon^\top \mathbf A \boldsymbol\varepsilon
        + \boldsymbol\kappa^\top \mathbf D \boldsymbol\kappa
        + \boldsymbol\gamma^\top \mathbf A_s \boldsymbol\gamma \right) dA
        + \frac{\gamma_{rz}}{2} \int_A \left(r_z - \theta_z\right)^2 dA,

with the membrane strains
:math:`\boldsymbol\varepsilon = (u_{,x},\ v_{,y},\ u_{,y} + v_{,x})`, the
curvatures :math:`\boldsymbol\kappa = (r_{y,x},\ -r_{x,y},\ r_{y,y} - r_{x,x})`,
the transverse shear strains :math:`\boldsymbol\gamma = (w_{,y} - r_x,\ w_{,x} + r_y)`
and, for an isotropic section of thickness :math:`h`,
:math:`\mathbf A = h\,\mathbf C`, :math:`\mathbf D = h^3 \mathbf C / 12`,
:math:`\mathbf A_s = \tfrac56 G h\,\mathbf I` where :math:`\mathbf C` is the
plane-stress elasticity matrix.

* Membrane and curvature fields are those of the linear (constant-strain)
  triangle.
* Transverse shear is the discrete shear gap field of Bletzinger, Bischoff
  and Ramm (2000): the shear gap :math:`\Delta w_i = (w_i - w_1) - \tfrac12
  (\boldsymbol\phi_1 + \boldsymbol\phi_i)\cdot(\mathbf x_i - \mathbf x_1)`,
  :math:`\boldsymbol\phi = (-r_y, r_x)`, is interpolated linearly and
  :math:`\boldsymbol\gamma = \sum_i \Delta w_i \nabla N_i`; constant curvature
  then gives no shear strain, which is what keeps the thin (1.5 mm) shells of
  the spacecraft free of shear locking. The element averages the three
  fields obtained by starting the gap from each vertex, so the result does
  not depend on node numbering.
* Drilling: the rotation about the normal is tied to the in-plane rotation of
  the membrane field, :math:`\theta_z = \tfrac12 (v_{,x} - u_{,y})`, by the
  variational regularisation of Hughes and Brezzi (1989) with the physical
  modulus :math:`\gamma_{rz} = A_{66} = G h`. The drilling degree of freedom
  therefore carries real strain energy (a rigid rotation about the normal
  costs none, a relative one does), which matters wherever two facets meet at
  an angle: the drilling rotation of one is a bending rotation of the other
  along the hub's box edges and the panels' root lines.
* Mass: consistent, from the kinetic energy
  :math:`\frac12 \int_A [\rho h (\dot u^2 + \dot v^2 + \dot w^2)
  + \frac{\rho h^3}{12} (\dot r_x^2 + \dot r_y^2)]\,dA`; the drilling
  rotation has no inertia of its own.

Element matrices are rotated to global axes and assembled into
``scipy.sparse`` matrices.

Why a library element, and why this one
---------------------------------------
Libraries looked at, with a quick measurement on a square plate where one
was possible:

* ``pyfe3d`` (0.11.0): flat shells with six degrees of freedom per node,
  consistent mass, element contributions written to sparse triplets.
  Its ``Quad4`` quadrilateral integrates transverse shear at one point and
  keeps, as its documentation says, a spurious zero-energy mode: a free
  square plate (4 x 4 and 8 x 8 elements) had seven zero frequencies
  instead of six, which rules it out for a free-free spacecraft.
  ``Tria3DSG`` gave exactly six zero frequencies on the free plate and
  converging cantilever parameters, and is used here (the verification
  tables of :mod:`studies.flexible.study` give the numbers). Its membrane
  field has no drilling enrichment (constant strain), which is stiff for
  in-plane bending; the spacecraft's low modes are governed by plate
  bending, and the mesh-convergence table of the full model shows what that
  costs.
* ``PyNiteFEA`` (3.2.0): its quadrilateral plate gives the drilling rotation
  a spring to ground equal to 1/1000 of the smallest rotational diagonal
  term, which resists rigid rotations about the normal (so a free structure
  has no exact rigid-body modes), and plates contribute nothing to its mass
  matrix.

The loop over elements runs in Python over ``pyfe3d``'s compiled element
routines; the node bookkeeping around it (sizes, positions in the sparse
triplets) is done with array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from pyfe3d import DOF, INT, Tria3DSG, Tria3DSGData, Tria3DSGProbe
from pyfe3d.shellprop_utils import isotropic_plate

from .mesh import ShellMesh


@dataclass(frozen=True)
class ShellSection:
    """Homogeneous isotropic shell section.

    Attributes
    ----------
    E : float
        Young's modulus, Pa.
    nu : float
        Poisson's ratio.
    rho : float
        Density, kg/m^3.
    h : float
        Thickness, m.
    """

    E: float
    nu: float
    rho: float
    h: float

    @property
    def D(self) -> float:
        """Bending stiffness :math:`E h^3 / (12 (1 - \\nu^2))`, N m."""
        return self.E * self.h**3 / (12.0 * (1.0 - self.nu**2))

    @property
    def areal_mass(self) -> float:
        """Mass per unit area :math:`\\rho h`, kg/m^2."""
        return self.rho * self.h


def assemble(mesh: ShellMesh, section: ShellSection, elements=None) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Assemble the stiffness and consistent mass matrices of shell elements.

    Parameters
    ----------
    mesh : ShellMesh
        The mesh; the matrices are numbered over all of its nodes, six
        degrees of freedom per node, :math:`(u, v, w, r_x, r_y, r_z)` of node
        ``n`` at ``6 n ... 6 n + 5``.
    section : ShellSection
        Section of every element assembled.
    elements : array_like of int, optional
        Indices of the triangles to assemble (all by default): a component's
        own matrices come from its own elements on the global numbering.

    Returns
    -------
    K, M : scipy.sparse.csr_matrix
        Symmetric ``(6 n_nodes, 6 n_nodes)`` stiffness and mass matrices.
    """
    tris = mesh.triangles if elements is None else mesh.triangles[np.asarray(elements)]
    n_dof = DOF * mesh.n_nodes
    data = Tria3DSGData()
    probe = Tria3DSGProbe()
    prop = isotropic_plate(thickness=section.h, E=section.E, nu=section.nu, rho=section.rho)
    x = np.ascontiguousarray(mesh.nodes.ravel(), dtype=np.float64)
    n_el = tris.shape[0]
    k_size, m_size = data.KC0_SPARSE_SIZE, data.M_SPARSE_SIZE
    Kr = np.zeros(k_size * n_el, dtype=INT)
    Kc = np.zeros_like(Kr)
    Kv = np.zeros(k_size * n_el)
    Mr = np.zeros(m_size * n_el, dtype=INT)
    Mc = np.zeros_like(Mr)
    Mv = np.zeros(m_size * n_el)
    first_dof = (DOF * tris).tolist()
    element = Tria3DSG(probe)
    for e, (c1, c2, c3) in enumerate(first_dof):
        element.c1, element.c2, element.c3 = c1, c2, c3
        element.init_k_KC0 = e * k_size
        element.init_k_M = e * m_size
        element.update_rotation_matrix(x)
        element.update_probe_xe(x)
        element.update_area()
        element.update_KC0(Kr, Kc, Kv, prop)
        element.update_M(Mr, Mc, Mv, prop)
    K = sp.csr_matrix((Kv, (Kr, Kc)), shape=(n_dof, n_dof))
    M = sp.csr_matrix((Mv, (Mr, Mc)), shape=(n_dof, n_dof))
    # The element routines are symmetric only to round-off; the eigensolvers
    # and the Rayleigh-Ritz bounds downstream assume exact symmetry.
    return 0.5 * (K + K.T).tocsr(), 0.5 * (M + M.T).tocsr()


def rigid_body_modes(nodes: np.ndarray, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    r"""Infinitesimal rigid-body motions of a set of nodes about a point.

    Column ``k < 3`` is a unit translation along axis ``k``; column ``3 + k``
    is a unit small rotation :math:`\boldsymbol\theta = \mathbf e_k` about
    ``origin``, which moves node :math:`\mathbf x` by
    :math:`\boldsymbol\theta \times (\mathbf x - \mathbf o)` and rotates it by
    :math:`\boldsymbol\theta`.

    Parameters
    ----------
    nodes : numpy.ndarray
        ``(n, 3)`` coordinates.
    origin : array_like
        Reference point :math:`\mathbf o`.

    Returns
    -------
    numpy.ndarray
        ``(6 n, 6)`` matrix, rows in the node-major order of :func:`assemble`.
    """
    r = np.asarray(nodes, dtype=float) - np.asarray(origin, dtype=float)
    n = r.shape[0]
    R = np.zeros((n, DOF, 6))
    eye = np.eye(3)
    R[:, :3, :3] = eye
    R[:, 3:, 3:] = eye
    for k in range(3):
        R[:, :3, 3 + k] = np.cross(eye[k], r)
    return R.reshape(n * DOF, 6)


def node_dofs(nodes: np.ndarray, components=range(DOF)) -> np.ndarray:
    """Global degree-of-freedom indices of the given components of some nodes, node-major."""
    nodes = np.asarray(nodes, dtype=np.int64)
    comps = np.asarray(list(components), dtype=np.int64)
    return (DOF * nodes[:, None] + comps[None, :]).ravel()
