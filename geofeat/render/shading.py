"""Gray Phong shading: the images that GeoLoRA and Diff3f feed to DINO.

Both render with pytorch3d's ``HardPhongShader`` (vikiehm/geo-lora ``utils/dino_utils.py``
and niladridutt/Diffusion-3D-Features ``render.py``, function ``run_rendering``):

* one ``PointLights`` at the camera centre (``location=camera.get_camera_center()``) with
  ``ambient_color=(0.6, 0.6, 0.6)``, ``diffuse_color=(0.4, 0.4, 0.5)``,
  ``specular_color=(0.01, 0.01, 0.01)``;
* vertex colours 0.8 (``TexturesVertex`` / ``Textures(verts_rgb=ones * 0.8)``, GeoLoRA
  ``utils/utils.py::convert_verts_faces_to_torch_mesh``, Diff3f ``utils.py``);
* pytorch3d's default ``Materials`` (facebookresearch/pytorch3d
  ``pytorch3d/renderer/materials.py``): ambient, diffuse and specular reflectivity 1,
  shininess 64;
* pytorch3d's default ``BlendParams`` (``pytorch3d/renderer/blending.py``): white background
  ``(1, 1, 1)``; ``hard_rgb_blend`` keeps the nearest face and does not clamp.

pytorch3d's Phong shading (``pytorch3d/renderer/mesh/shading.py::phong_shading`` and
``pytorch3d/renderer/lighting.py``) interpolates the positions and the area-weighted vertex
normals (``Meshes.verts_normals_packed``) with the rasterizer's perspective-correct
barycentrics, renormalises the normal, and computes per pixel, with ``L`` the unit vector to
the light, ``V`` the unit vector to the camera and ``n`` the unit normal::

    colour = (ambient + diffuse * max(0, n . L)) * texel
             + specular * (max(0, V . (2 (n . L) n - L)) * [n . L > 0]) ** shininess

With the light at the camera ``L = V``. On a surface facing the camera head-on this gives
``0.8 * (0.6 + 0.4) + 0.01 = 0.81`` in red and green and ``0.8 * (0.6 + 0.5) + 0.01 = 0.89``
in blue: the images are gray with a slight blue tint. Normals are not flipped towards the
camera, so a back face drawn without culling gets ambient light only.

Point clouds (`shade_points_phong`, `render_points_phong`) are shaded by the same formula:
every pixel of a point's disc takes the point's normal, estimated from its neighbours
(`cloud_normals`) and turned towards the camera, and the point's colour.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.errors import RenderError
from geofeat.geometry.normals import vertex_normals as geometry_normals
from geofeat.mesh import Mesh
from geofeat.render.cameras import Cameras, as_tensor
from geofeat.render.points import PointFragments, SplatSettings, cloud_tensor, rasterize_points, splat_points
from geofeat.render.rasterizer import Fragments, RasterSettings, mesh_tensors, rasterize, surface_points

Color = tuple[float, float, float]
_PIXELS_PER_CHUNK = 1 << 18


@dataclass(frozen=True)
class PhongSettings:
    """Light, material and background of the Phong shader (defaults: GeoLoRA / Diff3f).

    Parameters
    ----------
    ambient, diffuse, specular : (float, float, float)
        RGB intensities of the point light (pytorch3d's material reflectivities are all 1,
        so these are the products).
    shininess : float
        Specular exponent (pytorch3d ``Materials`` default 64).
    vertex_color : (float, float, float)
        Colour of every vertex when `shade_phong` gets no per-vertex colours.
    background : (float, float, float)
        Colour of pixels that no face covers.
    """

    ambient: Color = (0.6, 0.6, 0.6)
    diffuse: Color = (0.4, 0.4, 0.5)
    specular: Color = (0.01, 0.01, 0.01)
    shininess: float = 64.0
    vertex_color: Color = (0.8, 0.8, 0.8)
    background: Color = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        for name in ("ambient", "diffuse", "specular", "vertex_color", "background"):
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 3 or not all(np.isfinite(value)):
                raise RenderError(f"{name} must be three finite numbers (RGB); found {getattr(self, name)!r}.")
            object.__setattr__(self, name, value)
        if not (np.isfinite(self.shininess) and self.shininess >= 0):
            raise RenderError(f"shininess must be a finite number >= 0; found {self.shininess!r}.")


class Rendering(NamedTuple):
    """Shaded images and the fragments they were shaded from.

    Attributes
    ----------
    images : torch.Tensor, shape (N, H, W, 3), float32
        RGB, background as `PhongSettings.background`; not clamped (defaults stay in [0, 1]).
    fragments : Fragments or PointFragments
        The mesh rasterizer's, or the point renderer's for a point cloud.
    """

    images: torch.Tensor
    fragments: Fragments | PointFragments


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals (as pytorch3d's ``Meshes.verts_normals_packed``), as a tensor.

    Computed by `geofeat.geometry.normals.vertex_normals` (in float64, without gradients).

    Parameters
    ----------
    verts : torch.Tensor, shape (V, 3), float
    faces : torch.Tensor, shape (F, 3), int64

    Returns
    -------
    torch.Tensor, shape (V, 3), dtype and device of ``verts``
        Sum of the right-hand normals (length twice the area) of the faces around each
        vertex, normalised; zero for vertices in no face (and where the normals cancel).
    """
    normals = geometry_normals(
        verts.detach().to("cpu", torch.float64).numpy(), faces.detach().cpu().numpy(), face_weights="area", fallback=False
    )
    return torch.from_numpy(normals).to(device=verts.device, dtype=verts.dtype)


