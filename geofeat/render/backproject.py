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
  the ``reference`` presets. Each pixel's point looks for the first ``max_neighbours``
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
or ``V x M`` dense matrix is ever formed (neighbours come from a KD-tree).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.spatial.distance import pdist

from geofeat.checks import check_choice, check_integer
from geofeat.errors import RenderError

BACKPROJECT_MODES = ("ball", "face", "ball_last")
#: Ball radius as a fraction of the shape's size (GeoLoRA / Diff3f ``tolerance``).
BALL_RADIUS_FRACTION = 0.004
#: What the radius fraction multiplies: the bounding-box diagonal, or the largest vertex-to-vertex
#: distance (the diameter, as GeoLoRA and Diff3f compute it with ``cdist(...).max()``).
RADIUS_BASES = ("diagonal", "diameter")


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
    mode : {"ball", "face", "ball_last"}
    radius : float, optional
        Ball radius in mesh units; default ``BALL_RADIUS_FRACTION`` x the size that
        ``radius_basis`` names.
    device : torch.device or str
        Where the sums live (the pixel features' device).
    radius_basis : {"diagonal", "diameter"}
        Size that the default radius is a fraction of: the bounding-box diagonal, or the
        largest distance between two vertices (`shape_diameter`).
    max_neighbours : int, optional
        ``"ball_last"`` only: each pixel reaches at most this many vertices, the first ones in
        vertex order (pytorch3d ``ball_query``'s K); None: all within the radius.
    dtype : torch.dtype
        Precision of the sums (float16 reproduces GeoLoRA's half-precision sums).
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

    def __post_init__(self) -> None:
        if self.mode not in BACKPROJECT_MODES:
            raise RenderError(f"backprojection mode must be one of {BACKPROJECT_MODES}; found {self.mode!r}.")
        self.radius_basis = check_choice(self.radius_basis, "radius_basis", RADIUS_BASES, error=RenderError)
        if self.max_neighbours is not None:
            self.max_neighbours = check_integer(self.max_neighbours, "max_neighbours", low=1, error=RenderError)
        self.verts = np.asarray(self.verts, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if self.radius is None:
            if self.radius_basis == "diameter":
                size = shape_diameter(self.verts)
            else:
                size = float(np.linalg.norm(self.verts.max(axis=0) - self.verts.min(axis=0)))
            self.radius = BALL_RADIUS_FRACTION * size
        self.sums = torch.zeros(len(self.verts), self.n_channels, dtype=self.dtype, device=self.device)
        self.weights = torch.zeros(len(self.verts), dtype=torch.float32, device=self.device)

    def add(self, pixel_features: torch.Tensor, pix_to_face: torch.Tensor, bary: torch.Tensor) -> None:
        """Accumulate one batch of views given whole feature images (any per-pixel values).

        The foreground rows of ``pixel_features`` go through `add_foreground`. The multi-view
        DINO path (`geofeat.render.multiview`) never forms whole feature images; this is for
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
        pixels = torch.nonzero((pix_to_face >= 0).reshape(-1)).squeeze(1).cpu().numpy()
        if features.ndim != 2 or features.shape != (pixels.size, self.n_channels):
            raise RenderError(
                f"foreground features must have shape ({pixels.size}, {self.n_channels}) (one row per foreground pixel); "
                f"found {tuple(features.shape)}."
            )
        if points is not None and tuple(points.shape) != (pixels.size, 3):
            raise RenderError(
                f"points must have shape ({pixels.size}, 3), one per foreground pixel; found {tuple(points.shape)}."
            )
        if self.mode == "ball_last":
            views = pixels // (pix_to_face.shape[1] * pix_to_face.shape[2])
            self._add_last(features.to(self.device, self.dtype), views, self._points(pixels, pix_to_face, bary, points))
            return
        rows, local, values = self._entries(pixels, pix_to_face, bary, points)
        self._scatter(rows, local, values, features.to(self.device, torch.float32))

    def _points(
        self, pixels: np.ndarray, pix_to_face: torch.Tensor, bary: torch.Tensor, points: torch.Tensor | None
    ) -> np.ndarray:
        """The 3D point of each foreground pixel, (M, 3) float64: as given, or the surface point of its face."""
        if points is not None:
            return points.detach().to("cpu", torch.float64).numpy()
        face_ids = pix_to_face.reshape(-1)[pixels].cpu().numpy()
        weights_bary = bary.reshape(-1, 3)[pixels].cpu().numpy().astype(np.float64)  # (M, 3)
        return np.einsum("mk,mkd->md", weights_bary, self.verts[self.faces[face_ids]])

    def _entries(
        self, pixels: np.ndarray, pix_to_face: torch.Tensor, bary: torch.Tensor, points: torch.Tensor | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sparse (V, M) back-projection matrix of M foreground pixels: (vertex, pixel position in ``pixels``, weight)."""
        if pixels.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        if self.mode == "face":
            face_ids = pix_to_face.reshape(-1)[pixels].cpu().numpy()
            weights_bary = bary.reshape(-1, 3)[pixels].cpu().numpy().astype(np.float64)  # (M, 3)
            return self.faces[face_ids].ravel(), np.repeat(np.arange(pixels.size), 3), weights_bary.ravel()
        rows, local = _pairs_within(self.verts, self._points(pixels, pix_to_face, bary, points), self.radius)
        return rows, local, np.ones(rows.size)

    def _add_last(self, features: torch.Tensor, views: np.ndarray, points: np.ndarray) -> None:
        """``"ball_last"``: one view after the other, each vertex in reach takes the last candidate pixel's feature."""
        rows, local = _pairs_within(self.verts, points, self.radius)
        if self.max_neighbours is not None:
            rows, local = _first_per_point(rows, local, self.max_neighbours)
        for view in np.unique(views[local]) if local.size else ():
            in_view = views[local] == view
            self.sums = _LastWriteAdd.apply(self.sums, features, *_last_write_plan(rows[in_view], local[in_view], self.device))
            touched = torch.as_tensor(np.unique(rows[in_view]), device=self.device)
            self.weights.index_add_(0, touched, torch.ones(touched.numel(), device=self.device))

    def _scatter(self, rows: np.ndarray, cols: np.ndarray, values: np.ndarray, features: torch.Tensor) -> None:
        """``sums += S @ features`` and ``weights += S @ 1`` for the sparse (V, P) matrix S given by its entries."""
        if rows.size == 0:
            return
        index = torch.as_tensor(np.stack([rows, cols]), dtype=torch.int64, device=self.device)
        values = torch.as_tensor(values, dtype=torch.float32, device=self.device)
        matrix = torch.sparse_coo_tensor(index, values, (len(self.verts), features.shape[0]), check_invariants=False)
        with warnings.catch_warnings():  # "sparse CSR support is in beta": CSR products are the fast path here
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            self.sums += torch.sparse.mm(matrix.coalesce().to_sparse_csr(), features)
        self.weights.index_add_(0, index[0], values)

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


def _first_per_point(rows: np.ndarray, cols: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep, for each point (``cols``), its ``k`` lowest vertex indices (``rows``): ball_query's first K."""
    order = np.lexsort((rows, cols))
    rows, cols = rows[order], cols[order]
    starts = np.r_[0, np.flatnonzero(np.diff(cols)) + 1]
    rank = np.arange(cols.size) - np.repeat(starts, np.diff(np.r_[starts, cols.size]))
    keep = rank < k
    return rows[keep], cols[keep]


def _last_write_plan(rows: np.ndarray, cols: np.ndarray, device) -> tuple[torch.Tensor, ...]:
    """Index tensors for `_LastWriteAdd` from one view's (vertex, pixel) candidate pairs."""
    order = np.lexsort((cols, rows))  # by vertex, then pixel: the last of each vertex's run is its last pixel
    rows, cols = rows[order], cols[order]
    last = np.r_[rows[1:] != rows[:-1], True]
    vertices, counts = np.unique(rows, return_counts=True)

    def t(a):
        return torch.as_tensor(a, dtype=torch.int64, device=device)

    return t(rows), t(cols), t(rows[last]), t(cols[last]), t(vertices), t(counts)


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


def _pairs_within(verts: np.ndarray, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All (vertex, point) index pairs closer than ``radius``, as two int64 arrays."""
    neighbours = cKDTree(points).query_ball_point(verts, radius)
    counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(verts))
    rows = np.repeat(np.arange(len(verts), dtype=np.int64), counts)
    cols = np.fromiter((j for n in neighbours for j in n), dtype=np.int64, count=int(counts.sum()))
    return rows, cols
