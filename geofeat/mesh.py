"""Triangle meshes and point clouds: the `Mesh` record, validation, loading and normalisation.

Loading never merges, drops or reorders vertices: ground-truth correspondence files index
them by position in the file.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from geofeat.errors import MeshError
from geofeat.topology import edge_counts, triangle_areas, vertex_components

log = logging.getLogger(__name__)

_REPORTS_QUIET = contextvars.ContextVar("geofeat_mesh_reports_quiet", default=False)


@contextlib.contextmanager
def quiet_reports() -> Iterator[None]:
    """Meshes made inside the block do not log the problems of `Mesh.report`.

    For meshes derived in bulk whose problems are expected, such as the partial shapes of
    training samples (a plane cut can leave non-manifold edges); `Mesh.report` still lists them.
    """
    token = _REPORTS_QUIET.set(True)
    try:
        yield
    finally:
        _REPORTS_QUIET.reset(token)


#: File types `load_mesh` reads (and the ones ``geofeat extract --data`` and training folders look for).
MESH_SUFFIXES = (".off", ".obj", ".ply")


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh, or a point cloud when ``faces`` is None.

    Parameters
    ----------
    verts : array_like, shape (V, 3)
        Vertex coordinates, any real dtype; stored as float64.
    faces : array_like of int, shape (F, 3), optional
        0-based vertex indices of triangles; stored as int64. None for a point cloud.
    name : str
        A label (file stem when loaded); not part of the content hash.

    Notes
    -----
    The arrays are validated and made read-only, so the content hash stays true.
    Problems that can be handled (degenerate faces, unreferenced vertices, non-manifold
    edges, several components) are logged as warnings; see `Mesh.report`.
    """

    verts: np.ndarray
    faces: np.ndarray | None = None
    name: str = ""
    _hash: str = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        verts = _validated_verts(self.verts)
        faces = None if self.faces is None else _validated_faces(self.faces, len(verts))
        if faces is not None:
            faces = _without_repeated_faces(faces, str(self.name))
        verts.flags.writeable = False
        if faces is not None:
            faces.flags.writeable = False
        object.__setattr__(self, "verts", verts)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "name", str(self.name))
        object.__setattr__(self, "_hash", _content_hash(verts, faces))
        if not _REPORTS_QUIET.get():
            for problem in self.report():
                log.warning("mesh %r: %s", self.name or "<unnamed>", problem)

    @property
    def n_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.verts.shape[0])

    @property
    def is_point_cloud(self) -> bool:
        """True when the mesh has no faces."""
        return self.faces is None

    @property
    def hash(self) -> str:
        """SHA-256 hex digest of exactly the vertex and face arrays (not the name)."""
        return self._hash

    def renamed(self, name: str) -> Mesh:
        """The same (already validated, read-only) arrays and hash under another name."""
        clone = object.__new__(Mesh)
        for attribute in ("verts", "faces", "_hash"):
            object.__setattr__(clone, attribute, getattr(self, attribute))
        object.__setattr__(clone, "name", str(name))
        return clone

    def face_areas(self) -> np.ndarray:
        """Triangle areas, shape (F,) float64, read-only (computed once per mesh)."""
        if self.faces is None:
            raise MeshError(f"mesh {self.name!r} is a point cloud: it has no faces, so no face areas")
        return self._face_areas

    @cached_property
    def _face_areas(self) -> np.ndarray:
        areas = triangle_areas(self.verts, require_faces(self, "face areas"))
        areas.flags.writeable = False
        return areas

    def centroid(self) -> np.ndarray:
        """The area-weighted centroid of the triangles, shape (3,) float64, read-only (computed once per mesh).

        Raises
        ------
        MeshError
            For a point cloud, or a mesh of zero surface area.
        """
        return self._centroid

    @cached_property
    def _centroid(self) -> np.ndarray:
        areas = self.face_areas()
        if not areas.sum() > 0:
            raise MeshError(f"mesh {self.name!r} has zero surface area; it has no area-weighted centroid.")
        centroid = (self.verts[self.faces].mean(axis=1) * areas[:, None]).sum(axis=0) / areas.sum()
        centroid.flags.writeable = False
        return centroid

    def area(self) -> float:
        """Total surface area of the triangles."""
        return float(self.face_areas().sum())

    def report(self) -> list[str]:
        """Problems that geofeat handles but a user should know about.

        Returns
        -------
        list of str
            One sentence per kind of problem: degenerate faces, unreferenced vertices,
            non-manifold edges, several connected components. Empty for a clean mesh.
        """
        if self.faces is None:
            return []
        problems = []
        faces = self.faces
        n_degenerate = int(np.count_nonzero(self.face_areas() <= 1e-14 * max(self.bbox_diagonal(), 1e-300) ** 2))
        if n_degenerate:
            problems.append(f"{n_degenerate} degenerate face(s) (zero area or repeated vertex)")
        n_unref = int(np.count_nonzero(np.bincount(faces.ravel(), minlength=self.n_vertices) == 0))
        if n_unref:
            problems.append(f"{n_unref} unreferenced vertex(es): their features are copied from the nearest referenced vertex")
        n_nonmanifold = int(np.count_nonzero(edge_counts(faces) > 2))
        if n_nonmanifold:
            problems.append(f"{n_nonmanifold} non-manifold edge(s) (shared by more than two faces)")
        n_components = self.n_components()
        if n_components > 1:
            problems.append(f"{n_components} connected components")
        return problems

    def n_components(self) -> int:
        """Number of connected components of the face graph (unreferenced vertices not counted)."""
        if self.faces is None:
            return 1
        used = np.bincount(self.faces.ravel(), minlength=self.n_vertices) > 0
        _, labels = vertex_components(self.n_vertices, self.faces)
        return int(np.unique(labels[used]).size)

    def bbox_diagonal(self) -> float:
        """Length of the bounding-box diagonal."""
        return float(np.linalg.norm(self.verts.max(axis=0) - self.verts.min(axis=0)))

    def __setstate__(self, state: dict) -> None:
        """Unpickled (a copy, or a mesh from another process): its arrays read-only again, as when constructed."""
        for value in state.values():
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
        self.__dict__.update(state)

    def __repr__(self) -> str:
        kind = "point cloud" if self.faces is None else f"{len(self.faces)} faces"
        return f"Mesh(name={self.name!r}, {self.n_vertices} vertices, {kind}, hash={self.hash[:12]})"


