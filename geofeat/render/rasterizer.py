"""A triangle rasterizer in plain PyTorch: same code on CPU and CUDA, no OpenGL, no compiled code.

One face per pixel (the nearest), sampled at pixel centres (see `geofeat.render.cameras` for
the pixel convention), with perspective-correct barycentric coordinates.

How it works
------------
Every (view, face) pair is a *primitive*. Primitives with a vertex at or behind the near
plane, with zero screen area, facing away from the camera (when culling) or covering no
pixel centre are dropped. Each remaining primitive lists the pixel centres inside its
screen bounding box; those (primitive, pixel) *candidates* are generated in chunks of at
most ``RasterSettings.max_candidates`` (a bound on memory), tested against the triangle's
edges, and the nearest one per pixel is kept with a single ``scatter_reduce("amin")`` on a
64-bit key ``(float32 depth bits << 32) | face index`` (positive float32 numbers order
like their bit patterns; equal depths go to the lower face index). A last pass recomputes,
for the winning face of every covered pixel, the barycentrics and depth in float64, so the
result does not depend on how the work was chunked.

Faces with any vertex at ``z <= z_near`` are not drawn (there is no clipping). By default the
near plane follows the scene's own extent, ``RELATIVE_Z_NEAR`` times the farthest vertex depth
of the views being drawn, so a mesh at any scale is drawn alike; with the official camera
layout every point of the shape is at least 0.15 bounding-box diagonals in front of the
camera, so nothing is lost there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from geofeat.errors import RenderError
from geofeat.mesh import Mesh
from geofeat.render.cameras import Cameras, as_tensor

log = logging.getLogger(__name__)

_EMPTY_KEY = torch.iinfo(torch.int64).max
#: The default near plane, as a fraction of the largest vertex depth of the views drawn.
RELATIVE_Z_NEAR = 1e-6
_FACE_BITS = 32


class Fragments(NamedTuple):
    """Per-pixel output of the rasterizer for N views of H x W pixels.

    Attributes
    ----------
    pix_to_face : torch.Tensor, shape (N, H, W), int64
        Index into the mesh's faces of the nearest face at each pixel centre; -1 on background.
    bary : torch.Tensor, shape (N, H, W, 3), float32
        Perspective-correct barycentric coordinates of the pixel's surface point in that face
        (weights of its three corners, in ``faces`` order; they sum to 1); 0 on background.
    depth : torch.Tensor, shape (N, H, W), float32
        Camera-space z of that surface point (distance along the optical axis); +inf on background.
    """

    pix_to_face: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor

    @property
    def foreground(self) -> torch.Tensor:
        """Mask of pixels covered by a face, shape (N, H, W) bool."""
        return self.pix_to_face >= 0


@dataclass(frozen=True)
class RasterSettings:
    """How `rasterize` works; none of these change the result except ``cull_backfaces`` and ``z_near``.

    Parameters
    ----------
    cull_backfaces : bool
        Skip faces whose front side (counter-clockwise corners, right-hand normal) points away
        from the camera. GeoLoRA culls (``cull_backfaces=True``); Diff3f does not.
    z_near : float or None
        Faces with a vertex at camera depth ``<= z_near`` (world units) are not drawn. None
        (default): ``RELATIVE_Z_NEAR`` times the largest vertex depth of the views drawn
        together, so that the near plane scales with the scene.
    max_candidates : int
        At most this many (face, pixel) candidates, and covered pixels in the final pass, are
        held at once: the memory bound (about 300 bytes each on CPU, so about 150 MiB at the
        default 2**19). A face whose screen bounding box holds more pixels than this is processed alone.
    views_per_batch : int
        Views rasterized together (the per-pixel key buffer holds ``views_per_batch * H * W`` int64).
    """

    cull_backfaces: bool = True
    z_near: float | None = None
    max_candidates: int = 1 << 19
    views_per_batch: int = 8

    def __post_init__(self) -> None:
        if self.z_near is not None and not (np.isfinite(self.z_near) and self.z_near >= 0):
            raise RenderError(f"z_near must be None or a finite number >= 0; found {self.z_near!r}.")
        for name in ("max_candidates", "views_per_batch"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise RenderError(f"{name} must be a positive integer; found {value!r}.")


class _Primitives(NamedTuple):
    """Drawable (view, face) pairs of one batch of views, P of them."""

    view: torch.Tensor  # (P,) int64, view index within the batch
    face: torch.Tensor  # (P,) int64
    x0: torch.Tensor  # (P,) int64, first pixel column of the bounding box
    y0: torch.Tensor  # (P,) int64, first pixel row
    width: torch.Tensor  # (P,) int64, bounding-box width in pixels (>= 1)
    count: torch.Tensor  # (P,) int64, pixels in the bounding box
    edges: torch.Tensor  # (P, 3, 3) float32: screen barycentric b_k = e[k,0] * dx + e[k,1] * dy + e[k,2]
    inv_z: torch.Tensor  # (P, 3) float32, 1 / camera z of the three corners


def mesh_tensors(
    verts: Mesh | np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor | None = None,
    device: torch.device | str = "cpu",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validated ``verts (V, 3) float64`` and ``faces (F, 3) int64`` tensors on ``device``.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        A `Mesh` (then ``faces`` must be None) or vertex positions.
    faces : array_like of int, shape (F, 3), optional
    device : str or torch.device
    """
    if isinstance(verts, Mesh):
        if faces is not None:
            raise RenderError("pass either a Mesh or verts and faces, not a Mesh and faces.")
        if verts.faces is None:
            raise RenderError(f"mesh {verts.name!r} is a point cloud: it has no faces to rasterize.")
        verts, faces = verts.verts, verts.faces
    if faces is None:
        raise RenderError("faces are required to rasterize vertex positions.")
    verts_t = as_tensor(verts, device=device).detach().to(torch.float64)
    faces_t = as_tensor(faces, device=device)
    if verts_t.ndim != 2 or verts_t.shape[1] != 3:
        raise RenderError(f"verts must have shape (V, 3); found {tuple(verts_t.shape)}.")
    if faces_t.ndim != 2 or faces_t.shape[1] != 3 or faces_t.shape[0] == 0:
        raise RenderError(f"faces must have shape (F, 3) with F >= 1; found {tuple(faces_t.shape)}.")
    if faces_t.is_floating_point() or faces_t.dtype == torch.bool:
        raise RenderError(f"faces must be an integer array; found dtype {faces_t.dtype}.")
    faces_t = faces_t.to(torch.int64)
    if int(faces_t.min()) < 0 or int(faces_t.max()) >= verts_t.shape[0]:
        raise RenderError(
            f"face indices must lie in [0, {verts_t.shape[0] - 1}]; found [{int(faces_t.min())}, {int(faces_t.max())}]."
        )
    if faces_t.shape[0] >= 1 << (_FACE_BITS - 1):
        raise RenderError(f"at most {(1 << (_FACE_BITS - 1)) - 1} faces can be rasterized; found {faces_t.shape[0]}.")
    return verts_t, faces_t