def shade_phong(
    fragments: Fragments,
    verts: Mesh | np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor | None,
    cameras: Cameras,
    settings: PhongSettings | None = None,
    vertex_colors: np.ndarray | torch.Tensor | None = None,
) -> torch.Tensor:
    """Phong-shade rasterized views with a point light at each camera.

    Parameters
    ----------
    fragments : Fragments
        From `rasterize` with the same mesh and cameras.
    verts : Mesh or array_like, shape (V, 3)
    faces : array_like of int, shape (F, 3), or None with a Mesh
    cameras : Cameras
    settings : PhongSettings, optional
    vertex_colors : array_like, shape (V, 3), optional
        Per-vertex RGB, interpolated by barycentrics; default ``settings.vertex_color`` everywhere.

    Returns
    -------
    torch.Tensor, shape (N, H, W, 3), float32
    """
    settings = settings if settings is not None else PhongSettings()
    verts_t, faces_t = mesh_tensors(verts, faces, cameras.device)
    expected = (len(cameras), *cameras.image_size)
    if tuple(fragments.pix_to_face.shape) != expected:
        raise RenderError(f"fragments of shape {tuple(fragments.pix_to_face.shape)} do not match the cameras {expected}.")
    colors = _vertex_colors(vertex_colors, verts_t.shape[0], settings, cameras.device)
    normals = vertex_normals(verts_t, faces_t)
    images = torch.empty((*expected, 3), dtype=torch.float32, device=cameras.device)
    images[:] = torch.tensor(settings.background, dtype=torch.float32, device=cameras.device)
    n_pixels = expected[1] * expected[2]
    flat_images = images.view(-1, 3)
    pix_to_face = fragments.pix_to_face.to(cameras.device).reshape(-1)
    all_bary = fragments.bary.to(cameras.device).reshape(-1, 3)
    terms = _PhongTerms.of(settings, cameras.device)
    covered = torch.nonzero(pix_to_face >= 0, as_tuple=True)[0]  # every view at once: one search, one host wait
    for start in range(0, covered.numel(), _PIXELS_PER_CHUNK):  # bounds the float64 temporaries
        pixel = covered[start : start + _PIXELS_PER_CHUNK]
        corners = faces_t[pix_to_face[pixel]]  # (M, 3)
        bary = all_bary[pixel].to(torch.float64)[..., None]  # (M, 3, 1)
        shaded = _phong(
            points=surface_points(verts_t, corners, bary[..., 0]),
            normals=(bary * normals[corners]).sum(dim=1),
            texels=(bary * colors[corners]).sum(dim=1),
            eye=cameras.position[pixel // n_pixels],  # (M, 3): the camera of each pixel's view
            terms=terms,
        )
        flat_images[pixel] = shaded.float()
    return images


def render_phong(
    verts: Mesh | np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor | None,
    cameras: Cameras,
    raster_settings: RasterSettings | None = None,
    settings: PhongSettings | None = None,
    vertex_colors: np.ndarray | torch.Tensor | None = None,
) -> Rendering:
    """Rasterize and Phong-shade a mesh in every view (GeoLoRA's / Diff3f's images by default).

    Parameters
    ----------
    verts, faces : see `rasterize`
    cameras : Cameras
    raster_settings : RasterSettings, optional
        Default culls back faces, as GeoLoRA does.
    settings : PhongSettings, optional
    vertex_colors : array_like, shape (V, 3), optional

    Returns
    -------
    Rendering
        ``images`` (N, H, W, 3) float32 and the ``fragments``.
    """
    fragments = rasterize(verts, faces, cameras, raster_settings)
    images = shade_phong(fragments, verts, faces, cameras, settings, vertex_colors)
    return Rendering(images, fragments)


def cloud_normals(verts: Mesh | np.ndarray | torch.Tensor) -> torch.Tensor:
    """Unit normals of a point cloud, estimated from each point's neighbourhood, as a float64 tensor.

    `geofeat.geometry.normals.vertex_normals` without faces: the direction of least variance
    of each point's 30 nearest points. Their orientation is a guess (away from the centroid);
    `shade_points_phong` turns each towards the camera, so it does not matter there.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        Points (a `Mesh`'s faces are ignored).

    Returns
    -------
    torch.Tensor, shape (V, 3), float64, on the CPU
    """
    return torch.from_numpy(geometry_normals(cloud_tensor(verts).numpy(), None, fallback=True))


def shade_points_phong(
    fragments: PointFragments,
    verts: Mesh | np.ndarray | torch.Tensor,
    cameras: Cameras,
    settings: PhongSettings | None = None,
    normals: np.ndarray | torch.Tensor | None = None,
    vertex_colors: np.ndarray | torch.Tensor | None = None,
) -> torch.Tensor:
    """Phong-shade the splats of a point cloud with a point light at each camera, as `shade_phong` shades faces.

    Every pixel of a splat takes its point's normal, turned towards the camera (a disc is
    seen from either side, and estimated normals have no reliable orientation), and its
    point's colour; the lit position is the pixel's surface point (`splat_points`).

    Parameters
    ----------
    fragments : PointFragments
        From `rasterize_points` with the same points and cameras.
    verts : Mesh or array_like, shape (V, 3)
    cameras : Cameras
    settings : PhongSettings, optional
    normals : array_like, shape (V, 3), optional
        Point normals (any length > 0); default `cloud_normals`.
    vertex_colors : array_like, shape (V, 3), optional
        Per-point RGB; default ``settings.vertex_color`` everywhere.

    Returns
    -------
    torch.Tensor, shape (N, H, W, 3), float32
    """
    settings = settings if settings is not None else PhongSettings()
    points = cloud_tensor(verts, cameras.device)
    expected = (len(cameras), *cameras.image_size)
    if tuple(fragments.pix_to_point.shape) != expected:
        raise RenderError(f"fragments of shape {tuple(fragments.pix_to_point.shape)} do not match the cameras {expected}.")
    normals_t = cloud_normals(points.cpu()) if normals is None else as_tensor(normals).to(torch.float64)
    if tuple(normals_t.shape) != tuple(points.shape):
        raise RenderError(f"normals must have shape {tuple(points.shape)}, one per point; found {tuple(normals_t.shape)}.")
    normals_t = normals_t.to(cameras.device)
    colors = _vertex_colors(vertex_colors, points.shape[0], settings, cameras.device)
    images = torch.empty((*expected, 3), dtype=torch.float32, device=cameras.device)
    images[:] = torch.tensor(settings.background, dtype=torch.float32, device=cameras.device)
    flat_images = images.view(-1, 3)
    pix_to_point = fragments.pix_to_point.to(cameras.device)
    terms = _PhongTerms.of(settings, cameras.device)
    covered = torch.nonzero(pix_to_point.reshape(-1) >= 0, as_tuple=True)[0]
    for start in range(0, covered.numel(), _PIXELS_PER_CHUNK):
        pixel = covered[start : start + _PIXELS_PER_CHUNK]
        view_row_col = _unflatten(pixel, expected)
        point = pix_to_point.reshape(-1)[pixel]
        lit = splat_points(points, cameras, pix_to_point, view_row_col)
        eye = cameras.position[view_row_col[:, 0]]
        normal = normals_t[point]
        facing = ((eye - lit) * normal).sum(dim=-1, keepdim=True) < 0
        shaded = _phong(lit, torch.where(facing, -normal, normal), colors[point], eye, terms)
        flat_images[pixel] = shaded.float()
    return images


def render_points_phong(
    verts: Mesh | np.ndarray | torch.Tensor,
    cameras: Cameras,
    splat_settings: SplatSettings | None = None,
    settings: PhongSettings | None = None,
    normals: np.ndarray | torch.Tensor | None = None,
    vertex_colors: np.ndarray | torch.Tensor | None = None,
    radii: np.ndarray | torch.Tensor | None = None,
) -> Rendering:
    """Draw a point cloud as splats (`rasterize_points`) and Phong-shade them (`shade_points_phong`).

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        Points (a `Mesh`'s faces are ignored).
    cameras : Cameras
    splat_settings : SplatSettings, optional
        Default: each point's disc 0.5 x its local spacing.
    settings : PhongSettings, optional
    normals : array_like, shape (V, 3), optional
        Default: estimated (`cloud_normals`).
    vertex_colors : array_like, shape (V, 3), optional
    radii : array_like, shape (V,), optional
        The discs' world radii (`geofeat.render.points.splat_radii`); default from ``splat_settings``.

    Returns
    -------
    Rendering
        ``images`` (N, H, W, 3) float32 and the `PointFragments`.
    """
    fragments = rasterize_points(verts, cameras, splat_settings, radii)
    images = shade_points_phong(fragments, verts, cameras, settings, normals, vertex_colors)
    return Rendering(images, fragments)


def _unflatten(pixel: torch.Tensor, shape: tuple[int, int, int]) -> torch.Tensor:
    """(view, row, column) of flat pixel indices into an (N, H, W) image stack, shape (M, 3) int64."""
    _, height, width = shape
    return torch.stack((pixel // (height * width), pixel // width % height, pixel % width), dim=1)


class _PhongTerms(NamedTuple):
    """`PhongSettings` as tensors on the device, made once per call rather than once per chunk."""

    ambient: torch.Tensor  # (3,) float64
    diffuse: torch.Tensor  # (3,) float64
    specular: torch.Tensor  # (3,) float64
    shininess: float

    @classmethod
    def of(cls, settings: PhongSettings, device: torch.device) -> _PhongTerms:
        colors = torch.tensor([settings.ambient, settings.diffuse, settings.specular], dtype=torch.float64, device=device)
        return cls(colors[0], colors[1], colors[2], settings.shininess)


def _phong(points, normals, texels, eye, terms: _PhongTerms) -> torch.Tensor:
    """Colours (M, 3) of surface points lit by a point light at ``eye`` (3,) or (M, 3) and seen from it."""
    tiny = torch.finfo(points.dtype).tiny  # no absolute floor: a mesh at any scale is shaded alike
    normals = F.normalize(normals, dim=-1, eps=tiny)
    to_light = F.normalize(eye - points, dim=-1, eps=tiny)
    to_viewer = to_light  # the light sits at the camera
    cos_light = (normals * to_light).sum(dim=-1, keepdim=True)
    reflected = 2.0 * cos_light * normals - to_light
    highlight = (to_viewer * reflected).sum(dim=-1, keepdim=True).clamp(min=0.0) * (cos_light > 0)
    lit = terms.ambient + terms.diffuse * cos_light.clamp(min=0.0)
    return lit * texels + terms.specular * highlight.pow(terms.shininess)


def _vertex_colors(vertex_colors, n_vertices: int, settings: PhongSettings, device: torch.device) -> torch.Tensor:
    if vertex_colors is None:
        return torch.tensor(settings.vertex_color, dtype=torch.float64, device=device).expand(n_vertices, 3)
    colors = as_tensor(vertex_colors, device=device).to(torch.float64)
    if colors.shape != (n_vertices, 3):
        raise RenderError(f"vertex_colors must have shape ({n_vertices}, 3); found {tuple(colors.shape)}.")
    return colors