def require_faces(mesh: Mesh, what: str) -> np.ndarray:
    """The faces (F, 3) int64 of ``mesh``; `MeshError` naming ``what`` needs them for a point cloud."""
    if mesh.faces is None:
        raise MeshError(f"{mesh.name!r} is a point cloud: {what} needs a triangle mesh with faces.")
    return mesh.faces


def _validated_verts(verts) -> np.ndarray:
    arr = np.asarray(verts)
    if arr.dtype.kind not in "fiu" or arr.dtype == np.float16:
        raise MeshError(
            f"verts must be a real numeric array of shape (V, 3); found dtype {arr.dtype}. "
            "Convert with np.asarray(verts, dtype=np.float64)."
        )
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MeshError(f"verts must have shape (V, 3); found shape {arr.shape}.")
    if arr.shape[0] == 0:
        raise MeshError("the mesh is empty: verts has shape (0, 3); expected at least one vertex.")
    arr = np.array(arr, dtype=np.float64, order="C", copy=True)
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise MeshError(
            f"verts contain NaN or infinite coordinates at {idx.size} vertex(es), "
            f"first at index {idx[:5].tolist()}; clean or remove them before building a Mesh."
        )
    return arr


def _validated_faces(faces, n_vertices: int) -> np.ndarray:
    arr = np.asarray(faces)
    if arr.dtype == object:
        raise MeshError("faces have different numbers of corners; only triangles (F, 3) are supported. Triangulate first.")
    if arr.ndim != 2:
        raise MeshError(f"faces must have shape (F, 3); found shape {arr.shape}.")
    if arr.shape[1] != 3:
        raise MeshError(
            f"faces must be triangles, shape (F, 3); found {arr.shape[1]}-sided faces, shape {arr.shape}. "
            "Triangulate first (for example trimesh.Trimesh(...).triangles)."
        )
    if arr.shape[0] == 0:
        raise MeshError("faces has shape (0, 3): a mesh needs at least one face; pass faces=None for a point cloud.")
    if arr.dtype.kind not in "iu":
        raise MeshError(f"faces must be an integer array; found dtype {arr.dtype}. Convert with faces.astype(np.int64).")
    arr = np.array(arr, dtype=np.int64, order="C", copy=True)
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi >= n_vertices:
        raise MeshError(
            f"face indices must lie in [0, {n_vertices - 1}] (0-based, {n_vertices} vertices); "
            f"found range [{lo}, {hi}]. 1-based indices? Subtract 1."
        )
    return arr


