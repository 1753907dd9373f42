"""The multi-view feature path, one for inference and training: render, encode, back-project.

::

    Mesh + Cameras -> rasterize (pix_to_face, barycentrics, depth) -> gray Phong shading
         -> backbone (+ LoRA) patch grid -> bilinear samples at the foreground pixels only,
            L2-normalised -> back-projection ("ball" or "face") -> vertex features

The ``dinov2`` / ``dinov3`` / ``geolora`` descriptors call `multiview_features` with
gradients off; the GeoLoRA trainer calls it with gradients on (a training step) or off
(validation). Both take the same route through the same code; what differs is a switch, not
a copy: ``grad`` (autograd on or off), ``fill`` (unseen vertices: zeros for the training
loss, which masks them, or the nearest seen vertex's features) and ``autocast`` (bfloat16
backbone on CUDA while training).

Patch features are sampled at the foreground pixels (`geofeat.backbones.sample_patch_features`),
which equals upsampling the whole patch grid to the render size and reading those pixels,
without ever forming the (N, H, W, C) feature images (7 views of 512 x 512 x 768 are 5.6 GB
in float32).

A `FeatureRecipe` says how each stage is done. `RECIPES` holds the named ones:

``"default"``
    geofeat's own: the render goes to the backbone as it is, patch features are sampled at
    pixel centres in float32, and a vertex takes the mean of every pixel within its ball.
``"reference"``
    The official GeoLoRA code (vikiehm/geo-lora ``utils/dino_utils.py``), reproduced stage by
    stage (``benchmarks/parity_geolora.py``): the 512 x 512 render is resized to 518 x 518
    (bilinear) before the backbone, the tokens are cast to float16 and sampled on a
    corner-aligned grid (`geofeat.backbones.grid_sample_patch_features`), pixels are lifted
    to 3D from their depth at those corner-aligned positions, and back-projection is
    ``"ball_last"`` (`geofeat.render.backproject`) with the radius a fraction of the shape's
    diameter, at most 100 vertices a pixel, in float16 sums.
``"dsmk"``
    DeepShapeMatchingKit's DINO features (``utils/dino_util.py``, from Diff3f): as
    ``"reference"``, but back faces are drawn, and the render is cut to 8 bits and resized
    with Pillow before the backbone.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.backbones.dino import grid_sample_patch_features, sample_patch_features
from geofeat.checks import check_choice, check_integer
from geofeat.errors import RenderError
from geofeat.mesh import Mesh
from geofeat.progress import progress_bar
from geofeat.render.backproject import BACKPROJECT_MODES, RADIUS_BASES, VertexFeatureAccumulator, foreground_pixels
from geofeat.render.cameras import Cameras
from geofeat.render.rasterizer import RasterSettings
from geofeat.render.shading import render_phong

if TYPE_CHECKING:
    from geofeat.backbones.dino import DinoBackbone

__all__ = [
    "FILL_MODES",
    "PHASES",
    "RECIPES",
    "FeatureRecipe",
    "MultiviewFeatures",
    "PhaseTimer",
    "backbone_input",
    "multiview_features",
]

#: What vertices seen in no view get: the nearest seen vertex's features, or zeros.
FILL_MODES = ("nearest", "zero")
#: Phases that a `PhaseTimer` is charged with, in the order they run for each batch of views.
PHASES = ("render", "forward", "backproject")

#: ``timer(phase)`` returns a context manager around the work of that phase (one of `PHASES`).
PhaseTimer = Callable[[str], AbstractContextManager]

PIXEL_GRIDS = ("centers", "corners")
INPUT_CODECS = ("float", "uint8")
PRECISIONS = {"float32": torch.float32, "float16": torch.float16}


@dataclass(frozen=True)
class FeatureRecipe:
    """How the multi-view path does each stage (see the module notes and `RECIPES`).

    Parameters
    ----------
    backproject : {"ball", "face", "ball_last"}
        See `geofeat.render.backproject`.
    pixel_grid : {"centers", "corners"}
        Where a pixel samples the patch grid and where it is lifted to 3D: its centre, or
        GeoLoRA's corner-aligned grid (pixel ``col`` of ``W`` at ``col * W / (W - 1)``).
    input_size : int, optional
        Side that each render is resized to (bilinear) before the backbone, then cropped to
        a multiple of the patch size from the top-left, as a strided patch embedding does;
        None: the render as it is.
    input_codec : {"float", "uint8"}
        ``"uint8"``: the render is cut to 8 bits (truncated) and resized with Pillow, as
        torchvision's transforms do on a PIL image.
    precision : {"float32", "float16"}
        Precision of the patch tokens after the backbone, their sampling and the vertex sums.
    radius_basis : {"diagonal", "diameter"}
        Ball radius as ``0.004 x`` the bounding-box diagonal or the largest vertex distance.
    max_neighbours : int, optional
        ``"ball_last"``: at most this many vertices a pixel (pytorch3d ``ball_query``'s K).
    cull_backfaces : bool
        Skip faces turned away from the camera.
    """

    backproject: str = "ball"
    pixel_grid: str = "centers"
    input_size: int | None = None
    input_codec: str = "float"
    precision: str = "float32"
    radius_basis: str = "diagonal"
    max_neighbours: int | None = None
    cull_backfaces: bool = True

    def __post_init__(self) -> None:
        check_choice(self.backproject, "backproject", BACKPROJECT_MODES, error=RenderError)
        check_choice(self.pixel_grid, "pixel_grid", PIXEL_GRIDS, error=RenderError)
        check_choice(self.input_codec, "input_codec", INPUT_CODECS, error=RenderError)
        check_choice(self.precision, "precision", tuple(PRECISIONS), error=RenderError)
        check_choice(self.radius_basis, "radius_basis", RADIUS_BASES, error=RenderError)
        if self.input_size is not None:
            check_integer(self.input_size, "input_size", low=1, error=RenderError)
        if self.max_neighbours is not None:
            check_integer(self.max_neighbours, "max_neighbours", low=1, error=RenderError)

    @property
    def dtype(self) -> torch.dtype:
        """`precision` as a torch dtype."""
        return PRECISIONS[self.precision]


_REFERENCE = FeatureRecipe(
    backproject="ball_last",
    pixel_grid="corners",
    input_size=518,
    precision="float16",
    radius_basis="diameter",
    max_neighbours=100,
)
#: The named recipes: geofeat's ``"default"``, the official GeoLoRA code's ``"reference"``,
#: DeepShapeMatchingKit's ``"dsmk"`` (see the module notes).
RECIPES = {
    "default": FeatureRecipe(),
    "reference": _REFERENCE,
    "dsmk": replace(_REFERENCE, input_codec="uint8", cull_backfaces=False),
}


class MultiviewFeatures(NamedTuple):
    """Vertex features lifted from multi-view renders.

    Attributes
    ----------
    features : torch.Tensor, shape (V, C), float32
        Mean of the features the vertex received, on the backbone's device; differentiable
        with respect to the backbone's trainable parameters when computed with ``grad=True``.
        Vertices seen in no view are filled as ``fill`` said.
    seen : torch.Tensor, shape (V,), bool
        Vertices that received at least one pixel.
    """

    features: torch.Tensor
    seen: torch.Tensor


def _no_timer(phase: str) -> AbstractContextManager:
    return contextlib.nullcontext()


def multiview_features(
    mesh: Mesh,
    cameras: Cameras,
    backbone: DinoBackbone,
    *,
    recipe: FeatureRecipe | None = None,
    backproject: str | None = None,
    fill: str = "nearest",
    batch_size: int | None = None,
    grad: bool = False,
    autocast: bool = False,
    timer: PhaseTimer | None = None,
    progress: bool = False,
) -> MultiviewFeatures:
    """Render a mesh from every camera, encode the views and back-project the features to vertices.

    For each batch of views: rasterize and Phong-shade (``render``), run the backbone to its
    patch grid and sample that grid bilinearly at the foreground pixels, L2-normalised
    (``forward``), and add those pixels' features to the vertices (``backproject``). Memory
    grows with one batch of views (and, with ``grad=True``, with the autograd graph of all
    of them), never with full-resolution feature images.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh with V vertices (point clouds cannot be rendered).
    cameras : Cameras
        N views of H x W pixels, H and W multiples of ``backbone.patch_size``.
    backbone : DinoBackbone
        DINOv2 / DINOv3, with or without LoRA; C = ``backbone.embed_dim``.
    recipe : FeatureRecipe, optional
        How each stage is done; default ``RECIPES["default"]``.
    backproject : {"ball", "face", "ball_last"}, optional
        Overrides ``recipe.backproject`` (see `geofeat.render.backproject`).
    fill : {"nearest", "zero"}
        Features of vertices seen in no view: the nearest seen vertex's, or zeros.
    batch_size : int or None
        Views rendered and encoded together; None: all N at once.
    grad : bool
        Record the autograd graph from the backbone's parameters to the vertex features
        (`torch.enable_grad`), or not (`torch.no_grad`), whatever the caller's mode.
    autocast : bool
        Run the backbone under bfloat16 autocast on its device (sampling and back-projection
        stay float32).
    timer : PhaseTimer, optional
        Called as ``with timer(phase):`` around each phase of `PHASES`.
    progress : bool
        Show a progress bar over batches of views.

    Returns
    -------
    MultiviewFeatures
        ``features`` (V, C) float32 and ``seen`` (V,) bool, on the backbone's device.

    Raises
    ------
    RenderError
        ``mesh`` has no faces.
    RenderError
        Unknown ``backproject`` or ``fill`` mode, or a bad ``batch_size``.
    """
    if mesh.faces is None:
        raise RenderError(
            f"{mesh.name or 'the mesh'!r} is a point cloud: multi-view features need faces to render; "
            "give a triangle mesh (or reconstruct a surface first)."
        )
    recipe = RECIPES["default"] if recipe is None else recipe
    if backproject is not None:
        recipe = replace(recipe, backproject=backproject)
    fill = check_choice(fill, "fill", FILL_MODES, error=RenderError)
    batch_size = len(cameras) if batch_size is None else check_integer(batch_size, "batch_size", low=1, error=RenderError)
    timer = timer or _no_timer
    device = backbone.device
    size = (cameras.height, cameras.width)
    accumulator = VertexFeatureAccumulator(
        mesh.verts, mesh.faces, backbone.embed_dim, mode=recipe.backproject, device=device,
        radius_basis=recipe.radius_basis, max_neighbours=recipe.max_neighbours, dtype=recipe.dtype,
    )  # fmt: skip
    raster = RasterSettings(cull_backfaces=recipe.cull_backfaces)
    starts = range(0, len(cameras), batch_size)
    with torch.enable_grad() if grad else torch.no_grad():
        for start in progress_bar(starts, desc=f"views of {mesh.name or 'mesh'}", unit="batch", show=progress):
            views = cameras[start : start + batch_size]
            with timer("render"), torch.no_grad():  # the images do not depend on any parameter
                rendering = render_phong(mesh, None, views, raster)
                images = backbone_input(rendering.images, recipe, backbone.patch_size)
            fragments = rendering.fragments
            pixels = foreground_pixels(fragments.pix_to_face)
            with timer("forward"):
                amp = torch.autocast(device_type=device.type, dtype=torch.bfloat16) if autocast else contextlib.nullcontext()
                with amp:
                    grid = backbone.patch_features(images)  # (B, h, w, C)
                if recipe.pixel_grid == "centers":
                    features = sample_patch_features(grid, pixels, size)  # (M, C)
                else:
                    features = grid_sample_patch_features(grid, pixels, size, recipe.dtype)
            with timer("backproject"):
                points = corner_points(views, pixels, fragments.depth) if recipe.pixel_grid == "corners" else None
                accumulator.add_foreground(features, fragments.pix_to_face, fragments.bary, points)
        with timer("backproject"):
            return MultiviewFeatures(*accumulator.result_tensor(fill=fill))


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
