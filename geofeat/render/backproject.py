"""Back-projection of per-pixel features onto mesh vertices, streamed over batches of views.

Two modes:

* ``"ball"`` reproduces GeoLoRA and Diff3f: every foreground pixel is lifted to its 3D
  surface point and gives its feature to every vertex within ``radius`` (0.004 x the
  shape's bounding-box diagonal by default) of that point; a vertex takes the mean of what
  it received. The surface point is interpolated from the rasterizer's face index and
  perspective-correct barycentrics, which is the point that unprojecting the pixel by its
  depth gives, without the round trip through the camera.
* ``"face"`` gives each foreground pixel's feature to the three corners of its face,
  weighted by the barycentric coordinates.

Both are sparse products ``(V x M) @ (M x C)`` per batch of views, so memory grows with one
batch of pixels, never with the number of views, and no ``V x V`` or ``V x M`` dense
matrix is ever formed (neighbours come from a KD-tree).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from geofeat.errors import GeofeatError

BACKPROJECT_MODES = ("ball", "face")
#: Ball radius as a fraction of the bounding-box diagonal (GeoLoRA / Diff3f).
BALL_RADIUS_FRACTION = 0.004


class BackprojectError(GeofeatError, ValueError):
    """Bad input to back-projection (mode, shapes)."""


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
    mode : {"ball", "face"}
    radius : float, optional
        Ball radius in mesh units; default ``BALL_RADIUS_FRACTION`` x bounding-box diagonal.
    device : torch.device or str
        Where the sums live (the pixel features' device).
    """

    verts: np.ndarray
    faces: np.ndarray
    n_channels: int
    mode: str = "ball"
    radius: float | None = None
    device: torch.device | str = "cpu"
    sums: torch.Tensor = field(init=False)
    weights: torch.Tensor = field(init=False)

    def __post_init__(self) -> None:
        if self.mode not in BACKPROJECT_MODES:
            raise BackprojectError(f"backprojection mode must be one of {BACKPROJECT_MODES}; found {self.mode!r}.")
        self.verts = np.asarray(self.verts, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if self.radius is None:
            diagonal = float(np.linalg.norm(self.verts.max(axis=0) - self.verts.min(axis=0)))
            self.radius = BALL_RADIUS_FRACTION * diagonal
        self.sums = torch.zeros(len(self.verts), self.n_channels, dtype=torch.float32, device=self.device)
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
            raise BackprojectError(
                f"pixel features of shape {tuple(pixel_features.shape)} do not match fragments of shape "
                f"{tuple(pix_to_face.shape)} with {self.n_channels} channels."
            )
        foreground = (pix_to_face >= 0).reshape(-1).to(pixel_features.device)
        self.add_foreground(pixel_features.reshape(-1, self.n_channels)[foreground], pix_to_face, bary)

    def add_foreground(self, features: torch.Tensor, pix_to_face: torch.Tensor, bary: torch.Tensor) -> None:
        """Accumulate one batch of views given the features of its foreground pixels only.

        Parameters
        ----------
        features : torch.Tensor, shape (M, C), float
            One row per foreground pixel (``pix_to_face >= 0``), in flat (view, row, column)
            order, as `foreground_pixels` lists them.
        pix_to_face : torch.Tensor, shape (N, H, W), int64, -1 on background
        bary : torch.Tensor, shape (N, H, W, 3), float
        """
        pixels = torch.nonzero((pix_to_face >= 0).reshape(-1)).squeeze(1).cpu().numpy()
        if features.ndim != 2 or features.shape != (pixels.size, self.n_channels):
            raise BackprojectError(
                f"foreground features must have shape ({pixels.size}, {self.n_channels}) (one row per foreground pixel); "
                f"found {tuple(features.shape)}."
            )
        rows, local, values = self._entries(pixels, pix_to_face, bary)
        self._scatter(rows, local, values, features.to(self.device, torch.float32))

    def _entries(
        self, pixels: np.ndarray, pix_to_face: torch.Tensor, bary: torch.Tensor
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sparse (V, M) back-projection matrix of M foreground pixels: (vertex, pixel position in ``pixels``, weight)."""
        if pixels.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        face_ids = pix_to_face.reshape(-1)[pixels].cpu().numpy()
        weights_bary = bary.reshape(-1, 3)[pixels].cpu().numpy().astype(np.float64)  # (M, 3)
        if self.mode == "face":
            return self.faces[face_ids].ravel(), np.repeat(np.arange(pixels.size), 3), weights_bary.ravel()
        points = np.einsum("mk,mkd->md", weights_bary, self.verts[self.faces[face_ids]])  # surface points (M, 3)
        rows, local = _pairs_within(self.verts, points, self.radius)
        return rows, local, np.ones(rows.size)

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
            raise BackprojectError(f"fill must be 'nearest' or 'zero'; found {fill!r}.")
        seen = self.weights > 0
        features = self.sums / torch.where(seen, self.weights, 1.0)[:, None]  # unseen rows: 0 / 1 = 0
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


def _pairs_within(verts: np.ndarray, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """All (vertex, point) index pairs closer than ``radius``, as two int64 arrays."""
    neighbours = cKDTree(points).query_ball_point(verts, radius)
    counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(verts))
    rows = np.repeat(np.arange(len(verts), dtype=np.int64), counts)
    cols = np.fromiter((j for n in neighbours for j in n), dtype=np.int64, count=int(counts.sum()))
    return rows, cols
