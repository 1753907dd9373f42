"""What a head reads from a pair: its ground truth, the normalised pair, and per-vertex input features.

>>> pair = normalized_pair(pair, "unit_area")          # the references' preprocessing  # doctest: +SKIP
>>> feats = input_features(pair.x, "wks")               # (V_x, C) float32                # doctest: +SKIP
>>> map_yx = ground_truth_map(pair)                     # (V_y,) int64, -1 for none       # doctest: +SKIP

A point cloud (``faces=None``) goes where a triangle mesh goes: its area is the total mass
of its point-cloud Laplacian (`surface_area`), and its Laplacian is the point-cloud one
whatever Laplacian a head or its spectral input names for meshes (`laplacian_for`).

No torch here: the training-free heads and the evaluation workers use this module too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from geofeat.checks import is_boolean
from geofeat.datasets.records import ShapePair
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.compute import compute
from geofeat.errors import HeadError, UnusablePair
from geofeat.geometry.laplacian import laplacian
from geofeat.mesh import Mesh
from geofeat.storage.lru import LRUCache

__all__ = [
    "CLOUD_LAPLACIAN",
    "MESH_NORMALIZATIONS",
    "descriptor_params_for",
    "ground_truth_map",
    "ground_truth_overlaps",
    "input_features",
    "laplacian_for",
    "normalized_mesh",
    "normalized_pair",
    "surface_area",
    "unit_area_verts",
]

#: Values of `geofeat.adapters.heads.HeadConfig.mesh_normalization`.
MESH_NORMALIZATIONS = (None, "unit_area")
#: The Laplacian of a point cloud: the robust point-cloud Laplacian, the only one without faces
#: (and the one the DiffusionNet reference code builds for point clouds).
CLOUD_LAPLACIAN = "robust"
#: Point-cloud areas kept in memory (a Laplacian each).
_CLOUD_AREAS_KEPT = 64
_cloud_areas: LRUCache[str, float] = LRUCache(_CLOUD_AREAS_KEPT)


def ground_truth_map(pair: ShapePair) -> np.ndarray:
    """The ground-truth ``map_yx`` of a training pair, checked.

    Returns
    -------
    numpy.ndarray, shape (V_y,), int64
        A vertex of ``x`` for every vertex of ``y``, or -1.

    Raises
    ------
    HeadError
        A map of the wrong shape, type or range.
    UnusablePair
        No vertex of ``y`` has a counterpart (supervised heads skip such pairs).
    """
    map_yx = np.asarray(pair.map_yx)
    n_x, n_y = pair.x.n_vertices, pair.y.n_vertices
    if map_yx.shape != (n_y,) or not np.issubdtype(map_yx.dtype, np.integer):
        raise HeadError(
            f"pair {pair.name}: map_yx must be an integer array of shape ({n_y},); found {map_yx.dtype} {map_yx.shape}."
        )
    if map_yx.size and (map_yx.min() < -1 or map_yx.max() >= n_x):
        raise HeadError(
            f"pair {pair.name}: map_yx must hold vertices of x in [0, {n_x - 1}] or -1; "
            f"found range [{map_yx.min()}, {map_yx.max()}]."
        )
    if not (map_yx >= 0).any():
        raise UnusablePair(f"pair {pair.name}: no correspondence in the ground truth (map_yx is all -1).")
    return map_yx.astype(np.int64, copy=False)


def ground_truth_overlaps(pair: ShapePair) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth overlap masks of a training pair: its own, else derived from ``map_yx``.

    Returns
    -------
    overlap_x : numpy.ndarray, shape (V_x,), bool
        ``pair.overlap_x``, else the vertices of ``x`` that some vertex of ``y`` maps to;
        all True for a full-to-full pair without masks (every vertex of a full shape has a
        counterpart, even where a sparse ground truth such as FAUST_r's template gives
        none; the DPFM reference does the same).
    overlap_y : numpy.ndarray, shape (V_y,), bool
        ``pair.overlap_y``, else ``map_yx >= 0``; all True for a full-to-full pair.
    """
    map_yx = ground_truth_map(pair)
    overlap_x, overlap_y = pair.overlap_x, pair.overlap_y
    if pair.protocol == "f2f" and overlap_x is None and overlap_y is None:
        return np.ones(pair.x.n_vertices, dtype=bool), np.ones(pair.y.n_vertices, dtype=bool)
    if overlap_x is None:
        overlap_x = np.zeros(pair.x.n_vertices, dtype=bool)
        overlap_x[map_yx[map_yx >= 0]] = True
    if overlap_y is None:
        overlap_y = map_yx >= 0
    for name, mask, n in (("overlap_x", overlap_x, pair.x.n_vertices), ("overlap_y", overlap_y, pair.y.n_vertices)):
        if np.shape(mask) != (n,):
            raise HeadError(f"pair {pair.name}: {name} must have shape ({n},); found {np.shape(mask)}.")
    return np.asarray(overlap_x, dtype=bool), np.asarray(overlap_y, dtype=bool)


