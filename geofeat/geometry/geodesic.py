"""Geodesic distances on meshes: Dijkstra on the edge graph and the heat method.

Two entry points:

* `distances_from`: distances from a few source vertices, in the mesh's own units;
* `geodesic_matrix`: the all-pairs ``(V, V)`` matrix, by default divided by the square root
  of the surface area (the normalisation of the published geodesic-error protocols),
  cached in memory by mesh content;
* `GeodesicStore`: those matrices kept on disk by mesh content (evaluation and training read
  them back instead of computing them again).

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
import os
import re
import shutil
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from geofeat.config import cache_dir
from geofeat.entry_folder import EntryFolder, array_crc32
from geofeat.errors import GeodesicMemoryError, GeofeatError, MeshError, StoreError
from geofeat.files import atomic_write, probe_writable
from geofeat.lru import LRUCache
from geofeat.mesh import Mesh
from geofeat.progress import progress_bar
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
        raise MeshError(f"{mesh.name!r} is a point cloud: geodesics need faces.")
    edges = unique_edges(mesh.faces)
    lengths = np.linalg.norm(mesh.verts[edges[:, 0]] - mesh.verts[edges[:, 1]], axis=1)
    n = mesh.n_vertices
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    # built in one go (no sparse addition), so zero-length edges between coincident
    # vertices stay explicit entries, which scipy.sparse.csgraph treats as edges
    return sp.csr_matrix((np.concatenate([lengths, lengths]), (rows, cols)), shape=(n, n))


def distances_from(mesh: Mesh, sources, method: str = "dijkstra") -> np.ndarray:
    """Geodesic distances from some source vertices to every vertex, in the mesh's units.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh.
    sources : int or array_like of int, shape (S,)
        Source vertex indices.
    method : {"dijkstra", "heat"}
        ``"dijkstra"``: shortest paths along mesh edges (what published protocols use);
        ``"heat"``: the heat method of Crane et al. through potpourri3d (smoother, faster
        for few sources).

    Returns
    -------
    numpy.ndarray, shape (S, V), float64
        ``inf`` for vertices in another component (Dijkstra).
    """
    sources = np.atleast_1d(np.asarray(sources, dtype=np.int64))
    if sources.size and (sources.min() < 0 or sources.max() >= mesh.n_vertices):
        raise MeshError(f"source indices must lie in [0, {mesh.n_vertices - 1}]; found [{sources.min()}, {sources.max()}].")
    if method == "dijkstra":
        return dijkstra(edge_graph(mesh), directed=False, indices=sources)
    if method == "heat":
        import potpourri3d as pp3d

        if mesh.faces is None:
            raise MeshError(f"{mesh.name!r} is a point cloud: geodesics need faces.")
        solver = pp3d.MeshHeatMethodDistanceSolver(mesh.verts, mesh.faces)
        return np.stack([solver.compute_distance(int(s)) for s in sources]) if sources.size else np.zeros((0, mesh.n_vertices))
    raise MeshError(f"unknown geodesic method {method!r}; expected one of {GEODESIC_METHODS}.")


# ---------------------------------------------------------------------------------------
# All pairs
# ---------------------------------------------------------------------------------------

_matrix_cache: LRUCache[tuple, np.ndarray] = LRUCache(
    lambda: _CACHE_SIZE, max_weight=lambda: _CACHE_BYTES, weigh=lambda a: a.nbytes
)


def geodesic_matrix(
    mesh: Mesh, method: str = "dijkstra", normalize: bool = True, cache: bool = True, progress: bool = False
) -> np.ndarray:
    """All-pairs geodesic distances of a triangle mesh.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh (a point cloud raises `MeshError`).
    method : {"dijkstra", "heat"}
        ``"dijkstra"``: exact shortest paths along the mesh edges, weighted by their
        Euclidean length (the distances the published matching protocols use; they
        overestimate true surface geodesics by a few percent). ``"heat"``: the heat method
        of Crane et al. (potpourri3d, intrinsic-Delaunay Laplacian, ``t`` = mean edge
        length squared), one solve pair per source vertex, then symmetrised; closer to
        true surface geodesics, slower for all pairs.
    normalize : bool
        Divide by the square root of the total surface area, ``sqrt(mesh.area())``.
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
        For a point cloud, an unknown method, or ``normalize`` on a mesh of zero area.
    GeodesicMemoryError
        When the matrix does not fit in memory (`all_pairs_memory` estimates its size).

    Notes
    -----
    Cost for a 5,000-vertex FAUST_r shape on one CPU core (see
    ``benchmarks/speed_geodesic.py``): "dijkstra" well under a second (plain scipy Dijkstra
    from every vertex takes about 3 s), "heat" several seconds (about 1 ms per source).
    Memory: one float32 (V, V) matrix plus a few (patch, V) blocks.
    """
    if method not in GEODESIC_METHODS:
        raise MeshError(f"unknown geodesic method {method!r}; expected one of {GEODESIC_METHODS}.")
    if mesh.faces is None:
        raise MeshError(f"{mesh.name!r} is a point cloud: geodesic distances need faces (a triangle mesh).")
    key = (mesh.hash, method, bool(normalize))
    if cache and (dist := _matrix_cache.get(key)) is not None:
        return dist
    scale = _normalisation(mesh) if normalize else 1.0
    try:
        if method == "dijkstra":
            dist = _all_pairs_dijkstra(edge_graph(mesh) * scale, mesh.verts, progress=progress)
        else:
            dist = _all_pairs_heat(mesh, scale, progress=progress)
    except MemoryError as exc:
        n = mesh.n_vertices
        raise GeodesicMemoryError(
            f"{mesh.name!r} has {n} vertices: its all-pairs geodesic matrix needs about {format_size(all_pairs_memory(n))} "
            f"and does not fit in memory ({exc}). Evaluations compute only the distances they read "
            "(geofeat.geometry.geodesic.evaluation_distances); for a matrix, simplify the mesh first."
        ) from exc
    dist.flags.writeable = False
    if cache:
        _matrix_cache.put(key, dist)
    return dist


def clear_geodesic_cache() -> None:
    """Forget every cached geodesic matrix."""
    _matrix_cache.clear()


def _normalisation(mesh: Mesh) -> float:
    area = mesh.area()
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
    """``k`` vertex indices spread by farthest-point sampling, starting from vertex 0."""
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


def _face_components(mesh: Mesh) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """Connected components as (vertex indices (n,), faces re-indexed (f, 3) or None for a lone vertex)."""
    n_comp, labels = vertex_components(mesh.n_vertices, mesh.faces)
    referenced = np.zeros(mesh.n_vertices, dtype=bool)
    referenced[mesh.faces.ravel()] = True
    if n_comp == 1 and referenced.all():
        return [(np.arange(mesh.n_vertices), mesh.faces)]
    face_label = labels[mesh.faces[:, 0]]
    parts = []
    for label in range(n_comp):
        idx = np.flatnonzero(labels == label)
        if not referenced[idx[0]]:
            parts.append((idx, None))
            continue
        position = np.full(mesh.n_vertices, -1, dtype=np.int64)
        position[idx] = np.arange(idx.size)
        parts.append((idx, position[mesh.faces[face_label == label]]))
    return parts


# ---------------------------------------------------------------------------------------
# Memory: a bound on the all-pairs matrix, and the streamed entries used above it
# ---------------------------------------------------------------------------------------

#: Environment variable bounding the memory of one all-pairs matrix (``"4G"``, ``"512M"``, bytes).
MEMORY_ENV = "GEOFEAT_GEODESIC_MEMORY"
#: Default bound: this fraction of the memory available when the evaluation starts.
MEMORY_FRACTION = 0.5
_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_size(value: int | float | str, name: str, error: type[GeofeatError] = GeofeatError) -> int:
    """A number of bytes from ``4294967296``, ``"4G"``, ``"4GB"``, ``"4GiB"``, ``"512M"`` or ``"1.5g"`` (powers of 1024).

    Raises
    ------
    GeofeatError
        (``error``) For anything else, a negative size included; the message names ``name``.
    """
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        number, unit = float(value), ""
    else:
        found = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([kmgt]?)(?:i?b)?\s*", str(value), re.IGNORECASE)
        if found is None:
            raise error(f"{name} must be a size in bytes such as 4G, 512M or 1073741824; found {value!r}.")
        number, unit = float(found.group(1)), found.group(2).lower()
    if not np.isfinite(number) or number < 0:
        raise error(f"{name} must be a size of zero bytes or more; found {value!r}.")
    return int(number * _UNITS[unit])


def format_size(n_bytes: float) -> str:
    """``"6.4 GB"``: a size for messages, in powers of 1000."""
    for unit, factor in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n_bytes >= factor:
            return f"{n_bytes / factor:.1f} {unit}"
    return f"{int(n_bytes)} bytes"


def available_memory() -> int | None:
    """Bytes of memory available to this process now, or None where it cannot be told.

    ``psutil.virtual_memory().available`` where psutil is installed, else ``MemAvailable`` of
    ``/proc/meminfo``; lowered to the room left under a cgroup (container) memory limit.
    """
    available = None
    try:
        import psutil

        available = int(psutil.virtual_memory().available)
    except ImportError:
        try:
            with open("/proc/meminfo") as handle:
                for line in handle:
                    if line.startswith("MemAvailable:"):
                        available = int(line.split()[1]) * 1024
                        break
        except OSError:
            pass
    try:  # cgroup v2: a container's limit, invisible to /proc/meminfo
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            room = int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text())
            available = room if available is None else min(available, room)
    except (OSError, ValueError):
        pass
    return available


def memory_limit(limit: int | str | None = None) -> tuple[int | None, str]:
    """The bound on the memory of one all-pairs geodesic matrix, and where it comes from.

    Parameters
    ----------
    limit : int or str, optional
        Bytes (or ``"4G"``, see `parse_size`). Default: ``$GEOFEAT_GEODESIC_MEMORY``, else
        `MEMORY_FRACTION` of `available_memory`.

    Returns
    -------
    bytes : int or None
        None: no bound known (the available memory cannot be read).
    source : str
        For messages (``"half of the 12.0 GB available"``).
    """
    if limit is not None:
        return parse_size(limit, "memory_limit"), "memory_limit"
    env = os.environ.get(MEMORY_ENV)
    if env:
        return parse_size(env, MEMORY_ENV), MEMORY_ENV
    available = available_memory()
    if available is None:
        return None, "no bound: the available memory cannot be read"
    return int(MEMORY_FRACTION * available), f"{MEMORY_FRACTION:.0%} of the {format_size(available)} available"


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
    """Estimated bytes of the streamed entries (`GeodesicEntries.compute`) without its row cache and worst-case rows."""
    return int(n_vertices) * (8 * _ROW_CHUNK + 4 * 4 * 2 * PATCH_SIZE) + (64 << 20)


def evaluation_distances(
    mesh: Mesh, store: GeodesicStore | None = None, limit: int | str | None = None, *, limit_source: str | None = None
) -> np.ndarray | GeodesicEntries:
    """The geodesic distances an evaluation reads on a target: the matrix when it fits, else `GeodesicEntries`.

    Parameters
    ----------
    mesh : Mesh
        Target (full) shape with V vertices.
    store : GeodesicStore, optional
        A sound entry there is read back (mapped from the file, whatever its size); a
        matrix computed here is kept there (see `GeodesicStore.load`).
    limit : int or str, optional
        Memory bound (see `memory_limit`).
    limit_source : str, optional
        Where the bound comes from, for the warning (`evaluate_dataset` shares it among workers).

    Returns
    -------
    numpy.ndarray, shape (V, V), float32, or GeodesicEntries
        The matrix of `geodesic_matrix` (Dijkstra over ``sqrt(area)``) when `all_pairs_memory`
        is within the bound; above it, a `GeodesicEntries` that computes only the entries
        asked for, without forming the matrix or storing it (a warning says so).
    """
    if store is not None:
        stored = store.get(mesh)
        if stored is not None:
            return stored
    bound, source = memory_limit(limit)
    source = limit_source or source
    need = all_pairs_memory(mesh.n_vertices, store.dtype.name if store is not None else "float32")
    if bound is not None and need > bound:
        log.warning(
            "%r has %d vertices: its all-pairs geodesic matrix needs about %s in memory, above the bound of %s (%s; "
            "set %s to change it). Computing only the distances the evaluation reads, a few rows at a time, "
            "without forming the matrix or keeping it in the geodesic store.",
            mesh.name,
            mesh.n_vertices,
            format_size(need),
            format_size(bound),
            source,
            MEMORY_ENV,
        )
        return GeodesicEntries(mesh, limit=bound)
    if store is not None:
        return store.load(mesh)
    return geodesic_matrix(mesh, method="dijkstra", normalize=True)


class GeodesicEntries:
    """Some entries of a mesh's evaluation geodesic matrix, computed without forming the matrix.

    Stands for ``geodesic_matrix(mesh, "dijkstra", normalize=True)`` in the metrics of
    `geofeat.evaluation.metrics` (it is a `geofeat.evaluation.metrics.DistanceEntries`), in two rounds:

    1. asking: the metrics run once on it. ``entries[rows, cols]`` records the entries read
       and returns placeholders (``inf`` between connected components, as the matrix
       holds, else 0), ``worst_case(rows)`` records the rows;
    2. `compute` computes every recorded entry in one pass over the rows of the matrix,
       patch by patch, keeping only the entries asked for; then the metrics run again on
       it and read the values.

    The values are exactly those of the matrix: the rows are computed by the same code
    (separator rows by Dijkstra, patch rows by the same min-plus sums) and entry ``(i, j)``
    is the smaller of rows ``i`` and ``j`` at each other, as `geodesic_matrix` symmetrises.
    Reading an entry that was not asked for before `compute` raises `GeofeatError`.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh with V vertices.
    limit : int, optional
        Memory bound in bytes: the row cache and the worst-case rows are kept within it.

    Attributes
    ----------
    shape : tuple of int
        ``(V, V)``.
    """

    ndim = 2
    dtype = np.dtype(np.float32)

    def __init__(self, mesh: Mesh, limit: int | None = None):
        if mesh.faces is None:
            raise MeshError(f"{mesh.name!r} is a point cloud: geodesic distances need faces (a triangle mesh).")
        self.mesh = mesh
        self.shape = (mesh.n_vertices, mesh.n_vertices)
        self.limit = limit
        self._graph = edge_graph(mesh) * _normalisation(mesh)
        self._labels = connected_components(self._graph, directed=False)[1]
        self._asked: list[np.ndarray] = []
        self._asked_rows: list[np.ndarray] = []
        self._keys: np.ndarray | None = None
        self._values: np.ndarray | None = None
        self._worst_rows: np.ndarray | None = None
        self._worst: np.ndarray | None = None
        self.n_rows_computed = 0

    def __repr__(self) -> str:
        state = "computed" if self.computed else f"{sum(a.size for a in self._asked)} entries asked"
        return f"GeodesicEntries({self.mesh.name!r}, {self.shape[0]} vertices, {state})"

    @property
    def computed(self) -> bool:
        """Whether `compute` has run."""
        return self._keys is not None

    def __getitem__(self, key) -> np.ndarray:
        if not isinstance(key, tuple) or len(key) != 2:
            raise GeofeatError("GeodesicEntries reads entries as entries[rows, cols] (two integer arrays) only.")
        rows, cols = np.broadcast_arrays(np.asarray(key[0], dtype=np.int64), np.asarray(key[1], dtype=np.int64))
        flat = (rows * self.shape[0] + cols).ravel()
        if not self.computed:
            self._asked.append(flat.copy())
            apart = self._labels[rows] != self._labels[cols]
            return np.where(apart, np.inf, 0.0).astype(np.float32)
        at = np.minimum(np.searchsorted(self._keys, flat), self._keys.size - 1)
        if self._keys.size == 0 or not np.array_equal(self._keys[at], flat):
            raise GeofeatError("GeodesicEntries: an entry read now was not asked for before compute().")
        return self._values[at].reshape(rows.shape)

    def worst_case(self, rows) -> np.ndarray:
        """Largest finite distance from each of ``rows`` (0 where none), shape (len(rows),) float64."""
        rows = np.asarray(rows, dtype=np.int64).ravel()
        if not self.computed:
            self._asked_rows.append(rows.copy())
            return np.zeros(rows.size)
        at = np.minimum(np.searchsorted(self._worst_rows, rows), max(self._worst_rows.size - 1, 0))
        if self._worst_rows.size == 0 or not np.array_equal(self._worst_rows[at], rows):
            raise GeofeatError("GeodesicEntries: a worst case read now was not asked for before compute().")
        return self._worst[at]

    def compute(self, progress: bool = False) -> GeodesicEntries:
        """Compute every entry and worst case asked for so far, in one pass over the rows (more for many worst cases).

        Only the rows of asked vertices are computed, and the rows of the separator
        vertices around them; when worst cases are asked, every row (their columns are
        needed too). Memory: a few blocks of rows, a cache of separator rows, and two
        rows per worst case, within ``limit`` (several passes when the worst cases need more).

        Returns
        -------
        GeodesicEntries
            ``self``.
        """
        n = self.shape[0]
        keys = np.unique(np.concatenate(self._asked)) if self._asked else np.zeros(0, dtype=np.int64)
        worst_rows = np.unique(np.concatenate(self._asked_rows)) if self._asked_rows else np.zeros(0, dtype=np.int64)
        qi, qj = keys // n, keys % n
        forward = np.full(keys.size, np.inf, dtype=np.float32)  # row i at column j
        backward = np.full(keys.size, np.inf, dtype=np.float32)  # row j at column i
        worst = np.zeros(worst_rows.size)
        budget = max(0, (self.limit or 0) - streamed_memory(n))
        per_pass = max(1, (budget // 2) // max(8 * n, 1)) if self.limit else max(worst_rows.size, 1)
        starts = list(range(0, worst_rows.size, per_pass)) or [0]
        by_row_i, by_row_j = np.argsort(qi, kind="stable"), np.argsort(qj, kind="stable")
        for start in starts:
            first = start == 0
            group = worst_rows[start : start + per_pass]
            wanted = None if group.size else np.unique(np.concatenate([qi, qj]))
            w_row = np.full((group.size, n), np.inf, dtype=np.float32)
            w_col = np.full((group.size, n), np.inf, dtype=np.float32)
            w_at = np.full(n, -1, dtype=np.int64)
            w_at[group] = np.arange(group.size)
            for block, rows in self._row_blocks(wanted, budget // 2 if group.size else budget, progress):
                self.n_rows_computed += block.size
                if first:
                    for order, ends, other, out in ((by_row_i, qi, qj, forward), (by_row_j, qj, qi, backward)):
                        lo, hi = np.searchsorted(ends[order], [block.min(), block.max() + 1])
                        pick = order[lo:hi]
                        at = np.full(n, -1, dtype=np.int64)
                        at[block] = np.arange(block.size)
                        pick = pick[at[ends[pick]] >= 0]
                        out[pick] = rows[at[ends[pick]], other[pick]]
                if group.size:
                    mine = w_at[block] >= 0
                    w_row[w_at[block[mine]]] = rows[mine]
                    w_col[:, block] = rows[:, group].T
            if group.size:
                merged = np.minimum(w_row, w_col).astype(np.float64)
                worst[start : start + group.size] = np.where(np.isfinite(merged), merged, -np.inf).max(axis=1).clip(min=0.0)
        self._keys, self._values = keys, np.minimum(forward, backward)
        self._worst_rows, self._worst = worst_rows, worst
        return self

    def _row_blocks(self, wanted: np.ndarray | None, cache_bytes: int, progress: bool):
        """Blocks ``(indices (b,), rows (b, V) float32)`` of the rows `_all_pairs_dijkstra` computes before symmetrising.

        ``wanted``: the rows to give (None: all). Blocks hold increasing indices, each
        within the span of a separator chunk or a patch.
        """
        graph = sp.csr_matrix(self._graph, dtype=np.float64)
        n = graph.shape[0]
        separator = _separator(graph, self.mesh.verts, PATCH_SIZE)
        sep_idx = np.flatnonzero(separator)
        need = np.ones(n, dtype=bool) if wanted is None else np.isin(np.arange(n), wanted)
        cache: dict[int, np.ndarray] = {}
        room = max(0, cache_bytes) // max(4 * n, 1)

        def separator_rows(border: np.ndarray) -> np.ndarray:
            missing = np.array([k for k in border.tolist() if k not in cache], dtype=np.int64)
            fresh = dijkstra(graph, directed=True, indices=missing).astype(np.float32) if missing.size else None
            out = np.empty((border.size, n), dtype=np.float32)
            for j, k in enumerate(border.tolist()):
                out[j] = cache[k] if k in cache else fresh[np.searchsorted(missing, k)]
            if fresh is not None:
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


# ---------------------------------------------------------------------------------------
# On disk
# ---------------------------------------------------------------------------------------

#: Version of the layout of `GeodesicStore` entries (part of their file names).
STORE_VERSION = "2"
#: Default size limit of a `GeodesicStore` (all its entries together), bytes.
STORE_LIMIT = 4 << 30
#: Environment variable that changes it (``"10G"``, ``"500M"``, bytes).
STORE_LIMIT_ENV = "GEOFEAT_GEODESIC_STORE_LIMIT"
#: Folders of default stores already reported as not writable (warned once per process).
_UNWRITABLE_WARNED: set[str] = set()
#: Precisions a `GeodesicStore` keeps its matrices in.
STORE_DTYPES = ("float32", "float16")
#: File name of an entry (any precision and layout version): mesh hash, dtype, version, CRC-32.
_ENTRY_PATTERN = r"[0-9a-f]{64}-(float32|float16)-v[0-9]+-([0-9a-f]{8})\.npy"
_STORE_ENTRY = re.compile(_ENTRY_PATTERN)
#: Temporary file of an entry being written (`geofeat.files.atomic_write`): ``.<entry name>.<random>.tmp``.
_STORE_TEMPORARY = re.compile(rf"\.{_ENTRY_PATTERN}\.[^/]+\.tmp")


def _entry_problem(stored: np.ndarray, n: int, dtype: np.dtype, crc: str) -> str | None:
    """What is wrong with a store entry's array (expected: ``dtype``, shape (n, n), CRC-32 ``crc`` in hex), or None."""
    if stored.shape != (n, n) or stored.dtype != dtype:
        return f"holds a {stored.dtype} {stored.shape} array; expected {dtype.name} ({n}, {n})"
    if f"{array_crc32(stored):08x}" != crc:
        return f"fails its checksum (expected {crc})"
    return None


