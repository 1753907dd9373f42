"""Geodesic distances on meshes: Dijkstra on the edge graph and the heat method.

Two entry points:

* `distances_from`: distances from a few source vertices, in the mesh's own units;
* `geodesic_matrix`: the all-pairs ``(V, V)`` matrix, by default divided by the square root
  of the surface area (the normalisation of the published geodesic-error protocols),
  cached in memory by mesh content.

Both take point clouds too: the heat method on points (`geofeat.geometry.geodesic_cloud`,
potpourri3d's ``PointCloudHeatSolver``) is the only method there, and the area of a cloud is
that of its point-cloud Laplacian (`geofeat.geometry.geodesic_cloud.cloud_area`). Without a
``method``, each shape gets its evaluation method (`evaluation_method`): edge Dijkstra on
meshes, the heat method on points.

Built on this module: `geofeat.geometry.geodesic_store.GeodesicStore` keeps those matrices
on disk by mesh content (evaluation and training read them back instead of computing them
again), and `geofeat.geometry.geodesic_memory` gives an evaluation the matrix when it fits
in memory, else only the entries it reads (`dijkstra_row_blocks` streams their rows).

All-pairs Dijkstra does not run one Dijkstra per vertex. The vertices are split into
patches (graph Voronoi cells of farthest-point seeds); one side of every edge between two
patches forms a separator ``S``. Full Dijkstra runs only from ``S``. A shortest path from
a vertex ``i`` inside a patch either stays inside it or leaves it through a separator vertex
``k`` bordering it, so ``d(i, j) = min(d_in(i, j), min_k d_in(i, k) + d(k, j))``, where
``d_in`` are distances inside the patch (cheap local Dijkstra) and ``d(k, j)`` are the rows
already computed from ``S`` (a min-plus product). The result equals plain Dijkstra from
every vertex up to float32 rounding, several times faster.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from geofeat.errors import GeodesicMemoryError, MeshError
from geofeat.geometry.geodesic_cloud import cloud_area, cloud_heat_rows
from geofeat.mesh import Mesh, require_faces
from geofeat.runtime.progress import progress_bar
from geofeat.storage.lru import LRUCache
from geofeat.storage.sizes import format_size
from geofeat.topology import unique_edges, vertex_components

log = logging.getLogger(__name__)

GEODESIC_METHODS = ("dijkstra", "heat")
#: Target number of vertices per patch of the all-pairs Dijkstra (measured best near 200).
PATCH_SIZE = 192
#: At most this many matrices stay in the in-memory cache ...
_CACHE_SIZE = 4
#: ... and at most this many bytes (a 5,000-vertex matrix is 100 MB); the newest always stays.
_CACHE_BYTES = 1 << 30
_ROW_CHUNK = 256
#: Block side of `_symmetrize`: two float32 blocks of 256 x 256 stay in the L2 cache (512: 1.6x slower).
_SYM_BLOCK = 256


def edge_graph(mesh: Mesh) -> sp.csr_matrix:
    """Symmetric sparse graph of the mesh edges weighted by their Euclidean length.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (V, V), float64
        One stored entry per direction of every edge; an edge of length zero (coincident
        vertices) is kept as an explicit zero, an edge of weight 0 for scipy.sparse.csgraph.
    """
    if mesh.faces is None:
        raise MeshError(f"{mesh.name!r} is a point cloud: it has no edges to run Dijkstra on; use method='heat'.")
    edges = unique_edges(mesh.faces)
    lengths = np.linalg.norm(mesh.verts[edges[:, 0]] - mesh.verts[edges[:, 1]], axis=1)
    n = mesh.n_vertices
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    # built in one go (no sparse addition), so zero-length edges between coincident
    # vertices stay explicit entries, which scipy.sparse.csgraph treats as edges
    return sp.csr_matrix((np.concatenate([lengths, lengths]), (rows, cols)), shape=(n, n))


def evaluation_method(mesh: Mesh) -> str:
    """The geodesic method a shape gets by default: ``"dijkstra"`` on a triangle mesh, ``"heat"`` on a point cloud."""
    return "heat" if mesh.faces is None else "dijkstra"


def _resolved_method(mesh: Mesh, method: str | None) -> str:
    """``method``, or the shape's `evaluation_method`; `MeshError` for an unknown one or Dijkstra on points."""
    method = evaluation_method(mesh) if method is None else method
    if method not in GEODESIC_METHODS:
        raise MeshError(f"unknown geodesic method {method!r}; expected one of {GEODESIC_METHODS}.")
    if method == "dijkstra" and mesh.faces is None:
        raise MeshError(
            f"{mesh.name!r} is a point cloud: it has no edges to run Dijkstra on. Use method='heat' (the heat method on "
            "points), or leave method out."
        )
    return method


