"""Verification of the flat-shell model: plates against classical solutions, rigid-body modes, mass."""

import numpy as np
import pytest

from studies.flexible.mesh import box, merge, plate, rectangle
from studies.flexible.shell import ShellSection, assemble, rigid_body_modes
from studies.flexible.study import (
    CANTILEVER_CLASSICAL,
    FREE_PLATE_CLASSICAL,
    PLATE_SECTION,
    cantilever_plate,
    free_box_hz,
    free_plate,
    simply_supported_exact,
    simply_supported_plate,
)

SECTION = ShellSection(E=70e9, nu=0.33, rho=2700.0, h=1.5e-3)


@pytest.fixture(scope="module")
def cantilever():
    return {n: cantilever_plate(n) for n in (8, 16, 24)}


def test_cantilever_plate_within_one_percent_at_24x24(cantilever):
    # Within 1 % of Leissa's values; they are Ritz upper bounds lying
    # about 0.5 % above the converged plate, so a tighter bar would test the
    # reference rather than the element.
    rel = cantilever[24] / np.array(CANTILEVER_CLASSICAL) - 1.0
    assert np.all(np.abs(rel) < 0.01), rel


def test_cantilever_plate_converges_with_mesh(cantilever):
    # Successive refinements must change the parameters by less and less
    # (a converging sequence); the factor 2 leaves room for the non-
    # asymptotic 8x8 mesh while still failing a stalled or diverging element.
    change_coarse = np.abs(cantilever[16] / cantilever[8] - 1.0)
    change_fine = np.abs(cantilever[24] / cantilever[16] - 1.0)
    assert np.all(change_fine < change_coarse / 2.0), (change_coarse, change_fine)


def test_simply_supported_plate_converges_to_exact_at_second_order():
    exact = simply_supported_exact()
    err16 = simply_supported_plate(16) / exact - 1.0
    err32 = simply_supported_plate(32) / exact - 1.0
    # Linear triangles converge in frequency at second order: halving the
    # element size should divide the error by about 4; 3 allows for the
    # pre-asymptotic higher modes.
    assert np.all(err32 > 0.0) and np.all(err16 / err32 > 3.0), (err16, err32)
    # 32x32 is fine enough for the six lowest modes to sit within 1.5 % of
    # the exact thin-plate values (measured: 0.2 % to 1.1 %).
    assert np.all(err32 < 0.015), err32


def test_free_plate_has_six_rigid_body_modes_and_classical_elastic_ones():
    lam = free_plate(16)
    # Rigid-body eigenvalues are round-off: their frequency parameters must
    # be below 1e-4 of the first elastic one (measured ~1e-5 relative),
    # while a seventh zero (a spurious mechanism) would fail by orders.
    assert np.all(np.abs(lam[:6]) < 1e-4 * lam[6]), lam
    # 16x16 reproduces Leissa's first three free-plate parameters to 1 %
    # (measured 0.2 % to 0.7 %).
    assert np.allclose(lam[6:9], FREE_PLATE_CLASSICAL, rtol=0.01), lam[6:9]


def test_free_box_has_six_rigid_body_modes():
    f = free_box_hz(0.5)
    # A rigid-body frequency is one below 1e-3 Hz; the first
    # elastic mode of the 1.5 mm box is near 1 Hz.
    assert np.all(np.abs(f[:6]) < 1e-3), f
    assert f[6] > 0.5, f


def test_rigid_motions_store_no_strain_energy():
    nx, ny, nz = 4, 6, 6
    mesh = merge({"hub": box(2.0, 3.0, 3.0, nx, ny, nz)})
    K, _ = assemble(mesh, SECTION)
    R = rigid_body_modes(mesh.nodes, (0.3, -0.2, 0.1))
    # K R vanishes up to round-off of the element arithmetic, ~1e-16 of the
    # largest stiffness entry times the unit motions.
    assert np.abs(K @ R).max() < 1e-12 * np.abs(K).max()


def test_box_mesh_merges_shared_edges():
    nx, ny, nz = 4, 6, 6
    mesh = merge({"hub": box(2.0, 3.0, 3.0, nx, ny, nz)})
    # A closed box surface grid has 2 (nx ny + ny nz + nz nx) + 2 distinct nodes (Euler).
    assert mesh.n_nodes == 2 * (nx * ny + ny * nz + nz * nx) + 2
    assert mesh.triangles.shape[0] == 4 * (nx * ny + ny * nz + nz * nx)


