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
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from geofeat.config import cache_dir
from geofeat.errors import MeshError
from geofeat.files import EntryFolder, array_crc32, atomic_write
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
    if method == "dijkstra":
        dist = _all_pairs_dijkstra(edge_graph(mesh) * scale, mesh.verts, progress=progress)
    else:
        dist = _all_pairs_heat(mesh, scale, progress=progress)
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
            _fill_patch_rows(dist, graph, separator, patch)
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


def _fill_patch_rows(dist: np.ndarray, graph: sp.csr_matrix, separator: np.ndarray, patch: np.ndarray) -> None:
    """Rows ``dist[patch]`` from distances inside the patch and the separator rows already in ``dist``.

    ``patch`` must be a whole connected component of the graph without the separator, so
    that a path leaving it meets the separator first, at a vertex of its ``border``.
    """
    neighbours = np.unique(graph[patch].indices)
    border = neighbours[separator[neighbours]]
    around = np.concatenate([patch, border])
    sinks = np.arange(around.size) >= patch.size  # paths stop at the border
    inside = dijkstra(_without_out_edges(graph[around][:, around], sinks), directed=True, indices=np.arange(patch.size))
    rows = np.full((patch.size, dist.shape[1]), np.inf, dtype=np.float32)
    rows[:, around] = inside
    to_border = rows[:, border]
    step = np.empty_like(rows)
    for j, k in enumerate(border):
        np.add(to_border[:, j : j + 1], dist[k], out=step)
        np.minimum(rows, step, out=rows)
    dist[patch] = rows


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
# On disk
# ---------------------------------------------------------------------------------------

#: Version of the layout of `GeodesicStore` entries (part of their file names).
STORE_VERSION = "2"
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
    """

    label = "the geodesic store"

    def __init__(self, folder: str | os.PathLike | None = None, dtype: str = "float32", connected: bool = False):
        if dtype not in STORE_DTYPES:
            raise MeshError(f"GeodesicStore keeps matrices in one of {STORE_DTYPES}; found dtype={dtype!r}.")
        self.folder = Path(folder).expanduser() if folder is not None else cache_dir() / "geodesics"
        self.dtype = np.dtype(dtype)
        self.connected = bool(connected)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.folder)!r}, dtype={self.dtype.name!r})"

    @property
    def root(self) -> Path:
        """The folder (`geofeat.files.EntryFolder`'s name for it)."""
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

    def ensure(self, mesh: Mesh) -> Path:
        """Compute and store the matrix unless a sound entry is present; returns its file."""
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
        """
        for path in self._entries(mesh):
            dist = self._read(path, mesh)
            if isinstance(dist, np.ndarray):
                return dist
        return self._compute(mesh)[1]

    def _compute(self, mesh: Mesh) -> tuple[Path, np.ndarray]:
        # not in the in-memory cache as well: the file is the kept copy (read back mapped, no copy)
        dist = geodesic_matrix(mesh, method="dijkstra", normalize=True, cache=False)
        if self.connected and not np.isfinite(dist).all():
            raise MeshError(
                f"{mesh.name!r} is not connected: its geodesic distances are infinite; give a connected mesh "
                "(geofeat.geometry.partial.largest_component_submesh keeps its largest piece)."
            )
        stored = np.ascontiguousarray(dist, dtype=self.dtype)
        path = self.folder / f"{self._prefix(mesh)}{array_crc32(stored):08x}.npy"

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as handle:  # a handle: np.save would append ".npy" to the temporary name
                np.save(handle, stored)

        atomic_write(path, write, durable=False)  # every read checks the checksum: no need to wait for the disk
        if self.dtype == np.float32:
            return path, dist
        widened = stored.astype(np.float32)
        widened.flags.writeable = False
        return path, widened

    def _read(self, path: Path, mesh: Mesh) -> np.ndarray | None:
        """The checked float32 matrix in ``path``, or None after deleting a damaged entry."""
        n = mesh.n_vertices
        try:
            stored = np.load(path, mmap_mode="r")
            problem = _entry_problem(stored, n, self.dtype, path.stem.rsplit("-", 1)[1])
        except (OSError, ValueError, EOFError) as exc:
            problem = f"cannot be read ({exc})"
        if problem is None:
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
        path.unlink(missing_ok=True)
        return None
