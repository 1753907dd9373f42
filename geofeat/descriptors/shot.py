"""SHOT: Signature of Histograms of OrienTations (Tombari, Salti and Di Stefano 2010), compiled with numba.

The histogram follows the reference implementation that DeepShapeMatchingKit calls (pyshot, a
wrapper of the original C++ code) value for value, its quirks included, so that features
computed here can replace the recorded ones; `SHOT` lists each quirk. Neighbourhoods come
from a grid of cells as wide as the radius; each vertex is described on its own, by threads
working on chunks of vertices, so memory beyond the output does not grow with the mesh.

>>> import geofeat                                                      # doctest: +SKIP
>>> feats = geofeat.compute(mesh, "shot", radius=0.3)                   # (V, 192)  # doctest: +SKIP
>>> feats = geofeat.compute(mesh, "shot", recipe="dsmk")                # DeepShapeMatchingKit's  # doctest: +SKIP
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from geofeat.checks import check_boolean, check_choice, check_integer, check_number
from geofeat.descriptors.base import Descriptor
from geofeat.errors import DescriptorError
from geofeat.geometry.normals import vertex_normals
from geofeat.mesh import Mesh
from geofeat.runtime.progress import progress_bar

log = logging.getLogger(__name__)

__all__ = ["CLOUD_NORMALS", "QUERIES_PER_CHUNK", "RADIUS_UNITS", "SHOT", "SHOT_RECIPES", "ShotFrames", "shot_descriptors"]

#: How ``radius`` is read: in the mesh's units, or as a fraction of sqrt(surface area) or of the
#: bounding-box diagonal (the "diameter").
RADIUS_UNITS = ("absolute", "sqrt_area", "diameter")
#: Normals of a point cloud: estimated (`geofeat.geometry.normals.vertex_normals`) or zero (pyshot's).
CLOUD_NORMALS = ("estimate", "zero")
#: Vertices one thread describes per task.
QUERIES_PER_CHUNK = 512
#: Bits of each integer coordinate in the keys of the neighbour-search grid.
_GRID_BITS = 21
#: The reference needs this many neighbours for a local reference frame, whatever ``min_neighbors`` says.
MIN_LRF_NEIGHBORS = 5
#: Neighbours closer than this squared distance (input units) are counted but not binned (the reference's rule).
SKIP_SQUARED_DISTANCE = 1e-6
#: Local coordinates smaller than this in absolute value are set to zero (the reference's rule).
ZERO_COORDINATE = 1e-30

#: The parameters each recipe gives where they are not given: ``"dsmk"``, DeepShapeMatchingKit's
#: call of pyshot (``utils/shot_util.py``), radius in the mesh's units.
SHOT_RECIPES: dict[str, dict] = {
    "dsmk": {
        "radius": 0.3,
        "min_neighbors": 3,
        "n_bins": 5,
        "double_volumes_sectors": True,
        "use_interpolation": True,
        "use_normalization": True,
    },
}

# The reference's angle constants are float32 literals, promoted to double where used.
_PI_4 = float(np.float32(np.pi / 4))
_PI_2 = float(np.float32(np.pi / 2))
_PI_3_4 = float(np.float32(3 * np.pi / 4))
_PI_7_8 = float(np.float32(7 * np.pi / 8))


@dataclass(frozen=True)
class ShotFrames:
    """Local reference frames of a set of query vertices.

    Attributes
    ----------
    frames : numpy.ndarray, shape (Q, 3, 3), float64
        Rows X, Y, Z of each frame (X: largest-variance axis, Z: smallest, Y = Z x X).
    n_neighbors : numpy.ndarray, shape (Q,), int64
        Neighbours within the radius (the query excluded).
    sign_tie : numpy.ndarray, shape (Q,), bool
        The sign of X or Z was a tie (as many neighbours on each side): the eigensolver's
        arbitrary sign was kept, so another implementation may flip that axis.
    """

    frames: np.ndarray
    n_neighbors: np.ndarray
    sign_tie: np.ndarray


@njit(cache=True, nogil=True)
def _sector(x: float, y: float, phi: float) -> int:
    """Azimuth sector of 45 degrees of the local offset (x, y): k covers (-180 + 45 k, -180 + 45 (k + 1)] degrees.

    ``phi = atan2(y, x)`` decides away from the boundaries; on them (|x| = |y|, x = 0 or y = 0)
    the signs and |x| against |y| decide exactly; x = y = 0 gives 0.
    """
    ax, ay = abs(x), abs(y)
    if ax != ay and x != 0.0 and y != 0.0:
        return min(max(int(np.ceil((phi + np.pi) / (np.pi / 4))) - 1, 0), 7)
    if x == 0.0 and y == 0.0:
        return 0
    if y > 0.0:
        if x > 0.0 and ay <= ax:
            return 4
        if x >= 0.0:
            return 5
        return 6 if ay >= ax else 7
    if y < 0.0:
        if x < 0.0 and ay <= ax:
            return 0
        if x <= 0.0:
            return 1
        return 2 if ay >= ax else 3
    return 7 if x < 0.0 else 3  # y == 0


def _grid(verts: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The vertices sorted by the cell of a grid whose side is at least ``radius``.

    A cell is keyed ``(i << 42) | (j << 21) | k`` from its integer coordinates; a neighbour
    within the radius lies in one of the 27 cells around the query's. The side grows past the
    radius where the shape spans more than ``2**20`` radii, so that the keys fit.

    Returns
    -------
    keys : numpy.ndarray, shape (V,), int64
        Sorted cell keys.
    order : numpy.ndarray, shape (V,), int64
        Vertex index of each sorted entry.
    sorted_verts : numpy.ndarray, shape (V, 3), float64
        ``verts[order]``.
    origin : numpy.ndarray, shape (3,), float64
        Corner of the grid.
    cell : float
        Side of a cell.
    """
    origin = verts.min(axis=0)
    extent = float((verts.max(axis=0) - origin).max())
    # a little above the radius: the float32 threshold on squared distances can exceed radius²
    cell = max(radius * (1.0 + 1e-6), extent / 2 ** (_GRID_BITS - 1))
    ijk = np.floor((verts - origin) / cell).astype(np.int64)
    keys = (ijk[:, 0] << (2 * _GRID_BITS)) | (ijk[:, 1] << _GRID_BITS) | ijk[:, 2]
    order = np.argsort(keys, kind="stable")
    return keys[order], order, np.ascontiguousarray(verts[order]), origin, cell


