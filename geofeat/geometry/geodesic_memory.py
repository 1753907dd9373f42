"""The memory bound of an evaluation's geodesic distances: the matrix when it fits, else only the entries read.

An evaluation reads a few entries of a target's all-pairs geodesic matrix (the geodesic
error of each matched vertex, the worst case of each unmatched one). `evaluation_distances`
gives it the whole matrix (`geofeat.geometry.geodesic.geodesic_matrix`, read back from or
kept in a `geofeat.geometry.geodesic_store.GeodesicStore`) when `all_pairs_memory` is
within the bound of `memory_limit`; above it, a `GeodesicEntries` that computes only the
entries asked for, a few rows at a time. Point clouds take the same paths with the heat
method on points (`geofeat.geometry.geodesic_cloud`) in place of edge Dijkstra.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from scipy.sparse.csgraph import connected_components

from geofeat.errors import GeofeatError
from geofeat.geometry.geodesic import (
    all_pairs_memory,
    area_normalisation,
    dijkstra_row_blocks,
    edge_graph,
    geodesic_matrix,
    streamed_memory,
)
from geofeat.geometry.geodesic_cloud import cloud_heat_rows, cloud_layout
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.mesh import Mesh
from geofeat.storage.sizes import format_size, parse_size

__all__ = ["MEMORY_ENV", "MEMORY_FRACTION", "GeodesicEntries", "available_memory", "evaluation_distances", "memory_limit"]

log = logging.getLogger(__name__)

#: Environment variable bounding the memory of one all-pairs matrix (``"4G"``, ``"512M"``, bytes).
MEMORY_ENV = "GEOFEAT_GEODESIC_MEMORY"
#: Default bound: this fraction of the memory available when the evaluation starts.
MEMORY_FRACTION = 0.5


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
        Bytes (or ``"4G"``, see `geofeat.storage.sizes.parse_size`). Default: ``$GEOFEAT_GEODESIC_MEMORY``, else
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


def evaluation_distances(
    mesh: Mesh, store: GeodesicStore | None = None, limit: int | str | None = None, *, limit_source: str | None = None
) -> np.ndarray | GeodesicEntries:
    """The geodesic distances an evaluation reads on a target: the matrix when it fits, else `GeodesicEntries`.

    Parameters
    ----------
    mesh : Mesh
        Target (full) shape with V vertices: a triangle mesh or a point cloud.
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
        The matrix of `geodesic_matrix` (over ``sqrt(area)``: Dijkstra on a mesh, the heat
        method on a point cloud) when `all_pairs_memory`
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
    return geodesic_matrix(mesh, normalize=True)


class GeodesicEntries:
    """Some entries of a shape's evaluation geodesic matrix, computed without forming the matrix.

    Stands for ``geodesic_matrix(mesh, normalize=True)`` (Dijkstra on a mesh, the heat method
    on a point cloud) in the metrics of
    `geofeat.evaluation.metrics` (it is a `geofeat.evaluation.metrics.DistanceEntries`), in two rounds:

    1. asking: the metrics run once on it. ``entries[rows, cols]`` records the entries read
       and returns placeholders (``inf`` between connected components, as the matrix
       holds, else 0), ``worst_case(rows)`` records the rows;
    2. `compute` computes every recorded entry in one pass over the rows of the matrix,
       patch by patch, keeping only the entries asked for; then the metrics run again on
       it and read the values.

    The values are exactly those of the matrix: the rows are computed by the same code
    (separator rows by Dijkstra, patch rows by the same min-plus sums; on a point cloud, one
    heat solve per row) and entry ``(i, j)`` combines rows ``i`` and ``j`` at each other as
    `geodesic_matrix` symmetrises them: their minimum (Dijkstra), their mean (heat).
    Reading an entry that was not asked for before `compute` raises `GeofeatError`.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh or point cloud with V vertices.
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
        self.mesh = mesh
        self.shape = (mesh.n_vertices, mesh.n_vertices)
        self.limit = limit
        self._scale = area_normalisation(mesh)
        if mesh.faces is None:
            self._graph = None
            layout = cloud_layout(mesh)
            self._labels = layout.piece_of[layout.position_of]
        else:
            self._graph = edge_graph(mesh) * self._scale
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
        keys, values = self._keys, self._values
        if keys is None or values is None:  # not computed yet
            self._asked.append(flat.copy())
            apart = self._labels[rows] != self._labels[cols]
            return np.where(apart, np.inf, 0.0).astype(np.float32)
        at = np.minimum(np.searchsorted(keys, flat), keys.size - 1)
        if keys.size == 0 or not np.array_equal(keys[at], flat):
            raise GeofeatError("GeodesicEntries: an entry read now was not asked for before compute().")
        return values[at].reshape(rows.shape)

    def worst_case(self, rows) -> np.ndarray:
        """Largest finite distance from each of ``rows`` (0 where none), shape (len(rows),) float64."""
        rows = np.asarray(rows, dtype=np.int64).ravel()
        worst_rows, worst = self._worst_rows, self._worst
        if worst_rows is None or worst is None:  # not computed yet
            self._asked_rows.append(rows.copy())
            return np.zeros(rows.size)
        at = np.minimum(np.searchsorted(worst_rows, rows), max(worst_rows.size - 1, 0))
        if worst_rows.size == 0 or not np.array_equal(worst_rows[at], rows):
            raise GeofeatError("GeodesicEntries: a worst case read now was not asked for before compute().")
        return worst[at]

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
            cache_bytes = budget // 2 if group.size else budget
            for block, rows in self._row_blocks(wanted, cache_bytes, progress):
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
                merged = self._combine(w_row, w_col).astype(np.float64)
                worst[start : start + group.size] = np.where(np.isfinite(merged), merged, -np.inf).max(axis=1).clip(min=0.0)
        self._keys, self._values = keys, self._combine(forward, backward)
        self._worst_rows, self._worst = worst_rows, worst
        return self

    def _row_blocks(self, wanted: np.ndarray | None, cache_bytes: int, progress: bool) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Blocks ``(indices (b,), rows (b, V) float32)`` of the unsymmetrised rows, as `geodesic_matrix` computes them."""
        if self._graph is not None:
            yield from dijkstra_row_blocks(self._graph, self.mesh.verts, wanted, cache_bytes, progress)
            return
        for block, rows in cloud_heat_rows(self.mesh, wanted, self._scale, progress):
            yield block, rows.astype(np.float32)

    def _combine(self, row_ij: np.ndarray, row_ji: np.ndarray) -> np.ndarray:
        """Entry (i, j) from row i at j and row j at i: the symmetrisation of `geodesic_matrix`."""
        if self._graph is not None:
            return np.minimum(row_ij, row_ji)
        return 0.5 * (row_ij + row_ji)
