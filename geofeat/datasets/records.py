"""The pair record every dataset loader returns, and the match record every head predicts for a pair."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from geofeat.geometry.surface_points import SurfacePoints
from geofeat.mesh import Mesh

PROTOCOLS = ("p2f", "p2p", "f2f")


@dataclass(frozen=True, eq=False)
class ShapePair:
    """One evaluation pair, matched from ``y`` to ``x``.

    Attributes
    ----------
    x : Mesh
        The target shape (the full shape in partial-to-full protocols), V_x vertices.
    y : Mesh
        The source shape (the partial one in P2F), V_y vertices.
    map_yx : numpy.ndarray, shape (V_y,), int64
        Ground truth: for each vertex of ``y`` its counterpart in ``x`` (0-based), ``-1``
        where it has none.
    overlap_x, overlap_y : numpy.ndarray of bool, shapes (V_x,) and (V_y,), or None
        Ground-truth overlap masks, where the dataset defines them.
    map_yx_sym : numpy.ndarray, shape (V_y,), int64, or None
        Chirality ground truth: for each vertex of ``y`` the left-right mirror image of its
        counterpart in ``x`` (``-1`` where undefined), where the data has it.
    protocol : {"p2f", "p2p", "f2f"}
        Which evaluation protocol applies.
    corr_x, corr_y : numpy.ndarray, shape (T,), int64, or None
        For datasets with a common template (FAUST_r, SCAPE_r): the vertex of ``x`` and of
        ``y`` at each of the T template points. The references evaluate geodesic errors at
        these points (``protocol="template"`` of `geofeat.evaluation.metrics.template_geodesic_errors`);
        ``map_yx`` is derived from them.
    corr_x_sym : numpy.ndarray, shape (T,), int64, or None
        The vertex of ``x`` at each point of the left-right mirrored template.
    error_scale : float or None
        The length, in the units of ``x``, that geodesic errors on ``x`` are divided by, where
        the benchmark fixes one other than ``sqrt(area(x))`` (BeCoS: the square root of the
        area of the full shape ``x`` was cut from, also when ``x`` is partial). None:
        ``sqrt(area(x))``.
    x_surface, y_surface : SurfacePoints, or None
        Where a shape that is a point cloud made from a triangle mesh (a depth scan) came
        from: for each of its points, a face and barycentric coordinates on that mesh.
        With ``x_surface``, geodesic errors and chirality are measured on the mesh of
        ``x_surface`` (each point of ``x`` stands for the corner of its face with the largest
        barycentric weight) and normalised by the square root of that mesh's area; without
        it, a point cloud ``x`` is measured with the heat method on its points. ``y_surface``
        records where the points of ``y`` came from; the metrics do not read it.
    """

    x: Mesh
    y: Mesh
    map_yx: np.ndarray
    overlap_x: np.ndarray | None = None
    overlap_y: np.ndarray | None = None
    map_yx_sym: np.ndarray | None = None
    protocol: str = "p2f"
    corr_x: np.ndarray | None = None
    corr_y: np.ndarray | None = None
    corr_x_sym: np.ndarray | None = None
    error_scale: float | None = None
    x_surface: SurfacePoints | None = None
    y_surface: SurfacePoints | None = None

    @property
    def name(self) -> str:
        """``"<y name>-><x name>"``."""
        return f"{self.y.name}->{self.x.name}"


class Match(NamedTuple):
    """A predicted correspondence from ``y`` to ``x`` of a `ShapePair`.

    Heads (``geofeat.adapters.heads``) return it; `geofeat.evaluation.evaluate_pair` scores it.

    Attributes
    ----------
    map_yx : numpy.ndarray, shape (V_y,), int64
        For every vertex of ``y`` a vertex of ``x``.
    overlap_y : numpy.ndarray, shape (V_y,), bool
        Vertices of ``y`` predicted to have a counterpart (all True for heads without overlap prediction).
    overlap_x : numpy.ndarray, shape (V_x,), bool, or None
        Vertices of ``x`` predicted to have a counterpart, where the head predicts it.
    overlap_prob_y : numpy.ndarray, shape (V_y,), float32, or None
    overlap_prob_x : numpy.ndarray, shape (V_x,), float32, or None
        The overlap probabilities behind the masks, from heads that predict them.
    """

    map_yx: np.ndarray
    overlap_y: np.ndarray
    overlap_x: np.ndarray | None = None
    overlap_prob_y: np.ndarray | None = None
    overlap_prob_x: np.ndarray | None = None