@njit(cache=True, nogil=True)
def _neighbours(query, verts, keys, order, sorted_verts, origin, cell, threshold):
    """Neighbours of vertex ``query`` with squared distance < ``threshold``, the query removed as the reference does.

    The reference sorts a query's neighbours by (distance, index) and drops the first entry
    only when it is the query itself: a coincident duplicate of lower index keeps the query
    in its own list.

    Returns
    -------
    index : numpy.ndarray, shape (N,), int64
        Vertex indices of the neighbours.
    offset : numpy.ndarray, shape (N, 3), float64
        Their offsets from the query.
    squared : numpy.ndarray, shape (N,), float64
        Their squared distances.
    """
    p = verts[query]
    ci = int(np.floor((p[0] - origin[0]) / cell))
    cj = int(np.floor((p[1] - origin[1]) / cell))
    ck = int(np.floor((p[2] - origin[2]) / cell))
    spans = np.zeros((9, 2), dtype=np.int64)
    for a in range(3):
        for b in range(3):
            i, j = ci + a - 1, cj + b - 1
            if i < 0 or j < 0:
                continue
            base = (i << (2 * _GRID_BITS)) | (j << _GRID_BITS)
            spans[3 * a + b, 0] = np.searchsorted(keys, base | max(ck - 1, 0))
            spans[3 * a + b, 1] = np.searchsorted(keys, base | (ck + 1), side="right")
    count = 0
    lower_twin = False
    for s in range(9):
        for e in range(spans[s, 0], spans[s, 1]):
            dx, dy, dz = sorted_verts[e, 0] - p[0], sorted_verts[e, 1] - p[1], sorted_verts[e, 2] - p[2]
            sq = dx * dx + dy * dy + dz * dz
            if sq < threshold:
                count += 1
                lower_twin |= sq == 0.0 and order[e] < query
    n = count if lower_twin else count - 1
    index = np.empty(n, dtype=np.int64)
    offset = np.empty((n, 3))
    squared = np.empty(n)
    m = 0
    for s in range(9):
        for e in range(spans[s, 0], spans[s, 1]):
            if order[e] == query and not lower_twin:
                continue
            dx, dy, dz = sorted_verts[e, 0] - p[0], sorted_verts[e, 1] - p[1], sorted_verts[e, 2] - p[2]
            sq = dx * dx + dy * dy + dz * dz
            if sq < threshold:
                index[m] = order[e]
                offset[m, 0], offset[m, 1], offset[m, 2] = dx, dy, dz
                squared[m] = sq
                m += 1
    return index, offset, squared