def rasterize(
    verts: Mesh | np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor | None,
    cameras: Cameras,
    settings: RasterSettings | None = None,
) -> Fragments:
    """Nearest face, perspective-correct barycentrics and depth at every pixel centre of every view.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        A `Mesh` (pass ``faces=None``) or world-space vertex positions.
    faces : array_like of int, shape (F, 3), or None
        Triangles, counter-clockwise seen from their front side.
    cameras : Cameras
        N views; the work runs on ``cameras.device``.
    settings : RasterSettings, optional

    Returns
    -------
    Fragments
        ``pix_to_face`` (N, H, W) int64, ``bary`` (N, H, W, 3) float32, ``depth`` (N, H, W) float32.
    """
    return MeshRasterizer(cameras, settings)(verts, faces)


class MeshRasterizer:
    """Rasterizer bound to cameras and settings (like pytorch3d's ``MeshRasterizer``).

    Parameters
    ----------
    cameras : Cameras
    settings : RasterSettings, optional
    """

    def __init__(self, cameras: Cameras, settings: RasterSettings | None = None) -> None:
        if not isinstance(cameras, Cameras):
            raise RenderError(f"cameras must be a geofeat.render.Cameras; found {type(cameras).__name__}.")
        self.cameras = cameras
        self.settings = settings if settings is not None else RasterSettings()

    def __call__(self, verts: Mesh | np.ndarray | torch.Tensor, faces: np.ndarray | torch.Tensor | None = None) -> Fragments:
        """Rasterize a mesh in every view; see `rasterize`."""
        cameras, settings = self.cameras, self.settings
        verts_t, faces_t = mesh_tensors(verts, faces, cameras.device)
        n_views, (height, width) = len(cameras), cameras.image_size
        device = cameras.device
        pix_to_face = torch.full((n_views, height, width), -1, dtype=torch.int64, device=device)
        bary = torch.zeros((n_views, height, width, 3), dtype=torch.float32, device=device)
        depth = torch.full((n_views, height, width), float("inf"), dtype=torch.float32, device=device)
        for start in range(0, n_views, settings.views_per_batch):
            views = slice(start, min(start + settings.views_per_batch, n_views))
            out = Fragments(pix_to_face[views].view(-1), bary[views].view(-1, 3), depth[views].view(-1))
            _rasterize_batch(verts_t, faces_t, cameras[views], settings, out)
        return Fragments(pix_to_face, bary, depth)


