"""Raw DINOv2 / DINOv3 features and GeoLoRA features lifted from multi-view renders to mesh vertices.

The descriptors hold the parameters and the backbone; the path itself (cameras -> rasterize +
gray Phong shading -> backbone -> patch features sampled at the foreground pixels ->
back-projection to vertices, in batches of views) is `geofeat.multiview.multiview_features`, the
one the GeoLoRA trainer uses too. Point clouds take the same path, drawn as discs by the point
renderer (`geofeat.multiview.views`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from dataclasses import replace
from typing import TYPE_CHECKING, ClassVar, NamedTuple

import numpy as np
import torch

from geofeat.checks import check_boolean, check_choice, check_integer
from geofeat.descriptors.base import Descriptor
from geofeat.errors import DescriptorError
from geofeat.mesh import Mesh
from geofeat.multiview import multiview_features
from geofeat.multiview.backproject import BACKPROJECT_MODES
from geofeat.multiview.pipeline import (
    FILL_MODES,
    RECIPES,
    FeatureRecipe,
    RenderedBatch,
    auto_batch_size,
    render_batches,
)
from geofeat.render import make_cameras
from geofeat.render.camera_layouts import CAMERA_LAYOUTS
from geofeat.render.cameras import Cameras

if TYPE_CHECKING:
    from geofeat.backbones.dino import DinoBackbone

#: Views and render size of each recipe when ``views`` / ``image_size`` are not given
#: (``image_size`` None under "default": the kind's own, 448 for DINOv2 and 512 for DINOv3).
RECIPE_VIEWS = {"default": 49, "reference": 49, "dsmk": 100}
RECIPE_IMAGE_SIZE = {"default": None, "reference": 512, "dsmk": 512}
#: ``amp``: bfloat16 autocast of the backbone on, off, or on where it is safe and fast (CUDA, "default" recipe).
AMP_MODES = ("auto", "on", "off")


log = logging.getLogger(__name__)


class DinoFeatures(Descriptor):
    """Shared body of the ``dinov2`` and ``dinov3`` descriptors.

    Parameters
    ----------
    recipe : str
        How each stage of the multi-view path is done: ``"default"`` (geofeat's),
        ``"reference"`` (the official GeoLoRA code's, stage by stage) or, for ``dinov2``,
        ``"dsmk"`` (DeepShapeMatchingKit's); see `geofeat.multiview.pipeline.RECIPES`. The
        parameters below that are None take the recipe's value; the others override it.
    weights : str or None
        A Hugging Face model folder, an official Meta checkpoint (``.pth``) or a Hub id; None
        reads ``$GEOFEAT_DINOV2_WEIGHTS`` / ``$GEOFEAT_DINOV3_WEIGHTS`` (see
        `geofeat.backbones.load_backbone`).
    views : int or None
        Number of cameras (49 = the official 7 x 7 grid); None: 49, or 100 under ``"dsmk"``.
    image_size : int or None
        Render size in pixels; None: 512 under the ``"reference"`` and ``"dsmk"`` recipes
        (resized to 518 for the backbone, as the official code does), otherwise 448 for
        DINOv2 (patch 14) and 512 for DINOv3 (patch 16), which must then be a multiple of
        the patch size.
    camera_layout : {"official", "uniform"}
        See `geofeat.render.make_cameras`.
    backproject : {"ball", "face", "ball_last"} or None
        None: the recipe's (``"ball"``, or ``"ball_last"`` under ``"reference"`` and ``"dsmk"``).
    layer : int
        Transformer layer whose patch tokens are used (-1: the last, after the final norm).
    device : str
        ``"auto"``: CUDA when present, else CPU.
    batch_size : int or None
        Views rendered and encoded together; None: as many as the GPU's free memory allows
        (all 49 views at 512 x 512 of a ViT-B on a large GPU), 4 on the CPU
        (`geofeat.multiview.pipeline.auto_batch_size`). It does not change the features.
    amp : {"auto", "on", "off"}
        Run the backbone under bfloat16 autocast (``"on"``) or in float32 (``"off"``);
        ``"auto"``: bfloat16 on CUDA under the ``"default"`` recipe, float32 on the CPU and
        under the recipes that reproduce another code. bfloat16 features differ from float32
        ones by about 1e-2 (relative), so the cache keys them apart.
    fill : {"nearest", "zero"}
        Features of vertices seen in no view.
    random_rotation : bool
        Rotate the cameras about the up axis by a random angle drawn from ``seed``.
    seed : int
        Seed of the random rotation.
    """

    kind: ClassVar[str] = ""
    default_image_size: ClassVar[int] = 0
    recipes: ClassVar[tuple[str, ...]] = ("default", "reference")
    # 2: patch features sampled at the foreground pixels (geofeat.multiview.pipeline) instead of
    # read from upsampled whole images; equal up to float32 rounding (see README).
    # 3: recipes (the "reference" one of the official GeoLoRA code).
    # 4: amp (bfloat16 backbone) in the key; batch_size out of it (it does not change the features).
    version = "4"

    recipe: str
    weights: str | None
    views: int | None
    image_size: int | None
    camera_layout: str
    backproject: str | None
    layer: int
    device: str
    batch_size: int | None
    amp: str
    fill: str
    random_rotation: bool
    seed: int
    _backbone: DinoBackbone | None

    def __init__(
        self,
        *,
        recipe: str = "default",
        weights: str | None = None,
        views: int | None = None,
        image_size: int | None = None,
        camera_layout: str = "official",
        backproject: str | None = None,
        layer: int = -1,
        device: str = "auto",
        batch_size: int | None = None,
        amp: str = "auto",
        fill: str = "nearest",
        random_rotation: bool = False,
        seed: int = 0,
    ):
        self._store(
            recipe=recipe,
            weights=weights,
            views=views,
            image_size=image_size,
            camera_layout=camera_layout,
            backproject=backproject,
            layer=layer,
            device=device,
            batch_size=batch_size,
            amp=amp,
            fill=fill,
            random_rotation=random_rotation,
            seed=seed,
        )

    def _store(self, **params) -> None:
        """Check every parameter by type and range and store it in canonical Python form."""
        owner = self.name
        checked = dict(params)
        for name in ("weights", "checkpoint"):
            if name in params and params[name] is not None:
                if not isinstance(params[name], (str, os.PathLike)):
                    raise DescriptorError(
                        f"{owner}: {name} must be a path, a Hub id or None; found {params[name]!r} ({type(params[name]).__name__})."
                    )
                checked[name] = os.fspath(params[name])  # a pathlib.Path: keep the parameters JSON-serialisable
        checked["recipe"] = check_choice(params["recipe"], "recipe", self.recipes, owner=owner)
        for name in ("views", "image_size"):
            if params[name] is not None:
                checked[name] = check_integer(params[name], name, owner=owner, low=1)
        checked["camera_layout"] = check_choice(params["camera_layout"], "camera_layout", CAMERA_LAYOUTS, owner=owner)
        if params["backproject"] is not None:
            checked["backproject"] = check_choice(params["backproject"], "backproject", BACKPROJECT_MODES, owner=owner)
        checked["layer"] = check_integer(params["layer"], "layer", owner=owner)
        if not isinstance(params["device"], (str, torch.device)):
            raise DescriptorError(
                f"{owner}: device must be a string such as 'auto', 'cpu' or 'cuda'; found {params['device']!r}."
            )
        checked["device"] = str(params["device"])
        if params["batch_size"] is not None:
            checked["batch_size"] = check_integer(params["batch_size"], "batch_size", owner=owner, low=1)
        checked["amp"] = check_choice(params["amp"], "amp", AMP_MODES, owner=owner)
        checked["fill"] = check_choice(params["fill"], "fill", FILL_MODES, owner=owner)
        checked["random_rotation"] = check_boolean(params["random_rotation"], "random_rotation", owner=owner)
        checked["seed"] = check_integer(params["seed"], "seed", owner=owner, low=0)
        for name, value in checked.items():
            setattr(self, name, value)
        self._backbone = None

    def get_params(self) -> dict:
        """Parameters as given, except ``device`` and ``batch_size`` (they do not change the features), and ``amp`` resolved.

        ``amp="auto"`` is keyed as what it means on this descriptor's device (``"on"`` or
        ``"off"``), so bfloat16 and float32 features never share a cache entry.
        """
        params = super().get_params()
        params.pop("device")
        params.pop("batch_size")
        params["amp"] = "on" if self.autocast() else "off"
        return params

    def autocast(self) -> bool:
        """Whether the backbone runs under bfloat16 autocast (see ``amp``)."""
        if self.amp != "auto":
            return self.amp == "on"
        from geofeat.runtime.devices import resolve_device

        return self.recipe == "default" and resolve_device(self.device).type == "cuda"

    def backbone(self):
        """The loaded backbone (loaded once, on first use)."""
        if self._backbone is None:
            from geofeat.backbones import load_backbone

            self._backbone = load_backbone(self.weights, kind=self.kind, layer=self.layer, device=self.device)
        return self._backbone

    def weights_digest(self) -> str:
        """SHA-256 of the backbone's weights (part of the cache key)."""
        return self.backbone().weights_digest

    def _views(self, mesh: Mesh) -> tuple[Cameras, int]:
        """The cameras of ``mesh`` and the views per batch."""
        backbone = self.backbone()
        views = self.views or RECIPE_VIEWS[self.recipe]
        image_size = self.image_size or RECIPE_IMAGE_SIZE[self.recipe] or self.default_image_size
        cameras = make_cameras(
            mesh,
            views,
            layout=self.camera_layout,
            image_size=image_size,
            random_rotation=self.random_rotation,
            seed=self.seed,
            device=backbone.device,
        )
        batch_size = self.batch_size or auto_batch_size(len(cameras), cameras.height, cameras.width, backbone)
        return cameras, batch_size

    def prepare(self, mesh: Mesh) -> PreparedViews:
        """The cameras of ``mesh`` and all its views rendered and planned, on the backbone's device.

        May run on another thread while the backbone encodes another shape. On CUDA the work
        goes to a stream of its own, so the GPU renders while the backbone runs on the
        default stream; `compute_prepared` waits for it there.
        """
        backbone = self.backbone()
        stream = render_stream(backbone.device)
        with torch.cuda.stream(stream) if stream is not None else contextlib.nullcontext():
            if stream is not None:
                stream.wait_stream(torch.cuda.default_stream(backbone.device))  # the backbone's weights, moved there
            cameras, batch_size = self._views(mesh)
            rendered = list(
                render_batches(
                    [mesh], [cameras], backbone.patch_size, recipe=self._recipe(), batch_size=batch_size, device=backbone.device
                )
            )
            ready = stream.record_event() if stream is not None else None
        return PreparedViews(cameras, batch_size, rendered, ready)

    def compute_prepared(self, mesh: Mesh, prepared: object | None) -> np.ndarray:
        """Vertex features of shape (V, embed_dim), from the views `prepare` rendered (None: rendered here, batch by batch).

        The prepared tensors stay referenced until the features are on the host, after the
        default stream has finished with them, so their memory is never reused early.
        """
        if prepared is None:
            cameras, batch_size = self._views(mesh)
            rendered = None
        else:
            if not isinstance(prepared, PreparedViews):
                raise DescriptorError(f"{self.name}: prepared must be what prepare() returned; found {type(prepared).__name__}.")
            cameras, batch_size, rendered, ready = prepared
            if ready is not None:
                torch.cuda.current_stream(self.backbone().device).wait_event(ready)
        features, seen = multiview_features(
            mesh,
            cameras,
            self.backbone(),
            recipe=self._recipe(),
            fill=self.fill,
            batch_size=batch_size,
            autocast=self.autocast(),
            progress=True,
            rendered=rendered,
        )
        if self.fill == "zero" and not bool(seen.any()):
            log.warning(
                "%s: no vertex of %r was seen in any view; its features are all zeros (fill='zero').", self.name, mesh.name
            )
        return features.cpu().numpy().astype(np.float32, copy=False)

    def compute(self, mesh: Mesh) -> np.ndarray:
        """Vertex features of shape (V, embed_dim)."""
        return self.compute_prepared(mesh, None)

    def _recipe(self) -> FeatureRecipe:
        recipe = RECIPES[self.recipe]
        return replace(recipe, backproject=self.backproject) if self.backproject is not None else recipe


_RENDER_STREAMS: dict[torch.device, torch.cuda.Stream] = {}
_RENDER_STREAMS_LOCK = threading.Lock()


def render_stream(device: torch.device) -> torch.cuda.Stream | None:
    """The CUDA stream that `DinoFeatures.prepare` renders on, one per device (made on first use); None off CUDA."""
    if device.type != "cuda":
        return None
    device = torch.device("cuda", torch.cuda.current_device() if device.index is None else device.index)
    with _RENDER_STREAMS_LOCK:
        if device not in _RENDER_STREAMS:
            _RENDER_STREAMS[device] = torch.cuda.Stream(device)
        return _RENDER_STREAMS[device]


class PreparedViews(NamedTuple):
    """What `DinoFeatures.prepare` makes ahead of the backbone: cameras, views per batch, rendered and planned batches.

    ``ready`` is the CUDA event recorded on the rendering stream after the last of that work
    (None on the CPU).
    """

    cameras: Cameras
    batch_size: int
    rendered: list[RenderedBatch]
    ready: torch.cuda.Event | None = None


class DINOv2(DinoFeatures):
    """Raw DINOv2 features (patch 14) back-projected from multi-view renders; see `DinoFeatures`."""

    name = "dinov2"
    kind = "dinov2"
    default_image_size = 448
    recipes = ("default", "reference", "dsmk")


class DINOv3(DinoFeatures):
    """Raw DINOv3 features (patch 16) back-projected from multi-view renders; see `DinoFeatures`."""

    name = "dinov3"
    kind = "dinov3"
    default_image_size = 512


class GeoLoRA(DinoFeatures):
    """GeoLoRA features: DINOv3 with a trained LoRA, back-projected from multi-view renders.

    Parameters
    ----------
    checkpoint : str
        The LoRA: a folder written by `geofeat.backbones.save_lora` (``config.json`` +
        ``weights.safetensors``; every checkpoint of ``geofeat train-geolora``,
        ``<run>/checkpoints/step_NNNNNNN``, is one) or a GeoLoRA release
        checkpoint ``.pth`` (``saved_models/*.pth`` of the authors' repository, for DINOv3
        ViT-B/16).
    recipe, weights, views, image_size, camera_layout, backproject, layer, device, batch_size, amp, fill, random_rotation, seed
        As for ``dinov3`` (`DinoFeatures`): 49 views of the official grid at 512 x 512 by
        default; ``recipe="reference"`` reproduces the official GeoLoRA code.
    """

    name = "geolora"
    kind = "dinov3"
    default_image_size = 512

    checkpoint: str | None

    def __init__(
        self,
        *,
        checkpoint: str | None = None,
        recipe: str = "default",
        weights: str | None = None,
        views: int | None = None,
        image_size: int | None = None,
        camera_layout: str = "official",
        backproject: str | None = None,
        layer: int = -1,
        device: str = "auto",
        batch_size: int | None = None,
        amp: str = "auto",
        fill: str = "nearest",
        random_rotation: bool = False,
        seed: int = 0,
    ):
        self._store(
            checkpoint=checkpoint,
            recipe=recipe,
            weights=weights,
            views=views,
            image_size=image_size,
            camera_layout=camera_layout,
            backproject=backproject,
            layer=layer,
            device=device,
            batch_size=batch_size,
            amp=amp,
            fill=fill,
            random_rotation=random_rotation,
            seed=seed,
        )

    def backbone(self):
        """The DINOv3 backbone with the LoRA loaded (once, on first use)."""
        if self._backbone is None:
            from pathlib import Path

            from geofeat.backbones import load_backbone
            from geofeat.backbones.lora import load_lora, load_official_lora

            if not self.checkpoint:
                raise DescriptorError(
                    "geolora needs checkpoint=: a LoRA folder written by `geofeat train-geolora` "
                    "(<run>/checkpoints/step_NNNNNNN) or a GeoLoRA release .pth (saved_models/*.pth of vikiehm/geo-lora)."
                )
            path = Path(self.checkpoint).expanduser()
            if not path.exists():
                raise DescriptorError(f"geolora: the checkpoint {path} does not exist.")
            backbone = load_backbone(self.weights, kind=self.kind, layer=self.layer, device=self.device)
            if path.is_dir():
                load_lora(backbone, path)
            else:
                load_official_lora(backbone, path)
            self._backbone = backbone
        return self._backbone

    def weights_digest(self) -> str:
        """SHA-256 of the base weights together with the LoRA (part of the cache key)."""
        from geofeat.backbones.lora import loaded_lora_digest

        return loaded_lora_digest(self.backbone())