@njit(cache=True, nogil=True)
def _frame(offset, squared, radius, flip):
    """Local reference frame from the neighbours' offsets (N, 3) and squared distances (N,).

    ``flip`` turns axes round after the sign rule: bit 0 X, bit 1 Z (Y follows).

    Returns
    -------
    frame : numpy.ndarray, shape (3, 3)
        Rows X, Y, Z; the identity with fewer than `MIN_LRF_NEIGHBORS` neighbours.
    local : numpy.ndarray, shape (N, 3)
        The offsets in the frame, ``(q . X, q . Y, q . Z)``.
    tie : bool
        The sign of X or Z was a tie (as many neighbours on each side).
    """
    n = len(squared)
    cov = np.eye(3)
    if n >= MIN_LRF_NEIGHBORS:
        cov[:] = 0.0
        total = 0.0
        for p in range(n):
            w = radius - squared[p]  # the reference weighs by R - d² (squared distance)
            total += w
            for a in range(3):
                for b in range(a, 3):
                    cov[a, b] += offset[p, a] * w * offset[p, b]
        for a in range(3):
            for b in range(a, 3):
                cov[a, b] /= total
                cov[b, a] = cov[a, b]
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    frame = np.zeros((3, 3))
    frame[0], frame[2] = vecs[:, 2], vecs[:, 0]
    local = np.empty((n, 3))
    tie = False
    for bit, axis in ((1, 0), (2, 2)):
        # the axis points to the side with more neighbours (strictly positive ones; a tie keeps the sign)
        positive = 0
        for p in range(n):
            local[p, axis] = offset[p, 0] * frame[axis, 0] + offset[p, 1] * frame[axis, 1] + offset[p, 2] * frame[axis, 2]
            positive += local[p, axis] > 0.0
        tie |= 2 * positive == n
        if (positive < n - positive) != bool(flip & bit):
            frame[axis] = -frame[axis]
            local[:, axis] = -local[:, axis]
    frame[1] = np.cross(frame[2], frame[0])
    for p in range(n):
        local[p, 1] = offset[p, 0] * frame[1, 0] + offset[p, 1] * frame[1, 1] + offset[p, 2] * frame[1, 2]
    return frame, local, tie and n >= MIN_LRF_NEIGHBORS


