"""Clip a triangle mesh with a plane, cutting the triangles the plane crosses.

`clip_plane` gives what Open3D's ``open3d.t.geometry.TriangleMesh.clip_plane`` gives (Open3D
0.20): that method runs VTK's ``vtkClipPolyData`` with a ``vtkPlane`` and then
``vtkCleanPolyData``. Facts of that pipeline this module reproduces (read from the VTK and
Open3D sources and checked against Open3D 0.20 on FAUST, SMAL and TOSCA shapes):

* The signed value of vertex ``x`` is ``n . (x - p)`` (normal not normalised), evaluated in
  float64 and stored in float32. A vertex is kept when its stored value is ``> 0``: the side
  the normal points into is kept, a vertex on the plane is not.
* Every triangle is cut by the marching-triangles table of ``vtkTriangle::Clip``: 0, 1 or 2
  output triangles, each with the corner order of the table (so a kept triangle keeps its
  corner order and orientation).
* A new vertex lies on an edge crossed by the plane, at ``x1 + t (x2 - x1)`` with ``x1`` the
  endpoint of lower value and ``t = -s1 / (s2 - s1)`` (float64, from the float32 values),
  stored in the vertex dtype. It is on the plane up to that float32 rounding (about 1e-7 of
  the values along the edge), not to float64 precision.
* Vertices are merged by exact coordinates (``vtkMergePoints``): the two triangles beside a
  cut edge share its new vertex, and source vertices with equal coordinates become one.
  A triangle that so names a vertex twice is dropped.
* Output vertices are numbered in order of first use by the output triangles, which come
  in source-face order (``vtkCleanPolyData``); vertices no output triangle uses are dropped.
"""

from __future__ import annotations

import numpy as np

from geofeat.errors import MeshError

__all__ = ["clip_plane"]

# Marching-triangles table of vtkTriangle::Clip. Case index: bit k set when corner k is kept.
# Codes 0, 1, 2 are the edges (0, 1), (1, 2), (2, 0) (a new vertex where the plane crosses
# them); codes 3, 4, 5 are the corners 0, 1, 2. Each case lists its output triangles.
_CASES: tuple[tuple[tuple[int, int, int], ...], ...] = (
    (),
    ((0, 2, 3),),
    ((1, 0, 4),),
    ((1, 2, 3), (1, 3, 4)),
    ((2, 1, 5),),
    ((0, 1, 5), (5, 3, 0)),
    ((0, 4, 2), (2, 4, 5)),
    ((3, 4, 5),),
)
_COUNTS = np.array([len(triangles) for triangles in _CASES])
_TABLE = np.array([list(triangles) + [(0, 0, 0)] * (2 - len(triangles)) for triangles in _CASES], dtype=np.int64)
_EDGE_ENDS = np.array([[0, 1], [1, 2], [2, 0]])


