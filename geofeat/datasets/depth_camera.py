"""A virtual depth camera: scans a triangle mesh into a point cloud that remembers where each point came from.

`scan_mesh` places a pinhole camera at a random viewpoint around a shape, casts one ray
through every pixel centre with geofeat's rasterizer (`geofeat.render.rasterizer.rasterize`:
the nearest face at each pixel and the barycentric coordinates of the point hit, back faces
included), and returns a `Scan`: the point cloud, and for each point the face and
barycentric coordinates of the surface point its ray hit (`SurfacePoints`), so that ground
truth through the scanned mesh is exact.

What the camera does (settings in `DepthCamera`):

1. **Viewpoint.** +y is up (as in the camera layouts of `geofeat.render.camera_layouts`;
   FAUST_r and the built-in humans stand along +y). The camera looks at the centre of the
   shape's bounding box from a direction of azimuth uniform in [0, 360) degrees and
   elevation drawn uniformly over the area of the band ``elevation_degrees`` (uniform
   ``sin(elevation)``), at ``distance_factor`` times the distance at which the bounding
   sphere (about that centre) just fills the field of view.
2. **Rays.** One per pixel centre of an ``image_size`` image with ``fov_degrees`` across its
   shorter side (the pixel convention of `geofeat.render.cameras`); a ray that hits nothing
   gives no point. Points come in image order (row by row).
3. **Grazing dropout** (``dropout_start_degrees``, None: off). A real sensor loses returns
   where the surface turns away from it: a point whose ray meets the surface at an angle
   theta from its normal is kept with probability ``(90 - theta) / (90 - start)``, clipped
   to [0, 1] (always kept up to ``start`` degrees, never at 90).
4. **Depth noise.** Each kept point moves along its ray by a Gaussian amount of standard
   deviation ``depth_noise`` times the bounding-box diagonal; its surface point (the ground
   truth) stays where the ray hit.

Everything random comes from one ``seed`` (viewpoint, dropout, noise, in that order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from geofeat.errors import MeshError, RenderError
from geofeat.geometry.surface_points import SurfacePoints
from geofeat.geometry.visibility import visible_faces
from geofeat.mesh import Mesh, require_faces
from geofeat.storage.jsonconfig import JsonConfig

__all__ = ["MIN_SCAN_POINTS", "DepthCamera", "Scan", "scan_mesh"]

#: Fewest points a scan may have (a spectral descriptor on points needs more than 30).
MIN_SCAN_POINTS = 100
#: Elevations beyond this (degrees) would look along the up axis, where a look-at frame is undefined.
_MAX_ELEVATION = 80.0


@dataclass(frozen=True)
class DepthCamera(JsonConfig):
    """Settings of the virtual depth camera (see the module notes for what each does).

    Parameters
    ----------
    image_size : int or (int, int)
        ``(H, W)`` pixels, one ray each; an int is a square image. The default gives a
        FAUST_r body about 2,000 to 4,000 points, depending on the side it is seen from.
    fov_degrees : float
        Field of view across the shorter image side, in (0, 180).
    elevation_degrees : (float, float)
        Range of the viewpoint's elevation above the horizontal plane, within [-80, 80].
    distance_factor : float
        Camera distance, in units of the distance at which the bounding sphere fills the
        field of view (>= 1: the whole shape is in view).
    depth_noise : float
        Standard deviation of the noise along each ray, a fraction of the bounding-box
        diagonal (0: none).
    dropout_start_degrees : float or None
        Incidence angle from which points start to drop out, in [0, 90); None: no dropout.
    """

    error: ClassVar[type] = RenderError

    image_size: int | tuple[int, int] = 160
    fov_degrees: float = 50.0
    elevation_degrees: tuple[float, float] = (-30.0, 30.0)
    distance_factor: float = 1.0
    depth_noise: float = 0.002
    dropout_start_degrees: float | None = 70.0

    def __post_init__(self) -> None:
        size = (self.image_size, self.image_size) if isinstance(self.image_size, (int, np.integer)) else self.image_size
        if len(tuple(size)) != 2 or not all(isinstance(s, (int, np.integer)) and s >= 1 for s in size):
            raise RenderError(f"image_size must be a positive int or (H, W) of positive ints; found {self.image_size!r}.")
        if not 0.0 < float(self.fov_degrees) < 180.0:
            raise RenderError(f"fov_degrees must lie in (0, 180); found {self.fov_degrees!r}.")
        low, high = (float(v) for v in self.elevation_degrees)
        if not -_MAX_ELEVATION <= low <= high <= _MAX_ELEVATION:
            raise RenderError(
                f"elevation_degrees must be (low, high) with -{_MAX_ELEVATION:g} <= low <= high <= {_MAX_ELEVATION:g}; "
                f"found {self.elevation_degrees!r}."
            )
        if not (math.isfinite(self.distance_factor) and self.distance_factor >= 1.0):
            raise RenderError(
                f"distance_factor must be a finite number >= 1 (the shape in view); found {self.distance_factor!r}."
            )
        if not (math.isfinite(self.depth_noise) and self.depth_noise >= 0.0):
            raise RenderError(f"depth_noise must be a finite number >= 0; found {self.depth_noise!r}.")
        start = self.dropout_start_degrees
        if start is not None and not 0.0 <= float(start) < 90.0:
            raise RenderError(f"dropout_start_degrees must be None or lie in [0, 90); found {start!r}.")
        object.__setattr__(self, "image_size", tuple(int(s) for s in size))
        object.__setattr__(self, "elevation_degrees", (low, high))


@dataclass(frozen=True, eq=False)
class Scan:
    """A depth scan of a mesh.

    Attributes
    ----------
    cloud : Mesh
        The scanned points, P of them (a point cloud: ``faces`` None), noise included.
    surface : SurfacePoints
        For each point, the face and barycentric coordinates of the surface point its ray hit
        on the scanned mesh (``surface.mesh``), before noise.
    eye : numpy.ndarray, shape (3,), float64
        The camera position.
    target : numpy.ndarray, shape (3,), float64
        The point looked at (the centre of the mesh's bounding box).
    pixels : numpy.ndarray, shape (P, 2), int64
        ``(row, column)`` of each point's pixel.
    """

    cloud: Mesh
    surface: SurfacePoints
    eye: np.ndarray
    target: np.ndarray
    pixels: np.ndarray

    def seen_faces(self) -> np.ndarray:
        """Faces of the scanned mesh the camera sees (`geofeat.geometry.visibility.visible_faces`), shape (F,) bool.

        Whatever the resolution: a face smaller than a pixel may have no point and still be seen.
        """
        return visible_faces(self.surface.mesh, self.eye, self.target)


def scan_mesh(
    mesh: Mesh, camera: DepthCamera | None = None, seed=0, name: str | None = None, min_points: int = MIN_SCAN_POINTS
) -> Scan:
    """Scan a triangle mesh with a virtual depth camera from a random viewpoint.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh, +y up.
    camera : DepthCamera, optional
        Settings (default `DepthCamera()`).
    seed : int or numpy.random.Generator
        Draws the viewpoint, the dropout and the noise.
    name : str, optional
        Name of the point cloud (default ``"<mesh name>_scan"``).
    min_points : int
        Fewest points accepted.

    Returns
    -------
    Scan

    Raises
    ------
    MeshError
        A point cloud for ``mesh``, a mesh of zero size, or a scan of fewer than
        ``min_points`` points.
    """
    from geofeat.render.camera_layouts import look_at_rotation
    from geofeat.render.cameras import Cameras
    from geofeat.render.rasterizer import RasterSettings, rasterize

    camera = camera if camera is not None else DepthCamera()
    faces = require_faces(mesh, "a depth scan")
    rng = np.random.default_rng(seed)
    target, eye = _viewpoint(mesh, camera, rng)
    rotation = look_at_rotation(eye[None], target)
    cameras = Cameras(rotation, eye[None], camera.image_size, camera.fov_degrees, device="cpu")
    fragments = rasterize(mesh, None, cameras, RasterSettings(cull_backfaces=False))
    hit = (fragments.pix_to_face[0] >= 0).numpy()
    pixels = np.argwhere(hit).astype(np.int64)  # row-major: image order
    face = fragments.pix_to_face[0].numpy()[hit].astype(np.int64)
    bary = np.clip(fragments.bary[0].numpy()[hit].astype(np.float64), 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    surface = SurfacePoints(mesh, face, bary)
    points = surface.positions()
    rays = points - eye
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    keep = _kept_after_dropout(mesh.verts[faces[face]], rays, camera.dropout_start_degrees, rng)
    noise = rng.normal(0.0, camera.depth_noise * mesh.bbox_diagonal(), size=int(keep.sum()))
    if keep.sum() < min_points:
        raise MeshError(
            f"the scan of {mesh.name!r} has {int(keep.sum())} points, fewer than {min_points}: the camera sees too little "
            "of it. Raise image_size, or check that the mesh is not degenerate."
        )
    surface = SurfacePoints(mesh, face[keep], bary[keep])
    cloud = Mesh(points[keep] + noise[:, None] * rays[keep], None, name=name or f"{mesh.name}_scan")
    for array in (eye, target, pixels):
        array.flags.writeable = False
    return Scan(cloud, surface, eye, target, pixels[keep])


def _viewpoint(mesh: Mesh, camera: DepthCamera, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The target (bounding-box centre) and a random eye position, each shape (3,) float64."""
    target = 0.5 * (mesh.verts.min(axis=0) + mesh.verts.max(axis=0))
    radius = float(np.linalg.norm(mesh.verts - target, axis=1).max())
    if not radius > 0:
        raise MeshError(f"{mesh.name!r} has zero size: every vertex is at one point; there is nothing to scan.")
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    low, high = (math.sin(math.radians(e)) for e in camera.elevation_degrees)
    elevation = math.asin(rng.uniform(low, high))
    direction = np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation), math.cos(elevation) * math.cos(azimuth)])
    distance = camera.distance_factor * radius / math.sin(math.radians(camera.fov_degrees) / 2.0)
    return target, target + distance * direction


def _kept_after_dropout(
    corners: np.ndarray, rays: np.ndarray, start_degrees: float | None, rng: np.random.Generator
) -> np.ndarray:
    """Which points survive the grazing dropout, shape (P,) bool (all without dropout).

    ``corners`` (P, 3, 3) are the corners of each point's face, ``rays`` (P, 3) unit ray directions.
    """
    if start_degrees is None:
        return np.ones(rays.shape[0], dtype=bool)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normals, axis=1)
    cosine = np.abs(np.einsum("pi,pi->p", normals, rays)) / np.where(length > 0, length, np.inf)
    angle = np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))
    keep_probability = np.clip((90.0 - angle) / (90.0 - start_degrees), 0.0, 1.0)
    return rng.random(rays.shape[0]) < keep_probability
