import io
import sys

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from shapes import bumpy

from geofeat import Mesh
from geofeat.errors import MeshError
from geofeat.geometry import geodesic
from geofeat.geometry.geodesic import clear_geodesic_cache, distances_from, edge_graph, geodesic_matrix


def grid(n: int, spacing: float = 1.0) -> Mesh:
    """Flat n x n grid in the z = 0 plane; every square is split along its (+1, +1) diagonal."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    verts = np.stack([i.ravel() * spacing, j.ravel() * spacing, np.zeros(n * n)], axis=1)
    corner = (i * n + j)[:-1, :-1].ravel()
    faces = np.concatenate(
        [np.stack([corner, corner + n, corner + n + 1], axis=1), np.stack([corner, corner + n + 1, corner + 1], axis=1)]
    )
    return Mesh(verts, faces, name=f"grid{n}")


def grid_edge_path_lengths(n: int, spacing: float) -> np.ndarray:
    """Shortest edge-path lengths on `grid`: diagonal steps help only along the (+1, +1) direction."""
    i, j = np.divmod(np.arange(n * n), n)
    di, dj = i[None, :] - i[:, None], j[None, :] - j[:, None]
    same_sign = di * dj >= 0
    a, b = np.abs(di), np.abs(dj)
    along = np.minimum(a, b) * np.sqrt(2.0) + np.abs(a - b)
    return spacing * np.where(same_sign, along, a + b)


def test_dijkstra_on_a_flat_grid_equals_the_known_edge_path_lengths():
    n, spacing = 30, 0.5  # 900 vertices: several patches and a separator
    dist = geodesic_matrix(grid(n, spacing), "dijkstra", normalize=False, cache=False)
    np.testing.assert_allclose(dist, grid_edge_path_lengths(n, spacing), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("patch_size", [4, 16, 64, 10_000])
def test_patch_decomposition_never_changes_the_result(patch_size):
    mesh = bumpy(0, 3)
    graph = edge_graph(mesh)
    dist = geodesic._all_pairs_dijkstra(graph, mesh.verts, patch_size=patch_size)
    np.testing.assert_allclose(dist, dijkstra(graph, directed=False), rtol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_all_pairs_dijkstra_on_random_graphs_with_zero_edges_and_components(seed):
    rng = np.random.default_rng(seed)
    n = 300
    rows, cols = rng.integers(0, n, 700), rng.integers(0, n, 700)
    keep = rows != cols
    upper = sp.triu(sp.coo_matrix((rng.uniform(0.01, 2.0, keep.sum()), (rows[keep], cols[keep])), shape=(n, n)), 1)
    graph = sp.csr_matrix(upper + upper.T)
    graph.data[graph.data < 0.2] = 0.0  # explicit zero-weight edges, still symmetric
    assert (graph.data == 0).any()
    points = None if seed == 2 else rng.standard_normal((n, 3))
    dist = geodesic._all_pairs_dijkstra(graph, points, patch_size=12)
    expected = dijkstra(graph, directed=False)
    assert np.array_equal(np.isinf(dist), np.isinf(expected))
    finite = np.isfinite(expected)
    np.testing.assert_allclose(dist[finite], expected[finite], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("block", [1, 7, 256, 10_000])
def test_symmetrize_does_not_depend_on_its_block_size(monkeypatch, block):
    rng = np.random.default_rng(block)
    matrix = rng.uniform(0.0, 1.0, (300, 300)).astype(np.float32)
    monkeypatch.setattr(geodesic, "_SYM_BLOCK", block)
    smallest, mean = matrix.copy(), matrix.copy()
    geodesic._symmetrize(smallest, np.minimum)
    geodesic._symmetrize(mean, geodesic._mean)
    assert np.array_equal(smallest, np.minimum(matrix, matrix.T))
    assert np.array_equal(mean, 0.5 * (matrix + matrix.T))


def test_heat_on_a_flat_square_is_close_to_euclidean():
    mesh = grid(41, 1 / 40)  # the unit square
    dist = geodesic_matrix(mesh, "heat", normalize=False, cache=False)
    euclidean = np.linalg.norm(mesh.verts[:, None] - mesh.verts[None], axis=2)
    far = euclidean > 0.2
    relative = np.abs(dist - euclidean)[far] / euclidean[far]
    assert relative.mean() < 0.03
    assert np.abs(dist - euclidean).max() < 0.06
    edge_paths = geodesic_matrix(mesh, "dijkstra", normalize=False, cache=False)
    assert relative.mean() < 0.5 * (np.abs(edge_paths - euclidean)[far] / euclidean[far]).mean()


@pytest.mark.parametrize("method", ["dijkstra", "heat"])
def test_matrix_is_symmetric_float32_with_zero_diagonal_and_read_only(method):
    dist = geodesic_matrix(bumpy(1, 3), method, cache=False)
    assert dist.dtype == np.float32 and dist.flags.c_contiguous
    assert np.array_equal(dist, dist.T)
    assert np.all(dist.diagonal() == 0) and np.all(dist >= 0) and np.isfinite(dist).all()
    with pytest.raises(ValueError):
        dist[0, 1] = 1.0


@pytest.mark.parametrize("method", ["dijkstra", "heat"])
def test_normalisation_by_sqrt_area(method):
    mesh = bumpy(2, 2)
    raw = geodesic_matrix(mesh, method, normalize=False, cache=False)
    normalised = geodesic_matrix(mesh, method, normalize=True, cache=False)
    np.testing.assert_allclose(normalised * np.sqrt(mesh.area()), raw, rtol=1e-5, atol=1e-6)
    bigger = Mesh(mesh.verts * 3.0, mesh.faces)
    np.testing.assert_allclose(geodesic_matrix(bigger, method, cache=False), normalised, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("method", ["dijkstra", "heat"])
def test_components_and_unreferenced_vertices_are_infinitely_far(method):
    a, b = grid(6), grid(5)
    verts = np.concatenate([a.verts, b.verts + [10.0, 0, 0], [[50.0, 50.0, 50.0]]])
    faces = np.concatenate([a.faces, b.faces + a.n_vertices])
    mesh = Mesh(verts, faces, name="two-grids-and-a-lone-vertex")
    dist = geodesic_matrix(mesh, method, normalize=False, cache=False)
    first, second, lone = slice(0, 36), slice(36, 61), 61
    assert np.isinf(dist[first, second]).all() and np.isinf(dist[second, first]).all()
    assert np.isinf(dist[lone, :lone]).all() and dist[lone, lone] == 0
    assert np.isfinite(dist[first, first]).all() and np.isfinite(dist[second, second]).all()
    alone = geodesic_matrix(b, method, normalize=False, cache=False)
    np.testing.assert_allclose(dist[second, second], alone, rtol=1e-5, atol=1e-6)


def test_rows_agree_with_distances_from_and_heat_with_its_solver():
    mesh = bumpy(3, 3)
    sources = [0, 17, 300, mesh.n_vertices - 1]
    dist = geodesic_matrix(mesh, "dijkstra", normalize=False, cache=False)
    np.testing.assert_allclose(dist[sources], distances_from(mesh, sources), rtol=1e-6)
    heat = geodesic_matrix(mesh, "heat", normalize=False, cache=False)
    rows = distances_from(mesh, sources, method="heat")
    scale = rows.max()
    assert np.abs(heat[sources] - rows).max() < 0.02 * scale  # the same solver, symmetrised


def test_in_memory_cache_by_content_method_and_normalisation():
    clear_geodesic_cache()
    mesh = bumpy(4, 2)
    first = geodesic_matrix(mesh)
    assert geodesic_matrix(Mesh(mesh.verts.copy(), mesh.faces.copy(), name="copy")) is first
    assert geodesic_matrix(mesh, normalize=False) is not first
    assert geodesic_matrix(mesh, "heat") is not first
    assert geodesic_matrix(mesh, cache=False) is not first
    clear_geodesic_cache()
    again = geodesic_matrix(mesh)
    assert again is not first and np.array_equal(again, first)


def test_cache_stays_small(monkeypatch):
    clear_geodesic_cache()
    monkeypatch.setattr(geodesic, "_CACHE_SIZE", 2)
    meshes = [bumpy(seed, 1) for seed in range(3)]
    oldest = geodesic_matrix(meshes[0])
    for mesh in meshes[1:]:
        geodesic_matrix(mesh)
    assert len(geodesic._matrix_cache) == 2
    assert geodesic_matrix(meshes[0]) is not oldest
    monkeypatch.setattr(geodesic, "_CACHE_BYTES", 1)  # only the newest entry stays
    geodesic_matrix(meshes[1])
    assert len(geodesic._matrix_cache) == 1
    clear_geodesic_cache()


def test_bad_input_errors():
    mesh = bumpy(0, 1)
    with pytest.raises(MeshError, match="unknown geodesic method 'fmm'"):
        geodesic_matrix(mesh, "fmm")
    with pytest.raises(ValueError, match="expected one of"):
        geodesic_matrix(mesh, method="Dijkstra")
    with pytest.raises(MeshError, match="point cloud: it has no edges to run Dijkstra on"):
        geodesic_matrix(Mesh(mesh.verts), "dijkstra")


def test_progress_bar_can_be_shown(monkeypatch):
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setattr(sys, "stderr", Terminal())  # bars are drawn on a terminal only
    geodesic_matrix(grid(8), "dijkstra", cache=False, progress=True)
    geodesic_matrix(grid(8), "heat", cache=False, progress=True)
    assert "geodesics (dijkstra)" in sys.stderr.getvalue() and "geodesics (heat)" in sys.stderr.getvalue()


def test_faust_matrices(faust_mesh):
    dist = geodesic_matrix(faust_mesh, "dijkstra", cache=False)
    n = faust_mesh.n_vertices
    assert dist.shape == (n, n) and dist.dtype == np.float32 and np.isfinite(dist).all()
    assert np.array_equal(dist, dist.T) and np.all(dist.diagonal() == 0)
    sources = np.arange(0, n, 997)
    expected = distances_from(faust_mesh, sources) / np.sqrt(faust_mesh.area())
    np.testing.assert_allclose(dist[sources], expected, rtol=1e-6)
    assert 1.0 < dist.max() < 3.0  # a human body: diameter about 2 sqrt(area)

    heat = geodesic_matrix(faust_mesh, "heat", cache=False)
    assert heat.shape == (n, n) and np.isfinite(heat).all() and np.array_equal(heat, heat.T)
    far = dist > 0.1
    # edge paths overestimate surface geodesics by a few percent; the heat method sits below them
    ratio = heat[far] / dist[far]
    assert 0.9 < np.median(ratio) < 1.0 and np.abs(ratio - 1).mean() < 0.1


def test_streamed_row_blocks_symmetrised_are_the_matrix_exactly():
    mesh = bumpy(0, 3)  # 642 vertices: a separator and patches
    n = mesh.n_vertices
    graph = edge_graph(mesh) * geodesic.area_normalisation(mesh)
    rows = np.full((n, n), np.nan, dtype=np.float32)
    for indices, block in geodesic.dijkstra_row_blocks(graph, mesh.verts):
        assert np.all(np.diff(indices) > 0) and block.shape == (indices.size, n) and block.dtype == np.float32
        rows[indices] = block
    assert not np.isnan(rows).any()  # every row given once
    assert np.array_equal(np.minimum(rows, rows.T), geodesic_matrix(mesh, "dijkstra", normalize=True, cache=False))
    wanted = np.array([3, 300, 641])
    given = {}
    for indices, block in geodesic.dijkstra_row_blocks(graph, mesh.verts, wanted=wanted, cache_bytes=0):
        given.update(zip(indices.tolist(), block, strict=True))
    assert set(wanted.tolist()) <= set(given) and len(given) < n  # the wanted rows, not every row
    for i, row in given.items():
        assert np.array_equal(row, rows[i])  # with no row cache too
