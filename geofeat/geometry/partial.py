"""Partial shapes cut from a full mesh, with free ground truth (CUTS, HOLES, RAY).

Every generator keeps a subset of the source mesh's faces (no new vertices are made, no
vertex moves), takes the largest connected component and returns a `PartialShape` whose
``vertex_map`` gives, for each partial vertex, its index in the source mesh. The ground
truth of a partial-to-full pair is therefore exact: ``partial.mesh.verts ==
source.verts[partial.vertex_map]``.

The three kinds follow the synthetic partial shapes used to train GeoLoRA (Ehm et al.,
"Teaching DINOv3 About Partial 3D Geometry", CVPR 2026; facts read from the release
repository ``vikiehm/geo-lora``, ``utils/shape_dataset.py``, ``utils/ray_caster.py`` and
``utils/utils.py``):

* **cuts**: a plane with a normal drawn from an isotropic Gaussian (uniform on the sphere),
  one side kept, largest component; accepted only when it keeps 10-90 % of the vertices,
  else drawn again (GeoLoRA: the plane passes through the bounding-box centre; here the
  area-weighted centroid by default, ``center="bbox"`` for theirs).
* **holes**: ``m`` geodesic balls removed, ``m`` uniform in {4, ..., 12}; one radius ``r``
  uniform in [0.10, 0.16) shared by all balls of a shape, in units of the square root of the
  surface area; centres are uniformly random vertices, drawn with replacement; geodesics are
  shortest paths along mesh edges; a vertex is kept when its distance to every centre is at
  least ``r``.
* **ray**: the faces a pinhole camera sees, largest component by area. GeoLoRA keeps the
  faces hit by a 300 x 300 grid of rays (90 degree field of view, up = +y) from a camera
  on the unit sphere looking at the origin, its direction drawn with azimuth uniform in
  [0, 2 pi) and elevation uniform in [-pi/2, pi/2] about the z axis. Here the camera looks
  at the shape's centre from outside its bounding sphere, in a direction uniform on the
  sphere, and a face is visible when the segment from the eye to its centroid crosses no
  other face (exact, no image resolution, so no pin-holes from faces a ray grid misses).

Components are edge-connected sets of faces (faces sharing an edge); the largest is the
one with the largest surface area (GeoLoRA uses face count for cuts and holes, area for
ray; on FAUST_r the two picks agreed in 87 of 90 draws, and area does not depend on how
finely a region happens to be meshed).

The visibility test of RAY (`visible_faces`) and `shape_centre` live in
`geofeat.geometry.visibility` and are importable from here as well.

`geofeat.geometry.partial_reference` makes CUTS and HOLES exactly as GeoLoRA's code does
(a cut splits triangles, the ground truth is the nearest source vertex), draw for draw; its
records have ``exact=False`` (see `PartialShape`).
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

import numpy as np

from geofeat.errors import MeshError
from geofeat.geometry.geodesic import distances_from
from geofeat.geometry.visibility import CENTER_KINDS, Centre, shape_centre, visible_faces
from geofeat.mesh import Mesh, require_faces
from geofeat.topology import face_components

log = logging.getLogger(__name__)

__all__ = [
    "CENTER_KINDS",
    "PARTIAL_KINDS",
    "Centre",
    "PartialShape",
    "cut_partial",
    "faces_within",
    "holes_partial",
    "largest_component",
    "largest_component_submesh",
    "make_partial",
    "random_unit_vector",
    "ray_partial",
    "shape_centre",
    "submesh",
    "visible_faces",
]

PARTIAL_KINDS = ("cuts", "holes", "ray")

Seed = int | np.random.Generator
#: A draw returns the kept source face indices and what was drawn (plane, balls, camera).
_Draw = Callable[[], tuple[np.ndarray, dict[str, Any]]]


@dataclass(frozen=True, eq=False)
class PartialShape:
    """A partial shape cut from a source mesh, with its map back to the source.

    Two kinds of record, told apart by ``exact``:

    * ``exact=True`` (`cut_partial`, `holes_partial`, `ray_partial`): the partial vertices
      are source vertices, ``mesh.verts == source.verts[vertex_map]``, in increasing source
      index, and the faces are source faces re-indexed (same corner order).
    * ``exact=False`` (the reference generators of `geofeat.geometry.partial_reference`,
      equal to GeoLoRA's own code): the partial vertices may be new points (where a plane
      cut a triangle) and ``vertex_map`` is the ground truth GeoLoRA trains with, the
      nearest source vertex of each partial vertex; it may repeat and need not increase.

    Attributes
    ----------
    mesh : Mesh
        The partial shape.
    vertex_map : numpy.ndarray, shape (V_p,), int64
        For each partial vertex a source vertex: itself (strictly increasing) when
        ``exact``, else its nearest source vertex.
    face_map : numpy.ndarray, shape (F_p,), int64
        For each partial face the source face it is (``exact``) or lies in (a cut triangle
        lies in the source face it was cut from); -1, only when not ``exact``, for a face
        that lies in no source face (a hole filled by the reference RAY).
    kind : {"cuts", "holes", "ray"}
        How the shape was made.
    info : Mapping[str, Any]
        What was drawn, read-only: ``"tries"`` (draws used, 1 = the first), ``"keep_fraction"``
        (``V_p / V``) and per kind ``"plane_point"``, ``"plane_normal"`` (cuts);
        ``"centres"`` (source vertex indices), ``"radius"`` (in sqrt-area units),
        ``"radius_abs"`` (in the mesh's units) (holes); ``"eye"``, ``"target"``,
        ``"direction"`` (ray). The reference generators document their own keys.
    exact : bool
        True when the partial vertices are source vertices (see above); default True.
    """

    mesh: Mesh
    vertex_map: np.ndarray
    face_map: np.ndarray
    kind: str
    info: Mapping[str, Any] = field(default_factory=dict)
    exact: bool = True

    def __post_init__(self) -> None:
        if self.kind not in PARTIAL_KINDS:
            raise MeshError(f"unknown partial-shape kind {self.kind!r}; expected one of {PARTIAL_KINDS}.")
        if not isinstance(self.exact, bool):
            raise MeshError(f"exact must be True or False; found {self.exact!r}.")
        vertex_map = _read_only_index_array(self.vertex_map, "vertex_map", self.mesh.n_vertices)
        if self.exact and vertex_map.size > 1 and np.any(np.diff(vertex_map) <= 0):
            raise MeshError(
                "vertex_map must be strictly increasing (partial vertices in source order) when exact=True; "
                "a nearest-vertex ground truth, which may repeat, needs exact=False."
            )
        n_faces = 0 if self.mesh.faces is None else len(self.mesh.faces)
        face_map = _read_only_index_array(self.face_map, "face_map", n_faces, lowest=0 if self.exact else -1)
        info = {key: _read_only(value) for key, value in dict(self.info).items()}
        object.__setattr__(self, "vertex_map", vertex_map)
        object.__setattr__(self, "face_map", face_map)
        object.__setattr__(self, "info", MappingProxyType(info))

    def source_to_partial(self, n_source_vertices: int) -> np.ndarray:
        """The inverse map: for each source vertex its partial vertex, ``-1`` where removed.

        Parameters
        ----------
        n_source_vertices : int
            Number of vertices of the source mesh.

        Returns
        -------
        numpy.ndarray, shape (n_source_vertices,), int64

        Raises
        ------
        MeshError
            When ``exact`` is False: a nearest-vertex map may repeat and has no inverse.
        """
        if not self.exact:
            raise MeshError(
                f"this {self.kind!r} partial shape is not exact (its vertex_map gives nearest source vertices, "
                "which may repeat), so no source vertex has a partial vertex of its own; there is no inverse map."
            )
        if self.vertex_map.size and self.vertex_map[-1] >= n_source_vertices:
            raise MeshError(
                f"the source mesh has at least {self.vertex_map[-1] + 1} vertices (vertex_map refers to "
                f"index {self.vertex_map[-1]}); found n_source_vertices={n_source_vertices}."
            )
        inverse = np.full(n_source_vertices, -1, dtype=np.int64)
        inverse[self.vertex_map] = np.arange(self.vertex_map.size, dtype=np.int64)
        return inverse


def _read_only_index_array(values, name: str, length: int, lowest: int = 0) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1 or arr.shape[0] != length or (arr.size and arr.dtype.kind not in "iu"):
        raise MeshError(f"{name} must be an integer array of shape ({length},); found dtype {arr.dtype}, shape {arr.shape}.")
    if arr.size and arr.min() < lowest:
        raise MeshError(f"{name} holds source indices, which are >= {lowest}; found {arr.min()}.")
    arr = np.array(arr, dtype=np.int64, copy=True)
    arr.flags.writeable = False
    return arr


def _read_only(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        value = value.copy()
        value.flags.writeable = False
    return value


# ---------------------------------------------------------------------------------------
# Shared helper: keep a subset, take the largest component, re-index.


def faces_within(mesh: Mesh, keep_vertices: np.ndarray) -> np.ndarray:
    """Faces whose three corners are all kept.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh with V vertices and F faces.
    keep_vertices : numpy.ndarray, shape (V,), bool

    Returns
    -------
    numpy.ndarray, shape (F,), bool
    """
    faces = require_faces(mesh, "a vertex subset")
    keep_vertices = np.asarray(keep_vertices)
    if keep_vertices.shape != (mesh.n_vertices,) or keep_vertices.dtype != bool:
        raise MeshError(
            f"keep_vertices must be a boolean mask of shape ({mesh.n_vertices},); "
            f"found dtype {keep_vertices.dtype}, shape {keep_vertices.shape}."
        )
    return keep_vertices[faces].all(axis=1)


def largest_component(mesh: Mesh, face_ids: np.ndarray) -> np.ndarray:
    """The largest edge-connected component, by surface area, of a set of faces.

    Two faces are connected when they share an edge (faces meeting at a single vertex are
    not). Ties go to the component holding the lowest face index.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh.
    face_ids : numpy.ndarray, shape (K,), int
        Indices of the faces to consider.

    Returns
    -------
    numpy.ndarray, shape (K',), int64
        The faces of the largest component, in increasing order; empty when K is 0.
    """
    faces = require_faces(mesh, "a face subset")
    face_ids = _sorted_unique(face_ids)
    if face_ids.size == 0:
        return face_ids
    labels = face_components(faces[face_ids])
    areas = mesh.face_areas()[face_ids]
    return face_ids[labels == np.argmax(np.bincount(labels, weights=areas))]


def submesh(mesh: Mesh, face_ids: np.ndarray, name: str | None = None) -> tuple[Mesh, np.ndarray]:
    """The mesh made of some faces of ``mesh``, without unreferenced vertices.

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh.
    face_ids : numpy.ndarray, shape (K,), int
        Source faces to keep (K >= 1); sorted and deduplicated here.
    name : str, optional
        Name of the new mesh (default: the source name).

    Returns
    -------
    mesh : Mesh
        Vertices in increasing source index, faces re-indexed in increasing source face index.
    vertex_map : numpy.ndarray, shape (V_p,), int64
        Source index of each vertex of the new mesh.
    """
    faces = require_faces(mesh, "a face subset")
    face_ids = _sorted_unique(face_ids)
    if face_ids.size == 0:
        raise MeshError(f"cannot make a sub-mesh of {mesh.name!r} from no faces; keep at least one face.")
    kept_faces = faces[face_ids]
    vertex_map = _used_vertices(kept_faces, mesh.n_vertices)
    new_index = np.empty(mesh.n_vertices, dtype=np.int64)  # only entries at vertex_map are read
    new_index[vertex_map] = np.arange(vertex_map.size)
    return Mesh(mesh.verts[vertex_map], new_index[kept_faces], name=mesh.name if name is None else name), vertex_map


def _sorted_unique(ids) -> np.ndarray:
    """``numpy.unique`` of an index array as int64, without its sort when ``ids`` is already strictly increasing."""
    ids = np.asarray(ids, dtype=np.int64)
    if ids.ndim == 1 and np.all(ids[1:] > ids[:-1]):
        return ids
    return np.unique(ids)


def _used_vertices(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """The vertices used by ``faces`` (K, 3), in increasing order: ``numpy.unique(faces)`` for valid indices."""
    used = np.zeros(n_vertices, dtype=bool)
    used[faces] = True
    return np.flatnonzero(used)


def largest_component_submesh(
    mesh: Mesh,
    keep_vertices: np.ndarray | None = None,
    keep_faces: np.ndarray | None = None,
    name: str | None = None,
) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """Keep a vertex subset and/or face subset, then the largest component (by area).

    A face survives when it is in ``keep_faces`` (default: all faces) and its three corners
    are in ``keep_vertices`` (default: all vertices). Unreferenced vertices are removed.

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh with V vertices and F faces.
    keep_vertices : numpy.ndarray, shape (V,), bool, optional
    keep_faces : numpy.ndarray, shape (F,), bool, optional
    name : str, optional
        Name of the new mesh (default: the source name).

    Returns
    -------
    mesh : Mesh
        The largest edge-connected component, vertices in increasing source index.
    vertex_map : numpy.ndarray, shape (V_p,), int64
        Source index of each kept vertex.
    face_map : numpy.ndarray, shape (F_p,), int64
        Source index of each kept face.
    """
    faces = require_faces(mesh, "a subset")
    mask = np.ones(len(faces), dtype=bool)
    if keep_faces is not None:
        keep_faces = np.asarray(keep_faces)
        if keep_faces.shape != (len(faces),) or keep_faces.dtype != bool:
            raise MeshError(
                f"keep_faces must be a boolean mask of shape ({len(faces)},); found dtype {keep_faces.dtype}, shape {keep_faces.shape}."
            )
        mask &= keep_faces
    if keep_vertices is not None:
        mask &= faces_within(mesh, keep_vertices)
    face_map = largest_component(mesh, np.flatnonzero(mask))
    partial, vertex_map = submesh(mesh, face_map, name)
    return partial, vertex_map, face_map


# ---------------------------------------------------------------------------------------
# Generators.


def cut_partial(
    mesh: Mesh,
    seed: Seed,
    *,
    keep_range: tuple[float, float] = (0.1, 0.9),
    center: Centre = "centroid",
    max_tries: int = 20,
) -> PartialShape:
    """CUTS: one side of a random plane through the shape's centre, largest component.

    The plane normal is uniform on the sphere; the half-space it points into is kept
    (vertices with ``(v - c) . n >= 0``, then the faces with three kept corners), so either
    side is equally likely. A draw is accepted when the kept fraction of vertices lies in
    ``keep_range``; otherwise the next plane is drawn.

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh.
    seed : int or numpy.random.Generator
        The same seed gives the same shape, bit for bit. A Generator is advanced.
    keep_range : (float, float)
        Accepted range of ``V_p / V``, inclusive.
    center : {"centroid", "bbox"}
        The point the plane passes through: the area-weighted centroid, or the bounding-box
        centre (what GeoLoRA uses).
    max_tries : int
        Draws before giving up.

    Returns
    -------
    PartialShape
        ``kind="cuts"``; ``info`` has ``"plane_point"`` (3,) and ``"plane_normal"`` (3,).

    Raises
    ------
    MeshError
        When no draw in ``max_tries`` keeps a fraction inside ``keep_range``.
    """
    _check_generator_args(mesh, "cuts", keep_range, max_tries)
    rng = np.random.default_rng(seed)
    plane_point = shape_centre(mesh, center)
    offsets = mesh.verts - plane_point

    def draw() -> tuple[np.ndarray, dict[str, Any]]:
        normal = random_unit_vector(rng)
        kept = faces_within(mesh, offsets @ normal >= 0)
        return largest_component(mesh, np.flatnonzero(kept)), {"plane_point": plane_point, "plane_normal": normal}

    return _first_accepted(mesh, "cuts", draw, keep_range, max_tries)


def holes_partial(
    mesh: Mesh,
    seed: Seed,
    *,
    n_holes: tuple[int, int] = (4, 12),
    radius_range: tuple[float, float] = (0.10, 0.16),
    keep_range: tuple[float, float] = (0.05, 1.0),
    geodesic: Literal["dijkstra", "heat"] = "dijkstra",
    max_tries: int = 20,
) -> PartialShape:
    """HOLES: remove random geodesic balls, keep the largest component.

    Each draw picks a number of holes uniform in ``n_holes`` (inclusive), one radius
    uniform in ``radius_range`` shared by all holes (in units of sqrt(surface area)) and the
    hole centres uniformly among the vertices, with replacement, as GeoLoRA does. A vertex
    is removed when its geodesic distance to some centre is below the radius.

    Geodesics default to Dijkstra on the edge graph: for at most a dozen sources it is
    faster than the heat method (which factorises a matrix on every call), it is exact for
    the distance it defines (so "no kept vertex within the radius" holds exactly) and it is
    the distance GeoLoRA and the benchmark protocols use.

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh.
    seed : int or numpy.random.Generator
        The same seed gives the same shape, bit for bit. A Generator is advanced.
    n_holes : (int, int)
        Smallest and largest number of holes (inclusive), >= 1.
    radius_range : (float, float)
        Radius range in units of sqrt(surface area), half-open as in ``Generator.uniform``.
    keep_range : (float, float)
        Accepted range of ``V_p / V``, inclusive.
    geodesic : {"dijkstra", "heat"}
        Method of `geofeat.geometry.geodesic.distances_from`.
    max_tries : int
        Draws before giving up.

    Returns
    -------
    PartialShape
        ``kind="holes"``; ``info`` has ``"centres"`` (n,) int64 source vertices,
        ``"radius"`` (sqrt-area units) and ``"radius_abs"`` (mesh units).

    Raises
    ------
    MeshError
        When no draw in ``max_tries`` keeps a fraction inside ``keep_range``.
    """
    _check_generator_args(mesh, "holes", keep_range, max_tries)
    lo_holes, hi_holes = _int_range(n_holes, "n_holes")
    lo_radius, hi_radius = _positive_range(radius_range, "radius_range")
    rng = np.random.default_rng(seed)
    sqrt_area = float(np.sqrt(mesh.area()))

    def draw() -> tuple[np.ndarray, dict[str, Any]]:
        count = int(rng.integers(lo_holes, hi_holes, endpoint=True))
        radius = float(rng.uniform(lo_radius, hi_radius))
        centres = rng.integers(0, mesh.n_vertices, size=count, dtype=np.int64)
        nearest_centre = distances_from(mesh, centres, method=geodesic).min(axis=0)
        kept = faces_within(mesh, nearest_centre >= radius * sqrt_area)
        info = {"centres": centres, "radius": radius, "radius_abs": radius * sqrt_area}
        return largest_component(mesh, np.flatnonzero(kept)), info

    return _first_accepted(mesh, "holes", draw, keep_range, max_tries)


def ray_partial(
    mesh: Mesh,
    seed: Seed,
    *,
    camera_distance: float = 2.0,
    keep_range: tuple[float, float] = (0.05, 1.0),
    center: Centre = "centroid",
    max_tries: int = 20,
) -> PartialShape:
    """RAY: the part of the surface a random camera sees, largest component by area.

    The camera looks at the shape's centre ``c`` from ``c + camera_distance * R * d``, with
    ``R`` the radius of the bounding sphere about ``c`` and ``d`` uniform on the sphere.
    A face is visible when the segment from the eye to its centroid crosses no other face
    (see `visible_faces`).

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh.
    seed : int or numpy.random.Generator
        The same seed gives the same shape, bit for bit. A Generator is advanced.
    camera_distance : float
        Distance from the centre in bounding-sphere radii, > 1 (the camera is outside).
    keep_range : (float, float)
        Accepted range of ``V_p / V``, inclusive.
    center : {"centroid", "bbox"}
        Where the camera looks: the area-weighted centroid or the bounding-box centre.
    max_tries : int
        Draws before giving up.

    Returns
    -------
    PartialShape
        ``kind="ray"``; ``info`` has ``"eye"`` (3,), ``"target"`` (3,) and ``"direction"``
        (3,), the unit vector from the target to the eye.

    Raises
    ------
    MeshError
        When no draw in ``max_tries`` keeps a fraction inside ``keep_range``.
    """
    _check_generator_args(mesh, "ray", keep_range, max_tries)
    if not camera_distance > 1:
        raise MeshError(
            f"camera_distance is in bounding-sphere radii and must be > 1 (camera outside the shape); found {camera_distance}."
        )
    target = shape_centre(mesh, center)
    radius = float(np.linalg.norm(mesh.verts - target, axis=1).max())
    rng = np.random.default_rng(seed)

    def draw() -> tuple[np.ndarray, dict[str, Any]]:
        direction = random_unit_vector(rng)
        eye = target + camera_distance * radius * direction
        seen = visible_faces(mesh, eye, target)
        return largest_component(mesh, np.flatnonzero(seen)), {"eye": eye, "target": target, "direction": direction}

    return _first_accepted(mesh, "ray", draw, keep_range, max_tries)


GENERATORS: dict[str, Callable[..., PartialShape]] = {"cuts": cut_partial, "holes": holes_partial, "ray": ray_partial}


def make_partial(mesh: Mesh, kind: str, seed: Seed, **options: Any) -> PartialShape:
    """Make a partial shape of the given kind: `cut_partial`, `holes_partial` or `ray_partial`.

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh.
    kind : {"cuts", "holes", "ray"}
    seed : int or numpy.random.Generator
    **options
        Keyword options of the chosen generator (for example ``keep_range``).

    Returns
    -------
    PartialShape
    """
    return partial_generator(kind, options)(mesh, seed, **options)


def partial_generator(kind: str, options: Mapping[str, Any] | None = None) -> Callable[..., PartialShape]:
    """The generator of ``kind``, after checking that it takes every option in ``options``.

    Raises
    ------
    MeshError
        An unknown kind, or an option the generator does not take.
    """
    if kind not in GENERATORS:
        raise MeshError(f"unknown partial-shape kind {kind!r}; expected one of {PARTIAL_KINDS}.")
    generator = GENERATORS[kind]
    accepted = [name for name, p in inspect.signature(generator).parameters.items() if p.kind is p.KEYWORD_ONLY]
    unknown = sorted(set(options or ()) - set(accepted))
    if unknown:
        raise MeshError(f"unknown option(s) {unknown} for partial kind {kind!r}; it accepts {accepted}.")
    return generator


def _first_accepted(mesh: Mesh, kind: str, draw: _Draw, keep_range: tuple[float, float], max_tries: int) -> PartialShape:
    """Call ``draw`` until the kept fraction lies in ``keep_range``; build the record."""
    lo, hi = keep_range
    faces = require_faces(mesh, f"a {kind!r} partial shape")
    fractions = []
    for attempt in range(1, max_tries + 1):
        face_ids, drawn = draw()
        n_kept = _used_vertices(faces[face_ids], mesh.n_vertices).size
        fraction = n_kept / mesh.n_vertices
        fractions.append(fraction)
        if face_ids.size and lo <= fraction <= hi:
            partial, vertex_map = submesh(mesh, face_ids, name=f"{mesh.name}-{kind}")
            info = {**drawn, "tries": attempt, "keep_fraction": fraction}
            return PartialShape(partial, vertex_map, face_ids, kind, info)
        log.debug("%s draw %d on %r kept %.3f of the vertices, outside %s", kind, attempt, mesh.name, fraction, keep_range)
    raise MeshError(
        f"could not make a {kind!r} partial shape of {mesh.name!r} ({mesh.n_vertices} vertices): all {max_tries} "
        f"random draws kept a vertex fraction outside keep_range=[{lo:g}, {hi:g}] (found {min(fractions):.3f} to "
        f"{max(fractions):.3f}). Widen keep_range or raise max_tries."
    )


# ---------------------------------------------------------------------------------------
# Small geometric pieces.


def random_unit_vector(rng: np.random.Generator) -> np.ndarray:
    """A direction uniform on the unit sphere (normalised isotropic Gaussian), shape (3,) float64."""
    while True:
        vector = rng.standard_normal(3)
        norm = float(np.linalg.norm(vector))
        if norm > 1e-12:
            return vector / norm


# ---------------------------------------------------------------------------------------
# Argument checks.


def _check_generator_args(mesh: Mesh, kind: str, keep_range, max_tries) -> None:
    require_faces(mesh, f"a {kind!r} partial shape")
    lo, hi = keep_range
    if not 0 <= lo <= hi <= 1:
        raise MeshError(f"keep_range is a fraction of vertices (lo, hi) with 0 <= lo <= hi <= 1; found {keep_range!r}.")
    if int(max_tries) != max_tries or max_tries < 1:
        raise MeshError(f"max_tries must be a positive integer; found {max_tries!r}.")


def _int_range(bounds, name: str) -> tuple[int, int]:
    lo, hi = bounds
    if int(lo) != lo or int(hi) != hi or not 1 <= lo <= hi:
        raise MeshError(f"{name} must be integers (lo, hi) with 1 <= lo <= hi; found {bounds!r}.")
    return int(lo), int(hi)


def _positive_range(bounds, name: str) -> tuple[float, float]:
    lo, hi = bounds
    if not 0 < lo <= hi:
        raise MeshError(f"{name} must be (lo, hi) with 0 < lo <= hi; found {bounds!r}.")
    return float(lo), float(hi)