def test_assembled_matrices_symmetric_and_mass_exact():
    mesh = merge({"hub": box(2.0, 3.0, 3.0, 4, 6, 6)})
    K, M = assemble(mesh, SECTION)
    assert abs(K - K.T).max() == 0.0 and abs(M - M.T).max() == 0.0
    R = rigid_body_modes(mesh.nodes)
    rigid_mass = R.T @ (M @ R)
    area = 2.0 * (2.0 * 3.0 + 2.0 * 3.0 + 3.0 * 3.0)
    mass = SECTION.areal_mass * area
    # Thin-wall inertia of the box about its centre, face by face: a face
    # normal to axis a at distance d_a, with sides along b and c, adds
    # m_f (d_a^2 + s_b^2/12) about axis c, and so on.
    half = np.array([1.0, 1.5, 1.5])
    side = 2.0 * half
    J = np.zeros(3)
    for a in range(3):
        b, c = [k for k in range(3) if k != a]
        m_face = SECTION.areal_mass * side[b] * side[c]
        second = np.zeros(3)
        second[a] = half[a] ** 2
        second[b] = side[b] ** 2 / 12.0
        second[c] = side[c] ** 2 / 12.0
        for axis in range(3):
            J[axis] += 2.0 * m_face * (second.sum() - second[axis])
    # Consistent linear-triangle mass integrates rigid motions exactly; the
    # only other term is the walls' rotary inertia rho h^3/12 (relative size
    # ~1e-7), hence 1e-6.
    assert np.allclose(np.diag(rigid_mass[:3, :3]), mass, rtol=1e-12)
    assert np.allclose(np.diag(rigid_mass[3:, 3:]), J, rtol=1e-6)
    assert np.abs(rigid_mass[3:, 3:] - np.diag(np.diag(rigid_mass[3:, 3:]))).max() < 1e-9 * J.max()


def test_drilling_rotation_is_stiff_but_rigid_drilling_is_free():
    mesh = plate(1.0, 1.0, 2, 2)
    K, _ = assemble(mesh, PLATE_SECTION)
    centre = int(np.argmin(np.linalg.norm(mesh.nodes - [0.5, 0.5, 0.0], axis=1)))
    # A drilling rotation of one node alone is resisted by the Hughes-Brezzi
    # term gamma (r_z - theta_z)^2 with gamma = G h, whose diagonal entry is
    # gamma times the integral of the squared linear shape function over the
    # node's patch, G h A_patch / 6; the quadrature is exact for it, so only
    # round-off separates the two (1e-9). A weak artificial spring would miss
    # by orders of magnitude.
    k_drill = K[6 * centre + 5, 6 * centre + 5]
    G = PLATE_SECTION.E / (2.0 * (1.0 + PLATE_SECTION.nu))
    patch = mesh.triangles[np.any(mesh.triangles == centre, axis=1)]
    e1 = mesh.nodes[patch[:, 1]] - mesh.nodes[patch[:, 0]]
    e2 = mesh.nodes[patch[:, 2]] - mesh.nodes[patch[:, 0]]
    patch_area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum()
    assert np.isclose(k_drill, G * PLATE_SECTION.h * patch_area / 6.0, rtol=1e-9)
    # The rigid rotation about the normal (drilling of every node with the
    # matching in-plane motion) costs nothing.
    theta_z = rigid_body_modes(mesh.nodes, (0.5, 0.5, 0.0))[:, 5]
    assert theta_z @ (K @ theta_z) < 1e-12 * k_drill


def test_rectangle_triangles_are_counter_clockwise():
    nodes, tris = rectangle((0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 1.0, 0.0), 3, 2)
    e1 = nodes[tris[:, 1]] - nodes[tris[:, 0]]
    e2 = nodes[tris[:, 2]] - nodes[tris[:, 0]]
    area = 0.5 * np.cross(e1, e2)[:, 2]
    assert np.all(area > 0.0)
    assert np.isclose(area.sum(), 2.0)