def _rasterize_batch(
    verts: torch.Tensor, faces: torch.Tensor, cameras: Cameras, settings: RasterSettings, out: Fragments
) -> None:
    """Rasterize a few views into ``out`` (flat views of the output tensors, already set to background)."""
    screen = _screen_vertices(verts, cameras)  # (n, V, 3): x, y in pixels, camera z
    primitives = _drawable_primitives(screen, faces, cameras.image_size, settings)
    n_views, (height, width) = len(cameras), cameras.image_size
    keys = torch.full((n_views * height * width,), _EMPTY_KEY, dtype=torch.int64, device=verts.device)
    for chunk in _chunks(primitives.count, settings.max_candidates):
        _scatter_nearest(keys, _take(primitives, chunk), height, width)
    covered = torch.nonzero(keys != _EMPTY_KEY, as_tuple=True)[0]
    for start in range(0, covered.numel(), settings.max_candidates):
        pixel = covered[start : start + settings.max_candidates]
        _resolve(pixel, keys[pixel], screen, faces, cameras.image_size, out)


def _screen_vertices(verts: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """Pixel x, pixel y and camera z of every vertex in every view, shape (n, V, 3) float64."""
    projected = cameras.project(verts)
    return torch.cat((projected.pixels, projected.depth[..., None]), dim=-1)


def _drawable_primitives(
    screen: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int], settings: RasterSettings
) -> _Primitives:
    height, width = image_size
    corners = screen[:, faces]  # (n, F, 3 corners, 3)
    x, y, z = corners.unbind(-1)  # each (n, F, 3)
    area = (x[..., 1] - x[..., 0]) * (y[..., 2] - y[..., 0]) - (y[..., 1] - y[..., 0]) * (x[..., 2] - x[..., 0])
    # x right, y down: a counter-clockwise face seen from its front has negative signed area.
    z_near = settings.z_near if settings.z_near is not None else RELATIVE_Z_NEAR * float(z.amax().clamp(min=0))
    keep = (z.amin(dim=-1) > z_near) & (area != 0) & torch.isfinite(area)
    if settings.cull_backfaces:
        keep &= area < 0
    # bounding box of the pixel centres (c + 0.5) inside [min, max], clipped to the image
    x0 = torch.ceil(x.amin(-1) - 0.5).clamp(0, width)
    x1 = torch.floor(x.amax(-1) - 0.5).clamp(-1, width - 1)
    y0 = torch.ceil(y.amin(-1) - 0.5).clamp(0, height)
    y1 = torch.floor(y.amax(-1) - 0.5).clamp(-1, height - 1)
    keep &= (x1 >= x0) & (y1 >= y0)
    view, face = torch.nonzero(keep, as_tuple=True)
    x0, y0 = x0[view, face].long(), y0[view, face].long()
    box_width = x1[view, face].long() - x0 + 1
    count = box_width * (y1[view, face].long() - y0 + 1)
    corners = corners[view, face]  # (P, 3, 3)
    edges = _edge_coefficients(corners[..., :2], area[view, face], x0, y0)
    log.debug("rasterizer: %d drawable (view, face) pairs, %d candidate pixels", view.numel(), int(count.sum()))
    return _Primitives(view, face, x0, y0, box_width, count, edges.float(), (1.0 / corners[..., 2]).float())


def _edge_coefficients(xy: torch.Tensor, area: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor) -> torch.Tensor:
    """Affine maps from a pixel offset ``(dx, dy)`` to screen-space barycentrics, shape (P, 3, 3).

    The offset is measured from the corner ``(x0, y0)`` of the primitive's pixel box, so the
    float32 values evaluated per candidate stay small and exact; these coefficients are float64.
    """
    origin = torch.stack((x0, y0), dim=-1).to(xy.dtype)
    local = xy - origin[:, None, :]  # corners relative to the box corner, (P, 3, 2)
    coefficients = []
    for k in range(3):
        a, b = local[:, (k + 1) % 3], local[:, (k + 2) % 3]
        # b_k(p) = ((b - a) x (p - a)) / area, written as e0 * px + e1 * py + e2
        e0 = -(b[:, 1] - a[:, 1])
        e1 = b[:, 0] - a[:, 0]
        e2 = -(e0 * a[:, 0] + e1 * a[:, 1])
        coefficients.append(torch.stack((e0, e1, e2), dim=-1) / area[:, None])
    return torch.stack(coefficients, dim=1)


