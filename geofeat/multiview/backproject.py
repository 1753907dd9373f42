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
no search structure built per view (`geofeat.multiview.neighbours`): on a mesh, a pixel's
point lies on (or, for points lifted from depth, near) the face the rasterizer gave it, so
each face's candidate vertices are listed once (`FaceCandidates`); on a point cloud the
points are sorted into a grid of cells two radii wide (`PointGrid`). Either gives exactly
the set of (vertex, pixel) pairs within the radius, as a KD-tree query would.

Point clouds
------------
A point cloud (``faces`` None) is drawn by the point renderer (`geofeat.render.points`),
which gives each pixel its nearest point instead of a face and barycentrics. ``"face"``
gives the pixel's feature whole to that point (the point is the pixel's only primitive).
The ball modes need each pixel's 3D point: where its ray meets its point's disc
(`geofeat.render.points.splat_points`), or lifted from depth on the corner-aligned grid.
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
from geofeat.multiview.neighbours import FaceCandidates, PointGrid
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
    """How pixels reach the vertices of one mesh or point cloud: the mode, the ball radius, the neighbour search.

    Makes a `BackprojectionPlan` per batch of views from its fragments alone (`plan`); a
    `VertexFeatureAccumulator` then adds the pixels' features along it.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
        Mesh vertices or cloud points (the coordinates the renderer used).
    faces : numpy.ndarray, shape (F, 3), int, or None
        None for a point cloud: its fragments give each pixel a point, not a face.
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
    faces: np.ndarray | None
    mode: str = "ball"
    radius: float | None = None
    device: torch.device | str = "cpu"
    radius_basis: str = "diagonal"
    max_neighbours: int | None = None
    _faces_tensor: torch.Tensor | None = field(init=False, default=None, repr=False)
    _face_candidates: FaceCandidates | None = field(init=False, default=None, repr=False)
    _point_grid: PointGrid | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        if self.mode not in BACKPROJECT_MODES:
            raise RenderError(f"backprojection mode must be one of {BACKPROJECT_MODES}; found {self.mode!r}.")
        self.radius_basis = check_choice(self.radius_basis, "radius_basis", RADIUS_BASES, error=RenderError)
        if self.max_neighbours is not None:
            self.max_neighbours = check_integer(self.max_neighbours, "max_neighbours", low=1, error=RenderError)
        self.device = torch.device(self.device)
        self.verts = np.asarray(self.verts, dtype=np.float64)
        self.faces = None if self.faces is None else np.asarray(self.faces, dtype=np.int64)
        if self.radius is None:
            if self.radius_basis == "diameter":
                size = shape_diameter(self.verts)
            else:
                size = float(np.linalg.norm(self.verts.max(axis=0) - self.verts.min(axis=0)))
            self.radius = BALL_RADIUS_FRACTION * size

    def plan(
        self, pix_to_face: torch.Tensor, bary: torch.Tensor | None, points: torch.Tensor | None = None
    ) -> BackprojectionPlan:
        """Which foreground pixels of a batch of views feed which vertices: the geometry of `add_planned`.

        It depends on the fragments only, not on the features, so it can be made before the
        features exist (on another thread, while the backbone encodes other views); the waits
        on the device that listing the pairs needs all happen here.

        Parameters
        ----------
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
            The face of each pixel; for a point cloud its point (``pix_to_point``).
        bary : torch.Tensor, shape (N, H, W, 3), float, or None
            The barycentrics of each pixel in its face; None for a point cloud.
        points : torch.Tensor, shape (M, 3), optional
            Ball modes: the 3D point of each of the M foreground pixels (flat order).
            Default on a mesh: the surface point that the face index and barycentrics give;
            required on a point cloud (`geofeat.render.points.splat_points`).

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
            rows, cols, values = self._face_weights(face_ids, bary, pixels)
            return BackprojectionPlan(None, rows, values, _sparse_rows(rows, cols, values, (n_vertices, pixels.numel())))
        if self.faces is None:
            if points is None:
                raise RenderError(
                    "a point cloud's pixels have no barycentrics: give the ball modes each pixel's 3D point "
                    "(geofeat.render.points.splat_points), or back-project with mode='face'."
                )
            rows, cols = self._grid(device).pairs_within(points, self.radius)
        else:
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

    def _face_weights(
        self, face_ids: torch.Tensor, bary: torch.Tensor | None, pixels: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``"face"``: (vertex, pixel, weight) triples: a face's corners by barycentrics, or a cloud's point whole."""
        cols = torch.arange(pixels.numel(), device=pixels.device)
        if self.faces is None:
            return face_ids, cols, torch.ones(face_ids.numel(), device=pixels.device)
        if bary is None:
            raise RenderError("back-projection by face needs the barycentrics of the mesh's fragments; found None.")
        values = bary.reshape(-1, 3).to(pixels.device)[pixels].float().reshape(-1)  # (3 M,)
        return self._faces_on(pixels.device)[face_ids].reshape(-1), cols.repeat_interleave(3), values

    def _grid(self, device: torch.device) -> PointGrid:
        """A point cloud's grid of cells for the ball, on ``device`` (built once, on first use)."""
        if self._point_grid is None or self._point_grid.device != device:
            self._point_grid = PointGrid(self.verts, self.radius, device)
        return self._point_grid

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
        Mesh vertices or cloud points (the coordinates the renderer used).
    faces : numpy.ndarray, shape (F, 3), int, or None
        None for a point cloud (see `Backprojector`).
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
    faces: np.ndarray | None
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

    def add(self, pixel_features: torch.Tensor, pix_to_face: torch.Tensor, bary: torch.Tensor | None) -> None:
        """Accumulate one batch of views given whole feature images (any per-pixel values).

        The foreground rows of ``pixel_features`` go through `add_foreground`. The multi-view
        DINO path (`geofeat.multiview.pipeline`) never forms whole feature images; this is for
        other per-pixel values, such as unprojected surface points.

        Parameters
        ----------
        pixel_features : torch.Tensor, shape (N, H, W, C), float
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
            The face of each pixel; for a point cloud its point.
        bary : torch.Tensor, shape (N, H, W, 3), float, or None
            None for a point cloud (which then back-projects by ``"face"`` only: the ball
            modes need each pixel's point, given to `add_foreground`).
        """
        if pixel_features.shape[:3] != pix_to_face.shape or pixel_features.shape[-1] != self.n_channels:
            raise RenderError(
                f"pixel features of shape {tuple(pixel_features.shape)} do not match fragments of shape "
                f"{tuple(pix_to_face.shape)} with {self.n_channels} channels."
            )
        foreground = (pix_to_face >= 0).reshape(-1).to(pixel_features.device)
        self.add_foreground(pixel_features.reshape(-1, self.n_channels)[foreground], pix_to_face, bary)

    def add_foreground(
        self,
        features: torch.Tensor,
        pix_to_face: torch.Tensor,
        bary: torch.Tensor | None,
        points: torch.Tensor | None = None,
    ) -> None:
        """Accumulate one batch of views given the features of its foreground pixels only.

        `Backprojector.plan` followed by `add_planned` with the rows of the pixels that reach a vertex.

        Parameters
        ----------
        features : torch.Tensor, shape (M, C), float
            One row per foreground pixel (``pix_to_face >= 0``), in flat (view, row, column)
            order, as `foreground_pixels` lists them.
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
            The face of each pixel; for a point cloud its point.
        bary : torch.Tensor, shape (N, H, W, 3), float, or None
            None for a point cloud.
        points : torch.Tensor, shape (M, 3), optional
            Ball modes: the 3D point of each foreground pixel. Default on a mesh: the surface
            point that the face index and barycentrics give; required on a point cloud.
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
