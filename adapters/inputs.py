"""What a head reads from a pair: its ground truth, the normalised pair, and per-vertex input features.

>>> pair = normalized_pair(pair, "unit_area")          # the references' preprocessing  # doctest: +SKIP
>>> feats = input_features(pair.x, "wks")               # (V_x, C) float32                # doctest: +SKIP
>>> map_yx = ground_truth_map(pair)                     # (V_y,) int64, -1 for none       # doctest: +SKIP

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
from geofeat.mesh import Mesh, normalize
from geofeat.storage.lru import LRUCache

__all__ = [
    "MESH_NORMALIZATIONS",
    "ground_truth_map",
    "ground_truth_overlaps",
    "input_features",
    "normalized_mesh",
    "normalized_pair",
    "unit_area_verts",
]

#: Values of `geofeat.adapters.heads.HeadConfig.mesh_normalization`.
MESH_NORMALIZATIONS = (None, "unit_area")


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


def unit_area_verts(mesh: Mesh, frame: Mesh | None = None, required: bool = True) -> np.ndarray:
    """Vertices centred at the mean vertex of ``frame`` and divided by the square root of its area.

    The unit-area transform of the heads (`normalized_mesh`, the ``"xyz"`` input features,
    DPFM's sample points): `geofeat.mesh.normalize` with ``center="mean"``, as the
    references' preprocessing does, in the frame of another mesh where one is given.

    Parameters
    ----------
    mesh : Mesh
    frame : Mesh, optional
        The mesh whose mean vertex and total face area define the transform (default ``mesh``).
    required : bool
        True: a ``frame`` without surface area (a point cloud) raises `HeadError`. False: it
        is only centred (scale 1).

    Returns
    -------
    numpy.ndarray, shape (V, 3), float64
        ``(mesh.verts - mean(frame.verts)) / sqrt(area(frame))``.
    """
    frame = mesh if frame is None else frame
    if frame.faces is not None and frame.area() > 0:
        return normalize(mesh, center="mean", frame=frame).verts
    if required:
        raise HeadError(f"mesh {frame.name!r} has no surface area: mesh_normalization='unit_area' needs a triangle mesh.")
    return mesh.verts - frame.verts.mean(axis=0)


def normalized_mesh(mesh: Mesh, how: str | None, frame: Mesh | None = None) -> Mesh:
    """A mesh moved and scaled as the references' preprocessing does (see `normalized_pair`).

    Parameters
    ----------
    mesh : Mesh
    how : {None, "unit_area"}
        None returns ``mesh`` itself. ``"unit_area"``: subtract the mean vertex of
        ``frame`` and divide by the square root of its total face area (`unit_area_verts`),
        then round to float32 (the references read their preprocessed meshes as float32).
    frame : Mesh, optional
        The triangle mesh whose mean and area define the transform (default ``mesh``).

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
        shape (`unit_area_verts`; a point cloud is only centred); False: the coordinates as
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
