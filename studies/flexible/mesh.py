"""Structured triangular meshes of flat rectangular shell parts.

A part is a rectangle in space, spanned from a corner by two edge vectors and
divided into a grid of quadrilaterals, each cut into two three-node
triangles. The diagonal alternates from one quadrilateral to the next (a
chequerboard of diagonals), so that the mesh has no preferred direction: a
mesh with all diagonals parallel makes the triangles respond differently to
bending about the two diagonals. Parts are joined by merging the nodes that
coincide, which makes the shells share their translations and rotations
along common edges (the box edges of the hub, the root line of a panel).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np


@dataclass(frozen=True)
class ShellMesh:
    """Nodes and three-node triangles of a flat-faceted shell.

    Attributes
    ----------
    nodes : numpy.ndarray
        Node coordinates, shape ``(n_nodes, 3)``.
    triangles : numpy.ndarray
        Node indices of each triangle, shape ``(n_elements, 3)``, counter-
        clockwise about the normal of the part it was made from.
    groups : Mapping[str, numpy.ndarray]
        Element indices of each named part (``"hub"``, ``"panel+y"``...).
    """

    nodes: np.ndarray
    triangles: np.ndarray
    groups: Mapping[str, np.ndarray]

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return self.nodes.shape[0]

    def group_nodes(self, name: str) -> np.ndarray:
        """Sorted indices of the nodes used by the elements of a group."""
        return np.unique(self.triangles[self.groups[name]])


def rectangle(corner, edge1, edge2, n1: int, n2: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate the rectangle ``corner + s edge1 + t edge2``, ``s, t in [0, 1]``.

    Parameters
    ----------
    corner, edge1, edge2 : array_like
        3-vectors: one corner and the two (orthogonal) edge vectors from it.
    n1, n2 : int
        Number of grid intervals along ``edge1`` and ``edge2``.

    Returns
    -------
    nodes : numpy.ndarray
        ``(n1 + 1) (n2 + 1)`` node coordinates, index ``i (n2 + 1) + j`` at
        ``s = i / n1``, ``t = j / n2``.
    triangles : numpy.ndarray
        ``2 n1 n2`` triangles, counter-clockwise about ``edge1 x edge2``.
    """
    if n1 < 1 or n2 < 1:
        raise ValueError(f"a rectangle needs at least one interval each way, got {n1} x {n2}")
    corner, edge1, edge2 = (np.asarray(v, dtype=float) for v in (corner, edge1, edge2))
    s = np.linspace(0.0, 1.0, n1 + 1)
    t = np.linspace(0.0, 1.0, n2 + 1)
    nodes = (corner + s[:, None, None] * edge1 + t[None, :, None] * edge2).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n1), np.arange(n2), indexing="ij")
    i, j = i.ravel(), j.ravel()
    a = i * (n2 + 1) + j
    b = a + (n2 + 1)
    c = b + 1
    d = a + 1
    even = (i + j) % 2 == 0
    first = np.where(even[:, None], np.column_stack([a, b, c]), np.column_stack([a, b, d]))
    second = np.where(even[:, None], np.column_stack([a, c, d]), np.column_stack([b, c, d]))
    return nodes, np.vstack([first, second])


def merge(parts: Mapping[str, list[tuple[np.ndarray, np.ndarray]]], tol: float = 1e-6) -> ShellMesh:
    """Join rectangles into one mesh, merging nodes closer than ``tol``.

    Parameters
    ----------
    parts : Mapping[str, list of (nodes, triangles)]
        For each group name, the rectangles (as returned by :func:`rectangle`)
        that make it up.
    tol : float
        Coordinates are snapped to a grid of this spacing before comparison;
        it must be far below the element size and far above round-off.

    Returns
    -------
    ShellMesh
    """
    all_nodes, all_tris, groups = [], [], {}
    n_nodes = n_elements = 0
    for name, rects in parts.items():
        first = n_elements
        for nodes, tris in rects:
            all_nodes.append(nodes)
            all_tris.append(tris + n_nodes)
            n_nodes += nodes.shape[0]
            n_elements += tris.shape[0]
        groups[name] = np.arange(first, n_elements)
    nodes = np.vstack(all_nodes)
    key = np.round(nodes / tol).astype(np.int64)
    _, first_index, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return ShellMesh(nodes[first_index], inverse.ravel()[np.vstack(all_tris)], groups)


def plate(a: float, b: float, n1: int, n2: int) -> ShellMesh:
    """Flat rectangular plate ``[0, a] x [0, b]`` in the plane ``z = 0``, one group ``"plate"``."""
    return merge({"plate": [rectangle((0.0, 0.0, 0.0), (a, 0.0, 0.0), (0.0, b, 0.0), n1, n2)]})


def box(lx: float, ly: float, lz: float, nx: int, ny: int, nz: int,
        center=(0.0, 0.0, 0.0)) -> list[tuple[np.ndarray, np.ndarray]]:
    """The six faces of a closed box, as rectangles for :func:`merge`.

    Parameters
    ----------
    lx, ly, lz : float
        Edge lengths along x, y and z.
    nx, ny, nz : int
        Grid intervals along each axis, shared by every face that spans that
        axis so that the nodes of adjacent faces coincide on the box edges.
    center : array_like
        Centre of the box.
    """
    c = np.asarray(center, dtype=float)
    ex, ey, ez = np.diag([lx, ly, lz])
    lo = c - 0.5 * np.array([lx, ly, lz])
    faces = []
    for axis, (e1, n1), (e2, n2) in ((0, (ey, ny), (ez, nz)), (1, (ez, nz), (ex, nx)), (2, (ex, nx), (ey, ny))):
        offset = np.diag([lx, ly, lz])[axis]
        faces.append(rectangle(lo, e2, e1, n2, n1))
        faces.append(rectangle(lo + offset, e1, e2, n1, n2))
    return faces