def clip_plane(verts, faces, point, normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The part of a triangle mesh on the side of a plane its normal points into.

    Triangles the plane crosses are cut: their kept part is triangulated with new vertices
    on the crossed edges. The result equals Open3D 0.20's
    ``open3d.t.geometry.TriangleMesh.clip_plane`` (VTK ``vtkClipPolyData`` then
    ``vtkCleanPolyData``), vertex and face order included; see the module docstring.

    Parameters
    ----------
    verts : array_like, shape (V, 3), float32 or float64
        Vertex coordinates. The output vertices have this dtype (Open3D's tensor meshes made
        by ``from_legacy`` are float32: pass float32 for its results).
    faces : array_like of int, shape (F, 3)
        Triangles, 0-based.
    point : array_like, shape (3,)
        A point of the plane.
    normal : array_like, shape (3,)
        Plane normal, any non-zero length; the side it points into is kept.

    Returns
    -------
    verts : numpy.ndarray, shape (V', 3), dtype of ``verts``
        Kept source vertices and new vertices on the plane, merged by coordinates, in order
        of first use by the output faces.
    faces : numpy.ndarray, shape (F', 3), int64
        Output triangles, in order of their source faces.
    parent : numpy.ndarray, shape (F',), int64
        For each output triangle the source face it was cut from (non-decreasing).

    Raises
    ------
    MeshError
        For arrays of the wrong shape or dtype, indices out of range, a non-finite plane or
        a zero normal.
    """
    verts, faces, point, normal = _checked(verts, faces, point, normal)
    dtype = verts.dtype
    coords = verts.astype(np.float64)
    # the plane function of vtkPlane, evaluated in float64 and stored in a float32 array
    value = normal[0] * (coords[:, 0] - point[0]) + normal[1] * (coords[:, 1] - point[1])
    value = (value + normal[2] * (coords[:, 2] - point[2])).astype(np.float32).astype(np.float64)
    kept = value > 0
    case = kept[faces] @ np.array([1, 2, 4])

    # Output triangles in source-face order, the triangles of one face in table order.
    count = _COUNTS[case]
    parent = np.repeat(np.arange(len(faces), dtype=np.int64), count)
    slot = np.arange(parent.size) - np.repeat(np.cumsum(count) - count, count)
    codes = _TABLE[case[parent], slot]

    corners = _corner_coordinates(coords, value, faces[parent], codes).astype(dtype)
    # vtkMergePoints: one vertex per distinct coordinate triple (-0.0 equals 0.0)
    corners = corners + dtype.type(0)
    keys = np.ascontiguousarray(corners).view(np.dtype((np.void, 3 * dtype.itemsize))).ravel()
    _, first, merged = np.unique(keys, return_index=True, return_inverse=True)
    merged = merged.reshape(-1, 3)
    distinct = (merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2]) & (merged[:, 0] != merged[:, 2])
    merged, parent = merged[distinct], parent[distinct]
    # vtkCleanPolyData: number the used vertices in order of first use
    flat = merged.ravel()
    used, first_use = np.unique(flat, return_index=True)
    new_order = used[np.argsort(first_use, kind="stable")]
    new_index = np.empty(len(first), dtype=np.int64)
    new_index[new_order] = np.arange(new_order.size)
    out_verts = corners[first[new_order]]
    out_faces = new_index[merged].reshape(-1, 3)
    return out_verts, out_faces, parent


def _corner_coordinates(coords: np.ndarray, value: np.ndarray, faces: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Coordinates (T * 3, 3) float64 of the corners of T output triangles given as codes."""
    rows = np.repeat(np.arange(len(faces)), 3)
    codes = codes.ravel()
    out = np.empty((codes.size, 3), dtype=np.float64)
    is_corner = codes >= 3
    out[is_corner] = coords[faces[rows[is_corner], codes[is_corner] - 3]]
    edge = ~is_corner
    a = faces[rows[edge], _EDGE_ENDS[codes[edge], 0]]
    b = faces[rows[edge], _EDGE_ENDS[codes[edge], 1]]
    # vtkTriangle::Clip interpolates from the endpoint of lower value
    swap = ~(value[b] - value[a] > 0)
    low, high = np.where(swap, b, a), np.where(swap, a, b)
    delta = value[high] - value[low]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(delta == 0.0, 0.0, (0.0 - value[low]) / delta)
    out[edge] = coords[low] + t[:, None] * (coords[high] - coords[low])
    return out


def _checked(verts, faces, point, normal):
    verts = np.asarray(verts)
    if verts.ndim != 2 or verts.shape[1] != 3 or verts.dtype not in (np.float32, np.float64):
        raise MeshError(
            f"verts must be a float32 or float64 array of shape (V, 3); found dtype {verts.dtype}, shape {verts.shape}."
        )
    if not np.isfinite(verts).all():
        raise MeshError("verts contain NaN or infinite coordinates; a plane clip needs finite vertices.")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and faces.dtype.kind not in "iu"):
        raise MeshError(f"faces must be an integer array of shape (F, 3); found dtype {faces.dtype}, shape {faces.shape}.")
    faces = faces.astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise MeshError(f"face indices must lie in [0, {len(verts) - 1}]; found [{faces.min()}, {faces.max()}].")
    point = np.asarray(point, dtype=np.float64)
    normal = np.asarray(normal, dtype=np.float64)
    if point.shape != (3,) or normal.shape != (3,):
        raise MeshError(f"point and normal must have shape (3,); found {point.shape} and {normal.shape}.")
    if not (np.isfinite(point).all() and np.isfinite(normal).all()):
        raise MeshError(f"point and normal must be finite; found point {point.tolist()}, normal {normal.tolist()}.")
    if not np.any(normal):
        raise MeshError("normal is the zero vector: it gives no plane; pass a non-zero normal.")
    return np.ascontiguousarray(verts), faces, point, normal