def _without_repeated_faces(faces: np.ndarray, name: str) -> np.ndarray:
    """``faces`` without the faces that name a vertex twice and without repeats of a triangle.

    Such faces have no area and add nothing to a surface, but a solver can pay for each of
    them: the robust Laplacian's time grows with the square of the number of faces on one
    edge. A repeat is a face with the same three vertices as an earlier one, in any order;
    the first is kept. Each kind dropped is logged as a warning with its count.

    Parameters
    ----------
    faces : numpy.ndarray, shape (F, 3), int64
    name : str
        The mesh's name, for the warning.

    Returns
    -------
    numpy.ndarray, shape (F', 3), int64
        ``faces`` itself when nothing is dropped, else the kept rows in their order.

    Raises
    ------
    MeshError
        If every face names a vertex twice.
    """
    corners = np.sort(faces, axis=1)
    collapsed = (corners[:, 0] == corners[:, 1]) | (corners[:, 1] == corners[:, 2])
    n_collapsed = int(np.count_nonzero(collapsed))
    if n_collapsed == len(faces):
        raise MeshError(f"mesh {name or '<unnamed>'!r}: every face names one vertex twice; there is no surface left.")
    candidates = np.flatnonzero(~collapsed)
    n_vertices = int(corners.max()) + 1
    if n_vertices < 2**21:  # one int64 key per triangle: a 1-D sort instead of a sort of rows
        keys = (corners[candidates, 0] * n_vertices + corners[candidates, 1]) * n_vertices + corners[candidates, 2]
        _, first = np.unique(keys, return_index=True)
    else:
        _, first = np.unique(corners[candidates], axis=0, return_index=True)
    keep = np.zeros(len(faces), dtype=bool)
    keep[candidates[first]] = True
    n_repeats = len(candidates) - len(first)
    if n_collapsed:
        log.warning("mesh %r: dropped %d face(s) that name one vertex twice (no area)", name or "<unnamed>", n_collapsed)
    if n_repeats:
        log.warning(
            "mesh %r: dropped %d repeated face(s) (the same three vertices as an earlier face)", name or "<unnamed>", n_repeats
        )
    return faces if keep.all() else faces[keep]


def _content_hash(verts: np.ndarray, faces: np.ndarray | None) -> str:
    digest = hashlib.sha256()
    digest.update(f"verts{verts.shape}<f8".encode())
    digest.update(verts.astype("<f8", copy=False).tobytes())
    if faces is None:
        digest.update(b"faces:none")
    else:
        digest.update(f"faces{faces.shape}<i8".encode())
        digest.update(faces.astype("<i8", copy=False).tobytes())
    return digest.hexdigest()


def normalize(mesh: Mesh, center: bool | str = True, frame: Mesh | None = None) -> Mesh:
    """Scale a mesh to unit surface area, optionally centring it first.

    Parameters
    ----------
    mesh : Mesh
        Input triangle mesh.
    center : bool or {"centroid", "mean"}
        True or ``"centroid"``: subtract the area-weighted centroid; ``"mean"``: subtract the
        mean vertex (the preprocessing of the DPFM and ULRSSM references); False: no translation.
    frame : Mesh, optional
        The mesh whose surface area and centre define the transform (default: ``mesh``). A
        partial shape normalised in the frame of the full shape it was cut from keeps its
        place and scale relative to it.

    Returns
    -------
    Mesh
        A new mesh with the same faces and vertex order:
        ``(mesh.verts - centre(frame)) / sqrt(area(frame))``.

    Raises
    ------
    MeshError
        ``frame`` has no surface area (a point cloud, or degenerate triangles only), or
        ``center`` is not one of the values above.
    """
    frame = mesh if frame is None else frame
    if center not in (True, False, "centroid", "mean"):
        raise MeshError(f"center must be True, False, 'centroid' or 'mean'; found {center!r}.")
    area = frame.area()  # MeshError for a point cloud
    if not area > 0:
        raise MeshError(f"mesh {frame.name!r} has zero surface area; it cannot be normalised to unit area.")
    verts = mesh.verts
    if center:
        verts = verts - (frame.verts.mean(axis=0) if center == "mean" else frame.centroid())
    return Mesh(verts / np.sqrt(area), mesh.faces, name=mesh.name)


