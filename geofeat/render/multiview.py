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
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, NamedTuple

import torch
from tqdm.auto import tqdm

from geofeat.backbones.dino import sample_patch_features
from geofeat.checks import check_choice, check_integer
from geofeat.mesh import Mesh
from geofeat.render.backproject import BACKPROJECT_MODES, BackprojectError, VertexFeatureAccumulator, foreground_pixels
from geofeat.render.cameras import Cameras
from geofeat.render.errors import RenderError
from geofeat.render.shading import render_phong

if TYPE_CHECKING:
    from geofeat.backbones.dino import DinoBackbone

__all__ = ["FILL_MODES", "PHASES", "MultiviewFeatures", "PhaseTimer", "multiview_features"]

#: What vertices seen in no view get: the nearest seen vertex's features, or zeros.
FILL_MODES = ("nearest", "zero")
#: Phases that a `PhaseTimer` is charged with, in the order they run for each batch of views.
PHASES = ("render", "forward", "backproject")

#: ``timer(phase)`` returns a context manager around the work of that phase (one of `PHASES`).
PhaseTimer = Callable[[str], AbstractContextManager]


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
    backproject: str = "ball",
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
    backproject : {"ball", "face"}
        See `geofeat.render.backproject`.
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
    BackprojectError
        Unknown ``backproject`` or ``fill`` mode, or a bad ``batch_size``.
    """
    if mesh.faces is None:
        raise RenderError(
            f"{mesh.name or 'the mesh'!r} is a point cloud: multi-view features need faces to render; "
            "give a triangle mesh (or reconstruct a surface first)."
        )
    backproject = check_choice(backproject, "backproject", BACKPROJECT_MODES, error=BackprojectError)
    fill = check_choice(fill, "fill", FILL_MODES, error=BackprojectError)
    batch_size = len(cameras) if batch_size is None else check_integer(batch_size, "batch_size", low=1, error=BackprojectError)
    timer = timer or _no_timer
    device = backbone.device
    size = (cameras.height, cameras.width)
    accumulator = VertexFeatureAccumulator(mesh.verts, mesh.faces, backbone.embed_dim, mode=backproject, device=device)
    starts = range(0, len(cameras), batch_size)
    with torch.enable_grad() if grad else torch.no_grad():
        for start in tqdm(starts, desc=f"views of {mesh.name or 'mesh'}", unit="batch", disable=not progress):
            with timer("render"), torch.no_grad():  # the images do not depend on any parameter
                rendering = render_phong(mesh, None, cameras[start : start + batch_size])
            pix_to_face, bary = rendering.fragments.pix_to_face, rendering.fragments.bary
            with timer("forward"):
                amp = torch.autocast(device_type=device.type, dtype=torch.bfloat16) if autocast else contextlib.nullcontext()
                with amp:
                    grid = backbone.patch_features(rendering.images)  # (B, H / p, W / p, C)
                features = sample_patch_features(grid, foreground_pixels(pix_to_face), size)  # (M, C)
            with timer("backproject"):
                accumulator.add_foreground(features, pix_to_face, bary)
        with timer("backproject"):
            return MultiviewFeatures(*accumulator.result_tensor(fill=fill))