def distances_from(mesh: Mesh, sources, method: str | None = None) -> np.ndarray:
    """Geodesic distances from some source vertices to every vertex, in the mesh's units.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh or point cloud.
    sources : int or array_like of int, shape (S,)
        Source vertex indices.
    method : {"dijkstra", "heat"}, optional
        ``"dijkstra"``: shortest paths along mesh edges (what published protocols use);
        ``"heat"``: the heat method of Crane et al. through potpourri3d (smoother, faster
        for few sources), on a mesh or on points (see `geofeat.geometry.geodesic_cloud`).
        Default: `evaluation_method` (Dijkstra on a mesh, heat on a point cloud).

    Returns
    -------
    numpy.ndarray, shape (S, V), float64
        ``inf`` for vertices in another component (Dijkstra) or another piece of a point cloud.

    Raises
    ------
    MeshError
        Indices out of range, an unknown method, Dijkstra on a point cloud, or a point cloud
        the heat method cannot use (`geofeat.geometry.geodesic_cloud.cloud_layout`).
    """
    sources = np.atleast_1d(np.asarray(sources, dtype=np.int64))
    if sources.size and (sources.min() < 0 or sources.max() >= mesh.n_vertices):
        raise MeshError(f"source indices must lie in [0, {mesh.n_vertices - 1}]; found [{sources.min()}, {sources.max()}].")
    method = _resolved_method(mesh, method)
    if not sources.size:
        return np.zeros((0, mesh.n_vertices))
    if method == "dijkstra":
        return dijkstra(edge_graph(mesh), directed=False, indices=sources)
    if mesh.faces is None:
        unique = np.unique(sources)
        rows = np.empty((unique.size, mesh.n_vertices))
        for block, values in cloud_heat_rows(mesh, unique):
            rows[np.searchsorted(unique, block)] = values
        return rows[np.searchsorted(unique, sources)]
    import potpourri3d as pp3d

    solver = pp3d.MeshHeatMethodDistanceSolver(mesh.verts, mesh.faces)
    return np.stack([solver.compute_distance(int(s)) for s in sources])


# ---------------------------------------------------------------------------------------
# All pairs
# ---------------------------------------------------------------------------------------

_matrix_cache: LRUCache[tuple, np.ndarray] = LRUCache(
    lambda: _CACHE_SIZE, max_weight=lambda: _CACHE_BYTES, weigh=lambda a: a.nbytes
)