def _chunks(count: torch.Tensor, budget: int) -> list[slice]:
    """Consecutive primitive ranges whose candidate counts sum to at most ``budget`` (or one primitive)."""
    ends = torch.cumsum(count, 0).cpu()  # candidates up to and including each primitive
    chunks, start = [], 0
    while start < count.numel():
        already = int(ends[start - 1]) if start else 0
        stop = int(torch.searchsorted(ends, already + budget, right=True))
        stop = max(stop, start + 1)  # a primitive over budget goes alone
        chunks.append(slice(start, stop))
        start = stop
    return chunks


def _take(primitives: _Primitives, index: slice) -> _Primitives:
    return _Primitives(*(field[index] for field in primitives))


def _scatter_nearest(keys: torch.Tensor, primitives: _Primitives, height: int, width: int) -> None:
    """Test every candidate pixel of these primitives and keep the nearest face per pixel in ``keys``."""
    owner = torch.repeat_interleave(torch.arange(primitives.count.numel(), device=keys.device), primitives.count)
    first = torch.cumsum(primitives.count, 0) - primitives.count
    local = torch.arange(owner.numel(), device=keys.device) - first[owner]
    box_width = primitives.width[owner]
    col, row = local % box_width, local // box_width  # offsets inside the box
    edges = primitives.edges[owner]  # (T, 3, 3)
    dx = (col.float() + 0.5)[:, None]
    dy = (row.float() + 0.5)[:, None]
    screen_bary = edges[..., 0] * dx + edges[..., 1] * dy + edges[..., 2]  # (T, 3)
    inside = (screen_bary >= 0).all(dim=-1)
    owner, col, row, screen_bary = owner[inside], col[inside], row[inside], screen_bary[inside]
    depth = 1.0 / (screen_bary * primitives.inv_z[owner]).sum(dim=-1)
    pixel = (primitives.view[owner] * height + primitives.y0[owner] + row) * width + primitives.x0[owner] + col
    key = (depth.contiguous().view(torch.int32).to(torch.int64) << _FACE_BITS) | primitives.face[owner]
    keys.scatter_reduce_(0, pixel, key, reduce="amin")


def _resolve(
    pixel: torch.Tensor, key: torch.Tensor, screen: torch.Tensor, faces: torch.Tensor, image_size: tuple[int, int], out: Fragments
) -> None:
    """Write face, perspective-correct barycentrics and depth of the winning faces at covered pixels into ``out``."""
    height, width = image_size
    face = key & ((1 << _FACE_BITS) - 1)
    view, rest = pixel // (height * width), pixel % (height * width)
    centre = torch.stack(((rest % width).double() + 0.5, (rest // width).double() + 0.5), dim=-1)  # (M, 2)
    corners = screen[view[:, None], faces[face]]  # (M, 3, 3) float64
    weights = _screen_barycentrics(corners[..., :2], centre) / corners[..., 2]
    inv_depth = weights.sum(dim=-1, keepdim=True)
    out.pix_to_face[pixel] = face
    out.bary[pixel] = (weights / inv_depth).float()
    out.depth[pixel] = (1.0 / inv_depth[:, 0]).float()


def surface_points(verts: torch.Tensor, corners: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Points of faces given by barycentric coordinates, exact wherever the mesh sits.

    ``v0 + b1 (v1 - v0) + b2 (v2 - v0)``: the barycentric combination written with edge
    vectors only, so that the float32 barycentrics' rounding (their sum is 1 only to about
    1e-7) scales with the face's size, not with the distance of the mesh from the origin
    (``sum_k b_k v_k`` would move a point of a mesh placed at 1e6 by about 0.1).

    Parameters
    ----------
    verts : torch.Tensor, shape (V, 3), float64
    corners : torch.Tensor, shape (M, 3), int64
        The three vertices of each point's face.
    bary : torch.Tensor, shape (M, 3), float
        The point's barycentric coordinates in that face (the rasterizer's).

    Returns
    -------
    torch.Tensor, shape (M, 3), float64
    """
    bary = bary.to(torch.float64)
    origin = verts.index_select(0, corners[:, 0])
    points = origin + bary[:, 1:2] * (verts.index_select(0, corners[:, 1]) - origin)
    return points + bary[:, 2:3] * (verts.index_select(0, corners[:, 2]) - origin)


def _screen_barycentrics(xy: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """Barycentrics of 2D points in 2D triangles, clamped to the triangle, shape (M, 3) float64."""
    a, b, c = xy.unbind(1)

    def cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]

    area = cross(b - a, c - a)
    weights = torch.stack((cross(c - b, point - b), cross(a - c, point - c), cross(b - a, point - a)), dim=-1) / area[:, None]
    weights = weights.clamp(min=0.0)  # float32 inclusion vs float64 recomputation: within rounding
    return weights / weights.sum(dim=-1, keepdim=True)