def as_mesh(obj: Any) -> Mesh:
    """A `Mesh` from any mesh input geofeat accepts.

    Parameters
    ----------
    obj : Mesh, path, (verts, faces) or trimesh object
        A `Mesh` (returned as is); a ``.off``/``.obj``/``.ply`` path (read with `load_mesh`);
        a pair ``(verts, faces)`` of arrays, ``faces`` None for a point cloud; a
        ``trimesh.Trimesh`` or ``trimesh.PointCloud`` (its vertices in the order it holds
        them: trimesh merges duplicate vertices on load unless ``process=False``).

    Returns
    -------
    Mesh

    Raises
    ------
    MeshError
        Anything else (a bare array, a ``trimesh.Scene``, ...); the message lists what is accepted.
    """
    if isinstance(obj, Mesh):
        return obj
    if isinstance(obj, (str, os.PathLike)):
        return load_mesh(obj)
    if isinstance(obj, (tuple, list)) and len(obj) == 2:
        verts, faces = obj
        return Mesh(verts, faces)
    module = type(obj).__module__ or ""
    if module.split(".")[0] == "trimesh":
        import trimesh

        if isinstance(obj, trimesh.Trimesh):
            return Mesh(np.asarray(obj.vertices), np.asarray(obj.faces) if len(obj.faces) else None, name=_trimesh_name(obj))
        if isinstance(obj, trimesh.PointCloud):
            return Mesh(np.asarray(obj.vertices), None, name=_trimesh_name(obj))
        if isinstance(obj, trimesh.Scene):
            raise MeshError(
                "found a trimesh.Scene (several geometries); expected one mesh. Merge it first with "
                "scene.to_geometry() (trimesh >= 4.5) or trimesh.util.concatenate(list(scene.geometry.values())), "
                "or load the file with trimesh.load(path, force='mesh')."
            )
    if isinstance(obj, np.ndarray):
        found = f"a numpy array of shape {obj.shape}"
    else:
        found = f"a {type(obj).__module__}.{type(obj).__qualname__}"
    raise MeshError(
        f"cannot use {found} as a mesh; expected a geofeat.Mesh, a .off/.obj/.ply path, a (verts, faces) pair "
        "(verts (V, 3), faces (F, 3) int or None for a point cloud) or a trimesh.Trimesh / trimesh.PointCloud. "
        "For a bare vertex array pass geofeat.Mesh(verts) (a point cloud) or (verts, faces)."
    )


def _trimesh_name(obj: Any) -> str:
    metadata = getattr(obj, "metadata", None) or {}
    name = metadata.get("file_name") or metadata.get("name") or ""
    return Path(str(name)).stem if name else ""


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read a mesh from ``.off``, ``.obj`` or ``.ply`` keeping the file's vertex order exactly.

    Parameters
    ----------
    path : str or PathLike
        Mesh file. A file without faces gives a point cloud.

    Returns
    -------
    Mesh
        ``verts`` (V, 3) float64 and ``faces`` (F, 3) int64 or None, named after the file stem.
        `Mesh` drops repeated and collapsed faces (with a warning); `read_mesh_arrays` gives
        the faces as the file lists them.
    """
    path = Path(path)
    verts, faces = read_mesh_arrays(path)
    try:
        return Mesh(verts, faces, name=path.stem)
    except MeshError as err:
        raise MeshError(f"{path}: {err}") from None


def read_mesh_arrays(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """The vertex and face arrays of a mesh file exactly as the file lists them, unchecked.

    For ground truth that indexes the file's own faces (SHREC'16's ``.baryc_gt`` names
    triangles by their row): `load_mesh` builds a `Mesh`, which drops repeated faces.

    Parameters
    ----------
    path : str or PathLike
        A ``.off``, ``.obj`` or ``.ply`` file.

    Returns
    -------
    verts : numpy.ndarray, shape (V, 3)
    faces : numpy.ndarray, shape (F, 3), int64, or None
        None for a file without faces.

    Raises
    ------
    MeshError
        An unsupported suffix, a missing file, or a file that is not in the format its suffix names.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"cannot read {path}: unsupported suffix {path.suffix!r}; expected one of {', '.join(MESH_SUFFIXES)}.")
    if not path.is_file():
        raise MeshError(f"cannot read {path}: no such file.")
    reader = {".off": _read_off, ".obj": _read_obj, ".ply": _read_ply}[suffix]
    try:
        return reader(path)
    except MeshError as err:
        raise MeshError(f"{path}: {err}") from None
    except (ValueError, IndexError, UnicodeDecodeError) as err:
        # the message says what was expected, never what the file holds (it may be any file)
        raise MeshError(
            f"{path}: malformed {suffix[1:].upper()} file: expected ASCII numbers in the layout of the format "
            f"(vertex coordinates, then faces as vertex counts and indices), found something else."
        ) from err


