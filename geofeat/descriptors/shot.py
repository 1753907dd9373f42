"""SHOT: Signature of Histograms of OrienTations (Tombari, Salti and Di Stefano 2010), vectorised.

The histogram follows the reference implementation that DeepShapeMatchingKit calls (pyshot, a
wrapper of the original C++ code) value for value, its quirks included, so that features
computed here can replace the recorded ones; `SHOT` lists each quirk. Neighbourhoods come
from a `scipy.spatial.cKDTree`; the work runs over chunks of (query, neighbour) pairs, so
memory is bounded by `PAIRS_PER_CHUNK` whatever the mesh size.

>>> import geofeat                                                      # doctest: +SKIP
>>> feats = geofeat.compute(mesh, "shot", radius=0.3)                   # (V, 192)  # doctest: +SKIP
>>> feats = geofeat.compute(mesh, SHOT.preset("dsmk"))                  # DeepShapeMatchingKit's  # doctest: +SKIP
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from geofeat.checks import check_boolean, check_choice, check_integer, check_number
from geofeat.descriptors.base import Descriptor
from geofeat.errors import DescriptorError
from geofeat.geometry.normals import vertex_normals
from geofeat.mesh import Mesh
from geofeat.runtime.progress import progress_bar

log = logging.getLogger(__name__)

__all__ = ["CLOUD_NORMALS", "PAIRS_PER_CHUNK", "RADIUS_UNITS", "SHOT", "SHOT_PRESETS", "ShotFrames", "shot_descriptors"]

#: How ``radius`` is read: in the mesh's units, or as a fraction of sqrt(surface area) or of the
#: bounding-box diagonal (the "diameter").
RADIUS_UNITS = ("absolute", "sqrt_area", "diameter")
#: Normals of a point cloud: estimated (`geofeat.geometry.normals.vertex_normals`) or zero (pyshot's).
CLOUD_NORMALS = ("estimate", "zero")
#: Largest number of (query, neighbour) pairs one worker holds at once (about 100 MB of temporaries).
PAIRS_PER_CHUNK = 250_000
#: The reference needs this many neighbours for a local reference frame, whatever ``min_neighbors`` says.
MIN_LRF_NEIGHBORS = 5
#: Neighbours closer than this squared distance (input units) are counted but not binned (the reference's rule).
SKIP_SQUARED_DISTANCE = 1e-6
#: Local coordinates smaller than this in absolute value are set to zero (the reference's rule).
ZERO_COORDINATE = 1e-30

#: Named parameter sets; ``"dsmk"`` is DeepShapeMatchingKit's ``compute_shot_desc``.
SHOT_PRESETS: dict[str, dict] = {
    "dsmk": {
        "radius": 0.3,
        "radius_unit": "absolute",
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


def _octant(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Azimuth sector of 45 degrees: k covers (-180 + 45 k, -180 + 45 (k + 1)] degrees, shape of ``x``, int64.

    Decided by signs and by |x| against |y| (exact on the boundaries); x = y = 0 gives 0.
    """
    ax, ay = np.abs(x), np.abs(y)
    k = np.zeros(x.shape, dtype=np.int64)
    k[(y > 0) & (x > 0) & (ay <= ax)] = 4
    k[(y > 0) & (x >= 0) & (ay > ax)] = 5
    k[(y > 0) & (x < 0) & (ay >= ax)] = 6
    k[(y >= 0) & (x < 0) & (ay < ax)] = 7
    k[(y < 0) & (x < 0) & (ay <= ax)] = 0
    k[(y < 0) & (x <= 0) & (ay > ax)] = 1
    k[(y < 0) & (x > 0) & (ay >= ax)] = 2
    k[(y <= 0) & (x > 0) & (ay < ax)] = 3
    k[(x == 0) & (y == 0)] = 0
    return k


