"""GeoLoRA's RAY partial shapes reproduced draw by draw: the "reference" RAY.

`ray_partial_reference` makes, for a given camera position (the *draw*), the partial shape
that the GeoLoRA training code makes (Ehm et al., CVPR 2026; release repository
``vikiehm/geo-lora``, ``utils/ray_caster.py`` ``RayCaster.get_partial_shape``
called by ``utils/shape_dataset.py`` ``generate_random_view_ray``), without open3d.
`official_ray_eye` draws the camera position the way the training does, from numpy's legacy
global random state, so that a seeded stream of draws can be replayed. geofeat's own RAY
(`geofeat.geometry.partial.ray_partial`) is a different, exact visibility test; this module
exists to compare with the published training data.

What the official RAY does, step by step (read from the code above and checked against it
running with open3d 0.20.0, trimesh 4.5.0 and numpy 2.2):

1. **Camera.** ``cam_generator("low", n_cam_pos=1)[0, :, 0]``: a point on the unit sphere
   with azimuth uniform in [0, 2 pi) about the z axis and elevation uniform in
   [-pi/2, pi/2] (so not uniform on the sphere: the poles +-z are favoured). It consumes
   seven ``numpy.random.rand`` numbers in the order given in `official_ray_eye`.
2. **Scale.** The vertices are float32 (open3d's tensor mesh stores them so; the training
   hands it float32 vertices). A mesh whose bounding-box diagonal is >= 2 is cast at scale
   0.8 (``float32(0.8) * vertices`` in float32); the partial shape keeps the unscaled positions.
3. **Rays.** open3d ``RaycastingScene.create_rays_pinhole(fov_deg=90, center=0, eye,
   up=(0, 1, 0), width_px=300, height_px=300)``: every ray starts at the eye; the ray of
   pixel ``(x, y)`` (column ``x``, row ``y``, both from 0) has the direction
   ``R.T @ ((x + 0.5 - W / 2) / f, (y + 0.5 - H / 2) / f, 1)``, not normalised, with the
   focal length ``f = (W / 2) / tan(fov / 2)`` (150 px) and the rows of ``R``
   ``right = normalise(up x forward)``, ``forward x right`` and ``forward =
   normalise(center - eye)``. Rays go through pixel centres, the image rows grow along
   ``forward x right`` (the up direction, so row 0 is at the bottom of the picture) and
   the columns along ``up x forward`` (to the left of the picture). The ray parameter of a
   hit is its depth along ``forward``. (Open3D computes ``R.T @ inverse(K)`` in float64 and
   applies it in float32.) This is `pinhole_camera`: a geofeat `Cameras` with rotation ``R``
   whose `Cameras.unproject` at depth 1 gives the same rays.
4. **Hits.** ``cast_rays`` (Embree, both sides of every triangle, nearest hit at t >= 0);
   the hit triangles are ``numpy.unique`` of the primitive ids of the rays with a finite
   ``t_hit``. Here: `first_hits`, geofeat's rasterizer (which samples pixel centres and
   keeps the nearest face, with back faces kept) plus an exact ray-triangle test for the
   few faces that cross the camera's plane (the rasterizer does not clip).
5. **Largest component.** ``trimesh.Trimesh(all vertices, hit faces,
   process=False).split(only_watertight=False)``, sorted by area (descending, a stable
   sort), first one. In trimesh 4.5 that split (see `official_components` and
   `official_filled_holes`):

   * joins two hit faces when they share an edge that *exactly two* hit faces use (an edge
     of three or more faces joins none of them; a shared vertex joins nothing);
   * **fills holes of every component** (``util.submesh(repair=True)`` calls
     ``repair.fill_holes`` even with ``only_watertight=False``): a boundary loop of three
     edges gets one triangle, a loop of four edges two triangles. Most of these are source
     faces that no ray hit (pin-holes); some are not source faces (a four-edge hole split
     along the other diagonal). The area that picks the largest component counts them;
   * gives the component's vertices in increasing source index, its faces in an order set by
     numpy's (unstable) ``argsort`` of the component labels, followed by the filled faces;
   * breaks area ties by the component holding the lowest hit face.

6. **Ground truth.** For each partial vertex, the nearest full vertex (``cdist`` then
   ``argmin``). Every partial vertex is a full vertex, so this is the vertex itself, or the
   lowest-indexed vertex at exactly the same position when the source has duplicate
   positions.

Open3D's hits and the rasterizer's differ only on rays that pass within rounding of a
triangle's edge or vertex (both test in float32, in different ways) and on equal depths.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

from geofeat.errors import MeshError, RenderError
from geofeat.geometry.partial import PartialShape
from geofeat.mesh import Mesh, require_faces
from geofeat.render.cameras import Cameras
from geofeat.render.rasterizer import RasterSettings, rasterize

__all__ = [
    "OFFICIAL_RAY_FOV_DEGREES",
    "OFFICIAL_RAY_IMAGE_SIZE",
    "OFFICIAL_RAY_SCALE",
    "OFFICIAL_RAY_SCALE_DIAGONAL",
    "OFFICIAL_RAY_UP",
    "RayHits",
    "first_hits",
    "official_components",
    "official_filled_holes",
    "official_ray_eye",
    "pinhole_camera",
    "pinhole_rays",
    "ray_partial_reference",
]

#: Width and height of the official ray grid, in rays.
OFFICIAL_RAY_IMAGE_SIZE = 300
#: Field of view of the official ray grid (across its width).
OFFICIAL_RAY_FOV_DEGREES = 90.0
#: World up direction of the official camera.
OFFICIAL_RAY_UP = (0.0, 1.0, 0.0)
#: Scale at which a large mesh is cast ...
OFFICIAL_RAY_SCALE = 0.8
#: ... when its bounding-box diagonal is at least this.
OFFICIAL_RAY_SCALE_DIAGONAL = 2.0

_FAR = np.inf
_Z_NEAR = 1e-6  # world units: nearer faces go to the exact ray-triangle test
_ZERO_NORMAL = 1e-13  # trimesh.tol.zero: a filled triangle with a shorter normal is dropped


def official_ray_eye(random_state: np.random.RandomState | None = None) -> np.ndarray:
    """The camera position of one official RAY draw: ``cam_generator("low", 1)[0, :, 0]``.

    Consumes seven numbers of ``random_state.rand`` in the official order: two azimuths,
    two elevations (one camera each of a pair; the first is used), one azimuth offset, one
    number choosing the sign of the elevation offset, one elevation offset (both offsets
    are multiplied by zero in the "low" setting).

    Parameters
    ----------
    random_state : numpy.random.RandomState, optional
        Default: numpy's legacy global state (what ``numpy.random.rand`` uses), so that
        ``numpy.random.seed(s)`` followed by a sequence of calls replays the official draws.

    Returns
    -------
    numpy.ndarray, shape (3,), float64
        A point on the unit sphere, ``(cos(e) sin(a), cos(e) cos(a), sin(e))`` with azimuth
        ``a`` uniform in [0, 2 pi) and elevation ``e`` uniform in [-pi/2, pi/2).
    """
    rand = np.random.rand if random_state is None else random_state.rand
    view_range = np.pi  # the "low" similarity setting
    azimuth = rand(2) * (2 * view_range)
    elevation = rand(2) * view_range - view_range / 2.0
    azimuth += rand(1) * 2 * (np.pi - view_range)
    azimuth = np.clip(azimuth, 0, 2 * np.pi)
    if rand(1) > 0.5:
        elevation += rand(1) * (np.pi - view_range) / 2
    else:
        elevation -= rand(1) * (np.pi - view_range) / 2
    elevation = np.clip(elevation, -np.pi / 2, np.pi / 2)
    point = np.array([np.cos(elevation[0]) * np.sin(azimuth[0]), np.cos(elevation[0]) * np.cos(azimuth[0]), np.sin(elevation[0])])
    return point / np.sqrt(np.add.reduce(point * point))


def pinhole_camera(
    eye,
    center=(0.0, 0.0, 0.0),
    up=OFFICIAL_RAY_UP,
    image_size: int | tuple[int, int] = OFFICIAL_RAY_IMAGE_SIZE,
    fov_degrees: float = OFFICIAL_RAY_FOV_DEGREES,
) -> Cameras:
    """The camera of open3d's ``RaycastingScene.create_rays_pinhole`` as a geofeat `Cameras`.

    Rotation rows ``normalise(up x forward)``, ``forward x right`` and ``forward =
    normalise(center - eye)``; focal length ``(W / 2) / tan(fov / 2)`` for both axes (open3d
    measures the field of view across the width); principal point ``(W / 2, H / 2)``.

    Parameters
    ----------
    eye : array_like, shape (3,)
        Camera position.
    center : array_like, shape (3,)
        Point looked at.
    up : array_like, shape (3,)
        World up direction; must not be parallel to ``center - eye``.
    image_size : int or (int, int)
        ``(H, W)`` in rays; an int means a square grid.
    fov_degrees : float
        Field of view across the width, in (0, 180).

    Returns
    -------
    Cameras
        One view on the CPU.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    forward = np.asarray(center, dtype=np.float64).reshape(3) - eye
    up = np.asarray(up, dtype=np.float64).reshape(3)
    if not (np.isfinite(eye).all() and np.isfinite(forward).all() and np.linalg.norm(forward) > 0):
        raise RenderError(f"the eye must be a finite point away from the centre; found eye={eye.tolist()}.")
    forward = forward / np.linalg.norm(forward)
    right = np.cross(up / np.linalg.norm(up), forward)
    if not np.linalg.norm(right) > 1e-12:
        raise RenderError(f"the camera at {eye.tolist()} looks along the up vector {up.tolist()}; its frame is undefined.")
    right = right / np.linalg.norm(right)
    rotation = np.stack((right, np.cross(forward, right), forward))
    height, width = (image_size, image_size) if isinstance(image_size, (int, np.integer)) else image_size
    # geofeat's field of view spans the shorter side; open3d's spans the width.
    half_tan = math.tan(math.radians(fov_degrees) / 2.0) * min(height, width) / width
    return Cameras(rotation[None], eye[None], (height, width), math.degrees(2.0 * math.atan(half_tan)), device="cpu")