def geodesic_matrix(
    mesh: Mesh, method: str | None = None, normalize: bool = True, cache: bool = True, progress: bool = False
) -> np.ndarray:
    """All-pairs geodesic distances of a triangle mesh or a point cloud.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh or point cloud.
    method : {"dijkstra", "heat"}, optional
        ``"dijkstra"``: exact shortest paths along the mesh edges, weighted by their
        Euclidean length (the distances the published matching protocols use; they
        overestimate true surface geodesics by a few percent). ``"heat"``: the heat method
        of Crane et al. (potpourri3d, intrinsic-Delaunay Laplacian, ``t`` = mean edge
        length squared), one solve pair per source vertex, then symmetrised; closer to
        true surface geodesics, slower for all pairs. On a point cloud only ``"heat"``
        exists (`geofeat.geometry.geodesic_cloud`: duplicates share their rows, separate
        pieces are ``inf`` apart). Default: `evaluation_method`, Dijkstra on a mesh and
        heat on a point cloud.
    normalize : bool
        Divide by the square root of the total surface area (`area_normalisation`; for a
        point cloud, the area of its point-cloud Laplacian).
    cache : bool
        Reuse a matrix computed before for the same mesh content, method and
        normalisation (in memory only, a small LRU; persistence on disk belongs to
        higher layers).
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    numpy.ndarray, shape (V, V), float32, read-only
        Symmetric with a zero diagonal; ``inf`` between vertices of different connected
        components (unreferenced vertices are components of their own). float32 halves the
        memory (100 MB for 5,000 vertices instead of 200 MB); the distances are computed in
        float64 and rounded once, a relative error below 1e-7. The heat method's matrix is
        not symmetric by nature; it is replaced by ``(D + D.T) / 2``. The array is shared
        through the cache: copy it before changing it.

    Raises
    ------
    MeshError
        For an unknown method, Dijkstra on a point cloud, a point cloud the heat method
        cannot use (`geofeat.geometry.geodesic_cloud.cloud_layout`), or ``normalize`` on a
        mesh of zero area.
    GeodesicMemoryError
        When the matrix does not fit in memory (`all_pairs_memory` estimates its size).

    Notes
    -----
    Cost for a 5,000-vertex FAUST_r shape on one CPU core (see
    ``benchmarks/speed/geodesic.py``): "dijkstra" well under a second (plain scipy Dijkstra
    from every vertex takes about 3 s), "heat" several seconds (about 1 ms per source).
    Memory: one float32 (V, V) matrix plus a few (patch, V) blocks. A point cloud: one
    heat solve per point, 10 to 30 s for 5,000 points (``benchmarks/cloud_geodesic.py``).
    """
    method = _resolved_method(mesh, method)
    key = (mesh.hash, method, bool(normalize))
    if cache and (dist := _matrix_cache.get(key)) is not None:
        return dist
    scale = area_normalisation(mesh) if normalize else 1.0
    try:
        if method == "dijkstra":
            dist = _all_pairs_dijkstra(edge_graph(mesh) * scale, mesh.verts, progress=progress)
        elif mesh.faces is None:
            dist = _all_pairs_cloud_heat(mesh, scale, progress=progress)
        else:
            dist = _all_pairs_heat(mesh, scale, progress=progress)
    except MemoryError as exc:
        n = mesh.n_vertices
        raise GeodesicMemoryError(
            f"{mesh.name!r} has {n} vertices: its all-pairs geodesic matrix needs about {format_size(all_pairs_memory(n))} "
            f"and does not fit in memory ({exc}). Evaluations compute only the distances they read "
            "(geofeat.geometry.geodesic_memory.evaluation_distances); for a matrix, simplify the mesh first."
        ) from exc
    dist.flags.writeable = False
    if cache:
        _matrix_cache.put(key, dist)
    return dist


def clear_geodesic_cache() -> None:
    """Forget every cached geodesic matrix."""
    _matrix_cache.clear()


def area_normalisation(mesh: Mesh) -> float:
    """``1 / sqrt(area)``: the factor by which ``normalize=True`` scales the distances.

    The area is ``mesh.area()`` for a triangle mesh and
    `geofeat.geometry.geodesic_cloud.cloud_area` (the lumped masses of the point-cloud
    Laplacian) for a point cloud.

    Raises
    ------
    MeshError
        For a shape of zero surface area, or a point cloud the heat method cannot use.
    """
    area = cloud_area(mesh) if mesh.faces is None else mesh.area()
    if not area > 0:
        raise MeshError(f"{mesh.name!r} has zero surface area: cannot normalise by sqrt(area). Pass normalize=False.")
    return 1.0 / float(np.sqrt(area))


# ---------------------------------------------------------------------------------------
# Exact all-pairs shortest paths on a graph
# ---------------------------------------------------------------------------------------