@njit(cache=True, nogil=True)
def _histogram(hist, local, squared, cosines, radius, n_bins, double_volumes, interpolate):
    """Add the neighbours' histogram to ``hist`` (n_volumes * (n_bins + 1),) and return how many were binned.

    With interpolation every binned neighbour adds ``1 - |s|`` of each of its four
    interpolation offsets ``s`` (cosine, radial, elevation, azimuth) to its own cell and
    ``|s|`` (or nothing, on the far side of a bin centre) to the neighbouring cell of that
    offset, which is the reference's sum written without its branches.
    """
    n_volumes = 32 if double_volumes else 16
    width = n_bins + 1
    wrap = n_volumes - 4  # the reference's azimuth neighbour wraps modulo n_volumes - 4
    binned = 0
    for p in range(len(squared)):
        if squared[p] < SKIP_SQUARED_DISTANCE:
            continue
        binned += 1
        x, y, z = local[p, 0], local[p, 1], local[p, 2]
        x = 0.0 if abs(x) < ZERO_COORDINATE else x
        y = 0.0 if abs(y) < ZERO_COORDINATE else y
        z = 0.0 if abs(z) < ZERO_COORDINATE else z
        dist = np.sqrt(squared[p])
        phi = np.arctan2(y, x)
        sector = _sector(x, y, phi)
        if not double_volumes:
            sector //= 2
        outer = dist > radius / 2
        volume = 4 * sector + 2 * outer + (z > 0.0)
        t = (1.0 + cosines[p]) * (n_bins / 2.0)
        b = int(np.floor(t + 0.5))
        own = volume * width + b
        if not interpolate:
            hist[own] += 1.0
            continue
        # cosine: the share goes to the next bin modulo n_bins (bin n_bins - 1 wraps to 0)
        frac = t - b
        cos_share = abs(frac)
        cos_cell = volume * width + (b + (1 if frac > 0 else n_bins - 1)) % n_bins
        # radial: offset from the centre of the shell (R/4 or 3R/4), in units of R/2
        radial = (dist - (3 * radius / 4 if outer else radius / 4)) / (radius / 2)
        radial_share = max(-radial if outer else radial, 0.0)
        radial_cell = own + (-2 * width if outer else 2 * width)
        # elevation: offset from 45 or 135 degrees, in units of 90 degrees
        alpha = np.arccos(min(max(z / dist, -1.0), 1.0))
        lower = alpha > _PI_2 or (abs(alpha - _PI_2) < 1e-6 and z <= 0.0)
        elevation = (alpha - (_PI_3_4 if lower else _PI_4)) / _PI_2
        elevation_share = max(-elevation if lower else elevation, 0.0)
        elevation_cell = own + (width if lower else -width)
        # azimuth: offset from the sector centre
        if double_volumes:
            azimuth = min(max((phi - (-_PI_7_8 + _PI_4 * sector)) / _PI_4, -0.5), 0.5)
        else:
            azimuth = min(max((phi - (-_PI_3_4 + 2 * _PI_4 * sector)) / (2 * _PI_4), -0.5), 0.5)
        has_azimuth = x != 0.0 or y != 0.0
        if not has_azimuth:
            azimuth = 0.0
        azimuth_cell = ((volume + 4) % wrap if azimuth > 0 else (volume - 4 + wrap) % wrap) * width + b
        hist[own] += (3.0 + has_azimuth) - cos_share - abs(radial) - abs(elevation) - abs(azimuth)
        hist[cos_cell] += cos_share
        hist[radial_cell] += radial_share
        hist[elevation_cell] += elevation_share
        hist[azimuth_cell] += abs(azimuth)
    return binned