class GeodesicStore(EntryFolder):
    """All-pairs geodesic matrices on disk (edge Dijkstra over ``sqrt(area)``), one ``.npy`` file per mesh content.

    An entry is named ``<mesh hash>-<dtype>-v<version>-<crc>.npy``: a plain NumPy file whose
    name carries the CRC-32 of its array (dtype, shape and bytes). It is written through a
    temporary file and renamed (`geofeat.files.atomic_write`), so a reader sees a whole
    entry or none, with several processes too. Every read checks shape, dtype and checksum;
    a damaged entry (truncated, overwritten, bit rot) is logged, deleted and recomputed,
    never returned. Writes are not ``fsync``-ed: an entry that a power cut left empty or
    half written is such a damaged entry, found on its first read. A float32 entry read back
    is its file mapped in memory: the store only ever renames a new file over an entry or
    deletes it, which leaves a mapping intact; a file truncated or overwritten in place
    while a process holds its array would break that array (a bus error on Linux), so
    remove entries by deleting their files, never by editing them.

    `info`, `verify` and `clear` (``geofeat cache info|verify|clear``) see every entry of the
    folder, whatever its precision or layout version.

    Parameters
    ----------
    folder : str or os.PathLike, optional
        Default ``<geofeat cache>/geodesics`` (`geofeat.config.cache_dir`: ``$GEOFEAT_CACHE_DIR``
        or `geofeat.set_cache_dir` move it).
    dtype : {"float32", "float16"}
        ``"float32"``: exactly the matrix of `geodesic_matrix` (evaluation; 4 V^2 bytes, 100 MB
        for 5,000 vertices). ``"float16"``: about three significant digits in half the space
        (training loss weights).
    connected : bool
        Refuse meshes in several pieces (`MeshError`): their matrices hold ``inf``.
    limit : int or str, optional
        Most bytes the folder's entries may take together (``"4G"``, see `parse_size`).
        Default ``$GEOFEAT_GEODESIC_STORE_LIMIT``, else `STORE_LIMIT` (4 GiB). Before a new
        entry is written, the least recently used entries (by modification time, which
        every read refreshes) are deleted until it fits. An entry larger than the limit, or
        than half the free disk space, is not written: its matrix is computed and returned
        in memory, with a warning.

    Notes
    -----
    A store that cannot be written (read-only, disk full, ``$GEOFEAT_CACHE_DIR`` naming a
    file): the default store (no ``folder``) logs a warning once per folder and returns the
    matrices computed in memory; a store given a ``folder`` raises `StoreError`, before any
    computation where the problem can be seen then.
    """

    label = "the geodesic store"

    def __init__(
        self,
        folder: str | os.PathLike | None = None,
        dtype: str = "float32",
        connected: bool = False,
        limit: int | str | None = None,
    ):
        if dtype not in STORE_DTYPES:
            raise MeshError(f"GeodesicStore keeps matrices in one of {STORE_DTYPES}; found dtype={dtype!r}.")
        self.explicit = folder is not None
        self.folder = Path(folder).expanduser() if folder is not None else cache_dir() / "geodesics"
        self.dtype = np.dtype(dtype)
        self.connected = bool(connected)
        env = os.environ.get(STORE_LIMIT_ENV) if limit is None else None
        name = STORE_LIMIT_ENV if env else "limit"
        self.limit = parse_size(limit if limit is not None else env or STORE_LIMIT, name, StoreError)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.folder)!r}, dtype={self.dtype.name!r})"

    @property
    def root(self) -> Path:
        """The folder (`geofeat.entry_folder.EntryFolder`'s name for it)."""
        return self.folder

    def _scan(self) -> tuple[list[Path], list[Path], list[Path]]:
        entries, temporary, other = [], [], []
        if self.folder.is_dir():
            for path in self.folder.iterdir():
                regular = path.is_file() and not path.is_symlink()
                if regular and _STORE_ENTRY.fullmatch(path.name):
                    entries.append(path)
                elif regular and _STORE_TEMPORARY.fullmatch(path.name):
                    temporary.append(path)
                else:
                    other.append(path)
        return sorted(entries), sorted(temporary), sorted(other)

    def _is_sound(self, path: Path) -> bool:
        dtype, crc = _STORE_ENTRY.fullmatch(path.name).groups()
        try:
            stored = np.load(path, mmap_mode="r")
            n = stored.shape[0] if stored.ndim == 2 else -1
            return _entry_problem(stored, n, np.dtype(dtype), crc) is None
        except (OSError, ValueError, EOFError):
            return False

    def _prefix(self, mesh: Mesh) -> str:
        return f"{mesh.hash}-{self.dtype.name}-v{STORE_VERSION}-"

    def _entries(self, mesh: Mesh) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted(p for p in self.folder.glob(f"{self._prefix(mesh)}*.npy") if p.is_file())

    def path(self, mesh: Mesh) -> Path | None:
        """The file of the matrix of ``mesh``, or None when not stored."""
        entries = self._entries(mesh)
        return entries[0] if entries else None

    def get(self, mesh: Mesh) -> np.ndarray | None:
        """The stored matrix of ``mesh`` (checked, as `load` returns it), or None when not stored; never computes."""
        for path in self._entries(mesh):
            dist = self._read(path, mesh)
            if isinstance(dist, np.ndarray):
                return dist
        return None

    def ensure(self, mesh: Mesh) -> Path | None:
        """Compute and store the matrix unless a sound entry is present; returns its file.

        None when the matrix could not be stored (too large for the limit or the disk, or
        a default store that cannot be written: a warning says why).
        """
        for path in self._entries(mesh):
            if isinstance(self._read(path, mesh), np.ndarray):
                return path
        return self._compute(mesh)[0]

    def load(self, mesh: Mesh) -> np.ndarray:
        """The matrix of ``mesh``, read back (checked) or computed and stored.

        Returns
        -------
        numpy.ndarray, shape (V, V), float32, read-only
            A float32 store returns exactly `geodesic_matrix` (``method="dijkstra"``,
            ``normalize=True``); read back, it is the file mapped into memory (``mmap``,
            no copy: pages shared between processes, read from the page cache). A float16
            store returns its rounding, widened to float32.

        Raises
        ------
        StoreError
            A store given a folder cannot be written (read-only, disk full, a file in the way).
        """
        dist = self.get(mesh)
        return dist if dist is not None else self._compute(mesh)[1]

    def entry_bytes(self, n_vertices: int) -> int:
        """Size on disk of the entry of a mesh with ``n_vertices`` vertices (the ``.npy`` header included)."""
        return int(n_vertices) ** 2 * self.dtype.itemsize + 128

    def check_writable(self) -> None:
        """Raise `StoreError` unless a file can be created in the folder (created when missing)."""
        try:
            probe_writable(self.folder, prefix=".probe-", suffix=".tmp")
        except OSError as err:
            raise StoreError(self._unwritable(err)) from err

    def _unwritable(self, err: OSError) -> str:
        return (
            f"the geodesic store {self.folder} cannot be written: {err.strerror or err}. Set GEOFEAT_CACHE_DIR (or "
            "call geofeat.set_cache_dir) to a writable folder, give GeodesicStore another folder, or evaluate without "
            "the store (benchmarks/run.py --no-geodesic-store)."
        )

    def _not_kept(self, message: str) -> None:
        """A default store that cannot be written: warn once per folder (then compute in memory)."""
        if str(self.folder) not in _UNWRITABLE_WARNED:
            _UNWRITABLE_WARNED.add(str(self.folder))
            log.warning("geodesic matrices are computed in memory and not kept (this warning is shown once): %s", message)

    def _room(self, size: int) -> str | None:
        """Why an entry of ``size`` bytes cannot be written (too large for the limit or the disk), or None."""
        if size > self.limit:
            return f"larger than the store's limit of {format_size(self.limit)} ({STORE_LIMIT_ENV} changes it)"
        probe = self.folder
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        try:
            free = shutil.disk_usage(probe).free
        except OSError:
            return None
        if size > free // 2:
            return f"larger than half the {format_size(free)} free on the disk of {self.folder}"
        return None

    def _evict(self, incoming: int) -> None:
        """Delete the least recently used entries until ``incoming`` more bytes fit under the limit."""
        stats = []
        for path in self._scan()[0]:
            try:
                info = path.stat()
            except OSError:
                continue
            stats.append((info.st_mtime, info.st_size, path))
        total = sum(size for _, size, _ in stats)
        for _, size, path in sorted(stats):
            if total + incoming <= self.limit:
                break
            log.info(
                "geodesic store over its limit of %s: removing the least recently used entry %s",
                format_size(self.limit),
                path.name,
            )
            self._remove(path)
            if not path.exists():
                total -= size

    def _compute(self, mesh: Mesh) -> tuple[Path | None, np.ndarray]:
        size = self.entry_bytes(mesh.n_vertices)
        too_large = self._room(size)
        if too_large is None and self.explicit:
            self.check_writable()  # fail before the work, not after it
        # not in the in-memory cache as well: the file is the kept copy (read back mapped, no copy)
        dist = geodesic_matrix(mesh, method="dijkstra", normalize=True, cache=False)
        if self.connected and not np.isfinite(dist).all():
            raise MeshError(
                f"{mesh.name!r} is not connected: its geodesic distances are infinite; give a connected mesh "
                "(geofeat.geometry.partial.largest_component_submesh keeps its largest piece)."
            )
        stored = np.ascontiguousarray(dist, dtype=self.dtype)
        if self.dtype == np.float32:
            result = dist
        else:
            result = stored.astype(np.float32)
            result.flags.writeable = False
        if too_large is not None:
            log.warning(
                "the geodesic matrix of %r (%d vertices, %s) is not kept in the geodesic store: %s; it is computed in memory",
                mesh.name,
                mesh.n_vertices,
                format_size(size),
                too_large,
            )
            return None, result
        path = self.folder / f"{self._prefix(mesh)}{array_crc32(stored):08x}.npy"

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as handle:  # a handle: np.save would append ".npy" to the temporary name
                np.save(handle, stored)

        try:
            if self.folder.is_dir():
                self._evict(size)
            atomic_write(path, write, durable=False)  # every read checks the checksum: no need to wait for the disk
        except OSError as err:
            if self.explicit:
                raise StoreError(self._unwritable(err)) from err
            self._not_kept(self._unwritable(err))
            return None, result
        return path, result

    def _read(self, path: Path, mesh: Mesh) -> np.ndarray | None:
        """The checked float32 matrix in ``path``, or None after deleting a damaged entry."""
        n = mesh.n_vertices
        try:
            stored = np.load(path, mmap_mode="r")
            problem = _entry_problem(stored, n, self.dtype, path.stem.rsplit("-", 1)[1])
        except (OSError, ValueError, EOFError) as exc:
            problem = f"cannot be read ({exc})"
        if problem is None:
            try:
                os.utime(path)  # recently used: the last entry the limit evicts
            except OSError as err:  # a read-only store: the order of eviction does not matter there
                log.debug("cannot touch %s: %s", path, err)
            if self.dtype == np.float32:
                # No copy: the checked pages of the file are the matrix. The store never changes
                # a file in place (it renames a new one over it or deletes it, and a mapping
                # keeps the old content), so the array stays as checked; a copy would cost a
                # fresh 113 MB allocation per 5,000-vertex matrix, slower than the checksum.
                return stored.view(np.ndarray)
            dist = stored.astype(np.float32)
            dist.flags.writeable = False
            return dist
        log.warning("geodesic store entry %s of %r %s; recomputing it", path, mesh.name, problem)
        self._remove(path)
        return None