def _polygon_faces(polygons: list[list[int]]) -> np.ndarray | None:
    if not polygons:
        return None
    sizes = {len(p) for p in polygons}
    if sizes != {3}:
        raise MeshError(f"faces with {sorted(sizes)} corners found; only triangles are supported. Triangulate the file first.")
    return np.asarray(polygons, dtype=np.int64)


#: OFF variants named in an error (anything else is not quoted: the file may not be a mesh at all).
OFF_VARIANTS = frozenset({"COFF", "NOFF", "CNOFF", "STOFF", "STCOFF", "STNOFF", "4OFF", "nOFF"})


def _read_off(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    lines = []
    with open(path, encoding="ascii", errors="strict") as fh:
        for line in fh:
            line = line.split("#", 1)[0].strip()
            if line:
                lines.append(line)
    if not lines:
        raise MeshError("empty OFF file")
    header = lines[0].split()
    if not header[0].endswith("OFF"):
        raise MeshError("not an OFF file: its first line does not start with 'OFF'")
    if header[0] != "OFF":
        variant = repr(header[0]) if header[0] in OFF_VARIANTS else "an OFF variant"
        raise MeshError(f"{variant} is not supported; expected plain 'OFF' (vertices and triangles, no colours or normals)")
    counts = header[1:] if len(header) > 1 else lines.pop(1).split()
    n_verts, n_faces = int(counts[0]), int(counts[1])
    body = lines[1 : 1 + n_verts + n_faces]
    if len(body) < n_verts + n_faces:
        raise MeshError(f"header announces {n_verts} vertices and {n_faces} faces, file ends after {len(body)} rows")
    verts = np.array([row.split()[:3] for row in body[:n_verts]], dtype=np.float64).reshape(n_verts, 3)
    polygons = []
    for row in body[n_verts:]:
        values = row.split()
        n = int(values[0])
        polygons.append([int(v) for v in values[1 : 1 + n]])
    return verts, _polygon_faces(polygons)


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    verts, polygons = [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif parts[0] == "f":
                corners = []
                for token in parts[1:]:
                    index = int(token.split("/")[0])
                    corners.append(index - 1 if index > 0 else len(verts) + index)
                polygons.append(corners)
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), _polygon_faces(polygons)


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    from trimesh.exchange.ply import load_ply

    with open(path, "rb") as fh:
        data = load_ply(fh, fix_texture=False)
    sizes = _ply_polygon_sizes(data)
    if sizes and sizes != [3]:
        raise MeshError(f"faces with {sizes} corners found; only triangles are supported. Triangulate the file first.")
    faces = data.get("faces")
    faces = None if faces is None or len(faces) == 0 else np.asarray(faces, dtype=np.int64)
    return np.asarray(data["vertices"], dtype=np.float64), faces


def _ply_polygon_sizes(data: dict) -> list[int]:
    """Sorted distinct corner counts of the faces as the PLY file holds them (trimesh triangulates polygons)."""
    element = data.get("metadata", {}).get("_ply_raw", {}).get("face")
    if element is None:
        return []
    for key in ("vertex_indices", "vertex_index"):
        try:
            indices = element["data"][key]
        except (KeyError, ValueError, IndexError):
            continue
        indices = np.asarray(indices)
        if len(indices) == 0:
            return []
        if indices.dtype.names:  # binary: (count, fixed-size index array) records
            return sorted({int(c) for c in np.unique(indices[indices.dtype.names[0]])})
        if indices.dtype == object:  # ragged polygon lists
            return sorted({len(f) for f in indices})
        return [int(indices.shape[1])]
    return []