def _chunk_pairs(
    tree: cKDTree, verts: np.ndarray, queries: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(query, neighbour) pairs with squared distance < radius² (in float32), the query removed as the reference does.

    The reference sorts a query's neighbours by (distance, index) and drops the first entry
    only when it is the query itself: a coincident duplicate of lower index keeps the query
    in its own list.

    Returns
    -------
    qi, nj : numpy.ndarray, shape (P,), int64
        Positions in ``queries`` and vertex indices of the neighbours.
    q, sq : numpy.ndarray, shapes (P, 3) and (P,), float64
        Offsets of the neighbours from their query and their squared lengths.
    """
    query_verts = verts[queries]
    pairs = cKDTree(query_verts).sparse_distance_matrix(tree, radius, output_type="ndarray")
    qi, nj = np.ascontiguousarray(pairs["i"]), np.ascontiguousarray(pairs["j"])
    diff = np.take(verts, nj, axis=0)
    diff -= np.take(query_verts, qi, axis=0)
    sq = np.einsum("pd,pd->p", diff, diff)
    keep = sq < float(np.float32(radius) * np.float32(radius))  # the reference squares R in float32
    # the query itself is at distance 0, and is dropped unless a coincident vertex of lower
    # index sorts before it
    zero = np.flatnonzero(sq == 0.0)
    owner, other = qi[zero], nj[zero]
    has_lower_twin = np.zeros(len(queries), dtype=bool)
    has_lower_twin[owner[other < queries[owner]]] = True
    is_self = other == queries[owner]
    keep[zero[is_self & ~has_lower_twin[owner]]] = False
    kept = np.flatnonzero(keep)
    return qi[kept], nj[kept], np.take(diff, kept, axis=0), sq[kept]


def _frames(q: np.ndarray, sq: np.ndarray, qi: np.ndarray, n_query: int, radius: float) -> tuple[ShotFrames, np.ndarray]:
    """Local reference frames from neighbour offsets ``q`` (P, 3), squared distances ``sq`` (P,) and owners ``qi`` (P,).

    Returns the frames and the offsets in them, ``(q . X, q . Y, q . Z)`` per pair, shape (P, 3).
    """
    n = np.bincount(qi, minlength=n_query)
    weighted = q * (radius - sq)[:, None]  # the reference weighs by R - d² (squared distance)
    cov = np.empty((n_query, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(qi, weights=weighted[:, a] * q[:, b], minlength=n_query)
    total = np.bincount(qi, weights=radius - sq, minlength=n_query)
    valid = n >= MIN_LRF_NEIGHBORS
    cov[valid] /= total[valid, None, None]
    cov[~valid] = np.eye(3)
    _, vecs = np.linalg.eigh(cov)  # ascending eigenvalues
    x_axis, z_axis = vecs[:, :, 2], vecs[:, :, 0]
    frames = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)
    local = np.einsum("pkd,pd->pk", np.take(frames, qi, axis=0), q)  # np.take: faster than indexing
    # each of X and Z points to the side with more neighbours (strictly positive ones; a tie keeps the sign)
    signs = np.ones((n_query, 3))
    tie = np.zeros(n_query, dtype=bool)
    for axis in (0, 2):
        positive = np.bincount(qi, weights=local[:, axis] > 0, minlength=n_query)
        signs[positive < n - positive, axis] = -1.0
        tie |= 2 * positive == n
    signs[:, 1] = signs[:, 0] * signs[:, 2]  # Y = Z x X
    frames *= signs[:, :, None]
    local *= np.take(signs, qi, axis=0)
    return ShotFrames(frames, n.astype(np.int64), tie & valid), local


def _sectors(x: np.ndarray, y: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """`_octant` of every pair from the azimuth ``phi = atan2(y, x)``, exact on the boundaries, shape of ``x``, int64."""
    k = np.ceil((phi + np.pi) / (np.pi / 4)).astype(np.int64) - 1
    np.clip(k, 0, 7, out=k)
    edge = np.flatnonzero((np.abs(x) == np.abs(y)) | (x == 0) | (y == 0))
    k[edge] = _octant(x[edge], y[edge])
    return k


def _histograms(
    local: np.ndarray,
    sq: np.ndarray,
    cos: np.ndarray,
    qi: np.ndarray,
    n_query: int,
    radius: float,
    n_bins: int,
    double_volumes: bool,
    interpolate: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised histograms (n_query, n_volumes * (n_bins + 1)) and the number of binned neighbours per query.

    With interpolation every binned neighbour adds ``1 - |s|`` of each of its four
    interpolation offsets ``s`` (cosine, radial, elevation, azimuth) to its own cell and
    ``|s|`` (or nothing, on the far side of a bin centre) to the neighbouring cell of that
    offset, which is the reference's sum written without its branches.
    """
    n_volumes = 32 if double_volumes else 16
    width = n_bins + 1
    binned = sq >= SKIP_SQUARED_DISTANCE
    if not binned.all():
        kept = np.flatnonzero(binned)
        local, sq, cos, qi = np.take(local, kept, axis=0), sq[kept], cos[kept], qi[kept]
    local[np.abs(local) < ZERO_COORDINATE] = 0.0
    x, y, z = local[:, 0], local[:, 1], local[:, 2]
    dist = np.sqrt(sq)
    phi = np.arctan2(y, x)
    sector = _sectors(x, y, phi)
    if not double_volumes:
        sector //= 2
    outer = dist > radius / 2
    volume = 4 * sector + 2 * outer + (z > 0)
    t = (1.0 + cos) * (n_bins / 2.0)
    b = np.floor(t + 0.5).astype(np.int64)
    row = qi * (n_volumes * width)
    own = row + volume * width
    size = n_query * n_volumes * width
    if not interpolate:
        hist = np.bincount(own + b, minlength=size)
        return hist.reshape(n_query, -1).astype(np.float64), np.bincount(qi, minlength=n_query)

    # cosine: the share goes to the next bin modulo n_bins (bin n_bins - 1 wraps to 0)
    frac = t - b
    cos_share = np.abs(frac)
    cos_cell = own + (b + np.where(frac > 0, 1, n_bins - 1)) % n_bins
    own += b
    # radial: offset from the centre of the shell (R/4 or 3R/4), in units of R/2
    radial = (dist - np.where(outer, 3 * radius / 4, radius / 4)) / (radius / 2)
    radial_share = np.maximum(np.where(outer, -radial, radial), 0.0)
    radial_cell = own + np.where(outer, -2 * width, 2 * width)
    # elevation: offset from 45 or 135 degrees, in units of 90 degrees
    alpha = np.arccos(np.clip(z / dist, -1.0, 1.0))
    lower = (alpha > _PI_2) | ((np.abs(alpha - _PI_2) < 1e-6) & (z <= 0))
    elevation = (alpha - np.where(lower, _PI_3_4, _PI_4)) / _PI_2
    elevation_share = np.maximum(np.where(lower, -elevation, elevation), 0.0)
    elevation_cell = own + np.where(lower, width, -width)
    # azimuth: offset from the sector centre; the neighbour sector wraps modulo n_volumes - 4 (the reference's)
    if double_volumes:
        azimuth = np.clip((phi - (-_PI_7_8 + _PI_4 * sector)) / _PI_4, -0.5, 0.5)
    else:
        azimuth = np.clip((phi - (-_PI_3_4 + 2 * _PI_4 * sector)) / (2 * _PI_4), -0.5, 0.5)
    has_azimuth = (x != 0) | (y != 0)
    azimuth[~has_azimuth] = 0.0
    azimuth_share = np.abs(azimuth)
    wrap = n_volumes - 4
    azimuth_cell = row + np.where(azimuth > 0, (volume + 4) % wrap, (volume - 4 + wrap) % wrap) * width + b
    main = (3.0 + has_azimuth) - cos_share - np.abs(radial) - np.abs(elevation) - azimuth_share
    hist = np.bincount(own, weights=main, minlength=size)
    for cells, masses in (
        (cos_cell, cos_share),
        (radial_cell, radial_share),
        (elevation_cell, elevation_share),
        (azimuth_cell, azimuth_share),
    ):
        hist += np.bincount(cells, weights=masses, minlength=size)
    return hist.reshape(n_query, -1).astype(np.float64, copy=False), np.bincount(qi, minlength=n_query)


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
    pairs_per_chunk: int = PAIRS_PER_CHUNK,
    progress: bool = False,
    return_frames: bool = False,
    queries: np.ndarray | None = None,
    workers: int | None = None,
) -> tuple[np.ndarray, dict]:
    """SHOT histograms of every vertex, as the reference computes them.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
        Positions (float64).
    normals : numpy.ndarray, shape (V, 3)
        Unit normals of the vertices (zero rows allowed: they bin at cos = 0).
    radius : float
        Support radius in the units of ``verts`` (> 0); rounded to float32 as the reference does.
    min_neighbors, n_bins, double_volumes_sectors, use_interpolation, use_normalization
        As in `SHOT`.
    pairs_per_chunk : int
        Memory bound: most (query, neighbour) pairs held at once.
    progress : bool
        Show a progress bar over the chunks.
    return_frames : bool
        Add the frames of every vertex to the report (``"frames"``: a `ShotFrames`).
    queries : numpy.ndarray of int, shape (Q,), optional
        Describe only these vertices (their neighbours are still all vertices); rows and
        report entries follow this order. Default: every vertex.
    workers : int, optional
        Threads working on chunks at once (default: the CPU count); each holds up to
        ``pairs_per_chunk`` pairs. The result does not depend on it.

    Returns
    -------
    features : numpy.ndarray, shape (V, n_volumes * (n_bins + 1)) or (Q, ...), float64
        n_volumes = 32 with ``double_volumes_sectors``, else 16. Rows of vertices with fewer
        than ``max(5, min_neighbors)`` neighbours, or with every neighbour closer than 1e-3,
        are zero.
    report : dict
        ``"few_neighbors"`` and ``"nothing_binned"`` (bool masks, shape (V,)), ``"sign_tie"``
        (bool, shape (V,)), and ``"frames"`` when asked.
    """
    radius = float(np.float32(radius))
    tree = cKDTree(verts)
    queries = np.arange(len(verts)) if queries is None else np.asarray(queries, dtype=np.int64)
    n_vertices = len(queries)
    counts = tree.query_ball_point(verts[queries], radius, return_length=True).astype(np.int64)
    bounds = [0]
    total = 0
    for i, c in enumerate(counts):
        if total + c > pairs_per_chunk and i > bounds[-1]:
            bounds.append(i)
            total = 0
        total += c
    bounds.append(n_vertices)
    width = (32 if double_volumes_sectors else 16) * (n_bins + 1)
    features = np.zeros((n_vertices, width))
    few = np.zeros(n_vertices, dtype=bool)
    empty = np.zeros(n_vertices, dtype=bool)
    tie = np.zeros(n_vertices, dtype=bool)
    frames_all = np.zeros((n_vertices, 3, 3)) if return_frames else None
    n_all = np.zeros(n_vertices, dtype=np.int64)
    min_count = max(MIN_LRF_NEIGHBORS, min_neighbors)

    def describe(bound: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, ShotFrames]:
        chunk = queries[bound[0] : bound[1]]
        qi, nj, q, sq = _chunk_pairs(tree, verts, chunk, radius)
        lrf, local = _frames(q, sq, qi, len(chunk), radius)
        z_axes = np.take(lrf.frames[:, 2], qi, axis=0)
        cos = np.clip(np.einsum("pd,pd->p", z_axes, np.take(normals, nj, axis=0)), -1.0, 1.0)
        hist, n_binned = _histograms(local, sq, cos, qi, len(chunk), radius, n_bins, double_volumes_sectors, use_interpolation)
        too_few = lrf.n_neighbors < min_count
        nothing = ~too_few & (n_binned == 0)
        hist[too_few | nothing] = 0.0
        if use_normalization:
            norms = np.linalg.norm(hist, axis=1)
            hist[norms > 0] /= norms[norms > 0, None]
        return hist, too_few, nothing, lrf

    chunks = list(zip(bounds[:-1], bounds[1:], strict=True))
    workers = max(1, min(workers or os.cpu_count() or 1, len(chunks)))
    with ThreadPoolExecutor(max_workers=workers) as pool:  # NumPy releases the GIL in its array loops
        results = pool.map(describe, chunks) if workers > 1 else map(describe, chunks)
        bar = progress_bar(
            zip(chunks, results, strict=True), show=progress, total=len(chunks), desc="shot", unit="chunk", delay=1.0
        )
        for (start, stop), (hist, too_few, nothing, lrf) in bar:
            features[start:stop] = hist
            few[start:stop], empty[start:stop], tie[start:stop] = too_few, nothing, lrf.sign_tie & ~too_few
            n_all[start:stop] = lrf.n_neighbors
            if frames_all is not None:
                frames_all[start:stop] = lrf.frames
    report = {"few_neighbors": few, "nothing_binned": empty, "sign_tie": tie}
    if frames_all is not None:
        report["frames"] = ShotFrames(frames_all, n_all, tie)
    return features, report


