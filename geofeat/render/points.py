"""A point renderer in plain PyTorch: every point drawn as a disc, the nearest point per pixel.

Same code on CPU and CUDA, no compiled code, batched over views like the mesh rasterizer
(`geofeat.render.rasterizer`), whose conventions it keeps (pixel centres, camera frame, the
64-bit depth | index key).

What a point looks like
-----------------------
Each point is a flat disc facing the camera (a *splat*) of world radius ``r_i``, centred on
the point: in a view where the point has camera depth ``z`` it covers the pixel centres
within ``f r_i / z`` pixels of its projection (``f`` the focal length in pixels), and every
pixel it covers has the point's own depth ``z``. By default ``r_i`` is
``SplatSettings.radius_factor`` times the point's *local spacing* (`local_spacing`: its mean
distance to its ``n_neighbours`` nearest distinct points, kept within `SPACING_CLAMP` times
the median over the cloud, so that an isolated point does not cover the image and a
duplicate does not vanish), so neighbouring discs overlap, sparser regions get larger discs
and a sampled surface is drawn without holes; ``SplatSettings.radius`` gives every point one
radius instead. This is the model of pytorch3d's ``PointsRasterizer`` (camera-facing discs,
the point's depth as the pixel's depth), with radii in world units rather than screen units.

How it works
------------
Every (view, point) pair is a *primitive*. Points at or behind the near plane and discs that
cover no pixel centre are dropped. Each remaining primitive lists the pixel centres of its
disc's screen bounding box; those (primitive, pixel) *candidates* are generated in chunks of
at most ``SplatSettings.max_candidates`` (a bound on memory; the points themselves are
projected a chunk at a time too, so a cloud of any size is drawn in bounded memory), tested
against the disc, and the nearest point per pixel is kept with one ``scatter_reduce("amin")``
on the key ``(float32 depth bits << 32) | point index`` (equal depths go to the lower point
index). The depth and the index are both read back from the winning key, so the result does
not depend on how the work was chunked.

The surface point of a pixel, which back-projection lifts the pixel's feature to, is where
the pixel's ray meets its splat: `splat_points`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from geofeat.errors import RenderError
from geofeat.mesh import Mesh
from geofeat.render.cameras import Cameras, as_tensor
from geofeat.render.rasterizer import RELATIVE_Z_NEAR, _chunks

log = logging.getLogger(__name__)

_EMPTY_KEY = torch.iinfo(torch.int64).max
_POINT_BITS = 32
#: Points whose neighbours are looked up together by `local_spacing` (bounds its memory).
_SPACING_CHUNK = 1 << 16
#: A point's local spacing is kept between these multiples of the cloud's median spacing.
SPACING_CLAMP = (0.5, 2.0)


class PointFragments(NamedTuple):
    """Per-pixel output of the point renderer for N views of H x W pixels.

    Attributes
    ----------
    pix_to_point : torch.Tensor, shape (N, H, W), int64
        Index of the nearest point whose disc covers the pixel centre; -1 on background.
    depth : torch.Tensor, shape (N, H, W), float32
        Camera-space z of that point (its disc faces the camera); +inf on background.
    """

    pix_to_point: torch.Tensor
    depth: torch.Tensor

    @property
    def foreground(self) -> torch.Tensor:
        """Mask of pixels covered by a disc, shape (N, H, W) bool."""
        return self.pix_to_point >= 0


@dataclass(frozen=True)
class SplatSettings:
    """How `rasterize_points` draws; ``radius``, ``radius_factor``, ``n_neighbours`` and ``z_near`` change the result.

    Parameters
    ----------
    radius : float or None
        World radius of every disc. None (default): each point's ``radius_factor`` times
        its local spacing (`local_spacing` with ``n_neighbours``).
    radius_factor : float
        The default radii in units of the local spacing. At 0.5 the discs of a FAUST mesh's own
        vertices leave under 0.1 % of its rendered surface uncovered
        (``benchmarks/parity/point_renderer.py``).
    n_neighbours : int
        Neighbours of each point that its local spacing is averaged over.
    z_near : float or None
        Points at camera depth ``<= z_near`` (world units) are not drawn. None (default):
        `RELATIVE_Z_NEAR` times the largest point depth of the views drawn together.
    max_candidates : int
        At most this many (point, pixel) candidates, and projected (view, point) pairs, are
        held at once: the memory bound (about 200 bytes each on CPU). A disc whose screen
        bounding box holds more pixels is processed alone.
    views_per_batch : int
        Views drawn together (the per-pixel key buffer holds ``views_per_batch * H * W`` int64).
    """

    radius: float | None = None
    radius_factor: float = 0.5
    n_neighbours: int = 8
    z_near: float | None = None
    max_candidates: int = 1 << 19
    views_per_batch: int = 8

    def __post_init__(self) -> None:
        if self.radius is not None and not (np.isfinite(self.radius) and self.radius > 0):
            raise RenderError(f"radius must be None or a finite number > 0 (world units); found {self.radius!r}.")
        if not (np.isfinite(self.radius_factor) and self.radius_factor > 0):
            raise RenderError(f"radius_factor must be a finite number > 0; found {self.radius_factor!r}.")
        if self.z_near is not None and not (np.isfinite(self.z_near) and self.z_near >= 0):
            raise RenderError(f"z_near must be None or a finite number >= 0; found {self.z_near!r}.")
        for name in ("n_neighbours", "max_candidates", "views_per_batch"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise RenderError(f"{name} must be a positive integer; found {value!r}.")


def cloud_tensor(verts: Mesh | np.ndarray | torch.Tensor, device: torch.device | str = "cpu") -> torch.Tensor:
    """Validated point positions as a ``(V, 3)`` float64 tensor on ``device``.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        A `Mesh` (its faces, if any, are ignored: the vertices are drawn as points) or positions.
    device : str or torch.device
    """
    if isinstance(verts, Mesh):
        verts = verts.verts
    points = as_tensor(verts, device=device).detach().to(torch.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise RenderError(f"points must have shape (V, 3) with V >= 1; found {tuple(points.shape)}.")
    if not bool(torch.isfinite(points).all()):
        raise RenderError("points contain NaN or infinite coordinates; remove them before rendering.")
    if points.shape[0] >= 1 << (_POINT_BITS - 1):
        raise RenderError(f"at most {(1 << (_POINT_BITS - 1)) - 1} points can be drawn; found {points.shape[0]}.")
    return points


def local_spacing(verts: Mesh | np.ndarray | torch.Tensor, n_neighbours: int = 8) -> np.ndarray:
    """Each point's distance to its neighbours: its mean distance to its nearest distinct points.

    Duplicate points are looked up once (they share their spacing, and do not count as each
    other's neighbours); the spacings are kept within `SPACING_CLAMP` times their median.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
    n_neighbours : int
        Nearest distinct points averaged over (fewer when the cloud has fewer).

    Returns
    -------
    numpy.ndarray, shape (V,), float64
        In the cloud's units, > 0.

    Raises
    ------
    RenderError
        Fewer than two distinct points: no spacing (give `SplatSettings.radius`).
    """
    points, inverse = np.unique(cloud_tensor(verts).numpy(), axis=0, return_inverse=True)
    if len(points) < 2:
        raise RenderError(
            f"the splat radii are derived from the distances between points, and this cloud has {len(points)} distinct "
            "point(s); give SplatSettings(radius=...) in world units."
        )
    k = min(int(n_neighbours), len(points) - 1)
    tree = cKDTree(points)
    means = np.empty(len(points))
    for start in range(0, len(points), _SPACING_CHUNK):
        distance, _ = tree.query(points[start : start + _SPACING_CHUNK], k=k + 1)  # the first is the point itself
        means[start : start + _SPACING_CHUNK] = distance[:, 1:].mean(axis=1)
    median = float(np.median(means))
    return np.clip(means, SPACING_CLAMP[0] * median, SPACING_CLAMP[1] * median)[inverse.reshape(-1)]


def splat_radii(verts: Mesh | np.ndarray | torch.Tensor, settings: SplatSettings | None = None) -> np.ndarray:
    """World radius of every point's disc: ``settings.radius``, or ``radius_factor`` times its `local_spacing`.

    Returns
    -------
    numpy.ndarray, shape (V,), float64
    """
    settings = settings if settings is not None else SplatSettings()
    if settings.radius is not None:
        return np.full(cloud_tensor(verts).shape[0], float(settings.radius))
    return settings.radius_factor * local_spacing(verts, settings.n_neighbours)


def rasterize_points(
    verts: Mesh | np.ndarray | torch.Tensor,
    cameras: Cameras,
    settings: SplatSettings | None = None,
    radii: np.ndarray | torch.Tensor | None = None,
) -> PointFragments:
    """Nearest point and its depth at every pixel centre of every view.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        World-space points (a `Mesh`'s vertices; faces are ignored).
    cameras : Cameras
        N views; the work runs on ``cameras.device``.
    settings : SplatSettings, optional
    radii : array_like, shape (V,), optional
        World radius of each point's disc, as `splat_radii` gives it (worked out once for
        many calls); default from ``settings``.

    Returns
    -------
    PointFragments
        ``pix_to_point`` (N, H, W) int64 and ``depth`` (N, H, W) float32.
    """
    return PointRasterizer(cameras, settings)(verts, radii)


class PointRasterizer:
    """Point renderer bound to cameras and settings (the counterpart of `MeshRasterizer`).

    Parameters
    ----------
    cameras : Cameras
    settings : SplatSettings, optional
    """

    def __init__(self, cameras: Cameras, settings: SplatSettings | None = None) -> None:
        if not isinstance(cameras, Cameras):
            raise RenderError(f"cameras must be a geofeat.render.Cameras; found {type(cameras).__name__}.")
        self.cameras = cameras
        self.settings = settings if settings is not None else SplatSettings()

    def __call__(self, verts: Mesh | np.ndarray | torch.Tensor, radii: np.ndarray | torch.Tensor | None = None) -> PointFragments:
        """Draw the points in every view; see `rasterize_points`."""
        cameras, settings = self.cameras, self.settings
        points = cloud_tensor(verts, cameras.device)
        radius = _checked_radii(splat_radii(points.cpu(), settings) if radii is None else radii, points.shape[0])
        radius = radius.to(cameras.device)
        n_views, (height, width) = len(cameras), cameras.image_size
        keys = torch.empty((min(n_views, settings.views_per_batch) * height * width,), dtype=torch.int64, device=cameras.device)
        pix_to_point = torch.full((n_views, height, width), -1, dtype=torch.int64, device=cameras.device)
        depth = torch.full((n_views, height, width), float("inf"), dtype=torch.float32, device=cameras.device)
        for start in range(0, n_views, settings.views_per_batch):
            views = slice(start, min(start + settings.views_per_batch, n_views))
            batch_keys = keys[: (views.stop - start) * height * width].fill_(_EMPTY_KEY)
            _splat_batch(points, radius, cameras[views], settings, batch_keys)
            _resolve(batch_keys, pix_to_point[views].view(-1), depth[views].view(-1))
        return PointFragments(pix_to_point, depth)


class _Splats(NamedTuple):
    """Drawable (view, point) pairs of one chunk of points, P of them."""

    view: torch.Tensor  # (P,) int64, view index within the batch
    point: torch.Tensor  # (P,) int64
    x0: torch.Tensor  # (P,) int64, first pixel column of the bounding box
    y0: torch.Tensor  # (P,) int64, first pixel row
    width: torch.Tensor  # (P,) int64, bounding-box width in pixels (>= 1)
    count: torch.Tensor  # (P,) int64, pixels in the bounding box
    centre: torch.Tensor  # (P, 2) float32, the projection relative to the box corner (x0, y0)
    radius_sq: torch.Tensor  # (P,) float32, squared screen radius in pixels
    key_depth: torch.Tensor  # (P,) int64, the depth's float32 bits shifted into the key's high half


def _checked_radii(radii: np.ndarray | torch.Tensor, n_points: int) -> torch.Tensor:
    """Radii as a (V,) float64 tensor, each finite and > 0."""
    radii_t = as_tensor(radii).to(torch.float64)
    if tuple(radii_t.shape) != (n_points,):
        raise RenderError(f"radii must have shape ({n_points},), one per point; found {tuple(radii_t.shape)}.")
    if not bool((torch.isfinite(radii_t) & (radii_t > 0)).all()):
        raise RenderError("every splat radius must be a finite number > 0 (world units).")
    return radii_t


def _splat_batch(
    points: torch.Tensor, radius: torch.Tensor, cameras: Cameras, settings: SplatSettings, keys: torch.Tensor
) -> None:
    """Keep the nearest point of a few views per pixel in ``keys`` (flat, already set to empty)."""
    step = max(1, settings.max_candidates // len(cameras))  # (view, point) pairs projected at once
    z_near = settings.z_near if settings.z_near is not None else RELATIVE_Z_NEAR * _largest_depth(points, cameras, step)
    for start in range(0, points.shape[0], step):
        splats = _drawable_splats(points[start : start + step], start, radius[start : start + step], cameras, z_near)
        for chunk in _chunks(splats.count, settings.max_candidates):
            _scatter_nearest(keys, _take(splats, chunk), *cameras.image_size)


def _largest_depth(points: torch.Tensor, cameras: Cameras, step: int) -> float:
    """Largest camera depth of any point in these views (0 when all lie behind every camera)."""
    largest = 0.0
    for start in range(0, points.shape[0], step):
        largest = max(largest, float(cameras.world_to_camera(points[start : start + step])[..., 2].amax()))
    return largest


def _drawable_splats(points: torch.Tensor, first: int, radius: torch.Tensor, cameras: Cameras, z_near: float) -> _Splats:
    """The discs of points ``first ..`` (radii ``radius``, (c,)) in every view that lie before the near plane and cover a pixel centre."""
    height, width = cameras.image_size
    projected = cameras.project(points)  # float64
    x, y = projected.pixels.unbind(-1)  # each (n, c)
    depth = projected.depth
    keep = depth > z_near
    screen_radius = cameras.focal_length * radius / torch.where(keep, depth, 1.0)
    # bounding box of the pixel centres (c + 0.5) within the disc's square, clipped to the image
    x0 = torch.ceil(x - screen_radius - 0.5).clamp(0, width)
    x1 = torch.floor(x + screen_radius - 0.5).clamp(-1, width - 1)
    y0 = torch.ceil(y - screen_radius - 0.5).clamp(0, height)
    y1 = torch.floor(y + screen_radius - 0.5).clamp(-1, height - 1)
    keep &= (x1 >= x0) & (y1 >= y0)
    view, point = torch.nonzero(keep, as_tuple=True)
    x0, y0 = x0[view, point], y0[view, point]
    box_width = x1[view, point] - x0 + 1
    count = (box_width * (y1[view, point] - y0 + 1)).long()
    centre = torch.stack((x[view, point] - x0, y[view, point] - y0), dim=-1).float()
    depth_bits = depth[view, point].float().contiguous().view(torch.int32).to(torch.int64) << _POINT_BITS
    log.debug("point renderer: %d drawable (view, point) discs, %d candidate pixels", view.numel(), int(count.sum()))
    return _Splats(
        view,
        point + first,
        x0.long(),
        y0.long(),
        box_width.long(),
        count,
        centre,
        screen_radius[view, point].float() ** 2,
        depth_bits,
    )


def _take(splats: _Splats, index: slice) -> _Splats:
    return _Splats(*(field[index] for field in splats))


def _scatter_nearest(keys: torch.Tensor, splats: _Splats, height: int, width: int) -> None:
    """Test every candidate pixel of these discs and keep the nearest point per pixel in ``keys``."""
    owner = torch.repeat_interleave(torch.arange(splats.count.numel(), device=keys.device), splats.count)
    first = torch.cumsum(splats.count, 0) - splats.count
    local = torch.arange(owner.numel(), device=keys.device) - first[owner]
    box_width = splats.width[owner]
    col, row = local % box_width, local // box_width  # offsets inside the box
    offset_x = col.float() + 0.5 - splats.centre[owner, 0]
    offset_y = row.float() + 0.5 - splats.centre[owner, 1]
    inside = offset_x * offset_x + offset_y * offset_y <= splats.radius_sq[owner]
    owner, col, row = owner[inside], col[inside], row[inside]
    pixel = (splats.view[owner] * height + splats.y0[owner] + row) * width + splats.x0[owner] + col
    keys.scatter_reduce_(0, pixel, splats.key_depth[owner] | splats.point[owner], reduce="amin")


def _resolve(keys: torch.Tensor, pix_to_point: torch.Tensor, depth: torch.Tensor) -> None:
    """Write the winning point and its depth, both read from the key, at every covered pixel."""
    covered = torch.nonzero(keys != _EMPTY_KEY, as_tuple=True)[0]
    key = keys[covered]
    pix_to_point[covered] = key & ((1 << _POINT_BITS) - 1)
    depth[covered] = (key >> _POINT_BITS).to(torch.int32).view(torch.float32)


def splat_points(
    verts: Mesh | np.ndarray | torch.Tensor, cameras: Cameras, pix_to_point: torch.Tensor, pixels: torch.Tensor
) -> torch.Tensor:
    """The surface point of covered pixels: where the ray through the pixel centre meets its point's disc.

    The disc faces the camera at the point's depth ``z``, so this is the pixel centre
    unprojected at ``z`` (computed in float64 from the point, not from the float32 depth
    image). It lies within the point's disc radius of the point.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        The points that were drawn.
    cameras : Cameras
        The N views they were drawn in.
    pix_to_point : torch.Tensor, shape (N, H, W), int64
        From `rasterize_points`.
    pixels : torch.Tensor, shape (M, 3), int64
        (view, row, column) of covered pixels.

    Returns
    -------
    torch.Tensor, shape (M, 3), float64, on the cameras' device
    """
    device = cameras.device
    points = verts if torch.is_tensor(verts) and verts.dtype == torch.float64 else cloud_tensor(verts, device)
    pixels = pixels.to(device)
    view, row, col = pixels.unbind(1)
    point = pix_to_point.to(device)[view, row, col]
    if bool((point < 0).any()):
        raise RenderError("splat_points was given background pixels; pass covered pixels only (pix_to_point >= 0).")
    rotation, position = cameras.rotation[view], cameras.position[view]  # (M, 3, 3), (M, 3)
    z = ((points.to(device).index_select(0, point) - position) * rotation[:, 2]).sum(dim=1)
    cx, cy = cameras.principal_point
    f = cameras.focal_length
    camera = torch.stack(((col.double() + 0.5 - cx) * z / f, (row.double() + 0.5 - cy) * z / f, z), dim=-1)
    return torch.einsum("mji,mj->mi", rotation, camera) + position