@njit(cache=True, nogil=True)
def _describe_rows(
    start,
    stop,
    queries,
    verts,
    normals,
    grid,
    radius,
    threshold,
    min_count,
    n_bins,
    double_volumes,
    interpolate,
    normalize,
    flip_axes,
    features,
    frames,
    n_neighbors,
    sign_tie,
    few,
    nothing,
):
    """Fill rows ``start:stop`` of the outputs (see `shot_descriptors`) for ``queries[start:stop]``."""
    keys, order, sorted_verts, origin, cell = grid
    for row in range(start, stop):
        query = queries[row]
        index, offset, squared = _neighbours(query, verts, keys, order, sorted_verts, origin, cell, threshold)
        frame, local, tie = _frame(offset, squared, radius, flip_axes[row])
        n = len(squared)
        frames[row] = frame
        n_neighbors[row] = n
        few[row] = n < min_count
        if few[row]:
            continue
        sign_tie[row] = tie
        cosines = np.empty(n)
        for p in range(n):
            c = frame[2, 0] * normals[index[p], 0] + frame[2, 1] * normals[index[p], 1] + frame[2, 2] * normals[index[p], 2]
            cosines[p] = min(max(c, -1.0), 1.0)
        hist = np.zeros(features.shape[1])  # summed in float64, stored in the output's precision
        if _histogram(hist, local, squared, cosines, radius, n_bins, double_volumes, interpolate) == 0:
            nothing[row] = True
            continue
        if normalize:
            norm = np.sqrt(np.sum(hist * hist))
            if norm > 0:
                hist /= norm
        features[row] = hist


def _check_arrays(verts: np.ndarray, normals: np.ndarray, queries: np.ndarray, flip_axes: np.ndarray | None) -> None:
    """`DescriptorError` unless the arrays fit together (the compiled kernels do not check indices)."""
    if verts.ndim != 2 or verts.shape[1] != 3 or normals.shape != verts.shape:
        raise DescriptorError(f"shot: verts and normals must both have shape (V, 3); found {verts.shape} and {normals.shape}.")
    if queries.ndim != 1 or (len(queries) and (queries.min() < 0 or queries.max() >= len(verts))):
        raise DescriptorError(f"shot: queries must be vertex indices in [0, {len(verts)}), shape (Q,).")
    if flip_axes is not None and np.shape(flip_axes) != queries.shape:
        raise DescriptorError(f"shot: flip_axes must have one entry per described vertex, shape {queries.shape}.")


