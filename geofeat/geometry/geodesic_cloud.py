"""Geodesic distances on point clouds: the heat method on points, and the checks it needs first.

potpourri3d's ``PointCloudHeatSolver`` (Sharp and Crane's heat method on a point cloud: a
local Delaunay triangulation of each point's 30 nearest neighbours, intrinsic mollification,
one heat solve and one Poisson solve per source) gives the distances. It needs a point cloud
that samples a surface, so the cloud is first split and checked (`cloud_layout`):

* **duplicate points** (closer than `DUPLICATE_TOLERANCE` of the bounding-box diagonal)
  are solved once: they share their rows and lie at distance 0 from each other;
* **pieces**: two points are neighbours when one is among the other's 30 nearest and they
  are at most `PIECE_GAP` times the median nearest-neighbour distance apart; the connected
  pieces of that graph are solved apart, and distances between pieces are ``inf`` (as
  between the connected components of a mesh). An isolated point (an outlier far from the
  rest) is a piece of its own;
* pieces of fewer than `MIN_HEAT_POINTS` points are too small for the solver: distances
  inside them are straight-line distances (a warning says how many points that concerns).
  A cloud whose largest piece is that small raises `MeshError`;
* a piece whose points lie on a line somewhere (a neighbourhood whose spread across is
  below `FLAT_NEIGHBOURHOOD` of its spread along) raises `MeshError`: the solver would
  return wrong distances there without a word. A flat (planar) cloud is a surface and works.

`geofeat.geometry.geodesic` calls this module for point clouds (``method="heat"``, the
only method on points); `cloud_area` gives the area that normalises their distances.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from geofeat.errors import MeshError
from geofeat.geometry.laplacian import laplacian
from geofeat.mesh import Mesh
from geofeat.runtime.progress import progress_bar
from geofeat.storage.lru import LRUCache

__all__ = [
    "DUPLICATE_TOLERANCE",
    "FLAT_NEIGHBOURHOOD",
    "HEAT_NEIGHBOURS",
    "MIN_HEAT_POINTS",
    "PIECE_GAP",
    "CloudLayout",
    "clear_cloud_caches",
    "cloud_area",
    "cloud_heat_rows",
    "cloud_layout",
]

log = logging.getLogger(__name__)

#: Neighbours of each point in potpourri3d's point-cloud heat solver (its local triangulations).
HEAT_NEIGHBOURS = 30
#: The solver needs at least this many points (each point and its neighbours).
MIN_HEAT_POINTS = HEAT_NEIGHBOURS + 1
#: Points closer than this fraction of the bounding-box diagonal are one point.
DUPLICATE_TOLERANCE = 1e-9
#: Neighbours farther apart than this many median nearest-neighbour distances are not joined.
PIECE_GAP = 10.0
#: A neighbourhood whose spread across is below this fraction of its spread along is a line.
FLAT_NEIGHBOURHOOD = 1e-3
_ROW_CHUNK = 256

_layouts: LRUCache[str, CloudLayout] = LRUCache(8)
_areas: LRUCache[str, float] = LRUCache(64)


@dataclass(frozen=True, eq=False)
class CloudLayout:
    """How the heat method sees a point cloud of V points: its distinct points and their pieces.

    Attributes
    ----------
    points : numpy.ndarray, shape (U, 3), float64
        The distinct points (each the first of its duplicates).
    position_of : numpy.ndarray, shape (V,), int64
        The distinct point of each point of the cloud.
    pieces : tuple of numpy.ndarray of int64
        Indices into ``points`` of each piece, the largest first (ties: the piece holding the
        lowest index first).
    piece_of : numpy.ndarray, shape (U,), int64
        The piece of each distinct point (its place in ``pieces``).
    """

    points: np.ndarray
    position_of: np.ndarray
    pieces: tuple[np.ndarray, ...]
    piece_of: np.ndarray

    @property
    def n_duplicates(self) -> int:
        """Points that repeat an earlier one."""
        return int(self.position_of.size - self.points.shape[0])

    def solved(self, piece: int) -> bool:
        """Whether the heat method solves ``piece`` (else: straight-line distances inside it)."""
        return self.pieces[piece].size >= MIN_HEAT_POINTS


def _label(mesh: Mesh) -> str:
    return repr(mesh.name or "<unnamed>")


def cloud_layout(mesh: Mesh) -> CloudLayout:
    """Split and check a point cloud for the heat method (see the module notes); cached by content.

    Parameters
    ----------
    mesh : Mesh
        A point cloud (``faces`` None) of V points.

    Returns
    -------
    CloudLayout

    Raises
    ------
    MeshError
        For a triangle mesh; a cloud whose largest piece has fewer than `MIN_HEAT_POINTS`
        distinct points; a piece with points on a line.
    """
    if mesh.faces is not None:
        raise MeshError(f"{_label(mesh)} is a triangle mesh; cloud_layout takes point clouds (faces=None).")
    layout = _layouts.get(mesh.hash)
    if layout is None:
        layout = _build_layout(mesh)
        _layouts.put(mesh.hash, layout)
    return layout


def _build_layout(mesh: Mesh) -> CloudLayout:
    points, position_of = _distinct_points(mesh.verts)
    n_distinct = points.shape[0]
    if n_distinct < MIN_HEAT_POINTS:
        raise MeshError(
            f"point cloud {_label(mesh)} has {n_distinct} distinct point(s) ({mesh.n_vertices} in all); the heat method "
            f"on points joins each point to its {HEAT_NEIGHBOURS} nearest neighbours, so it needs at least "
            f"{MIN_HEAT_POINTS}. Sample the surface more densely, or pass the mesh with its faces."
        )
    if n_distinct < mesh.n_vertices:
        log.warning(
            "point cloud %s: %d point(s) repeat another point; they share its geodesic distances (0 between them)",
            _label(mesh),
            mesh.n_vertices - n_distinct,
        )
    pieces, piece_of = _pieces(points)
    if pieces[0].size < MIN_HEAT_POINTS:
        raise MeshError(
            f"point cloud {_label(mesh)} falls apart into {len(pieces)} pieces, the largest of {pieces[0].size} points: "
            f"the heat method needs a piece of at least {MIN_HEAT_POINTS} points that lie close together (no two neighbours "
            f"more than {PIECE_GAP:g} times the median nearest-neighbour distance apart). Expected points sampling a surface."
        )
    small = [piece for piece in pieces if piece.size < MIN_HEAT_POINTS]
    if small:
        log.warning(
            "point cloud %s: %d point(s) in %d piece(s) of fewer than %d points, apart from the rest (outliers?): "
            "distances inside each are straight lines, to the rest infinite",
            _label(mesh),
            sum(piece.size for piece in small),
            len(small),
            MIN_HEAT_POINTS,
        )
    for piece in pieces:
        if piece.size >= MIN_HEAT_POINTS:
            _check_not_linear(mesh, points, piece, position_of)
    for array in (points, position_of, piece_of, *pieces):
        array.flags.writeable = False
    return CloudLayout(points, position_of, tuple(pieces), piece_of)


def _distinct_points(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct points (U, 3) and the distinct point of every point (V,), duplicates within `DUPLICATE_TOLERANCE`."""
    n = verts.shape[0]
    diagonal = float(np.linalg.norm(verts.max(axis=0) - verts.min(axis=0)))
    if diagonal == 0.0:
        return verts[:1].copy(), np.zeros(n, dtype=np.int64)
    pairs = cKDTree(verts).query_pairs(DUPLICATE_TOLERANCE * diagonal, output_type="ndarray")
    if pairs.size == 0:
        return verts.copy(), np.arange(n, dtype=np.int64)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    first = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    order = np.argsort(first)  # distinct points in the order of their first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return verts[first[order]].copy(), rank[labels].astype(np.int64)


