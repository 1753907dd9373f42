"""Pinhole cameras for multi-view rendering: the `Cameras` record and the view layouts.

Conventions
-----------
Camera frame
    ``x`` right, ``y`` down, ``z`` forward (the viewing direction), right-handed. A world
    point ``X`` has camera coordinates ``R @ (X - C)``, where ``R`` (3, 3) is the
    world-to-camera rotation (its rows are the camera's x, y and z axes written in world
    coordinates) and ``C`` the camera position. Depth is the camera-space ``z``: the distance
    along the optical axis, not along the ray.
Pixels
    Continuous pixel coordinates ``(x, y)``: ``x`` grows to the right along a row (column
    index), ``y`` grows downwards (row index). Pixel ``[row, col]`` covers
    ``[col, col + 1) x [row, row + 1)`` and its centre is ``(col + 0.5, row + 0.5)``.
    The principal point is the image centre ``(W / 2, H / 2)`` unless given; the focal
    length in pixels is ``min(H, W) / 2 / tan(fov / 2)``, so ``fov_degrees`` spans the
    shorter image side. The rasterizer samples pixel centres, and `Cameras.project` /
    `Cameras.unproject` use the same coordinates, so
    ``cameras.unproject(cameras.pixel_centers()[mask], fragments.depth[view][mask])`` gives
    the surface points that the rasterizer saw.

Relation to pytorch3d (which GeoLoRA and Diff3f use): pytorch3d's camera frame is ``x``
left, ``y`` up, ``z`` forward, and its images put ``+x`` on the left and ``+y`` at the top,
so its pictures are the same as ours. A pytorch3d camera ``(R_p3d, T)`` from
``look_at_view_transform`` (row-vector convention ``X_view = X @ R_p3d + T``) is our camera
with ``R = diag(-1, -1, 1) @ R_p3d.T`` and ``C = -R_p3d @ T``. pytorch3d's default
``PerspectiveCameras`` (focal length 1 in NDC, principal point 0) is a 90 degree field of
view across the shorter image side.

Layouts
-------
``"official"``: `official_grid_cameras`, the layout of GeoLoRA (vikiehm/geo-lora,
``utils/dino_utils.py::run_rendering``) and Diff3f (niladridutt/Diffusion-3D-Features,
``render.py::run_rendering``). For ``N = s * s`` views, with ``a_k = k * 360 / s`` for
``k = 0 .. s - 1`` (``torch.linspace(0, 360 - 360 / s, s)``), view ``i`` has elevation
``a_(i mod s)`` and azimuth ``a_(i div s)`` (elevation varies fastest). The camera sits at
``target + d * (cos(e) sin(a), sin(e), cos(e) cos(a))`` with ``target`` the bounding-box
centre and ``d = 0.65 x`` the bounding-box diagonal, and looks at ``target`` with up = +y.
Elevations run over the whole circle, through the poles, so:

* when ``s`` is even, elevation ``e`` with azimuth ``a`` and elevation ``180 - e`` with
  azimuth ``a + 180`` are the same camera (same position, and the same rotation since the
  look-at frame depends on the position only): 4 views give 2 distinct camera positions,
  16 give 6, 36 give 18, 64 give 26, 100 give 50. Odd ``s`` (9, 25, 49, 81 views) has no
  repeats.
* when ``s`` is a multiple of 4, elevations 90 and 270 put cameras on the +y / -y axis,
  where the look-at frame with up = +y is undefined (pytorch3d then returns a rotation
  that depends on rounding or is singular; GeoLoRA and Diff3f catch the resulting
  ``LinAlgError`` and retry with random angle offsets). Here such a camera takes the limit of
  the frame as it approaches the pole from the side of its azimuth (``cos(elevation) > 0``):
  image up is ``-sin(e) * (sin(a), 0, cos(a))``. Deterministic; all cameras at one pole share
  their position, and their images differ by an in-plane rotation (their azimuth).

``"uniform"``: `fibonacci_cameras`, ``N`` directions on a Fibonacci sphere (distinct for every
``N``), same target, distance and field of view. None lies on the y axis (the nearest is
about ``sqrt(2 / N)`` radians from it), so the +y look-at frame stays well defined; a
camera exactly on the axis would get the azimuth-based up vector above.

Either layout can be turned about the vertical axis through the target by a random angle
(``random_rotation=True`` with a ``seed``), which is the same as GeoLoRA's random rotation
of the shape about y.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch

from geofeat.errors import RenderError
from geofeat.mesh import Mesh
from geofeat.runtime.devices import resolve_device

#: Camera distance as a multiple of the bounding-box diagonal (GeoLoRA / Diff3f ``scaling_factor``).
OFFICIAL_DISTANCE_FACTOR = 0.65
#: Field of view of pytorch3d's default ``PerspectiveCameras`` (focal length 1 in NDC).
OFFICIAL_FOV_DEGREES = 90.0
#: World up direction of the look-at frames (pytorch3d ``look_at_view_transform`` default).
WORLD_UP = (0.0, 1.0, 0.0)
CAMERA_LAYOUTS = ("official", "uniform")

_POLE_TOLERANCE = 1e-9  # |cross(up, view direction)| below this counts as looking along the up axis


def as_tensor(values, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> torch.Tensor:
    """`torch.as_tensor` that copies read-only numpy arrays (such as `Mesh.verts`) instead of warning."""
    if isinstance(values, np.ndarray) and not values.flags.writeable:
        values = values.copy()
    return torch.as_tensor(values, dtype=dtype, device=device)


class ProjectedPoints(NamedTuple):
    """World points seen by each camera.

    Attributes
    ----------
    pixels : torch.Tensor, shape (N, P, 2)
        Continuous pixel coordinates ``(x, y)`` (see the module conventions).
    depth : torch.Tensor, shape (N, P)
        Camera-space ``z``; points behind the camera have depth <= 0 and meaningless pixels.
    """

    pixels: torch.Tensor
    depth: torch.Tensor


@dataclass(frozen=True, eq=False)
class Cameras:
    """A batch of N pinhole cameras sharing one image size and field of view.

    Parameters
    ----------
    rotation : array_like, shape (N, 3, 3)
        World-to-camera rotations; rows are the camera's x (right), y (down) and z (forward)
        axes in world coordinates. Stored as float64.
    position : array_like, shape (N, 3)
        Camera centres in world coordinates. Stored as float64.
    image_size : int or (int, int)
        ``(H, W)`` in pixels; an int means a square image.
    fov_degrees : float
        Field of view across the shorter image side, in (0, 180).
    device : str or torch.device
        Where the tensors live; ``"auto"`` is CUDA when available, else CPU.
    principal_point : (float, float), optional
        ``(cx, cy)`` in continuous pixel coordinates; default the image centre ``(W / 2, H / 2)``.

    Notes
    -----
    Construct layouts with `official_grid_cameras`, `fibonacci_cameras` or `make_cameras`.
    """

    rotation: torch.Tensor
    position: torch.Tensor
    image_size: tuple[int, int]
    fov_degrees: float = OFFICIAL_FOV_DEGREES
    device: torch.device | str = "auto"
    principal_point: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        device = resolve_device(self.device)
        rotation = as_tensor(self.rotation, dtype=torch.float64, device=device)
        position = as_tensor(self.position, dtype=torch.float64, device=device)
        if rotation.ndim != 3 or rotation.shape[1:] != (3, 3):
            raise RenderError(f"camera rotation must have shape (N, 3, 3); found {tuple(rotation.shape)}.")
        if position.shape != (rotation.shape[0], 3):
            raise RenderError(
                f"camera position must have shape (N, 3) = ({rotation.shape[0]}, 3) to match the rotations; "
                f"found {tuple(position.shape)}."
            )
        if rotation.shape[0] == 0:
            raise RenderError("Cameras needs at least one view; found N = 0.")
        _check_rotations(rotation)
        if not torch.isfinite(position).all():
            raise RenderError("camera positions contain NaN or infinite values.")
        fov = float(self.fov_degrees)
        if not 0.0 < fov < 180.0:
            raise RenderError(f"fov_degrees must lie in (0, 180); found {self.fov_degrees!r}.")
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "position", position)
        image_size = _image_size(self.image_size)
        object.__setattr__(self, "image_size", image_size)
        object.__setattr__(self, "fov_degrees", fov)
        object.__setattr__(self, "device", device)
        object.__setattr__(self, "principal_point", _principal_point(self.principal_point, image_size))

    # ---------------------------------------------------------------- basic properties
    def __len__(self) -> int:
        return int(self.rotation.shape[0])

    @property
    def n_views(self) -> int:
        """Number of cameras N."""
        return len(self)

    @property
    def height(self) -> int:
        """Image height H in pixels."""
        return self.image_size[0]

    @property
    def width(self) -> int:
        """Image width W in pixels."""
        return self.image_size[1]

    @property
    def focal_length(self) -> float:
        """Focal length in pixels, ``min(H, W) / 2 / tan(fov / 2)`` (same for x and y)."""
        return min(self.image_size) / 2.0 / math.tan(math.radians(self.fov_degrees) / 2.0)

    def __getitem__(self, index: int | slice | torch.Tensor | np.ndarray | list) -> Cameras:
        """A sub-batch of views (an int keeps the view axis: N = 1)."""
        if isinstance(index, int):
            index = slice(index, index + 1) if index != -1 else slice(-1, None)
        return replace(self, rotation=self.rotation[index], position=self.position[index])

    def to(self, device: str | torch.device) -> Cameras:
        """The same cameras on another device."""
        return replace(self, device=device)

    def rotated_about_up(self, angle_degrees: float, center: np.ndarray | torch.Tensor | tuple[float, float, float]) -> Cameras:
        """Turn the whole rig about the vertical (+y) axis through ``center``.

        Rendering a shape with the turned rig is the same as rendering the shape turned by
        ``-angle_degrees`` with the original rig.

        Parameters
        ----------
        angle_degrees : float
            Counter-clockwise angle seen from +y (positive azimuth direction).
        center : array_like, shape (3,)
            A point on the rotation axis (the look-at target).
        """
        turn = torch.as_tensor(rotation_about_up(angle_degrees), device=self.device)
        center_t = torch.as_tensor(_as_numpy(center).reshape(3), device=self.device)
        position = (self.position - center_t) @ turn.T + center_t
        rotation = self.rotation @ turn.T
        return replace(self, rotation=rotation, position=position)

    # ---------------------------------------------------------------- transforms
    def world_to_camera(self, points: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Camera-frame coordinates of world points.

        Parameters
        ----------
        points : array_like, shape (P, 3) or (N, P, 3)
            World points, shared by all views or one set per view.

        Returns
        -------
        torch.Tensor, shape (N, P, 3)
            ``R @ (X - C)`` per view; float64 for float64 input, else float32.
        """
        points, dtype = self._points(points, "points")
        rotation, position = self.rotation.to(dtype), self.position.to(dtype)
        return torch.einsum("nij,npj->npi", rotation, points - position[:, None, :])

    def camera_to_world(self, points: torch.Tensor | np.ndarray) -> torch.Tensor:
        """World coordinates of camera-frame points, shape (N, P, 3) (inverse of `world_to_camera`)."""
        points, dtype = self._points(points, "camera points")
        rotation, position = self.rotation.to(dtype), self.position.to(dtype)
        return torch.einsum("nji,npj->npi", rotation, points) + position[:, None, :]

    def project(self, points: torch.Tensor | np.ndarray) -> ProjectedPoints:
        """Pixel coordinates and depth of world points in every view.

        Parameters
        ----------
        points : array_like, shape (P, 3) or (N, P, 3)

        Returns
        -------
        ProjectedPoints
            ``pixels`` (N, P, 2) and ``depth`` (N, P); float64 for float64 input, else float32.
        """
        cam = self.world_to_camera(points)
        depth = cam[..., 2]
        cx, cy = self.principal_point
        f = self.focal_length
        pixels = torch.stack((f * cam[..., 0] / depth + cx, f * cam[..., 1] / depth + cy), dim=-1)
        return ProjectedPoints(pixels, depth)

    def unproject(self, pixels: torch.Tensor | np.ndarray, depth: torch.Tensor | np.ndarray) -> torch.Tensor:
        """World points at given pixels and depths (inverse of `project`).

        Parameters
        ----------
        pixels : array_like, shape (P, 2) or (N, P, 2)
            Continuous pixel coordinates ``(x, y)``; pixel centres are ``(col + 0.5, row + 0.5)``.
        depth : array_like, shape (P,) or (N, P)
            Camera-space ``z`` (the rasterizer's ``Fragments.depth``).

        Returns
        -------
        torch.Tensor, shape (N, P, 3)
            float64 for float64 pixels, else float32.
        """
        pixels_t = as_tensor(pixels, device=self.device)
        depth_t = as_tensor(depth, device=self.device)
        dtype = torch.float64 if pixels_t.dtype == torch.float64 else torch.float32
        pixels_t, depth_t = pixels_t.to(dtype), depth_t.to(dtype)
        if pixels_t.shape[-1] != 2 or pixels_t.ndim not in (2, 3):
            raise RenderError(f"pixels must have shape (P, 2) or (N, P, 2); found {tuple(pixels_t.shape)}.")
        if depth_t.shape != pixels_t.shape[:-1]:
            raise RenderError(
                f"depth must have shape {tuple(pixels_t.shape[:-1])} to match the pixels; found {tuple(depth_t.shape)}."
            )
        cx, cy = self.principal_point
        f = self.focal_length
        cam = torch.stack(((pixels_t[..., 0] - cx) * depth_t / f, (pixels_t[..., 1] - cy) * depth_t / f, depth_t), dim=-1)
        return self.camera_to_world(cam)

    def pixel_centers(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """Continuous coordinates of every pixel centre, shape (H, W, 2): ``[r, c] = (c + 0.5, r + 0.5)``."""
        rows = torch.arange(self.height, dtype=dtype, device=self.device) + 0.5
        cols = torch.arange(self.width, dtype=dtype, device=self.device) + 0.5
        grid_y, grid_x = torch.meshgrid(rows, cols, indexing="ij")
        return torch.stack((grid_x, grid_y), dim=-1)

    def _points(self, points: torch.Tensor | np.ndarray, what: str) -> tuple[torch.Tensor, torch.dtype]:
        points_t = as_tensor(points, device=self.device)
        dtype = torch.float64 if points_t.dtype == torch.float64 else torch.float32
        points_t = points_t.to(dtype)
        if points_t.shape[-1:] != (3,) or points_t.ndim not in (2, 3):
            raise RenderError(f"{what} must have shape (P, 3) or (N, P, 3); found {tuple(points_t.shape)}.")
        if points_t.ndim == 2:
            points_t = points_t.expand(len(self), -1, -1)
        elif points_t.shape[0] != len(self):
            raise RenderError(
                f"{what} have {points_t.shape[0]} views in shape {tuple(points_t.shape)}; the cameras have {len(self)}."
            )
        return points_t, dtype

    def __repr__(self) -> str:
        return (
            f"Cameras(n_views={len(self)}, image_size={self.image_size}, fov_degrees={self.fov_degrees:g}, device={self.device})"
        )


# -------------------------------------------------------------------- look-at frames
def look_at_rotation(
    position: torch.Tensor | np.ndarray,
    target: torch.Tensor | np.ndarray,
    up: torch.Tensor | np.ndarray = WORLD_UP,
) -> torch.Tensor:
    """World-to-camera rotations of cameras at ``position`` looking at ``target``.

    Parameters
    ----------
    position : array_like, shape (N, 3)
    target : array_like, shape (3,) or (N, 3)
    up : array_like, shape (3,) or (N, 3)
        Image "up" (the camera's -y axis) is the part of ``up`` orthogonal to the viewing direction.

    Returns
    -------
    torch.Tensor, shape (N, 3, 3), float64
        Rows: camera x (right), y (down), z (forward) in world coordinates.

    Raises
    ------
    RenderError
        When a camera sits on its target or looks along ``up`` (the frame is undefined).
    """
    position = as_tensor(position, dtype=torch.float64)
    target = as_tensor(target, dtype=torch.float64, device=position.device).expand_as(position)
    up = as_tensor(up, dtype=torch.float64, device=position.device).expand_as(position)
    forward = target - position
    distance = forward.norm(dim=-1, keepdim=True)
    if bool((distance <= 0).any()):
        raise RenderError("a camera sits exactly on its look-at target; its viewing direction is undefined.")
    forward = forward / distance
    right = torch.linalg.cross(forward, up, dim=-1)
    right_norm = right.norm(dim=-1, keepdim=True)
    if bool((right_norm <= _POLE_TOLERANCE * up.norm(dim=-1, keepdim=True)).any()):
        raise RenderError(
            "a camera looks along its up vector, where the look-at frame is undefined; "
            "pass a per-view up vector (see geofeat.render.cameras.safe_up_vectors)."
        )
    right = right / right_norm
    down = torch.linalg.cross(forward, right, dim=-1)
    return torch.stack((right, down, forward), dim=1)


def safe_up_vectors(direction: torch.Tensor, azimuth_degrees: torch.Tensor) -> torch.Tensor:
    """+y, or an azimuth-based up vector for cameras on the y axis.

    Parameters
    ----------
    direction : torch.Tensor, shape (N, 3), float64
        Unit vectors from the target to each camera.
    azimuth_degrees : torch.Tensor, shape (N,), float64
        Each camera's azimuth, used only on the poles.

    Returns
    -------
    torch.Tensor, shape (N, 3), float64
        ``(0, 1, 0)`` where the look-at frame is defined; on the +y / -y axis,
        ``-sign(direction_y) * (sin(a), 0, cos(a))``: the limit of the +y frame as the camera
        reaches the pole from the side of its azimuth.
    """
    up = torch.zeros_like(direction)
    up[:, 1] = 1.0
    horizontal = torch.sqrt(direction[:, 0] ** 2 + direction[:, 2] ** 2)
    on_pole = horizontal <= _POLE_TOLERANCE
    if bool(on_pole.any()):
        azimuth = torch.deg2rad(azimuth_degrees[on_pole])
        sign = -torch.sign(direction[on_pole, 1])
        up[on_pole] = torch.stack((sign * torch.sin(azimuth), torch.zeros_like(azimuth), sign * torch.cos(azimuth)), dim=-1)
    return up


def spherical_directions(elevation_degrees: torch.Tensor, azimuth_degrees: torch.Tensor) -> torch.Tensor:
    """Unit vectors ``(cos(e) sin(a), sin(e), cos(e) cos(a))`` (pytorch3d's spherical convention), shape (N, 3) float64."""
    elevation = torch.deg2rad(as_tensor(elevation_degrees, dtype=torch.float64))
    azimuth = torch.deg2rad(as_tensor(azimuth_degrees, dtype=torch.float64))
    direction = torch.stack(
        (torch.cos(elevation) * torch.sin(azimuth), torch.sin(elevation), torch.cos(elevation) * torch.cos(azimuth)), dim=-1
    )
    # cos(90 deg) is ~6e-17 in float64: snap the poles so that they are recognised.
    near_zero = direction.abs() < 1e-12
    return torch.where(near_zero, torch.zeros_like(direction), direction)


def orbit_cameras(
    target: np.ndarray | torch.Tensor,
    distance: float,
    elevation_degrees: torch.Tensor | np.ndarray,
    azimuth_degrees: torch.Tensor | np.ndarray,
    image_size: int | tuple[int, int],
    fov_degrees: float = OFFICIAL_FOV_DEGREES,
    device: str | torch.device = "auto",
) -> Cameras:
    """Cameras on a sphere around ``target`` looking at it, up = +y (poles handled by `safe_up_vectors`).

    Parameters
    ----------
    target : array_like, shape (3,)
    distance : float
        Sphere radius (> 0).
    elevation_degrees, azimuth_degrees : array_like, shape (N,)
        pytorch3d's angles: position ``target + distance * (cos(e) sin(a), sin(e), cos(e) cos(a))``.
    image_size : int or (int, int)
    fov_degrees : float
    device : str or torch.device

    Returns
    -------
    Cameras
    """
    elevation = as_tensor(elevation_degrees, dtype=torch.float64).reshape(-1)
    azimuth = as_tensor(azimuth_degrees, dtype=torch.float64).reshape(-1)
    if elevation.shape != azimuth.shape:
        raise RenderError(f"elevation and azimuth must have the same length; found {elevation.numel()} and {azimuth.numel()}.")
    directions = spherical_directions(elevation, azimuth)
    return _cameras_from_directions(target, distance, directions, azimuth, image_size, fov_degrees, device)


def _cameras_from_directions(target, distance, directions, azimuth, image_size, fov_degrees, device) -> Cameras:
    if not (np.isfinite(distance) and distance > 0):
        raise RenderError(f"camera distance must be a positive finite number; found {distance!r}.")
    target_t = torch.as_tensor(_as_numpy(target).reshape(3))
    position = target_t + float(distance) * directions
    rotation = look_at_rotation(position, target_t, safe_up_vectors(directions, azimuth))
    return Cameras(rotation, position, image_size, fov_degrees, device)


# -------------------------------------------------------------------- layouts
def official_grid_angles(n_views: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Elevations and azimuths (degrees) of GeoLoRA's / Diff3f's ``sqrt(N) x sqrt(N)`` grid.

    Parameters
    ----------
    n_views : int
        A perfect square ``s * s``.

    Returns
    -------
    elevation, azimuth : torch.Tensor, shape (n_views,), float64
        ``elevation[i] = (i mod s) * 360 / s`` and ``azimuth[i] = (i div s) * 360 / s``.
    """
    steps = _grid_steps(n_views)
    values = torch.arange(steps, dtype=torch.float64) * (360.0 / steps)
    return values.repeat(steps), values.repeat_interleave(steps)


def official_grid_cameras(
    verts: Mesh | np.ndarray | torch.Tensor,
    n_views: int,
    image_size: int | tuple[int, int] = 512,
    fov_degrees: float = OFFICIAL_FOV_DEGREES,
    distance_factor: float = OFFICIAL_DISTANCE_FACTOR,
    random_rotation: bool = False,
    seed: int | np.random.Generator | None = None,
    device: str | torch.device = "auto",
) -> Cameras:
    """GeoLoRA's / Diff3f's camera layout around a shape (see the module notes on repeats and poles).

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        The shape (only its bounding box is used).
    n_views : int
        A perfect square (4, 9, 16, 25, 49, 100, ...).
    image_size : int or (int, int)
        ``(H, W)``; GeoLoRA renders 512 x 512.
    fov_degrees : float
        90 reproduces pytorch3d's default ``PerspectiveCameras``.
    distance_factor : float
        Camera distance from the bounding-box centre, in bounding-box diagonals.
    random_rotation : bool
        Turn the rig about the vertical axis through the target by an angle drawn from ``seed``.
    seed : int or numpy.random.Generator, optional
        Required when ``random_rotation`` is True.
    device : str or torch.device

    Returns
    -------
    Cameras
        ``n_views`` cameras in the official order (elevation varies fastest).
    """
    elevation, azimuth = official_grid_angles(n_views)
    target, diagonal = _bounding_box(verts)
    cameras = orbit_cameras(target, distance_factor * diagonal, elevation, azimuth, image_size, fov_degrees, device)
    return _maybe_rotated(cameras, target, random_rotation, seed)


def fibonacci_directions(n_views: int) -> torch.Tensor:
    """``n_views`` well-spread distinct unit vectors (a Fibonacci sphere), shape (n_views, 3) float64.

    ``y_i = 1 - (2 i + 1) / n`` (never exactly +-1), longitude ``i`` times the golden angle,
    measured like pytorch3d's azimuth (from +z towards +x).
    """
    if not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise RenderError(f"n_views must be a positive integer; found {n_views!r}.")
    index = torch.arange(int(n_views), dtype=torch.float64)
    y = 1.0 - (2.0 * index + 1.0) / n_views
    radius = torch.sqrt(torch.clamp(1.0 - y * y, min=0.0))
    longitude = index * (math.pi * (3.0 - math.sqrt(5.0)))
    return torch.stack((radius * torch.sin(longitude), y, radius * torch.cos(longitude)), dim=-1)


def fibonacci_cameras(
    verts: Mesh | np.ndarray | torch.Tensor,
    n_views: int,
    image_size: int | tuple[int, int] = 512,
    fov_degrees: float = OFFICIAL_FOV_DEGREES,
    distance_factor: float = OFFICIAL_DISTANCE_FACTOR,
    random_rotation: bool = False,
    seed: int | np.random.Generator | None = None,
    device: str | torch.device = "auto",
) -> Cameras:
    """A uniform layout without repeated positions: cameras on a Fibonacci sphere.

    Same target (bounding-box centre), distance and field of view as `official_grid_cameras`;
    any ``n_views >= 1`` works. Parameters as in `official_grid_cameras`.

    Returns
    -------
    Cameras
    """
    directions = fibonacci_directions(n_views)
    azimuth = torch.rad2deg(torch.atan2(directions[:, 0], directions[:, 2]))
    target, diagonal = _bounding_box(verts)
    cameras = _cameras_from_directions(target, distance_factor * diagonal, directions, azimuth, image_size, fov_degrees, device)
    return _maybe_rotated(cameras, target, random_rotation, seed)


def make_cameras(
    verts: Mesh | np.ndarray | torch.Tensor,
    n_views: int,
    layout: str = "official",
    image_size: int | tuple[int, int] = 512,
    fov_degrees: float = OFFICIAL_FOV_DEGREES,
    distance_factor: float = OFFICIAL_DISTANCE_FACTOR,
    random_rotation: bool = False,
    seed: int | np.random.Generator | None = None,
    device: str | torch.device = "auto",
) -> Cameras:
    """Cameras of a named layout: ``"official"`` (`official_grid_cameras`) or ``"uniform"`` (`fibonacci_cameras`)."""
    factories = {"official": official_grid_cameras, "uniform": fibonacci_cameras}
    if layout not in factories:
        raise RenderError(f"camera layout must be one of {CAMERA_LAYOUTS}; found {layout!r}.")
    return factories[layout](
        verts,
        n_views,
        image_size=image_size,
        fov_degrees=fov_degrees,
        distance_factor=distance_factor,
        random_rotation=random_rotation,
        seed=seed,
        device=device,
    )


# -------------------------------------------------------------------- helpers
def _maybe_rotated(cameras: Cameras, target: np.ndarray, random_rotation: bool, seed) -> Cameras:
    if not random_rotation:
        return cameras
    if seed is None:
        raise RenderError("random_rotation=True needs a seed (an int or a numpy.random.Generator) for reproducibility.")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return cameras.rotated_about_up(float(rng.uniform(0.0, 360.0)), target)


def _as_numpy(values) -> np.ndarray:
    if torch.is_tensor(values):
        return values.detach().to("cpu", torch.float64).numpy()
    return np.asarray(values, dtype=np.float64)


def _bounding_box(verts: Mesh | np.ndarray | torch.Tensor) -> tuple[np.ndarray, float]:
    """Bounding-box centre (3,) and diagonal length of a vertex set."""
    if isinstance(verts, Mesh):
        points = verts.verts
    else:
        points = _as_numpy(verts)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise RenderError(f"verts must have shape (V, 3) with V >= 1; found {points.shape}.")
    lo, hi = points.min(axis=0), points.max(axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    if not diagonal > 0:
        raise RenderError("the shape's bounding box has zero size (all vertices coincide); cameras cannot be placed.")
    return (lo + hi) / 2.0, diagonal


def _grid_steps(n_views: int) -> int:
    if not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise RenderError(f"n_views must be a positive integer; found {n_views!r}.")
    steps = math.isqrt(int(n_views))
    if steps * steps != n_views:
        raise RenderError(
            f"the official layout is a sqrt(N) x sqrt(N) grid, so n_views must be a perfect square; found {n_views} "
            f"(nearest: {steps * steps} or {(steps + 1) ** 2}). Use layout='uniform' for any number of views."
        )
    return steps


def _image_size(size) -> tuple[int, int]:
    if isinstance(size, (int, np.integer)):
        size = (int(size), int(size))
    try:
        height, width = (int(s) for s in size)
        valid = all(float(s) == int(s) for s in size)
    except (TypeError, ValueError):
        valid = False
    if not valid or height < 1 or width < 1:
        raise RenderError(f"image_size must be a positive int or a pair (H, W) of positive ints; found {size!r}.")
    return height, width


def _principal_point(point, image_size: tuple[int, int]) -> tuple[float, float]:
    if point is None:
        return image_size[1] / 2.0, image_size[0] / 2.0
    try:
        cx, cy = (float(v) for v in point)
    except (TypeError, ValueError):
        cx = cy = float("nan")
    if not (np.isfinite(cx) and np.isfinite(cy)):
        raise RenderError(f"principal_point must be two finite numbers (cx, cy) in pixels; found {point!r}.")
    return cx, cy


def _check_rotations(rotation: torch.Tensor) -> None:
    identity = torch.eye(3, dtype=rotation.dtype, device=rotation.device)
    error = (rotation @ rotation.transpose(1, 2) - identity).abs().amax()
    if not bool(torch.isfinite(error)) or float(error) > 1e-6:
        raise RenderError(f"camera rotations must be orthonormal (R @ R.T = I); largest deviation {float(error):.3g}.")
    if bool((torch.linalg.det(rotation) < 0).any()):
        raise RenderError("camera rotations must be proper (det = +1); found a reflection.")


def rotation_about_up(angle_degrees: float) -> np.ndarray:
    """The rotation about the vertical (+y) axis by ``angle_degrees``, counter-clockwise seen from +y.

    Turns camera rigs (`Cameras.rotated_about_up`) and training shapes
    (`geofeat.train.trainer.rotate_about_up`): points turn as ``points @ R.T``.

    Parameters
    ----------
    angle_degrees : float

    Returns
    -------
    numpy.ndarray, shape (3, 3), float64
        ``[[cos a, 0, sin a], [0, 1, 0], [-sin a, 0, cos a]]``.
    """
    a = math.radians(angle_degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