def _all_pairs_dijkstra(
    graph: sp.spmatrix, points: np.ndarray | None = None, patch_size: int = PATCH_SIZE, progress: bool = False
) -> np.ndarray:
    """Exact all-pairs shortest-path lengths of an undirected graph with non-negative weights.

    Parameters
    ----------
    graph : scipy.sparse matrix, shape (V, V)
        Symmetric edge weights (a missing entry means no edge).
    points : numpy.ndarray, shape (V, d), optional
        Vertex positions, used only to spread the patch seeds (farthest-point sampling);
        without them the seeds are spread along the graph.
    patch_size : int
        Target number of vertices per patch (affects speed, never the result).
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    numpy.ndarray, shape (V, V), float32
        Symmetric; ``inf`` between vertices that no path joins. Equal to
        ``scipy.sparse.csgraph.dijkstra(graph)`` up to float32 rounding.
    """
    graph = sp.csr_matrix(graph, dtype=np.float64)
    n = graph.shape[0]
    separator = _separator(graph, points, patch_size)
    sep_idx = np.flatnonzero(separator)
    dist = np.empty((n, n), dtype=np.float32)
    with progress_bar(total=n, desc="geodesics (dijkstra)", unit="vertex", show=progress) as bar:
        for chunk in np.array_split(sep_idx, max(1, -(-sep_idx.size // _ROW_CHUNK))):
            dist[chunk] = dijkstra(graph, directed=True, indices=chunk)  # symmetric: same as undirected, faster
            bar.update(chunk.size)
        for patch in _interior_components(graph, separator):
            dist[patch] = _patch_rows(graph, separator, patch, dist.__getitem__)
            bar.update(patch.size)
    _symmetrize(dist, np.minimum)
    log.debug("all-pairs dijkstra: %d vertices, %d separator vertices", n, sep_idx.size)
    return dist


def dijkstra_row_blocks(
    graph: sp.spmatrix,
    points: np.ndarray | None = None,
    wanted: np.ndarray | None = None,
    cache_bytes: int = 0,
    progress: bool = False,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Rows of the all-pairs shortest-path matrix, block by block, without forming the matrix.

    The rows are those the all-pairs Dijkstra of `geodesic_matrix` computes before it
    symmetrises them (separator rows by Dijkstra, patch rows by the same min-plus sums,
    with seeds spread over ``points`` and patches of `PATCH_SIZE`): entry ``(i, j)`` of its
    matrix is the smaller of row ``i`` at ``j`` and row ``j`` at ``i``.

    Parameters
    ----------
    graph : scipy.sparse matrix, shape (V, V)
        Symmetric non-negative edge weights (`edge_graph`, scaled as `geodesic_matrix` scales it).
    points : numpy.ndarray, shape (V, d), optional
        Vertex positions spreading the patch seeds (without them, the seeds are spread along the graph).
    wanted : numpy.ndarray of int, optional
        Rows that must be given (a patch holding one is given whole, the other separator
        rows are left out); None: every row.
    cache_bytes : int
        Bytes of separator rows kept for the patches that border them (the oldest leave first).
    progress : bool
        Show a tqdm progress bar.

    Yields
    ------
    indices : numpy.ndarray, shape (b,), int64
        Increasing row indices, each block within the span of a separator chunk or a patch.
    rows : numpy.ndarray, shape (b, V), float32
        Their rows.
    """
    graph = sp.csr_matrix(graph, dtype=np.float64)
    n = graph.shape[0]
    separator = _separator(graph, points, PATCH_SIZE)
    sep_idx = np.flatnonzero(separator)
    need = np.ones(n, dtype=bool) if wanted is None else np.isin(np.arange(n), wanted)
    cache: dict[int, np.ndarray] = {}
    room = max(0, cache_bytes) // max(4 * n, 1)

    def separator_rows(border: np.ndarray) -> np.ndarray:
        missing = np.array([k for k in border.tolist() if k not in cache], dtype=np.int64)
        if missing.size:
            fresh = dijkstra(graph, directed=True, indices=missing).astype(np.float32)
        else:
            fresh = np.empty((0, n), dtype=np.float32)
        out = np.empty((border.size, n), dtype=np.float32)
        for j, k in enumerate(border.tolist()):
            out[j] = cache[k] if k in cache else fresh[np.searchsorted(missing, k)]
        for k, row in zip(missing.tolist(), fresh, strict=True):
            if len(cache) >= room:
                if not cache or room == 0:
                    break
                cache.pop(next(iter(cache)))  # the oldest first
            cache[k] = row
        return out

    patches = [p for p in _interior_components(graph, separator) if need[p].any()]
    rows_from_separator = sep_idx[need[sep_idx]]
    total = rows_from_separator.size + sum(p.size for p in patches)
    with progress_bar(total=total, desc="geodesics (streamed)", unit="row", show=progress) as bar:
        for chunk in np.array_split(rows_from_separator, max(1, -(-rows_from_separator.size // _ROW_CHUNK))):
            if chunk.size:
                yield chunk, separator_rows(chunk)
                bar.update(chunk.size)
        for patch in patches:
            order = np.argsort(patch)
            yield patch[order], _patch_rows(graph, separator, patch, separator_rows)[order]
            bar.update(patch.size)


def _separator(graph: sp.csr_matrix, points: np.ndarray | None, patch_size: int) -> np.ndarray:
    """Boolean mask (V,) of vertices that split the graph into patches of about ``patch_size``."""
    n = graph.shape[0]
    n_seeds = int(n // max(int(patch_size), 1))
    if n_seeds < 2:
        return np.zeros(n, dtype=bool)
    seeds = _farthest_points(graph, points, n_seeds)
    _, _, cell = dijkstra(graph, directed=False, indices=seeds, min_only=True, return_predecessors=True)
    coo = graph.tocoo()
    crossing = cell[coo.row] < cell[coo.col]
    separator = np.zeros(n, dtype=bool)
    separator[coo.col[crossing]] = True
    return separator


def _farthest_points(graph: sp.csr_matrix, points: np.ndarray | None, k: int) -> np.ndarray:
    """``k`` vertex indices spread by farthest-point sampling, starting from vertex 0 (sorted, duplicates dropped).

    Not `geofeat.geometry.sampling.farthest_point_sampling`: without ``points`` the seeds are
    spread along the graph (Dijkstra), distances to unreachable vertices count as -1, and the
    seeds (hence the patches, the speed and the float32 rounding of the sums) stay those
    this function has always chosen.
    """
    seeds = np.zeros(k, dtype=np.int64)
    if points is None:
        nearest = dijkstra(graph, directed=False, indices=0)
    else:
        nearest = np.linalg.norm(points - points[0], axis=1)
    nearest = np.where(np.isfinite(nearest), nearest, -1.0)
    for i in range(1, k):
        seeds[i] = int(np.argmax(nearest))
        if points is None:
            step = dijkstra(graph, directed=False, indices=seeds[i])
        else:
            step = np.linalg.norm(points - points[seeds[i]], axis=1)
        nearest = np.minimum(nearest, step)
    return np.unique(seeds)


def _without_out_edges(graph: sp.csr_matrix, sinks: np.ndarray) -> sp.csr_matrix:
    """Directed copy of ``graph`` in which the ``sinks`` (boolean mask (V,)) have no outgoing edges."""
    keep = np.repeat(~sinks, np.diff(graph.indptr))
    indptr = np.concatenate([[0], np.cumsum(np.where(sinks, 0, np.diff(graph.indptr)))])
    return sp.csr_matrix((graph.data[keep], graph.indices[keep], indptr), shape=graph.shape)


def _interior_components(graph: sp.csr_matrix, separator: np.ndarray) -> list[np.ndarray]:
    """Vertex index arrays of the connected components of the graph without the separator."""
    interior = np.flatnonzero(~separator)
    if interior.size == 0:
        return []
    _, labels = connected_components(graph[interior][:, interior], directed=False)
    order = np.argsort(labels, kind="stable")
    bounds = np.flatnonzero(np.diff(labels[order], prepend=-1, append=-2))
    return [interior[order[a:b]] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _patch_rows(graph: sp.csr_matrix, separator: np.ndarray, patch: np.ndarray, separator_rows) -> np.ndarray:
    """Rows (len(patch), V) float32 of a patch, from distances inside it and the rows of the separator vertices around it.

    ``patch`` must be a whole connected component of the graph without the separator, so
    that a path leaving it meets the separator first, at a vertex of its ``border``.
    ``separator_rows(border)`` gives the rows (len(border), V) float32 of those vertices: the
    all-pairs matrix reads them from the matrix, the streamed evaluation computes them.
    """
    neighbours = np.unique(graph[patch].indices)
    border = neighbours[separator[neighbours]]
    around = np.concatenate([patch, border])
    sinks = np.arange(around.size) >= patch.size  # paths stop at the border
    inside = dijkstra(_without_out_edges(graph[around][:, around], sinks), directed=True, indices=np.arange(patch.size))
    rows = np.full((patch.size, graph.shape[0]), np.inf, dtype=np.float32)
    rows[:, around] = inside
    to_border = rows[:, border]
    border_rows = separator_rows(border)
    step = np.empty_like(rows)
    for j in range(border.size):
        np.add(to_border[:, j : j + 1], border_rows[j], out=step)
        np.minimum(rows, step, out=rows)
    return rows


def _symmetrize(dist: np.ndarray, combine) -> None:
    """In place: ``dist[i, j] = dist[j, i] = combine(dist[i, j], dist[j, i])``, block by block."""
    n = dist.shape[0]
    for a in range(0, n, _SYM_BLOCK):
        rows = slice(a, min(a + _SYM_BLOCK, n))
        for b in range(a, n, _SYM_BLOCK):
            cols = slice(b, min(b + _SYM_BLOCK, n))
            merged = combine(dist[rows, cols], dist[cols, rows].T)
            dist[rows, cols] = merged
            dist[cols, rows] = merged.T


# ---------------------------------------------------------------------------------------
# Heat method
# ---------------------------------------------------------------------------------------


def _all_pairs_heat(mesh: Mesh, scale: float, progress: bool = False) -> np.ndarray:
    """Symmetrised heat-method distances (V, V) float32, times ``scale``; inf across components."""
    import potpourri3d as pp3d

    n = mesh.n_vertices
    dist = np.full((n, n), np.inf, dtype=np.float32)
    with progress_bar(total=n, desc="geodesics (heat)", unit="vertex", show=progress) as bar:
        for idx, faces in _face_components(mesh):
            if faces is not None:
                solver = pp3d.MeshHeatMethodDistanceSolver(mesh.verts[idx], faces)
            whole = idx.size == n
            for local_source, vertex in enumerate(idx):
                if faces is None:
                    row = np.zeros(1)
                else:
                    row = np.maximum(solver.compute_distance(local_source), 0.0) * scale
                    row[local_source] = 0.0
                if whole:
                    dist[vertex] = row
                else:
                    dist[vertex, idx] = row
            bar.update(idx.size)
    _symmetrize(dist, _mean)
    return dist


def _mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 0.5 * (a + b)


def _all_pairs_cloud_heat(mesh: Mesh, scale: float, progress: bool = False) -> np.ndarray:
    """Symmetrised heat-method distances (V, V) float32 of a point cloud, times ``scale``; inf between its pieces."""
    n = mesh.n_vertices
    dist = np.empty((n, n), dtype=np.float32)
    for rows, values in cloud_heat_rows(mesh, None, scale, progress=progress):
        dist[rows] = values
    _symmetrize(dist, _mean)
    return dist


def _face_components(mesh: Mesh) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Connected components as (vertex indices (n,), faces re-indexed (f, 3) or None for a lone vertex)."""
    faces = require_faces(mesh, "geodesic distances")
    n_comp, labels = vertex_components(mesh.n_vertices, faces)
    referenced = np.zeros(mesh.n_vertices, dtype=bool)
    referenced[faces.ravel()] = True
    if n_comp == 1 and referenced.all():
        return [(np.arange(mesh.n_vertices), faces)]
    face_label = labels[faces[:, 0]]
    parts: list[tuple[np.ndarray, np.ndarray | None]] = []
    for label in range(n_comp):
        idx = np.flatnonzero(labels == label)
        if not referenced[idx[0]]:
            parts.append((idx, None))
            continue
        position = np.full(mesh.n_vertices, -1, dtype=np.int64)
        position[idx] = np.arange(idx.size)
        parts.append((idx, position[faces[face_label == label]]))
    return parts


# ---------------------------------------------------------------------------------------
# Memory estimates
# ---------------------------------------------------------------------------------------


def all_pairs_memory(n_vertices: int, dtype: str = "float32") -> int:
    """Estimated peak bytes of `geodesic_matrix` (Dijkstra) on ``n_vertices`` vertices.

    The float32 (V, V) matrix, 4 V^2 bytes, plus the working memory of the computation: a
    chunk of float64 Dijkstra rows and a few float32 blocks of patch rows (patches are
    irregular: twice `PATCH_SIZE` is allowed for). A float16 store (``dtype="float16"``)
    adds its rounded copy, 2 V^2 bytes.
    """
    n = int(n_vertices)
    working = n * (8 * _ROW_CHUNK + 4 * 4 * 2 * PATCH_SIZE) + (64 << 20)
    copy = 2 * n * n if np.dtype(dtype) == np.float16 else 0
    return 4 * n * n + copy + working


def streamed_memory(n_vertices: int) -> int:
    """Estimated working bytes of `dijkstra_row_blocks` without its row cache.

    What the streamed entries (`geofeat.geometry.geodesic_memory.GeodesicEntries.compute`)
    need besides their row cache and worst-case rows.
    """
    return int(n_vertices) * (8 * _ROW_CHUNK + 4 * 4 * 2 * PATCH_SIZE) + (64 << 20)
