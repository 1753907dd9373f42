"""GeoLoRA's own CUTS, HOLES and RAY partial shapes, equal draw by draw (reference generators).

`geofeat.geometry.partial` makes partial shapes in geofeat's way (whole source faces, exact
ground truth). This module reproduces what GeoLoRA's training code makes (Ehm et al., CVPR
2026; ``vikiehm/geo-lora``, ``utils/shape_dataset.py``: ``PartialShapeDataset.generate_random_cut``,
``generate_random_holes``, ``keep_largest_component``, ``get_gt_corres``), so that the same
draw gives the same partial shape and the same ground truth:

* **cuts**: `clip_plane` (Open3D's ``clip_plane``: triangles are cut, new vertices lie on the
  plane) through the centre of the axis-aligned bounding box, with a normal drawn by
  ``np.random.randn(3)``; then the largest component by face count. A try is accepted when
  it keeps more than a tenth and less than nine tenths of the vertices; up to 10 tries, else
  the whole mesh. As in the official loop, a cut first accepted at the 10th try is not used
  either (the loop counter is 0 then, which is what selects the whole mesh).
* **holes**: ``m = torch.randint(4, 13)`` centres drawn by ``torch.randint(0, V, (m,))``
  (with replacement) and one radius ``r = 0.06 * torch.rand(1) + 0.1`` (float32); a vertex
  is kept when its distance to every centre is at least ``r`` in the normalised geodesic
  matrix of the full shape; the faces with three kept corners, then the largest component
  by face count.
* **ground truth**: for every partial vertex the nearest full vertex in space, by
  ``torch.cdist`` and ``torch.min`` in float32 as ``get_gt_corres`` does (the first index
  among equal distances). It may repeat and is not the vertex itself where the full shape
  has two vertices at one position.

The official code works on float32 vertices (``verts_2``): these functions round
``mesh.verts`` to float32 first, so a mesh loaded from float32 data gives the official
result exactly. In GeoLoRA's training the full shape has by then been divided by the square
root of its area (``get_geodesic_distmat`` normalises the vertex array in place), so its
``verts_2`` are those scaled vertices; pass the mesh the official code sees.

The draws are separate functions that consume random numbers as the official code does
(`draw_cut_normal`: ``randn(3)`` of a legacy NumPy ``RandomState``; `draw_holes`: CPU torch
draws), so a seeded stream can be replayed on both sides.

Where the results differ from the official code's, on purpose:

* a triangle the official shape holds twice (the clip merges vertices at equal positions,
  so two source faces can become one triangle) is held once, as every `Mesh` holds it;
  ``info["repeated_faces"]`` counts the repeats dropped;
* where the official code stops with an error, a cut try with nothing on the kept side
  counts as rejected and holes that leave no face raise `MeshError`.

RAY is `geofeat.render.raycast.ray_partial_reference` (it casts rays with geofeat's
rasterizer); `geofeat.train.samples.training_partial_reference` draws one of the three as
GeoLoRA's training loop does.

``benchmarks/parity/partial_reference.py`` and ``benchmarks/parity/ray_reference.py`` compare
both sides draw by draw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geofeat.errors import MeshError
from geofeat.geometry.clip import clip_plane
from geofeat.geometry.partial import PartialShape
from geofeat.mesh import Mesh, require_faces
from geofeat.topology import face_components

__all__ = [
    "CUT_MAX_TRIES",
    "HolesDraw",
    "cut_partial_reference",
    "draw_cut_normal",
    "draw_holes",
    "holes_partial_reference",
    "largest_component_by_face_count",
    "nearest_source_vertices",
]

#: Tries of the official CUTS loop before it falls back to the whole mesh.
CUT_MAX_TRIES = 10
#: Official HOLES draw: ``torch.randint(HOLES_MIN, HOLES_MAX)`` holes (high end excluded) ...
HOLES_MIN, HOLES_MAX = 4, 13
#: ... and a radius ``(RADIUS_MAX - RADIUS_MIN) * torch.rand(1) + RADIUS_MIN``.
RADIUS_MIN, RADIUS_MAX = 0.1, 0.16


def draw_cut_normal(rng: np.random.RandomState) -> np.ndarray:
    """The plane normal of one CUTS try, drawn as the official code does (``randn(3)``).

    Parameters
    ----------
    rng : numpy.random.RandomState
        The legacy generator; ``RandomState(s)`` gives the stream of ``np.random.seed(s)``.

    Returns
    -------
    numpy.ndarray, shape (3,), float64
        Not normalised (the clip does not need it).
    """
    if not isinstance(rng, np.random.RandomState):
        raise MeshError(f"rng must be a numpy.random.RandomState (the legacy stream of np.random); found {type(rng).__name__}.")
    return rng.randn(3)


def cut_partial_reference(mesh: Mesh, normals, *, max_tries: int = CUT_MAX_TRIES) -> PartialShape:
    """CUTS as GeoLoRA makes it: clip through the bounding-box centre, largest component.

    Parameters
    ----------
    mesh : Mesh
        The full shape (V vertices, F faces); its vertices are rounded to float32.
    normals : numpy.ndarray, shape (T, 3), or numpy.random.RandomState
        The normals of the tries, in order, or a generator to draw each with
        `draw_cut_normal` (it then advances as the official loop advances the global
        stream: one ``randn(3)`` per try). An array must hold a normal for every try made
        (at most ``max_tries``); more are left unused.
    max_tries : int
        Tries of the loop (official: 10). A try is accepted when its largest component keeps
        ``V_p`` vertices with ``V / 10 < V_p < 9 V / 10``; a try accepted only at the last
        try, or none, gives the whole mesh.

    Returns
    -------
    PartialShape
        ``kind="cuts"``, ``exact=False``: ``vertex_map`` is the nearest source vertex of each
        partial vertex, ``face_map`` the source face each partial face was cut from. ``info``:
        ``"tries"`` (normals used), ``"normals"`` (tries, 3), ``"whole_mesh"`` (the fallback was
        taken), ``"plane_point"`` (3,) and ``"plane_normal"`` (3,) (the accepted plane; the
        last one tried for the whole mesh), ``"keep_fraction"`` (``V_p / V``), ``"components"``
        (edge-connected components of the cut before the largest is kept; of the full mesh for
        the whole mesh) and ``"repeated_faces"`` (see below).

    Notes
    -----
    The clip merges vertices at equal positions, so two source faces whose corners share
    positions can become one triangle twice. The official shape then holds that triangle
    twice; a `Mesh` holds each triangle once, so the repeat is dropped (the first kept) and
    ``info["repeated_faces"]`` counts the repeats.

    Raises
    ------
    MeshError
        When ``normals`` runs out before a try is accepted or ``max_tries`` is reached.
    """
    faces = require_faces(mesh, "a reference cut")
    if int(max_tries) != max_tries or max_tries < 1:
        raise MeshError(f"max_tries must be a positive integer; found {max_tries!r}.")
    verts = mesh.verts.astype(np.float32)
    coords = verts.astype(np.float64)
    centre = (coords.min(axis=0) + coords.max(axis=0)) * 0.5  # Open3D's AxisAlignedBoundingBox.get_center
    n_source = mesh.n_vertices
    tried = []
    for attempt in range(1, max_tries + 1):
        normal = _next_normal(normals, attempt)
        tried.append(normal)
        if attempt == max_tries:
            break  # the official loop ends with its counter at 0: whole mesh, accepted or not
        cut_verts, cut_faces, parent = clip_plane(verts, faces, centre, normal)
        if len(cut_faces) == 0:
            continue  # nothing on the kept side (the official code stops with an error here)
        keep, n_components = _largest_and_count(cut_faces)
        part_verts, part_faces = _without_unreferenced(cut_verts, cut_faces[keep])
        if n_source / 10 < len(part_verts) < n_source * 9 / 10:
            info = _cut_info(attempt, tried, False, centre, normal, len(part_verts) / n_source, n_components)
            return _reference_shape(mesh, verts, part_verts, part_faces, parent[keep], "cuts", info)
    info = _cut_info(max_tries, tried, True, centre, tried[-1], 1.0, _largest_and_count(faces)[1])
    return _reference_shape(mesh, verts, verts, faces, np.arange(len(faces)), "cuts", info)


@dataclass(frozen=True)
class HolesDraw:
    """What one official HOLES call draws.

    Attributes
    ----------
    n_holes : int
        ``m``, in {4, ..., 12}.
    radius : numpy.float32
        ``r`` in [0.1, 0.16), in units of the normalised geodesic matrix.
    centres : numpy.ndarray, shape (m,), int64
        Centre vertices, drawn with replacement.
    """

    n_holes: int
    radius: np.float32
    centres: np.ndarray


def draw_holes(n_vertices: int, generator=None) -> HolesDraw:
    """Draw ``m``, ``r`` and the centres as ``generate_random_holes`` does, on the CPU.

    Parameters
    ----------
    n_vertices : int
        V of the full shape.
    generator : torch.Generator, optional
        A CPU generator; None uses torch's default one (what the official code uses, so
        ``torch.manual_seed(s)`` then this function replays it). The official code draws on
        the device of the geodesic matrix: on CUDA its stream differs.

    Returns
    -------
    HolesDraw
    """
    import torch

    if int(n_vertices) != n_vertices or n_vertices < 1:
        raise MeshError(f"n_vertices must be a positive integer; found {n_vertices!r}.")
    m = torch.randint(HOLES_MIN, HOLES_MAX, size=(1,), generator=generator)[0]
    r = (RADIUS_MAX - RADIUS_MIN) * torch.rand(1, generator=generator) + RADIUS_MIN
    centres = torch.randint(0, int(n_vertices), size=(int(m),), generator=generator)
    return HolesDraw(n_holes=int(m), radius=np.float32(r.item()), centres=centres.numpy().astype(np.int64))


def holes_partial_reference(mesh: Mesh, centres, radius, geodesics) -> PartialShape:
    """HOLES as GeoLoRA makes it: drop geodesic balls, keep the largest component.

    Parameters
    ----------
    mesh : Mesh
        The full shape (V vertices); its vertices are rounded to float32.
    centres : array_like of int, shape (m,)
        Centre vertices (repeats allowed).
    radius : float
        Ball radius, rounded to float32 (as the official ``torch.rand`` draw is).
    geodesics : numpy.ndarray, shape (V, V)
        The geodesic matrix the official code is given, float32: GeoLoRA's
        ``geodesic_dist_echo(normalize=True)`` of the full shape. Only the rows of the centres
        are read.

    Returns
    -------
    PartialShape
        ``kind="holes"``, ``exact=False``: the partial vertices are source vertices in
        increasing source index, but ``vertex_map`` is the nearest source vertex (the first
        of two at one position); ``face_map`` gives the source faces. ``info``: ``"centres"``
        (m,), ``"radius"``, ``"n_holes"``, ``"components"`` (edge-connected components before
        the largest is kept), ``"tries"`` (1), ``"keep_fraction"``, ``"repeated_faces"`` (0).

    Raises
    ------
    MeshError
        For centres out of range, a geodesic matrix of the wrong shape, or when no face
        keeps all three corners (the official code stops with an error there).
    """
    faces = require_faces(mesh, "reference holes")
    n_source = mesh.n_vertices
    centres = np.asarray(centres)
    if centres.ndim != 1 or centres.size == 0 or centres.dtype.kind not in "iu":
        raise MeshError(f"centres must be a non-empty 1-D integer array; found dtype {centres.dtype}, shape {centres.shape}.")
    if centres.min() < 0 or centres.max() >= n_source:
        raise MeshError(f"centres must be vertex indices in [0, {n_source - 1}]; found [{centres.min()}, {centres.max()}].")
    if getattr(geodesics, "shape", None) != (n_source, n_source):
        raise MeshError(
            f"geodesics must be the ({n_source}, {n_source}) geodesic matrix of the full shape; "
            f"found shape {getattr(geodesics, 'shape', None)}."
        )
    radius = np.float32(radius)
    keep_vertex = np.ones(n_source, dtype=bool)
    for centre in centres:
        keep_vertex &= np.asarray(geodesics[centre]) >= radius
    kept_faces = np.flatnonzero(keep_vertex[faces].all(axis=1))  # open3d select_by_index
    if kept_faces.size == 0:
        raise MeshError(
            f"no face of {mesh.name!r} keeps all three corners outside {centres.size} holes of radius {float(radius):g}; "
            "there is no partial shape."
        )
    keep, n_components = _largest_and_count(faces[kept_faces])
    face_map = kept_faces[keep]
    verts = mesh.verts.astype(np.float32)
    part_verts, part_faces = _without_unreferenced(verts, faces[face_map])
    info = {
        "centres": centres.astype(np.int64),
        "radius": float(radius),
        "n_holes": int(centres.size),
        "components": n_components,
        "tries": 1,
        "keep_fraction": len(part_verts) / n_source,
    }
    return _reference_shape(mesh, verts, part_verts, part_faces, face_map, "holes", info)


def largest_component_by_face_count(faces: np.ndarray) -> np.ndarray:
    """The faces of the edge-connected component with the most faces (``keep_largest_component``).

    Ties go to the component holding the lowest face index, as ``numpy.argmax`` of the
    component sizes of ``igl.facet_components`` (which numbers components from face 0 on).

    Parameters
    ----------
    faces : numpy.ndarray, shape (K, 3), int
        K >= 1.

    Returns
    -------
    numpy.ndarray, shape (K,), bool
    """
    return _largest_and_count(faces)[0]


def _largest_and_count(faces: np.ndarray) -> tuple[np.ndarray, int]:
    """`largest_component_by_face_count` and the number of components."""
    labels = face_components(faces)
    return labels == np.argmax(np.bincount(labels)), int(labels.max()) + 1


def nearest_source_vertices(partial_verts: np.ndarray, source_verts: np.ndarray) -> np.ndarray:
    """GeoLoRA's ground truth: the nearest source vertex of each partial vertex.

    ``torch.cdist`` and ``torch.min`` in float32 on the CPU, as ``get_gt_corres`` computes it
    (the first index among equal distances). On CUDA, where the official training runs it,
    a near tie can be broken the other way.

    Parameters
    ----------
    partial_verts : numpy.ndarray, shape (V_p, 3)
    source_verts : numpy.ndarray, shape (V, 3)

    Returns
    -------
    numpy.ndarray, shape (V_p,), int64
    """
    import torch

    partial = torch.from_numpy(np.ascontiguousarray(partial_verts, dtype=np.float32))
    source = torch.from_numpy(np.ascontiguousarray(source_verts, dtype=np.float32))
    return torch.cdist(partial, source).min(dim=1).indices.numpy().astype(np.int64)


def _next_normal(normals, attempt: int) -> np.ndarray:
    if isinstance(normals, np.random.RandomState):
        return draw_cut_normal(normals)
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim != 2 or normals.shape[1] != 3:
        raise MeshError(f"normals must be an array of shape (T, 3) or a numpy.random.RandomState; found shape {normals.shape}.")
    if attempt > len(normals):
        raise MeshError(
            f"the cut needs a normal for try {attempt}, but only {len(normals)} were given; "
            "pass more normals (up to max_tries) or a RandomState."
        )
    return normals[attempt - 1]


def _cut_info(
    tries: int, tried: list, whole: bool, centre: np.ndarray, normal: np.ndarray, fraction: float, components: int
) -> dict:
    return {
        "components": components,
        "tries": tries,
        "normals": np.array(tried).reshape(-1, 3),
        "whole_mesh": whole,
        "plane_point": centre,
        "plane_normal": np.asarray(normal, dtype=np.float64),
        "keep_fraction": fraction,
    }


def _without_unreferenced(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop the vertices no face uses, keeping the order of the others (open3d ``remove_unreferenced_vertices``)."""
    used = np.zeros(len(verts), dtype=bool)
    used[faces] = True
    new_index = np.cumsum(used) - 1
    return verts[used], new_index[faces]


def _reference_shape(
    mesh: Mesh, source_verts: np.ndarray, verts: np.ndarray, faces: np.ndarray, face_map: np.ndarray, kind: str, info: dict
) -> PartialShape:
    """The record of a reference shape; a triangle the official shape holds twice is kept once."""
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    once = np.zeros(len(faces), dtype=bool)
    once[first] = True
    vertex_map = nearest_source_vertices(verts, source_verts)
    partial = Mesh(verts, faces[once], name=f"{mesh.name}-{kind}-reference")
    info = {**info, "repeated_faces": int(len(faces) - first.size)}
    return PartialShape(partial, vertex_map, np.asarray(face_map, dtype=np.int64)[once], kind, info, exact=False)
