"""Mesh topology in one place: edges, connected components and triangle areas.

Plain functions of ``verts (V, 3) float64`` and ``faces (F, 3) int64`` arrays, used by
`geofeat.mesh.Mesh`, the geometry layer (geodesics, partial shapes) and the heads'
surface operators, so that every layer derives the same edges and components the same way.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

__all__ = ["corner_edges", "edge_counts", "face_components", "triangle_areas", "unique_edges", "vertex_components"]


def triangle_areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Areas of the triangles.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3), float64
    faces : numpy.ndarray, shape (F, 3), int

    Returns
    -------
    numpy.ndarray, shape (F,), float64
        Half the norm of the cross product of two edge vectors (0 for a degenerate face).
    """
    first = verts[faces[:, 0]]
    return 0.5 * np.linalg.norm(np.cross(verts[faces[:, 1]] - first, verts[faces[:, 2]] - first), axis=1)


def corner_edges(faces: np.ndarray) -> np.ndarray:
    """The three edges of every face, smaller vertex index first (repeats and self edges kept).

    Returns
    -------
    numpy.ndarray, shape (3F, 2), int
        Rows ``3f``, ``3f + 1``, ``3f + 2`` are the edges (0, 1), (1, 2), (2, 0) of face ``f``.
    """
    faces = np.asarray(faces)
    rolled = faces[:, [1, 2, 0]]  # corner k's edge goes to corner k + 1
    return np.stack([np.minimum(faces, rolled), np.maximum(faces, rolled)], axis=-1).reshape(-1, 2)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """The undirected edges of the triangles, each once, without self edges.

    Returns
    -------
    numpy.ndarray, shape (E, 2), int64
        Smaller vertex index first, rows in lexicographic order.
    """
    pairs = corner_edges(faces)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    base = int(pairs.max()) + 1
    keys = np.unique(_edge_keys(pairs, base))
    return np.stack([keys // base, keys % base], axis=1)


def _edge_keys(pairs: np.ndarray, base: int) -> np.ndarray:
    """One int64 per edge row ``(a, b)``, ``a * base + b``: sorting the keys sorts the rows lexicographically.

    ``base`` is above every vertex index; a 1-D `numpy.unique` of the keys is several times
    faster than ``numpy.unique(pairs, axis=0)`` and gives the same order.
    """
    return pairs[:, 0].astype(np.int64) * base + pairs[:, 1].astype(np.int64)


def edge_counts(faces: np.ndarray) -> np.ndarray:
    """How many face corners use each distinct edge (a count above 2 is a non-manifold edge).

    Returns
    -------
    numpy.ndarray, shape (E',), int64
        One count per distinct row of `corner_edges` (self edges of degenerate faces included).
    """
    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = corner_edges(faces)
    keys = np.sort(_edge_keys(pairs, int(pairs.max()) + 1), kind="stable")  # stable: fast on the runs faces make
    starts = np.flatnonzero(keys[1:] != keys[:-1]) + 1  # where a new edge begins
    return np.diff(starts, prepend=0, append=keys.size).astype(np.int64)


def vertex_components(n_vertices: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the vertices, joined by the triangle edges.

    Parameters
    ----------
    n_vertices : int
        V; vertices in no face are components of their own.
    faces : numpy.ndarray, shape (F, 3), int

    Returns
    -------
    n_components : int
    labels : numpy.ndarray, shape (V,), int32
        Component of each vertex, numbered in order of each component's lowest vertex index.
    """
    pairs = corner_edges(faces)
    graph = sp.csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n_vertices, n_vertices))
    n_components, labels = connected_components(graph, directed=False)
    return int(n_components), labels


def face_components(faces: np.ndarray) -> np.ndarray:
    """Component label of each face, faces joined through shared edges (not through a lone vertex).

    Parameters
    ----------
    faces : numpy.ndarray, shape (K, 3), int
        K >= 1.

    Returns
    -------
    numpy.ndarray, shape (K,), int32
    """
    pairs = corner_edges(faces)
    keys = _edge_keys(pairs, int(pairs.max()) + 1)
    order = np.argsort(keys, kind="stable")  # the corners of one edge become neighbours
    same_edge = keys[order[1:]] == keys[order[:-1]]
    face_of_corner = order // 3  # row 3f + k of corner_edges is a corner of face f
    # Joining each face to the next face on the same edge joins all faces of that edge.
    rows, cols = face_of_corner[:-1][same_edge], face_of_corner[1:][same_edge]
    graph = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(len(faces), len(faces)))
    _, labels = connected_components(graph, directed=False)
    return labels
