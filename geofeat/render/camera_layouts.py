"""Where the cameras go: look-at frames and the view layouts around a shape.

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

import numpy as np
import torch

from geofeat.errors import RenderError
from geofeat.mesh import Mesh
from geofeat.render.cameras import OFFICIAL_FOV_DEGREES, Cameras, as_numpy, as_tensor

#: Camera distance as a multiple of the bounding-box diagonal (GeoLoRA / Diff3f ``scaling_factor``).
OFFICIAL_DISTANCE_FACTOR = 0.65
#: World up direction of the look-at frames (pytorch3d ``look_at_view_transform`` default).
WORLD_UP = (0.0, 1.0, 0.0)
#: The view layouts of `make_cameras`.
CAMERA_LAYOUTS = ("official", "uniform")

_POLE_TOLERANCE = 1e-9  # |cross(up, view direction)| below this counts as looking along the up axis


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
            "pass a per-view up vector (see geofeat.render.camera_layouts.safe_up_vectors)."
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
    target_t = torch.as_tensor(as_numpy(target).reshape(3))
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


def _bounding_box(verts: Mesh | np.ndarray | torch.Tensor) -> tuple[np.ndarray, float]:
    """Bounding-box centre (3,) and diagonal length of a vertex set."""
    if isinstance(verts, Mesh):
        points = verts.verts
    else:
        points = as_numpy(verts)
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