def shot_descriptors(
    verts: np.ndarray,
    normals: np.ndarray,
    radius: float,
    *,
    min_neighbors: int = 3,
    n_bins: int = 5,
    double_volumes_sectors: bool = True,
    use_interpolation: bool = True,
    use_normalization: bool = True,
    chunk_size: int = QUERIES_PER_CHUNK,
    progress: bool = False,
    return_frames: bool = False,
    queries: np.ndarray | None = None,
    flip_axes: np.ndarray | None = None,
    workers: int | None = None,
) -> tuple[np.ndarray, dict]:
    """SHOT histograms of every vertex, as the reference computes them.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
        Positions.
    normals : numpy.ndarray, shape (V, 3)
        Unit normals of the vertices (zero rows allowed: they bin at cos = 0).
    radius : float
        Support radius in the units of ``verts`` (> 0); rounded to float32 as the reference does.
    min_neighbors, n_bins, double_volumes_sectors, use_interpolation, use_normalization
        As in `SHOT`.
    chunk_size : int
        Vertices a thread describes per task (the progress bar counts tasks).
    progress : bool
        Show a progress bar over the tasks.
    return_frames : bool
        Add the frames of every vertex to the report (``"frames"``: a `ShotFrames`).
    queries : numpy.ndarray of int, shape (Q,), optional
        Describe only these vertices (their neighbours are still all vertices); rows and
        report entries follow this order. Default: every vertex.
    flip_axes : numpy.ndarray of int, shape (Q,), optional
        Per described vertex, frame axes to turn round after the sign rule: 1 X, 2 Z, 3 both
        (Y follows). For comparisons with an implementation that chose the other sign at a
        tie; default none.
    workers : int, optional
        Threads at work at once (default: the CPUs this process may use). The result does
        not depend on it.

    Returns
    -------
    features : numpy.ndarray, shape (V, n_volumes * (n_bins + 1)) or (Q, ...), float32
        Summed in float64, stored in float32 (as the descriptors are). n_volumes = 32 with
        ``double_volumes_sectors``, else 16. Rows of vertices with fewer than
        ``max(5, min_neighbors)`` neighbours, or with every neighbour closer than 1e-3, are zero.
    report : dict
        ``"few_neighbors"`` and ``"nothing_binned"`` (bool masks, shape (V,)), ``"sign_tie"``
        (bool, shape (V,)), and ``"frames"`` when asked.

    Notes
    -----
    Memory beyond the output is a few arrays the size of one vertex's neighbourhood per
    thread, whatever the number of vertices.
    """
    radius32 = np.float32(radius)
    threshold = float(radius32 * radius32)  # the reference squares R in float32
    radius = float(radius32)
    verts = np.ascontiguousarray(verts, dtype=np.float64)
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    queries = np.arange(len(verts)) if queries is None else np.ascontiguousarray(queries, dtype=np.int64)
    n_rows = len(queries)
    _check_arrays(verts, normals, queries, flip_axes)
    width = (32 if double_volumes_sectors else 16) * (n_bins + 1)
    features = np.zeros((n_rows, width), dtype=np.float32)
    frames = np.zeros((n_rows, 3, 3))
    n_neighbors = np.zeros(n_rows, dtype=np.int64)
    tie, few, empty = (np.zeros(n_rows, dtype=bool) for _ in range(3))
    flip_axes = np.zeros(n_rows, dtype=np.int64) if flip_axes is None else np.ascontiguousarray(flip_axes, dtype=np.int64)
    grid = _grid(verts, radius)
    min_count = max(MIN_LRF_NEIGHBORS, min_neighbors)

    def describe(start: int) -> None:
        stop = min(start + chunk_size, n_rows)
        _describe_rows(
            start, stop, queries, verts, normals, grid, radius, threshold, min_count, n_bins,
            double_volumes_sectors, use_interpolation, use_normalization, flip_axes, features, frames, n_neighbors, tie, few, empty,
        )  # fmt: skip

    starts = range(0, n_rows, chunk_size)
    workers = max(1, min(workers or len(os.sched_getaffinity(0)), len(starts)))
    with ThreadPoolExecutor(max_workers=workers) as pool:  # the kernels release the GIL
        done = pool.map(describe, starts) if workers > 1 else map(describe, starts)
        for _ in progress_bar(done, show=progress, total=len(starts), desc="shot", unit="chunk", delay=1.0):
            pass
    report: dict[str, np.ndarray | ShotFrames] = {"few_neighbors": few, "nothing_binned": empty, "sign_tie": tie}
    if return_frames:
        report["frames"] = ShotFrames(frames, n_neighbors, tie)
    return features, report


