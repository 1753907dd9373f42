"""Which vertices lie within a radius of given points: the neighbour searches of ball back-projection.

Both run where the features are (CPU or GPU), return exactly the (vertex, point) pairs
closer than the radius (tested in float64, as a KD-tree query would give them), and hold
at most a bounded number of candidate pairs at once.

* `FaceCandidates` (meshes): a pixel's point lies on, or near, the face the rasterizer gave
  it, so the candidates of every face are listed once per mesh and a batch of points keeps
  those of its faces within the radius.
* `PointGrid` (point clouds): a uniform grid of cells two radii wide; a ball of the radius
  overlaps at most two cells along each axis, so a point's neighbours lie in 8 cells, found
  by binary search in the vertices sorted by cell.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from geofeat.errors import RenderError
from geofeat.render.rasterizer import _chunks

#: The 2 x 2 x 2 block of cells from a cell on, (8, 3) int64 offsets.
_BLOCK = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
#: Cells along the longest side of the grid at most, so that a cell's key fits in 63 bits.
_MAX_CELLS_PER_AXIS = 1 << 20


class FaceCandidates:
    """The vertices that a ball of radius ``r`` around any point of a face can reach, for every face.

    Vertex ``v`` is a candidate of face ``f`` when ``|v - c_f| <= r + R_f + slack``, with
    ``c_f`` the face's centroid and ``R_f`` its largest centroid-to-corner distance: every
    point of the face lies within ``R_f`` of ``c_f``, so every vertex within ``r`` of such a
    point is a candidate. ``slack`` widens the list for points that lie off their face
    (lifted from depth); `pairs_within` widens it again, once, when a point lies further off.
    Listed once per mesh: with a KD-tree on the CPU, by brute force in chunks on a GPU.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3), float64
    faces : numpy.ndarray, shape (F, 3), int64
    radius : float
        The ball radius r, in mesh units.
    device : torch.device
        Where the lists live and `pairs_within` runs.
    slack : float, optional
        Default ``1e-6`` x the bounding-box diagonal plus ``1e-3 r`` (rounding margins).

    Attributes
    ----------
    verts : torch.Tensor, shape (V, 3), float64, on ``device``
    start : torch.Tensor, shape (F,), int64
        Where face ``f``'s candidates begin in ``vertices``.
    count : torch.Tensor, shape (F,), int64
        How many candidates face ``f`` has.
    vertices : torch.Tensor, shape (sum(count),), int64
        The candidate vertices, face after face.
    """

    #: Entries (faces x vertices) of one chunk of the GPU's brute-force listing.
    CHUNK_ENTRIES = 2**24

    def __init__(self, verts: np.ndarray, faces: np.ndarray, radius: float, device, slack: float | None = None):
        self.device = torch.device(device)
        self._verts_np = np.asarray(verts, dtype=np.float64)
        self._faces_np = np.asarray(faces, dtype=np.int64)
        self.radius = float(radius)
        self.verts = torch.tensor(self._verts_np, device=self.device)
        corners = self._verts_np[self._faces_np]  # (F, 3, 3)
        self._centroids_np = corners.mean(axis=1)
        self._reach_np = np.linalg.norm(corners - self._centroids_np[:, None], axis=2).max(axis=1)  # R_f
        self.centroids = torch.as_tensor(self._centroids_np, device=self.device)
        self.face_reach = torch.as_tensor(self._reach_np, device=self.device)
        if slack is None:
            size = float(np.linalg.norm(np.ptp(self._verts_np, axis=0))) if len(self._verts_np) else 0.0
            slack = 1e-6 * size + 1e-3 * self.radius
        self._list(float(slack))

    def _list(self, slack: float) -> None:
        """List every face's candidates within ``radius + R_f + slack`` of its centroid."""
        self.slack = slack
        reach = self.radius + self._reach_np + slack
        if self.device.type == "cpu":
            found = cKDTree(self._verts_np).query_ball_point(self._centroids_np, reach)
            count = np.fromiter((len(n) for n in found), dtype=np.int64, count=len(found))
            vertices = np.fromiter((j for n in found for j in n), dtype=np.int64, count=int(count.sum()))
            self.count = torch.as_tensor(count)
            self.vertices = torch.as_tensor(vertices)
        else:
            self.count, self.vertices = self._list_by_brute_force(torch.as_tensor(reach, device=self.device))
        self.start = torch.cumsum(self.count, 0) - self.count

    def _list_by_brute_force(self, reach: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(count, vertices) from every centroid-to-vertex distance, a chunk of faces at a time."""
        n_faces, n_verts = len(self._faces_np), len(self._verts_np)
        step = max(1, self.CHUNK_ENTRIES // max(n_verts, 1))
        counts, vertices = [], []
        for first in range(0, n_faces, step):
            centres = self.centroids[first : first + step]
            distance_sq = ((centres[:, None, :] - self.verts[None, :, :]) ** 2).sum(-1)  # (chunk, V)
            face, vertex = torch.nonzero(distance_sq <= reach[first : first + step, None] ** 2, as_tuple=True)
            counts.append(torch.bincount(face, minlength=centres.shape[0]))
            vertices.append(vertex)
        if not counts:
            return torch.zeros(0, dtype=torch.int64, device=self.device), torch.zeros(0, dtype=torch.int64, device=self.device)
        return torch.cat(counts), torch.cat(vertices)

    def pairs_within(
        self, face_ids: torch.Tensor, points: torch.Tensor, radius: float, *, on_faces: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """All (vertex, point) pairs closer than ``radius`` (``<=``, in float64), points given with their faces.

        Parameters
        ----------
        face_ids : torch.Tensor, shape (M,), int64
            The face each point belongs to (the rasterizer's face of its pixel).
        points : torch.Tensor, shape (M, 3), float64
            On or near that face.
        radius : float
            At most the radius the candidates were listed for.
        on_faces : bool
            The points are known to lie on their faces (interpolated from barycentrics), so
            the check of how far they lie off them is skipped.

        Returns
        -------
        rows : torch.Tensor, shape (P,), int64
            Vertex of each pair.
        cols : torch.Tensor, shape (P,), int64
            Point of each pair (its position in ``points``), in increasing order.
        """
        if radius > self.radius:
            raise RenderError(f"the candidates were listed for a radius of {self.radius}; {radius} is larger.")
        if face_ids.numel() == 0:
            empty = torch.zeros(0, dtype=torch.int64, device=self.device)
            return empty, empty
        if not on_faces:
            off = torch.linalg.vector_norm(points - self.centroids[face_ids], dim=1) - self.face_reach[face_ids]
            off_face = float(off.max())
            if off_face > self.slack:  # points lifted from depth lie off their face: widen the lists once more
                self._list(2.0 * off_face)
        count = self.count[face_ids]
        total = int(count.sum())
        cols = torch.repeat_interleave(torch.arange(face_ids.numel(), device=self.device), count, output_size=total)
        first = torch.repeat_interleave(self.start[face_ids] - (torch.cumsum(count, 0) - count), count, output_size=total)
        rows = self.vertices.index_select(0, first + torch.arange(total, device=self.device))
        offset = self.verts.index_select(0, rows) - points.index_select(0, cols)
        distance_sq = (offset * offset).sum(1)
        close = distance_sq <= radius * radius
        return rows[close], cols[close]


class PointGrid:
    """The points of a cloud sorted into a uniform grid, for fixed-radius neighbour queries on any device.

    Cells are cubes of side ``max(2 radius, longest side / 2**20)``: at least the ball's
    diameter, so the ball around a query ``q`` lies in the 2 x 2 x 2 block of cells that
    starts at the cell of ``q - radius``. Cell ``(i, j, k)`` has the key ``(i ny + j) nz + k``
    and the points are sorted by key, so the points of a cell are one run found by binary
    search. No per-query structure is built, and a batch of queries holds at most
    `CHUNK_PAIRS` candidate pairs at once.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3), float64
        The cloud's points (the vertices that features go to).
    radius : float
        The largest radius that will be asked for, in the cloud's units (> 0).
    device : torch.device or str
        Where the grid lives and `pairs_within` runs.

    Attributes
    ----------
    verts : torch.Tensor, shape (V, 3), float64, on ``device``
    """

    #: Candidate (vertex, query) pairs tested at once.
    CHUNK_PAIRS = 1 << 22

    def __init__(self, verts: np.ndarray, radius: float, device: torch.device | str) -> None:
        self.device = torch.device(device)
        self.radius = float(radius)
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise RenderError(f"the neighbour radius must be a finite number > 0; found {radius!r}.")
        verts = np.asarray(verts, dtype=np.float64)
        self.verts = torch.tensor(verts, device=self.device)
        self.origin = torch.tensor(verts.min(axis=0), device=self.device)
        longest = float(np.ptp(verts, axis=0).max()) if len(verts) else 0.0
        self.cell = max(2.0 * self.radius, longest / _MAX_CELLS_PER_AXIS)
        cells = self._cells(self.verts)
        self.shape = cells.amax(dim=0) + 1  # (3,) cells per axis
        self.order = torch.argsort(self._keys(cells))
        self.sorted_keys = self._keys(cells).index_select(0, self.order)

    def _cells(self, points: torch.Tensor) -> torch.Tensor:
        """Integer cell coordinates of points, (M, 3) int64 (clamped to one cell beyond the grid)."""
        cells = torch.floor((points - self.origin) / self.cell)
        upper = float(_MAX_CELLS_PER_AXIS + 1)
        return cells.clamp(-1.0, upper).long()

    def _keys(self, cells: torch.Tensor) -> torch.Tensor:
        return (cells[..., 0] * self.shape[1] + cells[..., 1]) * self.shape[2] + cells[..., 2]

    def pairs_within(self, points: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
        """All (vertex, point) pairs closer than ``radius`` (``<=``, in float64).

        Parameters
        ----------
        points : torch.Tensor, shape (M, 3), float64
            Query points, anywhere.
        radius : float
            At most the radius the grid was built for.

        Returns
        -------
        rows : torch.Tensor, shape (P,), int64
            Vertex of each pair.
        cols : torch.Tensor, shape (P,), int64
            Query of each pair (its position in ``points``), in increasing order.
        """
        if radius > self.radius:
            raise RenderError(f"the grid was built for a radius of {self.radius}; {radius} is larger.")
        points = points.to(self.device, torch.float64)
        rows, cols = [], []
        step = max(1, self.CHUNK_PAIRS // _BLOCK.shape[0])
        for first in range(0, points.shape[0], step):  # bounds the (queries, 8) run tables
            queries = points[first : first + step]
            start, count = self._runs(queries)
            for chunk in _chunks(count.sum(dim=1), self.CHUNK_PAIRS):
                found = self._pairs_in_runs(queries[chunk], start[chunk], count[chunk], radius)
                rows.append(found[0])
                cols.append(found[1] + first + chunk.start)
        if not rows:
            empty = torch.zeros(0, dtype=torch.int64, device=self.device)
            return empty, empty
        return torch.cat(rows), torch.cat(cols)

    def _runs(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Where each query's 8 cells start in the sorted points and how many points each holds, (M, 8) each."""
        cells = self._cells(queries - self.radius)[:, None, :] + _BLOCK.to(self.device)  # (M, 8, 3)
        inside = ((cells >= 0) & (cells < self.shape)).all(dim=-1)
        keys = self._keys(cells.clamp(min=0))
        start = torch.searchsorted(self.sorted_keys, keys)
        stop = torch.searchsorted(self.sorted_keys, keys, right=True)
        return start, torch.where(inside, stop - start, 0)

    def _pairs_in_runs(self, queries: torch.Tensor, start: torch.Tensor, count: torch.Tensor, radius: float):
        """The pairs within ``radius`` among the points of these queries' runs; query indices local to ``queries``."""
        count, start = count.reshape(-1), start.reshape(-1)
        total = int(count.sum())
        run = torch.repeat_interleave(torch.arange(count.numel(), device=self.device), count, output_size=total)
        first = torch.cumsum(count, 0) - count
        position = start[run] + torch.arange(total, device=self.device) - first[run]
        rows = self.order.index_select(0, position)
        cols = run // _BLOCK.shape[0]
        offset = self.verts.index_select(0, rows) - queries.index_select(0, cols)
        close = (offset * offset).sum(dim=1) <= radius * radius
        return rows[close], cols[close]
