"""Which shape's geodesic distances score a pair, and how the points of ``x`` become its vertices.

Usually that shape is the target ``x`` itself, a triangle mesh or a point cloud. A point
cloud ``x`` made from a mesh (``ShapePair.x_surface``: a depth scan, a surface sample) is
scored on that mesh instead: each point of ``x`` stands for the corner of its face with the
largest barycentric weight (`geofeat.geometry.surface_points.SurfacePoints.nearest_corner`),
so that a scan is measured with the exact geodesics of the surface it samples.
"""

from __future__ import annotations

import numpy as np

from geofeat.datasets.records import ShapePair
from geofeat.errors import MetricError
from geofeat.mesh import Mesh

__all__ = ["check_surface", "evaluation_target", "points_on_target"]


def evaluation_target(pair: ShapePair) -> Mesh:
    """The shape whose geodesic distances score a pair: the mesh of ``pair.x_surface`` when given, else ``pair.x``."""
    return pair.x if pair.x_surface is None else pair.x_surface.mesh


def check_surface(pair: ShapePair) -> None:
    """`MetricError` unless ``pair.x_surface`` (when given) has one surface point per point of ``x``."""
    if pair.x_surface is not None and len(pair.x_surface) != pair.x.n_vertices:
        raise MetricError(
            f"pair {pair.name}: x_surface must give one surface point per point of x ({pair.x.n_vertices}); "
            f"found {len(pair.x_surface)}."
        )


def points_on_target(pair: ShapePair, indices, name: str) -> np.ndarray | None:
    """Indices of points of ``x`` (``-1``: none) as vertices of the pair's `evaluation_target`.

    Parameters
    ----------
    pair : ShapePair
    indices : array_like of int, shape (N,), or None
        Points of ``x`` (a predicted or true map, template points), ``-1`` where none.
    name : str
        What they are, for messages.

    Returns
    -------
    numpy.ndarray, shape (N,), int64, or None
        Without ``pair.x_surface``: ``indices`` as given (the metrics check them). With it:
        the nearest corner of each point's face on the mesh, ``-1`` kept. None for None.

    Raises
    ------
    MetricError
        With ``x_surface``: indices that are not a 1-D integer array in ``[-1, V_x)``.
    """
    if indices is None or pair.x_surface is None:
        return indices
    values = np.asarray(indices)
    if values.ndim != 1 or (values.size and values.dtype.kind not in "iu"):
        raise MetricError(f"pair {pair.name}: {name} must be a 1-D integer array; found {values.dtype} {values.shape}.")
    n_x = pair.x.n_vertices
    if values.size and (values.min() < -1 or values.max() >= n_x):
        raise MetricError(
            f"pair {pair.name}: {name} must hold 0-based indices of the points of x in [0, {n_x - 1}], or -1; "
            f"found range [{values.min()}, {values.max()}]."
        )
    corners = pair.x_surface.nearest_corner
    return np.where(values >= 0, corners[np.maximum(values, 0)], -1).astype(np.int64)