def pinhole_rays(cameras: Cameras) -> np.ndarray:
    """Directions of the rays through the pixel centres of the first view, as open3d makes them.

    Parameters
    ----------
    cameras : Cameras
        Typically from `pinhole_camera`; view 0 is used.

    Returns
    -------
    numpy.ndarray, shape (H, W, 3), float64
        ``directions[y, x] = R.T @ ((x + 0.5 - cx) / f, (y + 0.5 - cy) / f, 1)``: the point at
        depth 1 on the ray of pixel ``(x, y)``, minus the eye. All rays start at the eye.
    """
    view = cameras[0]
    pixels = view.pixel_centers(torch.float64).reshape(-1, 2)
    points = view.unproject(pixels, torch.ones(pixels.shape[0], dtype=torch.float64))[0]
    return (points - view.position[0]).reshape(view.height, view.width, 3).numpy()


class RayHits(NamedTuple):
    """The first face each ray of a pinhole grid hits.

    Attributes
    ----------
    face : numpy.ndarray, shape (H, W), int64
        Index of the nearest face along the ray of pixel ``[row, col]``; -1 where the ray misses.
    depth : numpy.ndarray, shape (H, W), float64
        Depth of the hit along the camera's forward axis (open3d's ``t_hit`` for its
        unnormalised rays); +inf where the ray misses.
    """

    face: np.ndarray
    depth: np.ndarray

    def hit_faces(self) -> np.ndarray:
        """Indices of the faces hit by at least one ray, increasing, shape (K,) int64."""
        return np.unique(self.face[self.face >= 0])


