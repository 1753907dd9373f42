"""Back-projection of per-pixel features onto mesh vertices, streamed over batches of views.

Three modes:

* ``"ball"`` (geofeat's default; GeoLoRA's and Diff3f's ball, made a true average): every
  foreground pixel is lifted to its 3D surface point and gives its feature to every vertex
  within ``radius`` (0.004 x the shape's bounding-box diagonal by default) of that point; a
  vertex takes the mean of what it received. The surface point is interpolated from the
  rasterizer's face index and perspective-correct barycentrics, which is the point that
  unprojecting the pixel by its depth gives, without the round trip through the camera.
* ``"face"`` gives each foreground pixel's feature to the three corners of its face,
  weighted by the barycentric coordinates.
* ``"ball_last"`` is what the GeoLoRA and DeepShapeMatchingKit (Diff3f) code computes, for
  the ``reference`` and ``dsmk`` recipes. Each pixel's point looks for the first ``max_neighbours``
  vertices (in vertex order) within the radius, as pytorch3d's ``ball_query`` with K=100.
  Their feature sums are then updated with an indexed in-place addition
  (``sums[idx] += features``), which with repeated indices is no sum: every vertex in
  reach gets ONE pixel's feature per view, and its count goes up by one per view. On the
  CPU the pixel is the last one in scan order; on CUDA it is whichever write lands last.
  Here it is always the last in scan order. The gradients are those of that indexed
  addition under autograd, which are not the gradients of its result: every candidate
  pixel of a vertex gets the vertex's gradient (not only the one that was kept), and the
  sums of earlier views are scaled by the number of candidates of each later view
  (`_LastWriteAdd`).

``"ball"`` and ``"face"`` are sparse products ``(V x M) @ (M x C)`` per batch of views, so
memory grows with one batch of pixels, never with the number of views, and no ``V x V``
or ``V x M`` dense matrix is ever formed.

The ball's neighbour search runs where the features are (the GPU when there is one), with
no search structure built per view: a pixel's point lies on (or, for points lifted from
depth, near) the face the rasterizer gave it, so every vertex within the radius of it is
within ``radius + R_f + slack`` of that face's centroid, ``R_f`` being the largest distance
from the centroid to a corner. These candidate vertices of each face are listed once per
mesh (`FaceCandidates`); a batch of pixels gathers its faces' candidates and keeps those
closer than the radius, in float64. The result is exactly the set of (vertex, pixel) pairs
within the radius, as a KD-tree query would give it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.distance import pdist

from geofeat.checks import check_choice, check_integer
from geofeat.errors import RenderError
from geofeat.render.rasterizer import surface_points

BACKPROJECT_MODES = ("ball", "face", "ball_last")
#: Ball radius as a fraction of the shape's size (GeoLoRA / Diff3f ``tolerance``).
BALL_RADIUS_FRACTION = 0.004
#: What the radius fraction multiplies: the bounding-box diagonal, or the largest vertex-to-vertex
#: distance (the diameter, as GeoLoRA and Diff3f compute it with ``cdist(...).max()``).
RADIUS_BASES = ("diagonal", "diameter")


class BackprojectionPlan(NamedTuple):
    """Which foreground pixels of one batch of views feed which vertices (`Backprojector.plan`).

    Attributes
    ----------
    pixels : torch.Tensor or None, shape (K,), int64
        Positions, in the batch's foreground pixel list (`foreground_pixels` order), of the
        pixels that reach at least one vertex, increasing: only their features are needed.
        None: every foreground pixel (``"face"``).
    rows : torch.Tensor, shape (P,), int64
        Vertices whose weight grows, with repeats.
    values : torch.Tensor, shape (P,), float32
        How much each grows by.
    matrix : torch.Tensor or None
        ``"ball"`` and ``"face"``: the sparse (V, K) CSR matrix of pixel weights, so that the
        vertex sums grow by ``matrix @ features``; None when no pixel reaches a vertex.
    last_writes : list of tuple
        ``"ball_last"``: one `_last_write_plan` per view, in view order.
    """

    pixels: torch.Tensor | None
    rows: torch.Tensor
    values: torch.Tensor
    matrix: torch.Tensor | None = None
    last_writes: list = []


def _sparse_rows(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, size: tuple[int, int]) -> torch.Tensor | None:
    """The sparse CSR matrix of ``size`` with ``values`` at (``rows``, ``cols``) (no pair twice); None when empty."""
    if rows.numel() == 0:
        return None
    matrix = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, size, check_invariants=False)
    with warnings.catch_warnings():  # "sparse CSR support is in beta": CSR products are the fast path here
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return matrix.coalesce().to_sparse_csr()


@dataclass
class Backprojector:
    """How pixels reach the vertices of one mesh: the mode, the ball radius, each face's candidate vertices.

    Makes a `BackprojectionPlan` per batch of views from its fragments alone (`plan`); a
    `VertexFeatureAccumulator` then adds the pixels' features along it.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
        Mesh vertices (the coordinates the rasterizer used).
    faces : numpy.ndarray, shape (F, 3), int
    mode : {"ball", "face", "ball_last"}
    radius : float, optional
        Ball radius in mesh units; default ``BALL_RADIUS_FRACTION`` x the size that
        ``radius_basis`` names.
    device : torch.device or str
        Where the plans are made (the pixel features' device).
    radius_basis : {"diagonal", "diameter"}
        Size that the default radius is a fraction of: the bounding-box diagonal, or the
        largest distance between two vertices (`shape_diameter`).
    max_neighbours : int, optional
        ``"ball_last"`` only: each pixel reaches at most this many vertices, the first ones in
        vertex order (pytorch3d ``ball_query``'s K); None: all within the radius.
    """

    verts: np.ndarray
    faces: np.ndarray
    mode: str = "ball"
    radius: float | None = None
    device: torch.device | str = "cpu"
    radius_basis: str = "diagonal"
    max_neighbours: int | None = None
    _faces_tensor: torch.Tensor | None = field(init=False, default=None, repr=False)
    _face_candidates: FaceCandidates | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        if self.mode not in BACKPROJECT_MODES:
            raise RenderError(f"backprojection mode must be one of {BACKPROJECT_MODES}; found {self.mode!r}.")
        self.radius_basis = check_choice(self.radius_basis, "radius_basis", RADIUS_BASES, error=RenderError)
        if self.max_neighbours is not None:
            self.max_neighbours = check_integer(self.max_neighbours, "max_neighbours", low=1, error=RenderError)
        self.device = torch.device(self.device)
        self.verts = np.asarray(self.verts, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if self.radius is None:
            if self.radius_basis == "diameter":
                size = shape_diameter(self.verts)
            else:
                size = float(np.linalg.norm(self.verts.max(axis=0) - self.verts.min(axis=0)))
            self.radius = BALL_RADIUS_FRACTION * size

    def plan(self, pix_to_face: torch.Tensor, bary: torch.Tensor, points: torch.Tensor | None = None) -> BackprojectionPlan:
        """Which foreground pixels of a batch of views feed which vertices: the geometry of `add_planned`.

        It depends on the fragments only, not on the features, so it can be made before the
        features exist (on another thread, while the backbone encodes other views); the waits
        on the device that listing the pairs needs all happen here.

        Parameters
        ----------
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
        bary : torch.Tensor, shape (N, H, W, 3), float
        points : torch.Tensor, shape (M, 3), optional
            Ball modes: the 3D point of each of the M foreground pixels (flat order).
            Default: the surface point that the face index and barycentrics give.

        Returns
        -------
        BackprojectionPlan
        """
        device = self.device
        pixels = torch.nonzero((pix_to_face >= 0).reshape(-1)).squeeze(1).to(device)
        if points is not None and tuple(points.shape) != (pixels.numel(), 3):
            raise RenderError(
                f"points must have shape ({pixels.numel()}, 3), one per foreground pixel; found {tuple(points.shape)}."
            )
        face_ids = pix_to_face.reshape(-1).to(device)[pixels]
        n_vertices = len(self.verts)
        if self.mode == "face":
            values = bary.reshape(-1, 3).to(device)[pixels].float().reshape(-1)  # (3 M,)
            rows = self._faces_on(device)[face_ids].reshape(-1)
            cols = torch.arange(pixels.numel(), device=device).repeat_interleave(3)
            return BackprojectionPlan(None, rows, values, _sparse_rows(rows, cols, values, (n_vertices, pixels.numel())))
        on_faces = points is None
        if on_faces:
            points = self._surface_points(face_ids, bary.reshape(-1, 3).to(device)[pixels])
        rows, cols = self._candidates(device).pairs_within(
            face_ids, points.to(device, torch.float64), self.radius, on_faces=on_faces
        )
        used, cols = torch.unique_consecutive(cols, return_inverse=True)  # cols come in increasing order
        if self.mode == "ball_last":
            views = pixels.index_select(0, used) // (pix_to_face.shape[1] * pix_to_face.shape[2])
            return self._plan_last(used, rows, cols, views)
        values = torch.ones(rows.numel(), device=device)
        return BackprojectionPlan(used, rows, values, _sparse_rows(rows, cols, values, (n_vertices, used.numel())))

    def _faces_on(self, device: torch.device) -> torch.Tensor:
        """The faces as an int64 tensor on ``device``, (F, 3)."""
        if self._faces_tensor is None or self._faces_tensor.device != device:
            self._faces_tensor = torch.tensor(self.faces, device=device)
        return self._faces_tensor

    def _candidates(self, device: torch.device) -> FaceCandidates:
        """Each face's candidate vertices for the ball, on ``device`` (listed once, on first use)."""
        if self._face_candidates is None or self._face_candidates.device != device:
            self._face_candidates = FaceCandidates(self.verts, self.faces, self.radius, device)
        return self._face_candidates

    def _surface_points(self, face_ids: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """The surface point of each pixel, (M, 3) float64: its barycentrics in its face (`surface_points`)."""
        verts, corners = self._candidates(face_ids.device).verts, self._faces_on(face_ids.device)[face_ids]  # (M, 3)
        return surface_points(verts, corners, bary)

    def _plan_last(self, used: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, views: torch.Tensor) -> BackprojectionPlan:
        """``"ball_last"``: view after view, each vertex in reach takes its last candidate pixel's feature.

        ``cols`` index ``used``, the pixels with a vertex in reach; ``views`` (K,) is the view of each of them.
        """
        if self.max_neighbours is not None:
            rows, cols = _first_per_point(rows, cols, self.max_neighbours, len(self.verts))
        writes, reached = [], []
        if rows.numel():
            pair_views = views[cols]
            for view in torch.unique(pair_views).tolist():
                in_view = pair_views == view
                write = _last_write_plan(rows[in_view], cols[in_view], used.numel())
                writes.append(write)
                reached.append(write[4])  # the vertices reached in this view: their count goes up by one
        rows = torch.cat(reached) if reached else rows.new_zeros(0)
        return BackprojectionPlan(used, rows, torch.ones(rows.numel(), device=rows.device), None, writes)


@dataclass
class VertexFeatureAccumulator:
    """Running weighted sums of pixel features per vertex.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
        Mesh vertices (the coordinates the rasterizer used).
    faces : numpy.ndarray, shape (F, 3), int
    n_channels : int
        Feature channels C.
    mode, radius, radius_basis, max_neighbours
        See `Backprojector`.
    device : torch.device or str
        Where the sums live (the pixel features' device).
    dtype : torch.dtype
        Precision of the sums (float16 reproduces GeoLoRA's half-precision sums).

    Attributes
    ----------
    backprojector : Backprojector
        The mesh's, with these settings: `add_foreground` plans with it.
    """

    verts: np.ndarray
    faces: np.ndarray
    n_channels: int
    mode: str = "ball"
    radius: float | None = None
    device: torch.device | str = "cpu"
    radius_basis: str = "diagonal"
    max_neighbours: int | None = None
    dtype: torch.dtype = torch.float32
    sums: torch.Tensor = field(init=False)
    weights: torch.Tensor = field(init=False)
    backprojector: Backprojector = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.backprojector = Backprojector(
            self.verts, self.faces, self.mode, self.radius, self.device, self.radius_basis, self.max_neighbours
        )
        self.verts, self.radius = self.backprojector.verts, self.backprojector.radius
        self.sums = torch.zeros(len(self.verts), self.n_channels, dtype=self.dtype, device=self.device)
        self.weights = torch.zeros(len(self.verts), dtype=torch.float32, device=self.device)

    def add(self, pixel_features: torch.Tensor, pix_to_face: torch.Tensor, bary: torch.Tensor) -> None:
        """Accumulate one batch of views given whole feature images (any per-pixel values).

        The foreground rows of ``pixel_features`` go through `add_foreground`. The multi-view
        DINO path (`geofeat.multiview.pipeline`) never forms whole feature images; this is for
        other per-pixel values, such as unprojected surface points.

        Parameters
        ----------
        pixel_features : torch.Tensor, shape (N, H, W, C), float
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
        bary : torch.Tensor, shape (N, H, W, 3), float
        """
        if pixel_features.shape[:3] != pix_to_face.shape or pixel_features.shape[-1] != self.n_channels:
            raise RenderError(
                f"pixel features of shape {tuple(pixel_features.shape)} do not match fragments of shape "
                f"{tuple(pix_to_face.shape)} with {self.n_channels} channels."
            )
        foreground = (pix_to_face >= 0).reshape(-1).to(pixel_features.device)
        self.add_foreground(pixel_features.reshape(-1, self.n_channels)[foreground], pix_to_face, bary)

    def add_foreground(
        self, features: torch.Tensor, pix_to_face: torch.Tensor, bary: torch.Tensor, points: torch.Tensor | None = None
    ) -> None:
        """Accumulate one batch of views given the features of its foreground pixels only.

        `Backprojector.plan` followed by `add_planned` with the rows of the pixels that reach a vertex.

        Parameters
        ----------
        features : torch.Tensor, shape (M, C), float
            One row per foreground pixel (``pix_to_face >= 0``), in flat (view, row, column)
            order, as `foreground_pixels` lists them.
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
        bary : torch.Tensor, shape (N, H, W, 3), float
        points : torch.Tensor, shape (M, 3), optional
            Ball modes: the 3D point of each foreground pixel. Default: the surface point that
            the face index and barycentrics give.
        """
        n_foreground = int((pix_to_face >= 0).sum())
        if features.ndim != 2 or features.shape != (n_foreground, self.n_channels):
            raise RenderError(
                f"foreground features must have shape ({n_foreground}, {self.n_channels}) (one row per foreground pixel); "
                f"found {tuple(features.shape)}."
            )
        plan = self.backprojector.plan(pix_to_face, bary, points)
        features = features.to(self.sums.device)
        self.add_planned(plan, features if plan.pixels is None else features.index_select(0, plan.pixels))

    def add_planned(self, plan: BackprojectionPlan, features: torch.Tensor) -> None:
        """Add the features of a plan's pixels to the vertex sums, with no wait on the device.

        Parameters
        ----------
        plan : BackprojectionPlan
            From `Backprojector.plan`, for this mesh, mode and radius.
        features : torch.Tensor, shape (K, C), float
            One row per pixel of ``plan.pixels`` (per foreground pixel when it is None), on
            the accumulator's device.
        """
        if plan.last_writes:
            features = features.to(self.dtype)
            for write in plan.last_writes:
                self.sums = _LastWriteAdd.apply(self.sums, features, *write)
        elif plan.matrix is not None:
            self.sums += torch.sparse.mm(plan.matrix, features.to(torch.float32))
        self.weights.index_add_(0, plan.rows, plan.values)

    def result_tensor(self, fill: str = "nearest") -> tuple[torch.Tensor, torch.Tensor]:
        """Mean feature per vertex as tensors on the accumulator's device.

        Differentiable with respect to the pixel features that were added while gradients
        were enabled (GeoLoRA training).

        Parameters
        ----------
        fill : {"nearest", "zero"}
            Vertices seen in no view get the feature of the nearest seen vertex, or zeros.

        Returns
        -------
        features : torch.Tensor, shape (V, C), float32
        seen : torch.Tensor, shape (V,), bool
            Vertices that received at least one pixel.
        """
        if fill not in ("nearest", "zero"):
            raise RenderError(f"fill must be 'nearest' or 'zero'; found {fill!r}.")
        seen = self.weights > 0
        features = (self.sums / torch.where(seen, self.weights, 1.0)[:, None].to(self.sums.dtype)).float()  # unseen rows: 0
        if fill == "nearest" and bool(seen.any()) and not bool(seen.all()):
            seen_np = seen.cpu().numpy()
            _, nearest = cKDTree(self.verts[seen_np]).query(self.verts[~seen_np])
            source = torch.nonzero(seen).squeeze(1)[torch.as_tensor(nearest, device=seen.device)]
            index = torch.arange(len(self.verts), device=seen.device)
            index[~seen] = source
            features = features.index_select(0, index)
        return features, seen

    def result(self, fill: str = "nearest") -> tuple[np.ndarray, np.ndarray]:
        """Mean feature per vertex, as numpy arrays (see `result_tensor`).

        Returns
        -------
        features : numpy.ndarray, shape (V, C), float32
        seen : numpy.ndarray, shape (V,), bool
        """
        features, seen = self.result_tensor(fill)
        return features.detach().cpu().numpy().astype(np.float32, copy=False), seen.cpu().numpy()


def foreground_pixels(pix_to_face: torch.Tensor) -> torch.Tensor:
    """(view, row, column) of every foreground pixel, in flat order.

    Parameters
    ----------
    pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background

    Returns
    -------
    torch.Tensor, shape (M, 3), int64, on the device of ``pix_to_face``
    """
    return torch.nonzero(pix_to_face >= 0)


def shape_diameter(verts: np.ndarray) -> float:
    """Largest distance between two vertices, in mesh units.

    The farthest pair lies on the convex hull, so only hull vertices are compared (a flat or
    straight vertex set uses its hull in the plane or on the line it spans).

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)

    Returns
    -------
    float
        ``max_ij |v_i - v_j|``; 0 for fewer than two distinct vertices.
    """
    verts = np.asarray(verts, dtype=np.float64)
    centred = verts - verts.mean(axis=0)
    _, singular, axes = np.linalg.svd(centred, full_matrices=False)
    rank = int((singular > singular[0] * 1e-12).sum()) if singular.size and singular[0] > 0 else 0
    if rank == 0:
        return 0.0
    coords = centred @ axes[:rank].T  # the points in the space they span
    if rank == 1:
        return float(np.ptp(coords[:, 0]))
    try:
        candidates = verts[ConvexHull(coords).vertices]
    except QhullError:  # nearly flat or straight beyond the rank test: compare every point
        candidates = verts
    return float(pdist(candidates).max())


def _first_per_point(rows: torch.Tensor, cols: torch.Tensor, k: int, n_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep, for each point (``cols``), its ``k`` lowest vertex indices (``rows``): ball_query's first K."""
    order = torch.argsort(cols * n_vertices + rows)  # by point, then vertex
    rows, cols = rows[order], cols[order]
    _, counts = torch.unique_consecutive(cols, return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(cols.numel(), device=cols.device) - torch.repeat_interleave(starts, counts)
    keep = rank < k
    return rows[keep], cols[keep]


def _last_write_plan(rows: torch.Tensor, cols: torch.Tensor, n_points: int) -> tuple[torch.Tensor, ...]:
    """Index tensors for `_LastWriteAdd` from one view's (vertex, pixel) candidate pairs."""
    order = torch.argsort(rows * n_points + cols)  # by vertex, then pixel: the last of each vertex's run is its last pixel
    rows, cols = rows[order], cols[order]
    vertices, counts = torch.unique_consecutive(rows, return_counts=True)
    last = torch.cumsum(counts, 0) - 1
    return rows, cols, rows[last], cols[last], vertices, counts


class _LastWriteAdd(torch.autograd.Function):
    """``sums[rows] += features[cols]`` with repeated ``rows``, as torch computes it (see the module notes).

    Forward: each vertex in ``rows`` gets the feature of its last pixel. Backward, as the
    autograd of that indexed addition: every candidate pixel gets its vertex's gradient, and
    the incoming sums get their gradient times the vertex's number of candidates.
    """

    @staticmethod
    def forward(ctx, sums, features, rows, cols, winner_rows, winner_cols, vertices, counts):
        ctx.save_for_backward(rows, cols, vertices, counts)
        ctx.n_features = features.shape[0]
        out = sums.clone()
        out[winner_rows] = sums[winner_rows] + features[winner_cols]
        return out

    @staticmethod
    def backward(ctx, grad):
        rows, cols, vertices, counts = ctx.saved_tensors
        grad_sums = grad.clone()
        grad_sums[vertices] = grad[vertices] * counts[:, None].to(grad.dtype)
        grad_features = torch.zeros((ctx.n_features, grad.shape[1]), dtype=grad.dtype, device=grad.device)
        grad_features.index_add_(0, cols, grad.index_select(0, rows))
        return grad_sums, grad_features, None, None, None, None, None, None


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