def surface_area(mesh: Mesh) -> float:
    """The area of a shape: of its triangles, or for a point cloud the total mass of its Laplacian.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh or point cloud.

    Returns
    -------
    float
        ``mesh.area()`` for a triangle mesh. For a point cloud, the sum of the lumped mass
        of its robust point-cloud Laplacian (`geofeat.geometry.laplacian.laplacian`): the
        area of the local triangulations around its points, close to the area of the
        surface they sample (its value for the last 64 clouds is kept).

    Raises
    ------
    geofeat.MeshError
        A point cloud on which the point-cloud Laplacian cannot be built (too few points).
    """
    if mesh.faces is not None:
        return mesh.area()
    return _cloud_areas.get_or_compute(mesh.hash, lambda: float(laplacian(mesh, CLOUD_LAPLACIAN).mass.sum()))


def laplacian_for(mesh: Mesh, kind: str) -> str:
    """The Laplacian a head builds on ``mesh``: ``kind`` on a triangle mesh, `CLOUD_LAPLACIAN` on a point cloud."""
    return CLOUD_LAPLACIAN if mesh.faces is None else kind


def descriptor_params_for(mesh: Mesh, params: dict | None) -> dict:
    """A descriptor's parameters as a head uses them on ``mesh``.

    Parameters
    ----------
    mesh : Mesh
    params : dict or None
        Keyword parameters of the head's input descriptor.

    Returns
    -------
    dict
        ``params`` (a new dict), with a ``"laplacian"`` entry (the spectral descriptors')
        replaced by `laplacian_for` on a point cloud, so that a head set up for meshes with
        ``laplacian="cotan"`` (the reference presets) takes point clouds too.
    """
    params = dict(params or {})
    if "laplacian" in params:
        params["laplacian"] = laplacian_for(mesh, params["laplacian"])
    return params


def unit_area_verts(mesh: Mesh, frame: Mesh | None = None, required: bool = True) -> np.ndarray:
    """Vertices centred at the mean vertex of ``frame`` and divided by the square root of its area.

    The unit-area transform of the heads (`normalized_mesh`, the ``"xyz"`` input features,
    DPFM's sample points), as the references' preprocessing does, in the frame of another
    shape where one is given. Either may be a point cloud, whose area is `surface_area`.

    Parameters
    ----------
    mesh : Mesh
    frame : Mesh, optional
        The shape whose mean vertex and area define the transform (default ``mesh``).
    required : bool
        True: a ``frame`` without area (triangles of zero area only) raises `HeadError`.
        False: it is only centred (scale 1).

    Returns
    -------
    numpy.ndarray, shape (V, 3), float64
        ``(mesh.verts - mean(frame.verts)) / sqrt(surface_area(frame))``.
    """
    frame = mesh if frame is None else frame
    centred = mesh.verts - frame.verts.mean(axis=0)
    area = surface_area(frame)
    if area > 0:
        return centred / np.sqrt(area)
    if required:
        raise HeadError(f"mesh {frame.name!r} has no surface area: mesh_normalization='unit_area' needs a surface.")
    return centred


