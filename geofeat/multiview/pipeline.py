"""The multi-view feature path, one for inference and training: render, encode, back-project.

::

    Mesh + Cameras -> rasterize (pix_to_face, barycentrics, depth) -> gray Phong shading
         -> backbone (+ LoRA) patch grid -> bilinear samples at the foreground pixels only,
            L2-normalised -> back-projection ("ball" or "face") -> vertex features

A point cloud (``faces`` None) takes the same path; only drawing it (discs instead of
triangles) and what a pixel shows (a point instead of a face and barycentrics) differ, and
those differences live in `geofeat.multiview.views`.

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
    stage (``benchmarks/parity/geolora.py``): the 512 x 512 render is resized to 518 x 518
    (bilinear) before the backbone, the tokens are cast to float16 and sampled on a
    corner-aligned grid (`geofeat.backbones.grid_sample_patch_features`), pixels are lifted
    to 3D from their depth at those corner-aligned positions, and back-projection is
    ``"ball_last"`` (`geofeat.multiview.backproject`) with the radius a fraction of the shape's
    diameter, at most 100 vertices a pixel, in float16 sums.
``"dsmk"``
    DeepShapeMatchingKit's DINO features (``utils/dino_util.py``, from Diff3f): as
    ``"reference"``, but back faces are drawn, and the render is cut to 8 bits and resized
    with Pillow before the backbone.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, NamedTuple

import torch

from geofeat.backbones.dino import grid_sample_patch_features, sample_patch_features
from geofeat.checks import check_choice, check_integer
from geofeat.errors import RenderError
from geofeat.mesh import Mesh
from geofeat.multiview.backproject import (
    BACKPROJECT_MODES,
    RADIUS_BASES,
    BackprojectionPlan,
    Backprojector,
    VertexFeatureAccumulator,
    foreground_pixels,
)
from geofeat.multiview.views import backbone_input, corner_points, pixel_points, pixel_primitives, shape_renderer
from geofeat.render.cameras import Cameras
from geofeat.render.rasterizer import RasterSettings
from geofeat.runtime.progress import progress_bar

if TYPE_CHECKING:
    from geofeat.backbones.dino import DinoBackbone

__all__ = [
    "FILL_MODES",
    "PHASES",
    "RECIPES",
    "FeatureRecipe",
    "MultiviewFeatures",
    "PhaseTimer",
    "RenderedBatch",
    "ViewSegment",
    "auto_batch_size",
    "backbone_input",
    "corner_points",
    "multiview_features",
    "multiview_features_many",
    "render_batches",
    "view_batches",
]

#: What vertices seen in no view get: the nearest seen vertex's features, or zeros.
FILL_MODES = ("nearest", "zero")
#: Phases that a `PhaseTimer` is charged with. For each batch of views: render, backproject (the
#: plan: which pixels reach which vertices), forward, backproject (the sums).
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
        See `geofeat.multiview.backproject`.
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


class ViewSegment(NamedTuple):
    """Views ``start:stop`` of shape ``shape`` (positions in the lists given to `multiview_features_many`)."""

    shape: int
    start: int
    stop: int


class RenderedBatch(NamedTuple):
    """One batch of views, rendered, planned for back-projection and ready for the backbone.

    Attributes
    ----------
    segments : list of ViewSegment
        Whose views the batch holds, in order.
    images : torch.Tensor, shape (B, H', W', 3)
        Every segment's images as the backbone sees them (`backbone_input`), concatenated.
    pixels : list of torch.Tensor
        One per segment, shape (K, 3) int64: (view within the segment, row, column) of the
        pixels whose features reach a vertex, in flat order; only these are sampled.
    plans : list of BackprojectionPlan
        One per segment: where those pixels' features go (`Backprojector.plan`).
    """

    segments: list[ViewSegment]
    images: torch.Tensor
    pixels: list[torch.Tensor]
    plans: list[BackprojectionPlan]


def view_batches(view_counts: list[int], batch_size: int) -> list[list[ViewSegment]]:
    """Pack the views of several shapes, in order, into batches of at most ``batch_size`` views.

    A batch may hold the last views of one shape and the first of the next, so ``N`` views in
    all take ``ceil(N / batch_size)`` backbone calls.

    Parameters
    ----------
    view_counts : list of int
        Views of each shape.
    batch_size : int

    Returns
    -------
    list of list of ViewSegment
    """
    batches: list[list[ViewSegment]] = [[]]
    room = batch_size
    for shape, count in enumerate(view_counts):
        start = 0
        while start < count:
            if room == 0:
                batches.append([])
                room = batch_size
            stop = min(count, start + room)
            batches[-1].append(ViewSegment(shape, start, stop))
            room -= stop - start
            start = stop
    return [batch for batch in batches if batch]


def render_batches(
    meshes: list[Mesh],
    cameras: list[Cameras],
    patch_size: int,
    *,
    recipe: FeatureRecipe,
    batch_size: int,
    device: torch.device | str | None = None,
    timer: PhaseTimer | None = None,
) -> Iterator[RenderedBatch]:
    """Render and plan the views of several shapes batch by batch (lazily: one batch per ``next``).

    Everything here depends on the geometry only, so it can run ahead of the backbone on
    another thread: rasterize (or, for a point cloud, splat), shade and resize the views
    (``render``), then list which foreground pixels reach which vertices (``backproject``:
    `Backprojector.plan`, with the recipe's mode and radius).

    Parameters
    ----------
    meshes : list of Mesh
        Triangle meshes or point clouds.
    cameras : list of Cameras
        The views of each mesh; all of the same size, on one device.
    patch_size : int
        The backbone's (`backbone_input` crops to a multiple of it).
    recipe : FeatureRecipe
    batch_size : int
        Views per batch (see `view_batches`).
    device : torch.device or str, optional
        Where the plans are made and the pixels listed: the backbone's; default the cameras'.
    timer : PhaseTimer, optional
        Charged with ``"render"`` and ``"backproject"``.

    Yields
    ------
    RenderedBatch
    """
    timer = timer or _no_timer
    raster = RasterSettings(cull_backfaces=recipe.cull_backfaces)
    device = cameras[0].device if device is None else torch.device(device)
    if cameras[0].device.type == "cuda":  # the GPU is kept busy by fewer, larger launches
        raster = replace(raster, views_per_batch=batch_size, max_candidates=CUDA_MAX_CANDIDATES)
    backprojectors: dict[int, Backprojector] = {}
    renderers: dict[int, Callable] = {}
    for batch in view_batches([len(c) for c in cameras], batch_size):
        with torch.no_grad():  # the images and plans do not depend on any parameter
            with timer("render"):
                views = [cameras[s.shape][s.start : s.stop] for s in batch]
                for segment in batch:
                    if segment.shape not in renderers:
                        renderers[segment.shape] = shape_renderer(meshes[segment.shape], raster)
                renderings = [renderers[s.shape](v) for s, v in zip(batch, views, strict=True)]
                images = torch.cat([backbone_input(r.images, recipe, patch_size) for r in renderings])
            with timer("backproject"):
                pixels, plans = [], []
                for segment, view, rendering in zip(batch, views, renderings, strict=True):
                    if segment.shape not in backprojectors:
                        mesh = meshes[segment.shape]
                        backprojectors[segment.shape] = Backprojector(
                            mesh.verts,
                            mesh.faces,
                            recipe.backproject,
                            device=device,
                            radius_basis=recipe.radius_basis,
                            max_neighbours=recipe.max_neighbours,
                        )
                    index, bary = pixel_primitives(rendering.fragments)  # faces and barycentrics, or points
                    foreground = foreground_pixels(index).to(device)  # (M, 3)
                    points = pixel_points(meshes[segment.shape], view, rendering.fragments, foreground, recipe.pixel_grid)
                    plan = backprojectors[segment.shape].plan(index, bary, points)
                    pixels.append(foreground if plan.pixels is None else foreground.index_select(0, plan.pixels))
                    plans.append(plan)
        yield RenderedBatch(batch, images, pixels, plans)


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
    rendered: Iterable[RenderedBatch] | None = None,
) -> MultiviewFeatures:
    """Render a mesh or point cloud from every camera, encode the views and back-project the features to vertices.

    `multiview_features_many` with one shape; see there for the parameters.

    Returns
    -------
    MultiviewFeatures
        ``features`` (V, C) float32 and ``seen`` (V,) bool, on the backbone's device.
    """
    return multiview_features_many(
        [mesh],
        [cameras],
        backbone,
        recipe=recipe,
        backproject=backproject,
        fill=fill,
        batch_size=batch_size,
        grad=grad,
        autocast=autocast,
        timer=timer,
        progress=progress,
        rendered=rendered,
    )[0]


def multiview_features_many(
    meshes: list[Mesh],
    cameras: list[Cameras],
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
    rendered: Iterable[RenderedBatch] | None = None,
) -> list[MultiviewFeatures]:
    """Render several meshes or point clouds from their cameras, encode all views together and back-project per shape.

    The views of all shapes are packed into batches (`view_batches`), so the backbone runs
    ``ceil(N / batch_size)`` times for ``N`` views in all (the GeoLoRA trainer sends a full
    shape and its partial shapes in one call). For each batch: rasterize (splat, for a point
    cloud) and Phong-shade (``render``), list which foreground pixels reach which vertices (``backproject``:
    `render_batches`, before the backbone, so that its waits on the device hold no backbone
    work up), run the backbone to its patch grid and sample that grid bilinearly at those
    pixels only, L2-normalised (``forward``), and add their features to their shape's
    vertices (``backproject``). Memory grows with one batch of views (and, with
    ``grad=True``, with the autograd graph of all of them), never with full-resolution
    feature images.

    Parameters
    ----------
    meshes : list of Mesh
        Triangle meshes or point clouds (drawn as discs, `geofeat.multiview.views`); mesh
        ``i`` has V_i vertices.
    cameras : list of Cameras
        The views of each mesh, all H x W pixels, H and W multiples of ``backbone.patch_size``.
    backbone : DinoBackbone
        DINOv2 / DINOv3, with or without LoRA; C = ``backbone.embed_dim``.
    recipe : FeatureRecipe, optional
        How each stage is done; default ``RECIPES["default"]``.
    backproject : {"ball", "face", "ball_last"}, optional
        Overrides ``recipe.backproject`` (see `geofeat.multiview.backproject`; on a point
        cloud ``"face"`` gives each pixel's feature to its own point).
    fill : {"nearest", "zero"}
        Features of vertices seen in no view: the nearest seen vertex's, or zeros.
    batch_size : int or None
        Views encoded together; None: all views at once.
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
    rendered : iterable of RenderedBatch, optional
        The batches already rendered and planned (`render_batches` with the same meshes,
        cameras, recipe, batch size and device, run ahead on another thread); default:
        rendered here, one batch at a time.

    Returns
    -------
    list of MultiviewFeatures
        One per mesh: ``features`` (V_i, C) float32 and ``seen`` (V_i,) bool, on the backbone's device.

    Raises
    ------
    RenderError
        The lists differ in length, the cameras differ in size, an unknown ``backproject``
        or ``fill`` mode, a bad ``batch_size``, or a point cloud whose splat radius cannot
        be derived (fewer than two distinct points).
    """
    if len(meshes) != len(cameras) or not meshes:
        raise RenderError(f"give one Cameras per mesh (at least one); found {len(meshes)} meshes and {len(cameras)} cameras.")
    sizes = {(c.height, c.width) for c in cameras}
    if len(sizes) != 1:
        raise RenderError(f"the cameras of the meshes must all have one image size; found {sorted(sizes)}.")
    size = sizes.pop()
    recipe = RECIPES["default"] if recipe is None else recipe
    if backproject is not None:
        recipe = replace(recipe, backproject=backproject)
    fill = check_choice(fill, "fill", FILL_MODES, error=RenderError)
    n_views = sum(len(c) for c in cameras)
    batch_size = n_views if batch_size is None else check_integer(batch_size, "batch_size", low=1, error=RenderError)
    timer = timer or _no_timer
    device = backbone.device
    accumulators = [
        VertexFeatureAccumulator(
            mesh.verts,
            mesh.faces,
            backbone.embed_dim,
            mode=recipe.backproject,
            device=device,
            radius_basis=recipe.radius_basis,
            max_neighbours=recipe.max_neighbours,
            dtype=recipe.dtype,
        )
        for mesh in meshes
    ]
    if rendered is None:
        rendered = render_batches(
            meshes, cameras, backbone.patch_size, recipe=recipe, batch_size=batch_size, device=device, timer=timer
        )
    batches = iter(rendered)
    n_batches = len(view_batches([len(c) for c in cameras], batch_size))
    with torch.enable_grad() if grad else torch.no_grad():
        for _ in progress_bar(range(n_batches), desc=_progress_label(meshes), unit="batch", show=progress):
            batch = next(batches)
            with timer("forward"):
                amp = torch.autocast(device_type=device.type, dtype=torch.bfloat16) if autocast else contextlib.nullcontext()
                with amp:
                    grid = backbone.patch_features(batch.images.to(device))  # (B, h, w, C)
                grids = grid.split([s.stop - s.start for s in batch.segments])
                samples = []
                for grid_part, pixels in zip(grids, batch.pixels, strict=True):
                    if recipe.pixel_grid == "centers":
                        samples.append(sample_patch_features(grid_part, pixels, size))  # (K, C)
                    else:
                        samples.append(grid_sample_patch_features(grid_part, pixels, size, recipe.dtype))
            with timer("backproject"):
                for segment, plan, features in zip(batch.segments, batch.plans, samples, strict=True):
                    accumulators[segment.shape].add_planned(plan, features)
        with timer("backproject"):
            if fill == "nearest":
                for mesh, camera, accumulator in zip(meshes, cameras, accumulators, strict=True):
                    _check_seen(mesh, camera, recipe, accumulator)
            return [MultiviewFeatures(*accumulator.result_tensor(fill=fill)) for accumulator in accumulators]


def _check_seen(mesh: Mesh, cameras: Cameras, recipe: FeatureRecipe, accumulator: VertexFeatureAccumulator) -> None:
    """Refuse a mesh none of whose vertices got a pixel: its features would be all zeros, with nothing to fill from."""
    if bool((accumulator.weights > 0).any()):
        return
    ball = f", ball radius {accumulator.radius:.3g}" if recipe.backproject != "face" else ""
    raise RenderError(
        f"no vertex of {mesh.name or 'the mesh'!r} ({mesh.n_vertices} vertices) received a pixel in any of its "
        f"{len(cameras)} views of {cameras.height} x {cameras.width} pixels (back-projection {recipe.backproject!r}{ball}): "
        "its features would be all zeros. Render larger images or more views, or back-project by face "
        "(backproject='face'), which gives every pixel to its face's corners (on a point cloud, to its point)."
    )


def _progress_label(meshes: list[Mesh]) -> str:
    if len(meshes) == 1:
        return f"views of {meshes[0].name or 'mesh'}"
    return f"views of {len(meshes)} meshes"


#: The rasterizer's candidates held at once on CUDA (about 600 MiB): fewer chunks, fewer launches.
CUDA_MAX_CANDIDATES = 1 << 21
#: Share of the GPU's free memory that `auto_batch_size` plans one batch of views to take.
BATCH_MEMORY_SHARE = 0.5
#: Views per batch on the CPU (`auto_batch_size`): the backbone is already busy on every core at this size.
CPU_BATCH_SIZE = 4


def auto_batch_size(n_views: int, height: int, width: int, backbone: DinoBackbone) -> int:
    """Views per batch for inference without gradients: as many as the GPU's free memory allows.

    On CUDA, one view of ``H x W`` pixels is planned at ``H W (8 C + 64)`` bytes (its
    foreground features in float32 twice over, the worst case where every pixel is
    foreground, plus the rasterizer's buffers) and ``h w C x 48`` bytes of backbone
    activations for its ``h w`` patches; the batch takes at most `BATCH_MEMORY_SHARE` of the
    free memory. On the CPU: `CPU_BATCH_SIZE`.

    Parameters
    ----------
    n_views : int
    height, width : int
        Render size in pixels.
    backbone : DinoBackbone

    Returns
    -------
    int
        Between 1 and ``n_views``.
    """
    device = backbone.device
    if device.type != "cuda":
        return max(1, min(n_views, CPU_BATCH_SIZE))
    channels = backbone.embed_dim
    patches = (height // backbone.patch_size) * (width // backbone.patch_size)
    per_view = height * width * (8 * channels + 64) + patches * channels * 48
    free, _ = torch.cuda.mem_get_info(device)
    return max(1, min(n_views, int(BATCH_MEMORY_SHARE * free) // per_view))