class SHOT(Descriptor):
    """SHOT descriptor (Signature of Histograms of OrienTations), equal to pyshot's ``get_descriptors``.

    Parameters
    ----------
    radius : float
        Support radius (> 0), read as ``radius_unit`` says.
    radius_unit : {"absolute", "sqrt_area", "diameter"}
        ``"absolute"``: in the mesh's units (as pyshot); ``"sqrt_area"``: a fraction of the
        square root of the surface area (meshes only); ``"diameter"``: a fraction of the
        bounding-box diagonal.
    min_neighbors : int
        Vertices with fewer neighbours get a zero row; at least 5 are always required (the
        reference's local reference frame needs them).
    n_bins : int
        Cosine bins per volume; each volume holds ``n_bins + 1`` entries (as the reference).
    double_volumes_sectors : bool
        32 volumes (8 azimuth sectors) instead of 16 (4 sectors).
    use_interpolation : bool
        Quadrilinear interpolation between neighbouring bins and volumes.
    use_normalization : bool
        Scale every row to unit Euclidean norm.
    cloud_normals : {"estimate", "zero"}
        Normals of a point cloud: estimated from the 30 nearest points and oriented away from
        the centroid (logged), or zero as pyshot does (then every neighbour bins at cos = 0).

    Notes
    -----
    Output: shape (V, n_volumes * (n_bins + 1)) with n_volumes = 32 or 16; the
    DeepShapeMatchingKit preset (`SHOT_PRESETS`, ``SHOT.preset("dsmk")``, also the defaults)
    gives 192 channels.

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
        radius: float = 0.3,
        radius_unit: str = "absolute",
        min_neighbors: int = 3,
        n_bins: int = 5,
        double_volumes_sectors: bool = True,
        use_interpolation: bool = True,
        use_normalization: bool = True,
        cloud_normals: str = "estimate",
    ):
        self.radius = check_number(radius, "radius", owner=self.name, low=0.0, low_open=True)
        self.radius_unit = check_choice(radius_unit, "radius_unit", RADIUS_UNITS, owner=self.name)
        self.min_neighbors = check_integer(min_neighbors, "min_neighbors", owner=self.name, low=0)
        self.n_bins = check_integer(n_bins, "n_bins", owner=self.name, low=1)
        self.double_volumes_sectors = check_boolean(double_volumes_sectors, "double_volumes_sectors", owner=self.name)
        self.use_interpolation = check_boolean(use_interpolation, "use_interpolation", owner=self.name)
        self.use_normalization = check_boolean(use_normalization, "use_normalization", owner=self.name)
        self.cloud_normals = check_choice(cloud_normals, "cloud_normals", CLOUD_NORMALS, owner=self.name)

    @classmethod
    def preset(cls, name: str, **overrides) -> SHOT:
        """The descriptor with the parameters of a named preset (`SHOT_PRESETS`), some replaced by ``overrides``.

        Raises
        ------
        DescriptorError
            Unknown preset name.
        """
        key = check_choice(name, "preset", tuple(SHOT_PRESETS), owner=cls.name)
        return cls(**{**SHOT_PRESETS[key], **overrides})

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
        """SHOT features of shape (V, n_volumes * (n_bins + 1)), float64.

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