class SHOT(Descriptor):
    """SHOT descriptor (Signature of Histograms of OrienTations), equal to pyshot's ``get_descriptors``.

    Parameters
    ----------
    recipe : {"dsmk"}
        Whose parameter values fill those left as None (`SHOT_RECIPES`): ``"dsmk"``,
        DeepShapeMatchingKit's (radius 0.3, 5 bins, 32 volumes, interpolation and
        normalisation on), the only recipe so far.
    radius : float, optional
        Support radius (> 0), read as ``radius_unit`` says.
    radius_unit : {"absolute", "sqrt_area", "diameter"}
        ``"absolute"``: in the mesh's units (as pyshot); ``"sqrt_area"``: a fraction of the
        square root of the surface area (meshes only); ``"diameter"``: a fraction of the
        bounding-box diagonal.
    min_neighbors : int, optional
        Vertices with fewer neighbours get a zero row; at least 5 are always required (the
        reference's local reference frame needs them).
    n_bins : int, optional
        Cosine bins per volume; each volume holds ``n_bins + 1`` entries (as the reference).
    double_volumes_sectors : bool, optional
        32 volumes (8 azimuth sectors) instead of 16 (4 sectors).
    use_interpolation : bool, optional
        Quadrilinear interpolation between neighbouring bins and volumes.
    use_normalization : bool, optional
        Scale every row to unit Euclidean norm.
    cloud_normals : {"estimate", "zero"}
        Normals of a point cloud: estimated from the 30 nearest points and oriented away from
        the centroid (logged), or zero as pyshot does (then every neighbour bins at cos = 0).

    Notes
    -----
    Output: shape (V, n_volumes * (n_bins + 1)) with n_volumes = 32 or 16; the
    ``"dsmk"`` recipe gives 192 channels.

    As in the reference:

    * neighbours are all vertices with squared distance < R² (Euclidean, not geodesic), the
      vertex itself excluded; R is rounded to float32;
    * the frame comes from the covariance of the neighbours centred on the vertex with
      weights ``R - d²``; X is the axis of largest variance, Z of smallest, each pointed to
      the side that holds more neighbours (one on the plane counts for the negative side), Y = Z x X.
      Z is therefore not the surface normal
      (it points inward on convex parts). The weights mix units (a length minus an area), so
      the frames, and the features, change a little when a shape and its radius are scaled
      together: relative radii (``radius_unit``) give the same neighbourhoods, not the same
      features;
    * the cosine is between Z and the neighbour's normal: on meshes the normalised sum of the
      unit normals of its faces (not area-weighted);
    * neighbours closer than 1e-3 (in the mesh's units) count for the frame but are not binned;
    * with interpolation, the cosine share of bin ``n_bins - 1`` goes to bin 0 and the azimuth
      share wraps modulo 28 (16 volumes: 12) instead of 32, so the last sector never
      receives shares;
    * pyshot's ``local_rf_radius`` is ignored by pyshot itself, so it is not a parameter.

    Differences, each deliberate: a vertex whose neighbours are all closer than 1e-3 gets a
    zero row and a warning (pyshot: NaN after normalisation); point clouds get estimated
    normals unless ``cloud_normals="zero"``; sums are in float64 (pyshot: float32, about
    1e-7 apart); at a sign tie of the frame (as many neighbours on each side of an axis,
    rare) the sign is NumPy's eigensolver's, pyshot's is Eigen's.
    """

    name = "shot"
    version = "1"

    def __init__(
        self,
        *,
        recipe: str = "dsmk",
        radius: float | None = None,
        radius_unit: str = "absolute",
        min_neighbors: int | None = None,
        n_bins: int | None = None,
        double_volumes_sectors: bool | None = None,
        use_interpolation: bool | None = None,
        use_normalization: bool | None = None,
        cloud_normals: str = "estimate",
    ):
        self.recipe = check_choice(recipe, "recipe", tuple(SHOT_RECIPES), owner=self.name)
        recipe_values = SHOT_RECIPES[self.recipe]

        def given(name: str, value: Any) -> Any:
            return recipe_values[name] if value is None else value

        self.radius = check_number(given("radius", radius), "radius", owner=self.name, low=0.0, low_open=True)
        self.radius_unit = check_choice(radius_unit, "radius_unit", RADIUS_UNITS, owner=self.name)
        self.min_neighbors = check_integer(given("min_neighbors", min_neighbors), "min_neighbors", owner=self.name, low=0)
        self.n_bins = check_integer(given("n_bins", n_bins), "n_bins", owner=self.name, low=1)
        self.double_volumes_sectors = check_boolean(
            given("double_volumes_sectors", double_volumes_sectors), "double_volumes_sectors", owner=self.name
        )
        self.use_interpolation = check_boolean(
            given("use_interpolation", use_interpolation), "use_interpolation", owner=self.name
        )
        self.use_normalization = check_boolean(
            given("use_normalization", use_normalization), "use_normalization", owner=self.name
        )
        self.cloud_normals = check_choice(cloud_normals, "cloud_normals", CLOUD_NORMALS, owner=self.name)

    def absolute_radius(self, mesh: Mesh) -> float:
        """The support radius in the units of ``mesh``.

        Raises
        ------
        DescriptorError
            ``radius_unit="sqrt_area"`` on a point cloud, or a mesh of zero area or size.
        """
        if self.radius_unit == "absolute":
            return self.radius
        if self.radius_unit == "sqrt_area":
            if mesh.is_point_cloud:
                raise DescriptorError(
                    "shot: radius_unit='sqrt_area' needs faces; this is a point cloud. Use radius_unit='diameter' or 'absolute'."
                )
            scale = float(np.sqrt(mesh.area()))
        else:
            scale = mesh.bbox_diagonal()
        if not scale > 0:
            raise DescriptorError(f"shot: the mesh has zero {self.radius_unit.replace('_', ' ')}; use radius_unit='absolute'.")
        return self.radius * scale

    def normals(self, mesh: Mesh) -> np.ndarray:
        """Normals used for the cosines, shape (V, 3): see ``cloud_normals`` and the Notes."""
        if mesh.is_point_cloud:
            if self.cloud_normals == "zero":
                return np.zeros_like(mesh.verts)
            log.info("shot: %r is a point cloud; its normals are estimated from the 30 nearest points.", mesh.name)
            return vertex_normals(mesh.verts, None, fallback=True)
        return vertex_normals(mesh.verts, mesh.faces, face_weights="unit", fallback=False)

    def compute(self, mesh: Mesh) -> np.ndarray:
        """SHOT features of shape (V, n_volumes * (n_bins + 1)), float32.

        Raises
        ------
        DescriptorError
            No vertex has enough neighbours within the radius, or every vertex has only neighbours
            closer than 1e-3 (every row would be zero).
        """
        radius = self.absolute_radius(mesh)
        if float(np.float32(radius)) <= 0:
            raise DescriptorError(f"shot: the radius {radius!r} rounds to zero in float32; use a larger radius.")
        n_unique = len(np.unique(mesh.verts, axis=0))
        if n_unique < mesh.n_vertices:
            log.warning(
                "shot: %r has %d duplicate vertex position(s); coincident neighbours count for the frame but are not binned.",
                mesh.name,
                mesh.n_vertices - n_unique,
            )
        features, report = shot_descriptors(
            mesh.verts,
            self.normals(mesh),
            radius,
            min_neighbors=self.min_neighbors,
            n_bins=self.n_bins,
            double_volumes_sectors=self.double_volumes_sectors,
            use_interpolation=self.use_interpolation,
            use_normalization=self.use_normalization,
            progress=mesh.n_vertices >= 50_000,
        )
        n_few = int(report["few_neighbors"].sum())
        if n_few == mesh.n_vertices:
            raise DescriptorError(
                f"shot: no vertex of {mesh.name or '<unnamed>'!r} has {max(MIN_LRF_NEIGHBORS, self.min_neighbors)} "
                f"neighbours within radius {radius:.6g} (mesh units; bounding-box diagonal {mesh.bbox_diagonal():.6g}); "
                "raise the radius."
            )
        if n_few:
            log.warning(
                "shot: %d of %d vertices of %r have fewer than %d neighbours within radius %.6g: their rows are zero.",
                n_few,
                mesh.n_vertices,
                mesh.name,
                max(MIN_LRF_NEIGHBORS, self.min_neighbors),
                radius,
            )
        n_empty = int(report["nothing_binned"].sum())
        if n_few + n_empty == mesh.n_vertices:
            raise DescriptorError(
                f"shot: every vertex of {mesh.name or '<unnamed>'!r} has all its neighbours within 1e-3 (mesh units), "
                f"which SHOT counts but does not bin, or too few neighbours: every row would be zero. The mesh is "
                f"small (bounding-box diagonal {mesh.bbox_diagonal():.3g}); scale it up (e.g. geofeat.normalize)."
            )
        if n_empty:
            log.warning(
                "shot: %d vertices of %r have all neighbours closer than 1e-3 (mesh units): their rows are zero.",
                n_empty,
                mesh.name,
            )
        return features