def _pieces(points: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Pieces of the neighbour graph (largest first) and the piece of every point."""
    n = points.shape[0]
    k = min(HEAT_NEIGHBOURS, n - 1)
    distance, neighbour = cKDTree(points).query(points, k=k + 1)
    gap = PIECE_GAP * float(np.median(distance[:, 1]))
    near = distance[:, 1:] <= gap
    rows = np.repeat(np.arange(n), k)[near.ravel()]
    graph = sp.coo_matrix((np.ones(rows.size), (rows, neighbour[:, 1:].ravel()[near.ravel()])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    members = [np.flatnonzero(labels == label) for label in range(labels.max() + 1)]
    members.sort(key=lambda piece: (-piece.size, piece[0]))
    piece_of = np.empty(n, dtype=np.int64)
    for index, piece in enumerate(members):
        piece_of[piece] = index
    return members, piece_of


def _check_not_linear(mesh: Mesh, points: np.ndarray, piece: np.ndarray, position_of: np.ndarray) -> None:
    """`MeshError` when the neighbours of some point of ``piece`` lie on a line (the solver cannot triangulate them)."""
    local = points[piece]
    _, neighbour = cKDTree(local).query(local, k=min(MIN_HEAT_POINTS, piece.size))
    patches = local[neighbour]  # (n, k, 3)
    centred = patches - patches.mean(axis=1, keepdims=True)
    spread = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", centred, centred))  # ascending, (n, 3)
    linear = spread[:, 1] <= (FLAT_NEIGHBOURHOOD**2) * spread[:, 2]
    if linear.any():
        first = int(np.flatnonzero(position_of == piece[np.flatnonzero(linear)[0]])[0])
        raise MeshError(
            f"point cloud {_label(mesh)}: the {HEAT_NEIGHBOURS} nearest neighbours of {int(linear.sum())} point(s), first "
            f"point {first}, lie on a line (their spread across is below {FLAT_NEIGHBOURHOOD:g} of their spread along). "
            "The heat method on points needs points sampling a surface; a curve or a line has none."
        )


def cloud_area(mesh: Mesh) -> float:
    """Surface area of a point cloud: the lumped masses of its robust point-cloud Laplacian, summed; cached by content.

    Only the pieces that the heat method solves count (an outlier's neighbours are far away,
    so its mass would be an artefact). On a uniformly sampled sphere it is within 0.1% of
    the true area; on the vertices of FAUST_r meshes a few percent above the meshes' areas
    (``benchmarks/cloud_geodesic.py`` measures it).

    Parameters
    ----------
    mesh : Mesh
        A point cloud.

    Returns
    -------
    float
        The area, in the cloud's units squared.

    Raises
    ------
    MeshError
        As `cloud_layout`.
    """
    area = _areas.get(mesh.hash)
    if area is None:
        layout = cloud_layout(mesh)
        area = 0.0
        for index, piece in enumerate(layout.pieces):
            if layout.solved(index):
                area += float(laplacian(Mesh(layout.points[piece], name=mesh.name), n_neighbors=HEAT_NEIGHBOURS).mass.sum())
        _areas.put(mesh.hash, area)
    return area


def cloud_heat_rows(
    mesh: Mesh, sources: np.ndarray | None = None, scale: float = 1.0, progress: bool = False
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Heat-method distances from some points of a cloud to all of them, block by block.

    Parameters
    ----------
    mesh : Mesh
        A point cloud of V points.
    sources : numpy.ndarray of int, optional
        Source points (repeats ignored); None: every point.
    scale : float
        Factor applied to every distance (``1 / sqrt(area)`` to normalise).
    progress : bool
        Show a tqdm progress bar.

    Yields
    ------
    indices : numpy.ndarray, shape (b,), int64
        Increasing source indices, all in one piece of the cloud.
    rows : numpy.ndarray, shape (b, V), float64
        Their distances to every point, times ``scale``: non-negative, 0 at the source and
        its duplicates, ``inf`` to the points of other pieces. Not symmetric (the heat
        method's distance from i to j differs slightly from j to i).

    Raises
    ------
    MeshError
        As `cloud_layout`, an index out of range, or a solver failure (non-finite distances).
    """
    layout = cloud_layout(mesh)
    n = mesh.n_vertices
    sources = np.arange(n, dtype=np.int64) if sources is None else np.unique(np.asarray(sources, dtype=np.int64))
    if sources.size and (sources.min() < 0 or sources.max() >= n):
        raise MeshError(f"source indices must lie in [0, {n - 1}]; found [{sources.min()}, {sources.max()}].")
    piece_of_point = layout.piece_of[layout.position_of]
    with progress_bar(total=sources.size, desc="geodesics (heat on points)", unit="point", show=progress) as bar:
        for index in np.unique(piece_of_point[sources]).tolist():
            mine = sources[piece_of_point[sources] == index]
            columns = np.flatnonzero(piece_of_point == index)
            local_rows = _PieceDistances(mesh, layout, index)
            for chunk in np.array_split(mine, max(1, -(-mine.size // _ROW_CHUNK))):
                rows = np.full((chunk.size, n), np.inf)
                rows[:, columns] = local_rows.at(chunk, columns) * scale
                yield chunk, rows
                bar.update(chunk.size)


class _PieceDistances:
    """Distances inside one piece of a cloud: the heat solver of the piece, or straight lines for a small piece."""

    def __init__(self, mesh: Mesh, layout: CloudLayout, index: int):
        self.mesh, self.layout = mesh, layout
        piece = layout.pieces[index]
        self.local_of = np.full(layout.points.shape[0], -1, dtype=np.int64)
        self.local_of[piece] = np.arange(piece.size)
        self.points = layout.points[piece]
        self.solver = None
        if layout.solved(index):
            import potpourri3d as pp3d

            try:
                self.solver = pp3d.PointCloudHeatSolver(self.points)
            except (RuntimeError, ValueError) as err:
                raise MeshError(f"the heat method could not be set up on point cloud {_label(mesh)}: {err}") from err

    def at(self, sources: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """Distances (len(sources), len(columns)) float64 between points of the cloud, all in this piece."""
        local_sources = self.local_of[self.layout.position_of[sources]]
        local_columns = self.local_of[self.layout.position_of[columns]]
        out = np.empty((sources.size, columns.size))
        for row, source in enumerate(local_sources.tolist()):
            out[row] = self._row(source)[local_columns]
        return out

    def _row(self, source: int) -> np.ndarray:
        if self.solver is None:
            return np.linalg.norm(self.points - self.points[source], axis=1)
        try:
            row = np.asarray(self.solver.compute_distance(source), dtype=np.float64)
        except (RuntimeError, ValueError) as err:
            raise MeshError(f"the heat method failed on point cloud {_label(self.mesh)}: {err}") from err
        if not np.isfinite(row).all():
            raise MeshError(
                f"the heat method gave non-finite distances on point cloud {_label(self.mesh)} (source {source} of its "
                "piece); check the cloud for points that do not sample a surface."
            )
        row = np.maximum(row, 0.0)
        row[source] = 0.0
        return row


def clear_cloud_caches() -> None:
    """Forget the cached layouts and areas of point clouds."""
    _layouts.clear()
    _areas.clear()