def first_hits(verts: np.ndarray, faces: np.ndarray, cameras: Cameras) -> RayHits:
    """Nearest face along every ray of the first view of ``cameras`` (both sides of every face).

    Faces wholly in front of the camera go through geofeat's rasterizer (nearest face at each
    pixel centre, back faces kept). A face with a corner at or behind the camera's plane
    (depth <= ``RasterSettings.z_near``) is not drawn by the rasterizer; the part of it in
    front of the camera is found here by an exact ray-triangle test against every ray.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
        World positions (float64 is used).
    faces : numpy.ndarray, shape (F, 3), int
    cameras : Cameras
        View 0 is used, on the CPU.

    Returns
    -------
    RayHits
        Face and depth per ray, shape (H, W) each.
    """
    view = cameras[0].to("cpu")
    verts = np.asarray(verts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    settings = RasterSettings(cull_backfaces=False, z_near=_Z_NEAR)
    fragments = rasterize(verts, faces, view, settings)
    face = fragments.pix_to_face[0].numpy().copy()
    depth = fragments.depth[0].numpy().astype(np.float64)

    corner_depth = view.project(verts).depth[0].numpy()[faces]  # (F, 3)
    crossing = np.flatnonzero((corner_depth.min(axis=1) <= settings.z_near) & (corner_depth.max(axis=1) > 0))
    if crossing.size:
        corners = view.world_to_camera(verts).numpy()[0][faces[crossing]]  # (K, 3, 3), eye at the origin
        rays = np.concatenate(
            (
                ((view.pixel_centers(torch.float64).numpy() - view.principal_point) / view.focal_length).reshape(-1, 2),
                np.ones((view.height * view.width, 1)),
            ),
            axis=1,
        )  # (P, 3): camera-frame directions with depth 1
        best_t, best_face = _nearest_crossing_hits(corners, rays)
        closer = best_t < depth.reshape(-1)
        face.reshape(-1)[closer] = crossing[best_face[closer]]
        depth.reshape(-1)[closer] = best_t[closer]
    return RayHits(face, depth)


def _nearest_crossing_hits(corners: np.ndarray, rays: np.ndarray, chunk: int = 1 << 16) -> tuple[np.ndarray, np.ndarray]:
    """Nearest of K triangles along P rays from the origin (Moller-Trumbore, both sides, t > 0).

    Parameters
    ----------
    corners : numpy.ndarray, shape (K, 3, 3)
    rays : numpy.ndarray, shape (P, 3)

    Returns
    -------
    t : numpy.ndarray, shape (P,), float64
        Ray parameter of the nearest hit (+inf: none).
    index : numpy.ndarray, shape (P,), int64
        Which triangle (0 .. K-1); meaningless where ``t`` is infinite.
    """
    best_t = np.full(rays.shape[0], _FAR)
    best = np.zeros(rays.shape[0], dtype=np.int64)
    for k, (a, b, c) in enumerate(corners):
        edge1, edge2 = b - a, c - a
        for start in range(0, rays.shape[0], chunk):
            d = rays[start : start + chunk]
            p = np.cross(d, edge2)
            det = p @ edge1
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / det
                u = (-a @ p.T) * inv
                q = np.cross(-a, edge1)
                v = (d @ q) * inv
                t = (edge2 @ q) * inv
            hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < best_t[start : start + chunk])
            best_t[start : start + chunk][hit] = t[hit]
            best[start : start + chunk][hit] = k
    return best_t, best


