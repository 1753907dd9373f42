"""The views of one shape as the multi-view path sees them: drawn, resized for the backbone, lifted to 3D.

Here, and only here, a triangle mesh and a point cloud take different roads:

========================  ==========================================  ==============================================
stage                     mesh                                        point cloud (``faces`` None)
========================  ==========================================  ==============================================
draw (`shape_renderer`)   rasterize + Phong (`render_phong`)          splat + Phong (`render_points_phong`): discs of
                                                                      0.5 x each point's spacing, estimated normals
pixel's primitive         its face and barycentrics                   its point (no barycentrics)
pixel's 3D point          interpolated on its face (None here: the    where its ray meets its point's disc
(`pixel_points`)          back-projector interpolates it)             (`splat_points`)
========================  ==========================================  ==============================================

On the corner-aligned grid of the reference recipes both lift the pixel from its depth
(`corner_points`). Everything after (backbone, sampling, back-projection, fill) is the same
code for both.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.mesh import Mesh
from geofeat.render.cameras import Cameras
from geofeat.render.points import PointFragments, SplatSettings, splat_points, splat_radii
from geofeat.render.rasterizer import Fragments, RasterSettings
from geofeat.render.shading import Rendering, cloud_normals, render_phong, render_points_phong

if TYPE_CHECKING:
    from geofeat.multiview.pipeline import FeatureRecipe

__all__ = ["backbone_input", "corner_points", "pixel_primitives", "pixel_points", "shape_renderer"]


def shape_renderer(mesh: Mesh, raster: RasterSettings) -> Callable[[Cameras], Rendering]:
    """The function that draws ``mesh`` in given cameras: rasterized and Phong-shaded, or splatted for a point cloud.

    For a point cloud, what does not depend on the views is worked out once here: the disc
    radii (`geofeat.render.points.splat_radii`) and the normals (`cloud_normals`).

    Parameters
    ----------
    mesh : Mesh
    raster : RasterSettings
        The mesh rasterizer's settings; a point cloud takes its memory bound
        (``max_candidates``) and ``views_per_batch`` (culling does not apply to discs).

    Returns
    -------
    callable
        ``render(cameras) -> Rendering``.
    """
    if not mesh.is_point_cloud:
        return partial(render_phong, mesh, None, raster_settings=raster)
    splat = SplatSettings(max_candidates=raster.max_candidates, views_per_batch=raster.views_per_batch)
    radii, normals = splat_radii(mesh.verts, splat), cloud_normals(mesh.verts)
    return partial(render_points_phong, mesh.verts, splat_settings=splat, normals=normals, radii=radii)


def pixel_primitives(fragments: Fragments | PointFragments) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What each pixel shows: ``(pix_to_face, bary)`` of a mesh, ``(pix_to_point, None)`` of a point cloud.

    Returns
    -------
    index : torch.Tensor, shape (N, H, W), int64, -1 on background
    bary : torch.Tensor, shape (N, H, W, 3), float32, or None
    """
    if isinstance(fragments, PointFragments):
        return fragments.pix_to_point, None
    return fragments.pix_to_face, fragments.bary


def pixel_points(
    mesh: Mesh, cameras: Cameras, fragments: Fragments | PointFragments, pixels: torch.Tensor, pixel_grid: str
) -> torch.Tensor | None:
    """The 3D point that each foreground pixel is lifted to for the ball back-projection.

    Parameters
    ----------
    mesh : Mesh
        The shape drawn.
    cameras : Cameras
        The N views drawn.
    fragments : Fragments or PointFragments
        Of those views.
    pixels : torch.Tensor, shape (M, 3), int64
        (view, row, column) of the foreground pixels, in flat order.
    pixel_grid : {"centers", "corners"}
        See `geofeat.multiview.pipeline.FeatureRecipe`.

    Returns
    -------
    torch.Tensor, shape (M, 3), float64, or None
        ``"corners"``: lifted from the depth (`corner_points`); ``"centers"``: where the
        pixel's ray meets its point's disc on a point cloud (`splat_points`), None on a mesh
        (the back-projector interpolates the surface point from the barycentrics).
    """
    if pixel_grid == "corners":
        return corner_points(cameras, pixels, fragments.depth)
    if isinstance(fragments, PointFragments):
        return splat_points(mesh.verts, cameras, fragments.pix_to_point, pixels)
    return None


def backbone_input(images: torch.Tensor, recipe: FeatureRecipe, patch_size: int) -> torch.Tensor:
    """The images that the backbone sees: the renders, resized and cropped as ``recipe`` says.

    Parameters
    ----------
    images : torch.Tensor, shape (N, H, W, 3), float in [0, 1]
    recipe : FeatureRecipe
    patch_size : int

    Returns
    -------
    torch.Tensor, shape (N, H', W', 3), float32 in [0, 1]
        ``H' = W' = input_size`` rounded down to a multiple of ``patch_size`` (the rows and
        columns that a strided patch embedding would ignore are dropped); the images as given
        when ``recipe.input_size`` is None.
    """
    if recipe.input_size is None:
        return images
    size = recipe.input_size
    if recipe.input_codec == "uint8":
        from PIL import Image

        codes = (images * 255).to(torch.uint8).cpu().numpy()  # truncation, as numpy's astype(uint8)
        resized = [np.asarray(Image.fromarray(c).resize((size, size), Image.BILINEAR)) for c in codes]
        out = torch.as_tensor(np.stack(resized), device=images.device).float() / 255.0
    else:
        chw = images.permute(0, 3, 1, 2).float()
        out = F.interpolate(chw, size=(size, size), mode="bilinear", align_corners=False, antialias=True).permute(0, 2, 3, 1)
    keep = size // patch_size * patch_size
    return out[:, :keep, :keep].contiguous()


def corner_points(cameras: Cameras, pixels: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """3D points of foreground pixels lifted from their depth at GeoLoRA's corner-aligned positions.

    The official code unprojects pixel ``(row, col)`` at NDC ``1 - 2 col / (W - 1)``,
    ``1 - 2 row / (H - 1)`` (pytorch3d's NDC, ``+x`` left, ``+y`` up): in our pixel
    coordinates ``(col W / (W - 1), row H / (H - 1))``, not the centre the rasterizer sampled.

    Parameters
    ----------
    cameras : Cameras
        The N views.
    pixels : torch.Tensor, shape (M, 3), int64
        (view, row, column) of each foreground pixel.
    depth : torch.Tensor, shape (N, H, W)
        Camera-space depth from the rasterizer.

    Returns
    -------
    torch.Tensor, shape (M, 3), float64, on the cameras' device
    """
    height, width = cameras.height, cameras.width
    pixels = pixels.to(cameras.device)
    points = torch.empty((pixels.shape[0], 3), dtype=torch.float64, device=cameras.device)
    for view in range(len(cameras)):
        mine = torch.nonzero(pixels[:, 0] == view).squeeze(1)
        rows, cols = pixels[mine, 1], pixels[mine, 2]
        where = torch.stack((cols * (width / (width - 1)), rows * (height / (height - 1))), dim=-1).double()
        z = depth[view].to(cameras.device)[rows, cols].double()
        points[mine] = cameras[view].unproject(where, z)[0]
    return points
