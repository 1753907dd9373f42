"""Pinhole cameras for multi-view rendering: the `Cameras` record and its conventions.

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

The view layouts that place these cameras around a shape are `geofeat.render.camera_layouts`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch

from geofeat.errors import RenderError
from geofeat.runtime.devices import resolve_device

#: Field of view of pytorch3d's default ``PerspectiveCameras`` (focal length 1 in NDC).
OFFICIAL_FOV_DEGREES = 90.0


def as_tensor(values, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> torch.Tensor:
    """`torch.as_tensor` that copies read-only numpy arrays (such as `Mesh.verts`) instead of warning."""
    if isinstance(values, np.ndarray) and not values.flags.writeable:
        values = values.copy()
    return torch.as_tensor(values, dtype=dtype, device=device)


def as_numpy(values) -> np.ndarray:
    """A tensor or an array_like as a float64 numpy array (a tensor is copied to the CPU)."""
    if torch.is_tensor(values):
        return values.detach().to("cpu", torch.float64).numpy()
    return np.asarray(values, dtype=np.float64)


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
        center_t = torch.as_tensor(as_numpy(center).reshape(3), device=self.device)
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