def official_components(faces: np.ndarray) -> np.ndarray:
    """Component labels of faces as trimesh 4.5's ``split`` finds them.

    Two faces are joined when they share an edge used by exactly two of the given faces
    (counting each face's three corner edges); an edge of three or more faces joins none.
    Labels number the components in the order of their lowest face.

    Parameters
    ----------
    faces : numpy.ndarray, shape (K, 3), int
        K >= 1.

    Returns
    -------
    numpy.ndarray, shape (K,), int32
    """
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    paired = np.flatnonzero(counts[inverse] == 2)  # corner edges whose edge has exactly two corners
    paired = paired[np.argsort(inverse[paired], kind="stable")].reshape(-1, 2) // 3  # the two faces of each
    n = len(faces)
    graph = sp.csr_matrix((np.ones(len(paired)), (paired[:, 0], paired[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def official_filled_holes(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The triangles trimesh 4.5's ``fill_holes`` adds to one component.

    Boundary edges (used by one face) form a graph; its cycle basis is found as
    ``networkx.cycle_basis`` finds it (nodes in order of first appearance in the boundary
    edges sorted by (larger, smaller) vertex; the last node is the first root; depth-first
    from it). A cycle ``h`` of three vertices becomes the triangle ``h``, one of four the
    triangles ``(h0, h1, h2)`` and ``(h2, h3, h0)``; longer ones stay open. A new
    triangle is reversed unless it runs along its first edge ``(h0, h1)`` against the
    face that owns that edge. Triangles with a normal shorter than 1e-13 are dropped.
    Nothing is added to a component of fewer than three faces or with fewer than three
    boundary edges.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3), float64
        Positions (to drop degenerate new triangles).
    faces : numpy.ndarray, shape (K, 3), int
        The component's faces, indices into ``verts``.

    Returns
    -------
    numpy.ndarray, shape (N, 3), int64
        New triangles, indices into ``verts``, in the order trimesh appends them.
    """
    none = np.zeros((0, 3), dtype=np.int64)
    if len(faces) < 3:
        return none
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lo, hi = directed.min(axis=1), directed.max(axis=1)
    key = hi * (int(directed.max()) + 1) + lo  # trimesh orders edges by (larger, smaller) vertex
    unique_key, first, counts = np.unique(key, return_index=True, return_counts=True)
    boundary = directed[first[counts == 1]]  # in increasing key
    if len(boundary) < 3:
        return none

    neighbours: dict[int, list[int]] = {}
    owner: dict[tuple[int, int], tuple[int, int]] = {}
    for u, v in boundary.tolist():
        for a, b in ((u, v), (v, u)):
            links = neighbours.setdefault(a, [])
            if b not in links:
                links.append(b)
        owner[(u, v)] = owner[(v, u)] = (u, v)

    new_faces = []
    for hole in _cycle_basis(neighbours):
        if len(hole) == 3:
            triangles = [hole]
        elif len(hole) == 4:
            triangles = [[hole[0], hole[1], hole[2]], [hole[2], hole[3], hole[0]]]
        else:
            continue
        for triangle in triangles:
            first_edge = owner[(triangle[0], triangle[1])]
            new_faces.append(triangle if triangle[0] == first_edge[1] else triangle[::-1])
    if not new_faces:
        return none
    new_faces = np.asarray(new_faces, dtype=np.int64)
    corners = verts[new_faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 1])
    return new_faces[np.sqrt((normal * normal).sum(axis=1)) > _ZERO_NORMAL]


def _cycle_basis(neighbours: dict[int, list[int]]) -> list[list[int]]:
    """Cycles of an undirected graph in the order and orientation of ``networkx.cycle_basis``.

    ``neighbours`` maps each node to its neighbours, both in insertion order. One
    depth-first spanning tree per connected component, rooted at the last remaining node;
    each non-tree edge closes the cycle from its far end back through the tree.
    """
    remaining = dict.fromkeys(neighbours)
    cycles = []
    while remaining:
        root = remaining.popitem()[0]
        stack, parent, seen_from = [root], {root: root}, {root: set()}
        while stack:
            node = stack.pop()
            for other in neighbours[node]:
                if other not in seen_from:
                    parent[other] = node
                    stack.append(other)
                    seen_from[other] = {node}
                elif other == node:
                    cycles.append([node])
                elif other not in seen_from[node]:
                    cycle, step = [other, node], parent[node]
                    while step not in seen_from[other]:
                        cycle.append(step)
                        step = parent[step]
                    cycle.append(step)
                    cycles.append(cycle)
                    seen_from[other].add(node)
        for node in parent:
            remaining.pop(node, None)
    return cycles


def _areas(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas as trimesh computes them, shape (K,) float64."""
    corners = verts[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 1])
    return np.sqrt((normal * normal).sum(axis=1)) / 2.0


def ray_partial_reference(mesh: Mesh, eye) -> PartialShape:
    """The official GeoLoRA RAY partial shape of ``mesh`` seen from ``eye`` (see the module notes).

    Parameters
    ----------
    mesh : Mesh
        Source triangle mesh. Its vertices are rounded to float32 first, as in the official
        training; for a float32 mesh nothing changes.
    eye : array_like, shape (3,)
        The draw: the camera position, looking at the origin with up = +y (for example
        `official_ray_eye`).

    Returns
    -------
    PartialShape
        ``kind="ray"``. ``mesh``: the official partial shape, vertices (float32 positions,
        unscaled) in increasing source index, then faces: the chosen component's source faces
        in increasing source index (the official order is numpy's unstable argsort), followed
        by the triangles that filled its holes (less any that repeats one of its faces: a
        `Mesh` holds a triangle once; ``info["n_filled_repeated"]`` counts them).
        ``exact=False``; ``vertex_map``: the official ground truth, the nearest source
        vertex of each vertex (its own source vertex, except where the source repeats a
        position). ``face_map``: source index of each face, -1 for a filled triangle.
        ``info``: ``"eye"`` (3,), ``"scale"`` (1.0 or 0.8), ``"source_vertices"`` (V_p,)
        int64 (the source index of each vertex, increasing), ``"hit_faces"`` (K,) int64
        (every face a ray hit), ``"n_components"`` (components of the hit faces),
        ``"n_filled"`` (filled triangles), ``"keep_fraction"`` (``V_p / V``), ``"tries"`` (1).

    Raises
    ------
    MeshError
        When no ray hits the mesh (the official code fails there too).
    """
    source_faces = require_faces(mesh, "a 'ray' partial shape").astype(np.int64)
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    positions = mesh.verts.astype(np.float32)
    extent = positions.max(axis=0) - positions.min(axis=0)
    scale = OFFICIAL_RAY_SCALE if float(np.sqrt(np.sum(extent * extent))) >= OFFICIAL_RAY_SCALE_DIAGONAL else 1.0
    cast = np.float32(scale) * positions if scale != 1.0 else positions

    hits = first_hits(cast, source_faces, pinhole_camera(eye))
    hit_faces = hits.hit_faces()
    if hit_faces.size == 0:
        raise MeshError(f"no ray from the camera at {eye.tolist()} hits {mesh.name!r}; there is no partial shape.")
    verts = positions.astype(np.float64)
    labels = official_components(source_faces[hit_faces])
    # component areas with their filled holes (only components of three faces or more get any)
    areas = np.bincount(labels, weights=_areas(verts, source_faces[hit_faces]))
    fills = {}
    for label in np.flatnonzero(np.bincount(labels) >= 3):
        fills[label] = official_filled_holes(verts, source_faces[hit_faces[labels == label]])
        areas[label] += _areas(verts, fills[label]).sum()
    best = int(np.argmax(areas))  # the first of equal areas, as a stable sort keeps it first
    kept = hit_faces[labels == best]
    filled = fills.get(best, np.zeros((0, 3), dtype=np.int64))
    # geofeat's Mesh keeps one copy of a triangle; trimesh can fill a hole with a copy of a face.
    fresh = _not_repeated(source_faces[kept], filled)
    n_repeated = int(len(filled) - fresh.sum())
    filled = filled[fresh]

    source_vertices = np.unique(source_faces[kept])
    new_index = np.full(mesh.n_vertices, -1, dtype=np.int64)
    new_index[source_vertices] = np.arange(source_vertices.size)
    faces = new_index[np.concatenate((source_faces[kept], filled))]
    face_map = np.concatenate((kept, np.full(len(filled), -1, dtype=np.int64)))
    partial = Mesh(verts[source_vertices], faces, name=f"{mesh.name}-ray")
    info = {
        "eye": eye,
        "scale": scale,
        "source_vertices": source_vertices,
        "hit_faces": hit_faces,
        "n_components": int(labels.max()) + 1,
        "n_filled": len(filled),
        "n_filled_repeated": n_repeated,
        "keep_fraction": source_vertices.size / mesh.n_vertices,
        "tries": 1,
    }
    ground_truth = _nearest_source_vertex(positions, source_vertices)
    return PartialShape(partial, ground_truth, face_map, "ray", info, exact=False)


def _not_repeated(faces: np.ndarray, new_faces: np.ndarray) -> np.ndarray:
    """Which new triangles name three vertices that no face and no earlier new triangle names.

    Parameters
    ----------
    faces : numpy.ndarray, shape (K, 3), int64
    new_faces : numpy.ndarray, shape (N, 3), int64

    Returns
    -------
    numpy.ndarray, shape (N,), bool
    """
    seen = set(map(tuple, np.sort(faces, axis=1).tolist()))
    fresh = np.ones(len(new_faces), dtype=bool)
    for index, triangle in enumerate(np.sort(new_faces, axis=1).tolist()):
        fresh[index] = tuple(triangle) not in seen
        seen.add(tuple(triangle))
    return fresh


def _nearest_source_vertex(positions: np.ndarray, vertex_map: np.ndarray) -> np.ndarray:
    """The official ground truth: the lowest-indexed source vertex at each kept vertex's position.

    ``argmin`` of the distances to all source vertices is the first source vertex at
    distance 0, that is at exactly the same position (-0.0 and 0.0 count as equal).

    Parameters
    ----------
    positions : numpy.ndarray, shape (V, 3), float32
    vertex_map : numpy.ndarray, shape (V_p,), int64

    Returns
    -------
    numpy.ndarray, shape (V_p,), int64
    """
    _, first, inverse = np.unique(positions + np.float32(0.0), axis=0, return_index=True, return_inverse=True)
    return first[inverse.reshape(-1)][vertex_map].astype(np.int64)
