"""`geofeat.topology`: the one place for edges, components and triangle areas."""

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from geofeat.mesh import Mesh
from geofeat.topology import corner_edges, edge_counts, face_components, triangle_areas, unique_edges, vertex_components

# two triangles sharing an edge, a fan touching them at vertex 3 only, a degenerate face,
# an unreferenced vertex (9) and a non-manifold edge (0, 1) used by three faces
VERTS = np.array(
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0], [2, 2, 0], [5, 5, 5], [6, 5, 5], [0, 0, 1], [9, 9, 9]],
    dtype=np.float64,
)
FACES = np.array([[0, 1, 2], [1, 3, 2], [3, 4, 5], [6, 7, 7], [0, 1, 8]], dtype=np.int64)


def test_areas_and_edges():
    np.testing.assert_allclose(triangle_areas(VERTS, FACES), [0.5, 0.5, 0.5, 0.0, 0.5])
    assert corner_edges(FACES[:1]).tolist() == [[0, 1], [1, 2], [0, 2]]
    edges = unique_edges(FACES)
    assert edges.dtype == np.int64 and (edges[:, 0] < edges[:, 1]).all()
    assert [tuple(e) for e in edges] == sorted({tuple(e) for e in edges})
    assert {tuple(e) for e in edges} == {(0, 1), (1, 2), (0, 2), (1, 3), (2, 3), (3, 4), (4, 5), (3, 5), (6, 7), (0, 8), (1, 8)}
    counts = edge_counts(FACES)
    assert counts.max() == 2 and edge_counts(np.vstack([FACES, [[0, 1, 9]]])).max() == 3
    assert edge_counts(np.zeros((0, 3), dtype=np.int64)).size == 0


def test_components_match_a_direct_derivation():
    n, labels = vertex_components(len(VERTS), FACES)
    rows, cols = FACES[:, [0, 1, 2]].ravel(), FACES[:, [1, 2, 0]].ravel()
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(len(VERTS),) * 2)
    expected_n, expected = connected_components(graph, directed=False)
    assert n == expected_n == 3 and np.array_equal(labels, expected)
    assert labels.tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 0, 2]  # numbered by lowest vertex
    # faces meet through edges only: the fan at vertex 3 is its own face component
    assert face_components(FACES).tolist() == [0, 0, 1, 2, 0]
    mesh = Mesh(VERTS, FACES, "toy")
    # Mesh drops face 3, which names vertex 7 twice: vertices 6 and 7 are then unreferenced,
    # like vertex 9, and unreferenced vertices are not counted
    assert len(mesh.faces) == len(FACES) - 1 and mesh.n_components() == 1
    assert Mesh(VERTS, np.vstack([FACES[:3], [[6, 7, 9]], FACES[4:]]), "toy").n_components() == 2
    assert any("non-manifold" in p for p in Mesh(VERTS, np.vstack([FACES, [[0, 1, 9]]]), "nm").report())


def _plain_face_components(faces: np.ndarray) -> np.ndarray:
    """Faces joined through shared edges, from the face-edge incidence matrix (every face pair of an edge)."""
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, edge_ids = np.unique(pairs, axis=0, return_inverse=True)
    incidence = sp.csr_matrix((np.ones(pairs.shape[0]), (np.repeat(np.arange(len(faces)), 3), edge_ids.ravel())))
    return connected_components(incidence @ incidence.T, directed=False)[1]


def test_fast_topology_matches_plain_derivations():
    rng = np.random.default_rng(0)
    n = 12
    grid = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = grid[:-1, :-1].ravel(), grid[1:, :-1].ravel(), grid[1:, 1:].ravel(), grid[:-1, 1:].ravel()
    plate = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    extra = np.array([[0, 1, 200], [0, 1, 201], [5, 5, 7]])  # edge (0, 1) gets three faces; a degenerate face
    faces = np.concatenate([plate, extra])
    for _ in range(20):
        subset = faces[rng.random(len(faces)) < 0.6]
        subset = subset[rng.permutation(len(subset))]
        assert np.array_equal(corner_edges(subset), np.sort(subset[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1))
        assert np.array_equal(face_components(subset), _plain_face_components(subset))
        _, counts = np.unique(np.sort(subset[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0, return_counts=True)
        assert np.array_equal(edge_counts(subset), counts)
    # faces on the non-manifold edge are one component even when the faces between them are gone
    assert len(set(face_components(extra[:2]).tolist())) == 1
    assert np.array_equal(edge_counts(extra), [2, 1, 1, 1, 1, 1, 2])  # (0, 1) ... (5, 5), (5, 7)