def normalized_mesh(mesh: Mesh, how: str | None, frame: Mesh | None = None) -> Mesh:
    """A mesh moved and scaled as the references' preprocessing does (see `normalized_pair`).

    Parameters
    ----------
    mesh : Mesh
    how : {None, "unit_area"}
        None returns ``mesh`` itself. ``"unit_area"``: subtract the mean vertex of
        ``frame`` and divide by the square root of its area (`unit_area_verts`; a point
        cloud's is `surface_area`), then round to float32 (the references read their
        preprocessed meshes as float32).
    frame : Mesh, optional
        The shape whose mean and area define the transform (default ``mesh``).

    Returns
    -------
    Mesh
        Same faces, vertex order and name.
    """
    if how is None:
        return mesh
    if how != "unit_area":
        raise HeadError(f"mesh_normalization must be one of {MESH_NORMALIZATIONS}; found {how!r}.")
    verts = unit_area_verts(mesh, frame)
    return Mesh(verts.astype(np.float32).astype(np.float64), mesh.faces, name=mesh.name)


def normalized_pair(pair: ShapePair, how: str | None, kept: LRUCache[tuple, Mesh] | None = None) -> ShapePair:
    """The pair a head computes on: `HeadConfig.mesh_normalization` applied the way the references' data has it.

    With ``"unit_area"`` every full shape is centred at its mean vertex and scaled to unit
    area; the partial shape ``y`` of a P2F pair stays in the frame of the full shape ``x``
    (moved and scaled like it), as in the SHREC'16 data of DPFM and ULRSSM, where a partial
    shape keeps the coordinates and scale of the full shape it was cut from. The two
    shapes of a P2P pair are normalised each by itself (the references define no rule).

    Parameters
    ----------
    pair : ShapePair
    how : {None, "unit_area"}
    kept : LRUCache, optional
        Normalised meshes to reuse and to add to, keyed by the content hashes of the mesh
        and of its frame and by ``how`` (a `Mesh` is validated and hashed when made, which
        costs more than the transform): a head that sees the same shapes at every epoch
        normalises each once.

    Returns
    -------
    ShapePair
        ``pair`` itself for None; else the same record with new ``x`` and ``y`` (vertex
        order, faces, names and ground truth unchanged).
    """
    if how is None:
        return pair
    x = _normalized_kept(pair.x, how, None, kept)
    y = _normalized_kept(pair.y, how, pair.x if pair.protocol == "p2f" else None, kept)
    return dataclasses.replace(pair, x=x, y=y)


def _normalized_kept(mesh: Mesh, how: str, frame: Mesh | None, kept: LRUCache[tuple, Mesh] | None) -> Mesh:
    """`normalized_mesh`, taken from ``kept`` when there (under the name of ``mesh``) and added to it otherwise."""
    if kept is None:
        return normalized_mesh(mesh, how, frame=frame)
    key = (mesh.hash, None if frame is None else frame.hash, how)
    found = kept.get_or_compute(key, lambda: normalized_mesh(mesh, how, frame=frame))
    return found if found.name == mesh.name else found.renamed(mesh.name)


def input_features(mesh: Mesh, descriptor: str | Descriptor, params: dict | None = None) -> np.ndarray:
    """Per-vertex input features of a head: a geofeat descriptor, or ``"xyz"`` coordinates.

    Parameters
    ----------
    mesh : Mesh
    descriptor : str or Descriptor
        A registered descriptor name, ``"xyz"``, or a descriptor instance (built once by the
        head, so that a model-backed descriptor loads its weights once, not once per mesh).
    params : dict, optional
        The descriptor's parameters (with a name only). ``"xyz"`` takes one, ``normalize`` (default True):
        centre the vertices on their mean and scale them to unit surface area, shape by
        shape (`unit_area_verts`; a point cloud's area is `surface_area`); False: the coordinates as
        they are (the reference presets, whose pairs are already normalised with a partial
        shape in the frame of its full shape, see `normalized_pair`).

    Returns
    -------
    numpy.ndarray, shape (V, C), float32
    """
    if descriptor == "xyz":
        params = dict(params or {})
        normalize = params.pop("normalize", True)
        if params or not is_boolean(normalize):
            raise HeadError(f"descriptor 'xyz' takes only normalize=True/False; found {sorted(params) or normalize!r}.")
        if not normalize:
            return np.ascontiguousarray(mesh.verts, dtype=np.float32)
        return np.ascontiguousarray(unit_area_verts(mesh, required=False), dtype=np.float32)
    if isinstance(descriptor, Descriptor):
        return compute(mesh, descriptor)
    return compute(mesh, descriptor, **(params or {}))
