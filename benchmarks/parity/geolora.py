"""Stage-by-stage parity of geofeat's DINO / GeoLoRA features and training step with the official code.

    python -m benchmarks.parity --geolora-repo PATH --dinov3-repo PATH [--dinov2-repo PATH] [--dsmk-repo PATH]

or this script alone with the same options. What it needs, in geofeat's environment:

* ``--geolora-repo``: a copy of vikiehm/geo-lora (``utils/dino_utils.py``, ``utils/utils.py``,
  ``utils/paths.py``, and for ``--partials`` ``utils/shape_dataset.py`` and ``utils/ray_caster.py``);
* ``--dinov3-repo`` / ``--dinov2-repo``: copies of facebookresearch/dinov3 and /dinov2 (their
  model code only: the models are built with random weights, ``pretrained=False``);
* ``--dsmk-repo``: a copy of xieyizheng/DeepShapeMatchingKit (``utils/dino_util.py``);
* pytorch3d (built from source for the CPU when no wheel fits), peft, and for ``--partials``
  open3d and libigl.

The reference code is imported from those folders at run time; nothing of it is copied into
geofeat. It imports ``torchvision.transforms``, whose CPU build does not load beside a CPU
torch on every machine, so `torchvision_stand_in` provides the five transforms it uses
(``Compose``, ``Resize``, ``Lambda``, ``Normalize``, ``ToTensor``) from their documented
equivalents: ``Resize`` on a tensor is bilinear ``F.interpolate`` with ``antialias=True``, on
a PIL image Pillow's bilinear ``resize``; ``ToTensor`` divides 8-bit values by 255.

Both implementations get the same mesh (FAUST_r), the same cameras, the same random
DINOv3 ViT-B/16 (or DINOv2 ViT-B/14) weights in the official layout, converted by geofeat's
loader, and the same random LoRA (peft on the fused ``qkv``, r=16, alpha=32), saved as the
official ``get_state_dict_lora`` does and read by `geofeat.backbones.load_official_lora`.
Every row gives the largest absolute difference and the largest magnitude of the
reference's values at one stage. "isolated" rows feed geofeat the reference's own input of
that stage, so that a difference upstream does not hide or cause one there. The tables go
to stdout and to ``benchmarks/results/parity/parity_geolora.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib
import sys
import tempfile
import time
import types
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine
from benchmarks.parity.common import Stage, compare, markdown
from geofeat.backbones import load_backbone
from geofeat.backbones.dino import grid_sample_patch_features, imagenet_normalized
from geofeat.backbones.lora import load_official_lora
from geofeat.geometry.partial import make_partial
from geofeat.multiview import multiview_features
from geofeat.multiview.backproject import VertexFeatureAccumulator
from geofeat.multiview.pipeline import RECIPES, backbone_input, corner_points
from geofeat.render import make_cameras
from geofeat.render.cameras import Cameras
from geofeat.render.rasterizer import RasterSettings
from geofeat.render.shading import render_phong

SIZE = 512
SEED = 0
#: Why the checks run on one thread (both codes, so that the times compare too).
ONE_THREAD = (
    "The reference's indexed in-place addition (sums[idx] += features) with repeated vertex indices is a race "
    "between CPU threads: with two, the vertices whose candidate pixels straddle the threads' halves of a view "
    "(about 11 of 2,400 a view) get another candidate's feature. On one thread every vertex gets its last "
    "candidate, which the reference recipe reproduces."
)


# ----------------------------------------------------------------------------- importing the reference


def torchvision_stand_in() -> types.ModuleType:
    """A ``torchvision`` module whose ``transforms`` holds the five transforms the reference code uses."""

    class Compose:
        def __init__(self, transforms):
            self.transforms = list(transforms)

        def __call__(self, x):
            for t in self.transforms:
                x = t(x)
            return x

    class Resize:
        def __init__(self, size):
            self.size = (size, size) if isinstance(size, int) else tuple(size)

        def __call__(self, x):
            from PIL import Image

            if isinstance(x, Image.Image):
                return x.resize(self.size[::-1], Image.BILINEAR)
            batched = x if x.ndim == 4 else x[None]
            out = F.interpolate(batched.float(), size=self.size, mode="bilinear", align_corners=False, antialias=True)
            return out if x.ndim == 4 else out[0]

    class Lambda:
        def __init__(self, fn):
            self.fn = fn

        def __call__(self, x):
            return self.fn(x)

    class Normalize:
        def __init__(self, mean, std):
            self.mean, self.std = torch.tensor(mean), torch.tensor(std)

        def __call__(self, x):
            return (x - self.mean.to(x)[:, None, None]) / self.std.to(x)[:, None, None]

    class ToTensor:
        def __call__(self, image):
            return torch.from_numpy(np.array(image, dtype=np.uint8)).permute(2, 0, 1).float() / 255.0

    transforms = types.ModuleType("torchvision.transforms")
    for cls in (Compose, Resize, Lambda, Normalize, ToTensor):
        setattr(transforms, cls.__name__, cls)
    module = types.ModuleType("torchvision")
    module.transforms = transforms
    return module


@contextlib.contextmanager
def reference_path(*folders: Path) -> Iterator[None]:
    """Put the reference folders first on ``sys.path`` (and the torchvision stand-in in ``sys.modules``)."""
    import peft  # noqa: F401  (imported first: their checks for torchvision must not find the stand-in)
    import transformers  # noqa: F401

    stand_in = torchvision_stand_in()
    saved = {name: sys.modules.get(name) for name in ("torchvision", "torchvision.transforms")}
    sys.modules["torchvision"], sys.modules["torchvision.transforms"] = stand_in, stand_in.transforms
    _forget(("utils",))
    for folder in folders:
        if not Path(folder).is_dir():
            raise SystemExit(
                f"benchmarks.parity.geolora: {folder} is not a folder; pass the path of your copy of the reference repository"
            )
        sys.path.insert(0, str(Path(folder).resolve()))
    try:
        yield
    finally:
        for folder in folders:
            sys.path.remove(str(Path(folder).resolve()))
        _forget(("utils",))
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def _forget(names: tuple[str, ...]) -> None:
    for name in list(sys.modules):
        if name.split(".")[0] in names:
            del sys.modules[name]


# ----------------------------------------------------------------------------- identical random weights


def official_vit(repo: Path, kind: str, seed: int = SEED) -> torch.nn.Module:
    """The official ViT-B (DINOv3 /16 or DINOv2 /14) with random weights that exercise every layer.

    The constructors' own initialisation leaves the layer scales at 1e-5 (every block nearly
    the identity) and the biases at zero, which would hide differences; they are redrawn.
    """
    sys.path.insert(0, str(Path(repo).resolve()))
    try:
        if kind == "dinov3":
            from dinov3.hub.backbones import dinov3_vitb16 as constructor
        else:
            from dinov2.hub.backbones import dinov2_vitb14 as constructor
        torch.manual_seed(seed)
        model = constructor(pretrained=False)
        if hasattr(model, "init_weights"):
            model.init_weights()  # sets DINOv3's k-bias mask (NaN until then)
        generator = torch.Generator().manual_seed(seed + 1)
        with torch.no_grad():
            for name, param in model.named_parameters():
                noise = torch.randn(param.shape, generator=generator)
                if name.endswith("gamma"):  # layer scales
                    param.copy_(0.1 + 0.05 * noise)
                elif name.endswith("bias"):
                    param.copy_(0.02 * noise)
                elif "norm" in name and name.endswith("weight"):
                    param.copy_(1.0 + 0.1 * noise)
        return model.eval()
    finally:
        sys.path.remove(str(Path(repo).resolve()))


def tiny_official_vit(repo: Path, kind: str, seed: int = SEED) -> torch.nn.Module:
    """The official model class at test size (width 16, 2 blocks, 2 heads), its ViT-B's other settings, random weights.

    The weights are rounded to float16 values, so that a float16 copy holds them exactly.
    """
    sys.path.insert(0, str(Path(repo).resolve()))
    try:
        torch.manual_seed(seed)
        if kind == "dinov3":
            from dinov3.models.vision_transformer import DinoVisionTransformer

            model = DinoVisionTransformer(
                img_size=224,
                patch_size=16,
                pos_embed_rope_base=100,
                pos_embed_rope_normalize_coords="separate",
                pos_embed_rope_rescale_coords=2,
                pos_embed_rope_dtype="fp32",
                embed_dim=16,
                depth=2,
                num_heads=2,
                ffn_ratio=2.0,
                qkv_bias=True,
                layerscale_init=1.0e-05,
                norm_layer="layernormbf16",
                ffn_layer="mlp",
                ffn_bias=True,
                proj_bias=True,
                n_storage_tokens=4,
                mask_k_bias=True,
            )
            model.init_weights()
        else:
            from dinov2.models.vision_transformer import DinoVisionTransformer

            model = DinoVisionTransformer(
                img_size=518,
                patch_size=14,
                embed_dim=16,
                depth=2,
                num_heads=2,
                mlp_ratio=2,
                init_values=1.0,
                ffn_layer="mlp",
                block_chunks=0,
                num_register_tokens=0,
                interpolate_antialias=False,
                interpolate_offset=0.1,
            )
        generator = torch.Generator().manual_seed(seed + 1)
        with torch.no_grad():
            for name, param in model.named_parameters():
                noise = torch.randn(param.shape, generator=generator)
                value = {"gamma": 0.3 + 0.1 * noise, "bias": 0.1 * noise}.get(name.rsplit(".", 1)[-1], 0.3 * noise)
                if "norm" in name and name.endswith("weight"):
                    value = 1.0 + 0.1 * noise
                param.copy_(value.half().float())
        return model.eval()
    finally:
        sys.path.remove(str(Path(repo).resolve()))


def official_lora(model: torch.nn.Module, seed: int = SEED, scale: float = 0.02):
    """peft LoRA on the fused ``qkv`` exactly as the official ``train.py`` configures it, with random A and B (float16 values)."""
    from peft import LoraConfig, get_peft_model

    peft_model = get_peft_model(model, LoraConfig(r=16, lora_alpha=32, target_modules=["qkv"], bias="none"))
    generator = torch.Generator().manual_seed(seed + 2)
    with torch.no_grad():
        for name, param in peft_model.named_parameters():
            if "lora_" in name:
                param.copy_((scale * torch.randn(param.shape, generator=generator)).half().float())
    return peft_model.eval()


def our_backbone(official: torch.nn.Module, kind: str, folder: Path):
    """geofeat's backbone from the official model's state dict, through the official-checkpoint converter."""
    path = folder / f"{kind}_official_random.pth"
    torch.save(official.state_dict(), path)
    return load_backbone(str(path), kind=kind, device="cpu")


# ----------------------------------------------------------------------------- recording the reference's stages


class RecordingModel:
    """Wraps the reference's model and keeps the input and output of every ``get_intermediate_layers`` call."""

    def __init__(self, model):
        self.model, self.inputs, self.tokens = model, [], []

    def __getattr__(self, name):
        return getattr(self.model, name)

    def get_intermediate_layers(self, x, **kwargs):
        out = self.model.get_intermediate_layers(x, **kwargs)
        self.inputs.append(x.detach().clone())
        self.tokens.append(out[0].detach().clone())
        return out


@dataclass
class ReferenceRun:
    """What one call of the reference's ``get_features_per_vertex`` computed, stage by stage."""

    renderings: torch.Tensor | None = None  # (N, H, W, 4)
    camera: object = None
    depth: torch.Tensor | None = None  # (N, H, W, 1), -1 on background
    pixel_features: list = field(default_factory=list)  # per view (1, C, H*W)
    points: list = field(default_factory=list)  # per view (P, 3): unprojected foreground pixels
    features: torch.Tensor | None = None  # (V, C)
    seconds: float = 0.0


@contextlib.contextmanager
def recording(module, run: ReferenceRun) -> Iterator[None]:
    """Wrap the reference module's ``batch_render``, ``get_dino_features`` and ``ball_query`` to keep their results."""
    originals = {name: getattr(module, name) for name in ("batch_render", "get_dino_features", "ball_query")}

    def batch_render(*args, **kwargs):
        out = originals["batch_render"](*args, **kwargs)
        run.renderings, run.camera, run.depth = out[0], out[2], out[3]
        return out

    def get_dino_features(*args, **kwargs):
        out = originals["get_dino_features"](*args, **kwargs)
        run.pixel_features.append(out.detach().clone())
        return out

    def ball_query(points, *args, **kwargs):
        run.points.append(points[0].detach().clone())
        return originals["ball_query"](points, *args, **kwargs)

    for name, wrapper in (("batch_render", batch_render), ("get_dino_features", get_dino_features), ("ball_query", ball_query)):
        setattr(module, name, wrapper)
    try:
        with contiguous_grid_sample():
            yield
    finally:
        for name, fn in originals.items():
            setattr(module, name, fn)


@contextlib.contextmanager
def contiguous_grid_sample() -> Iterator[None]:
    """The CPU patch of the reference: ``grid_sample`` gets a contiguous input.

    On the CPU, float16 ``grid_sample`` returns wrong values (NaN among them) for the permuted
    (channels-last) 768-channel token grid that the reference passes it (torch 2.13; CUDA is
    not affected), so without this the reference's per-pixel features are garbage on a CPU.
    Making the input contiguous changes nothing else.
    """
    original = F.grid_sample

    def grid_sample(input, grid, *args, **kwargs):
        return original(input.contiguous() if input.device.type == "cpu" else input, grid, *args, **kwargs)

    torch.nn.functional.grid_sample = grid_sample
    try:
        yield
    finally:
        torch.nn.functional.grid_sample = original


# ----------------------------------------------------------------------------- conversions


def cameras_from_pytorch3d(camera, image_size: int) -> Cameras:
    """Our `Cameras` of pytorch3d ``PerspectiveCameras(R, T)`` (90 degrees): ``R = diag(-1, -1, 1) R_p3d^T``, ``C = -R_p3d T``."""
    r_p3d = camera.R.detach().double()
    t = camera.T.detach().double()
    flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    rotation = flip @ r_p3d.transpose(1, 2)
    position = -(r_p3d @ t[:, :, None])[:, :, 0]
    return Cameras(rotation, position, image_size, 90.0, "cpu")


def _p3d_mesh(utils_module, mesh: geofeat.Mesh):
    return utils_module.convert_verts_faces_to_torch_mesh(
        torch.tensor(mesh.verts, dtype=torch.float32), torch.tensor(mesh.faces, dtype=torch.int64), torch.device("cpu")
    )


def _tokens_grid(tokens: torch.Tensor, side: int) -> torch.Tensor:
    return tokens.reshape(tokens.shape[0], side, side, tokens.shape[-1])


def _foreground_flat(depth: torch.Tensor) -> torch.Tensor:
    """(M, 3) (view, row, col) of the reference's foreground pixels (depth != -1), in flat order."""
    return torch.nonzero(depth[..., 0] != -1)


def cosine_rows(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    """Per-row cosine of two (V, C) feature matrices (1 where both rows are zero)."""
    a, b = a.double(), b.double()
    na, nb = a.norm(dim=1), b.norm(dim=1)
    cos = (a * b).sum(1) / (na * nb).clamp(min=1e-30)
    cos[(na == 0) & (nb == 0)] = 1.0
    return cos.numpy()


def nn_agreement(full_a, part_a, full_b, part_b) -> float:
    """Share of partial vertices whose nearest full vertex in feature space is the same with both feature sets."""
    match_a = torch.cdist(part_a.float(), full_a.float()).argmin(1)
    match_b = torch.cdist(part_b.float(), full_b.float()).argmin(1)
    return float((match_a == match_b).double().mean())


# ----------------------------------------------------------------------------- features, stage by stage


def feature_stages(
    dino_utils, utils_module, official_model, ours, mesh: geofeat.Mesh, n_views: int, recipe: str, *, lora: bool, label: str
) -> tuple[list[Stage], ReferenceRun, torch.Tensor]:
    """Stage rows of one shape through the reference's ``get_features_per_vertex`` and geofeat's `multiview_features`.

    ``dino_utils`` is the reference module holding ``get_features_per_vertex`` (GeoLoRA's or
    DeepShapeMatchingKit's); ``official_model`` its model (peft-wrapped when ``lora``).
    Returns the rows, the reference's run and geofeat's end-to-end vertex features.
    """
    rows: list[Stage] = []
    p3d_mesh = _p3d_mesh(utils_module, mesh)
    recorder = RecordingModel(official_model)
    run = ReferenceRun()
    start = time.perf_counter()
    with recording(dino_utils, run), torch.no_grad():
        if "pipe" in dino_utils.get_features_per_vertex.__code__.co_varnames[:3]:  # DeepShapeMatchingKit's signature
            features = dino_utils.get_features_per_vertex(
                device=torch.device("cpu"),
                pipe=None,
                dino_model=recorder,
                mesh=p3d_mesh,
                prompt="",
                mesh_vertices=p3d_mesh.verts_list()[0],
                num_views=n_views,
                H=SIZE,
                W=SIZE,
                tolerance=0.004,
            )
        else:
            features = dino_utils.get_features_per_vertex(
                torch.device("cpu"),
                recorder,
                p3d_mesh,
                num_views=n_views,
                H=SIZE,
                W=SIZE,
                tolerance=0.004,
                mesh_vertices=p3d_mesh.verts_list()[0],
                set_missing_features=True,
            )
    run.features, run.seconds = features.detach().float(), time.perf_counter() - start

    # cameras
    cameras = make_cameras(mesh, n_views, image_size=SIZE, device="cpu")
    theirs = cameras_from_pytorch3d(run.camera, SIZE)
    rows.append(compare(f"{label}: camera rotations", cameras.rotation, theirs.rotation))
    rows.append(compare(f"{label}: camera positions", cameras.position, theirs.position))

    # rasterization and shading (ours on our cameras; theirs as rendered)
    settings = RasterSettings(cull_backfaces=RECIPES[recipe].cull_backfaces)
    rendering = render_phong(mesh, None, cameras, settings)
    from pytorch3d.renderer import MeshRasterizer, RasterizationSettings

    raster = MeshRasterizer(
        cameras=run.camera,
        raster_settings=RasterizationSettings(
            image_size=(SIZE, SIZE), blur_radius=0.0, faces_per_pixel=1, cull_backfaces=RECIPES[recipe].cull_backfaces
        ),
    )
    fragments = raster(p3d_mesh.extend(n_views))
    n_faces = len(mesh.faces)
    their_faces = fragments.pix_to_face[..., 0]
    their_faces = torch.where(their_faces >= 0, their_faces % n_faces, their_faces)
    our_faces = rendering.fragments.pix_to_face
    differ = our_faces != their_faces
    edge = _face_edges(their_faces)
    rows.append(
        Stage(
            f"{label}: pixel-to-face (share of pixels that differ)",
            float(differ.double().mean()),
            1.0,
            f"{int(differ.sum())} of {differ.numel()} pixels; {float((differ & edge).sum()) / max(1, int(differ.sum())):.0%} of them "
            "on an edge between faces or at the silhouette",
        )
    )
    same = (~differ) & (our_faces >= 0)
    rows.append(compare(f"{label}: depth (pixels with the same face)", rendering.fragments.depth[same], run.depth[..., 0][same]))
    rows.append(
        compare(f"{label}: shaded image (pixels with the same face)", rendering.images[same], run.renderings[..., :3][same])
    )

    # backbone input and tokens, isolated: both fed the reference's render
    recipe_ = RECIPES[recipe]
    their_rgb = run.renderings[..., :3].float()
    our_input = backbone_input(their_rgb, recipe_, ours.patch_size)
    side = our_input.shape[1]
    their_input = torch.cat(recorder.inputs)[:, :, :side, :side]
    rows.append(
        compare(
            f"{label}: backbone input, isolated (resize to 518, crop, normalise)", imagenet_normalized(our_input), their_input
        )
    )
    with torch.no_grad():
        our_tokens = ours.patch_features(our_input)
    their_tokens = _tokens_grid(torch.cat(recorder.tokens), side // ours.patch_size)
    rows.append(compare(f"{label}: backbone patch tokens{' with LoRA' if lora else ''}, isolated", our_tokens, their_tokens))
    if lora:
        with official_model.disable_adapter(), torch.no_grad():
            plain = official_model.get_intermediate_layers(torch.cat(recorder.inputs), n=1)[0]
        with ours.model.disable_adapter(), torch.no_grad():
            our_plain = ours.patch_features(our_input)
        rows.append(
            compare(
                f"{label}: backbone patch tokens without LoRA, isolated", our_plain, _tokens_grid(plain, side // ours.patch_size)
            )
        )

    # per-pixel features, isolated: the reference's tokens through our sampler
    all_pixels = torch.stack(torch.meshgrid(torch.arange(SIZE), torch.arange(SIZE), indexing="ij"), -1).reshape(-1, 2)
    worst = 0.0
    scale = 0.0
    for view in range(n_views):
        pixels = torch.cat((torch.full((all_pixels.shape[0], 1), 0), all_pixels), dim=1)
        mine = grid_sample_patch_features(their_tokens[view : view + 1].float(), pixels, (SIZE, SIZE), recipe_.dtype)
        reference = run.pixel_features[view][0].T
        worst = max(worst, float((mine.float() - reference.float()).abs().nan_to_num(float("inf")).max()))
        scale = max(scale, float(reference.float().abs().max()))
    rows.append(Stage(f"{label}: per-pixel features (float16), isolated", worst, scale, "all pixels of every view"))

    # 3D points of the foreground pixels, isolated: the reference's cameras and depth through our unprojection
    their_fg = _foreground_flat(run.depth)
    our_points = corner_points(theirs, their_fg, run.depth[..., 0])
    rows.append(compare(f"{label}: unprojected pixels, isolated", our_points, torch.cat(run.points)))

    # back-projection and fill, isolated: the reference's points and per-pixel features into our accumulator
    accumulator = VertexFeatureAccumulator(
        mesh.verts,
        mesh.faces,
        ours.embed_dim,
        mode=recipe_.backproject,
        radius_basis=recipe_.radius_basis,
        max_neighbours=recipe_.max_neighbours,
        dtype=recipe_.dtype,
    )
    for view in range(n_views):
        in_view = their_fg[:, 0] == view
        depth_view = run.depth[view : view + 1, ..., 0]
        fake_faces = torch.where(depth_view != -1, 0, -1)  # foreground mask in the accumulator's layout
        pixel_rows = run.pixel_features[view][0].T[(depth_view.reshape(-1) != -1)]
        accumulator.add_foreground(pixel_rows, fake_faces, torch.zeros(1, SIZE, SIZE, 3), torch.cat(run.points)[in_view])
    unfilled, seen = accumulator.result_tensor(fill="zero")
    filled, _ = accumulator.result_tensor(fill="nearest")
    rows.append(
        compare(
            f"{label}: back-projected vertex features, isolated (seen vertices)",
            unfilled[seen],
            run.features[seen],
            f"{int(seen.sum())} seen vertices; reference on one thread",
        )
    )
    rows.append(
        compare(
            f"{label}: unseen-vertex fill, isolated", filled[~seen], run.features[~seen], f"{int((~seen).sum())} unseen vertices"
        )
    )

    # end to end
    start = time.perf_counter()
    with torch.no_grad():
        ours_end, _ = multiview_features(mesh, cameras, ours, recipe=recipe_, fill="nearest", batch_size=4)
    seconds = time.perf_counter() - start
    cos = cosine_rows(ours_end, run.features)
    rows.append(
        compare(
            f"{label}: vertex features end to end (geofeat '{recipe}' vs reference)",
            ours_end,
            run.features,
            f"per-vertex cosine min {cos.min():.4f}, mean {cos.mean():.5f}; {(cos < 0.99).sum()} vertices below 0.99",
        )
    )
    rows.append(Stage(f"{label}: seconds per shape ({n_views} views), reference / geofeat", run.seconds, seconds, "times"))
    return rows, run, ours_end


def full_view_stages(dino_utils, utils_module, official_peft, ours, mesh: geofeat.Mesh, n_views: int) -> list[Stage]:
    """End to end at full view count: the reference's features against geofeat's ``reference`` and default recipes."""
    run = ReferenceRun()
    start = time.perf_counter()
    with recording(dino_utils, run), torch.no_grad():
        theirs = dino_utils.get_features_per_vertex(
            torch.device("cpu"),
            official_peft,
            _p3d_mesh(utils_module, mesh),
            num_views=n_views,
            H=SIZE,
            W=SIZE,
            tolerance=0.004,
            set_missing_features=True,
        ).float()
    seconds_ref = time.perf_counter() - start
    rows = []
    cameras = make_cameras(mesh, n_views, image_size=SIZE, device="cpu")
    for recipe in ("reference", "default"):
        start = time.perf_counter()
        with torch.no_grad():
            mine, _ = multiview_features(mesh, cameras, ours, recipe=RECIPES[recipe], fill="nearest", batch_size=4)
        seconds = time.perf_counter() - start
        cos = cosine_rows(mine, theirs)
        rows.append(
            Stage(
                f"geofeat '{recipe}' recipe: 1 - per-vertex cosine to the reference",
                float(1 - cos.min()),
                1.0,
                f"cosine min {cos.min():.5f}, mean {cos.mean():.6f}, {(cos < 0.999).sum()} of {cos.size} vertices below 0.999; "
                f"{seconds:.1f} s per shape (reference {seconds_ref:.1f} s)",
            )
        )
    return rows


def _face_edges(faces: torch.Tensor) -> torch.Tensor:
    """Pixels with a 4-neighbour of another face (or background)."""
    edge = torch.zeros_like(faces, dtype=torch.bool)
    edge[:, 1:] |= faces[:, 1:] != faces[:, :-1]
    edge[:, :-1] |= faces[:, 1:] != faces[:, :-1]
    edge[:, :, 1:] |= faces[:, :, 1:] != faces[:, :, :-1]
    edge[:, :, :-1] |= faces[:, :, 1:] != faces[:, :, :-1]
    return edge


# ----------------------------------------------------------------------------- one training step


def training_pair(mesh: geofeat.Mesh, seed: int = SEED):
    """An identical full/partial pair for both codes: the full shape turned about y, a CUTS partial of it turned again."""
    from geofeat.train.trainer import rotate_about_up

    rng = np.random.default_rng(seed)
    full = rotate_about_up(mesh, float(rng.uniform(0, 360)))
    partial = make_partial(full, "cuts", seed=seed)
    turned = rotate_about_up(partial.mesh, float(rng.uniform(0, 360)))
    return full, turned, torch.as_tensor(partial.vertex_map, dtype=torch.int64)


def step_stages(
    dino_utils, utils_module, official_peft, ours, mesh: geofeat.Mesh, views_full: int, views_partial: int
) -> list[Stage]:
    """Loss and LoRA gradients of one GeoLoRA step on an identical pair, geofeat's trainer path against ``train.py``'s."""
    from geofeat.geometry.geodesic import geodesic_matrix
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    rows: list[Stage] = []
    full, partial, gt = training_pair(mesh)
    # geodesic distances: the reference's Dijkstra on the edge graph / sqrt(area) against ours
    theirs_geo = torch.as_tensor(utils_module.geodesic_dist_echo(full.verts.copy(), full.faces.copy()), dtype=torch.float32)
    ours_geo = torch.as_tensor(geodesic_matrix(full, method="dijkstra", normalize=True, cache=False), dtype=torch.float32)
    rows.append(compare("step: geodesic distances of the full shape", ours_geo, theirs_geo))

    def official_step(train_mode: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor], float]:
        with contiguous_grid_sample():
            return _official_step(train_mode)

    def _official_step(train_mode: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor], float]:
        official_peft.zero_grad(set_to_none=True)
        official_peft.train(train_mode)
        start = time.perf_counter()
        verts_f, faces_f = torch.tensor(full.verts, dtype=torch.float32), torch.tensor(full.faces).int()
        verts_p, faces_p = torch.tensor(partial.verts, dtype=torch.float32), torch.tensor(partial.faces).int()
        feat_full = dino_utils.compute_features(
            torch.device("cpu"), official_peft, verts_f, faces_f, num_views=views_full
        ).float()
        feat_partial = dino_utils.compute_features(
            torch.device("cpu"), official_peft, verts_p, faces_p, num_views=views_partial
        ).float()
        # the loss as train.py forms it: observed partial vertices, positives at their ground truth
        observed = feat_partial.sum(dim=1) != 0
        loss = utils_module.weighted_contrastive_loss(
            feat_partial[gt != -1][observed], feat_full[gt[gt != -1]][observed], feat_full, gt[gt != -1][observed], theirs_geo
        )
        loss.backward()
        seconds = time.perf_counter() - start
        grads = {n: p.grad.detach().clone() for n, p in official_peft.named_parameters() if "lora_" in n and p.grad is not None}
        official_peft.eval()
        return loss.detach(), grads, seconds

    loss_ref, grads_ref, seconds_ref = official_step(False)

    with tempfile.TemporaryDirectory() as tmp:
        config = TrainConfig(
            data="unused",
            out=str(Path(tmp) / "run"),
            recipe="reference",
            views_full=views_full,
            views_partial=views_partial,
            image_size=SIZE,
            device="cpu",
            amp="off",
            progress=False,
        )
        trainer = GeoLoraTrainer(config, backbone=ours, shapes=[full])
        trainer.geodesics = None  # not used: the step below is given the reference's distances
        for p in ours.model.parameters():
            p.grad = None
        lora = [p for n, p in ours.model.named_parameters() if "lora_" in n]
        for p in lora:
            p.requires_grad_(True)
        start = time.perf_counter()
        with torch.enable_grad():
            feat_full, seen_full = trainer.mesh_features(full, views_full)
            feat_partial, seen_partial = trainer.mesh_features(partial, views_partial)
            loss = trainer._loss(feat_partial, feat_full, gt, theirs_geo, seen_partial, seen_full)
            loss.backward()
        seconds = time.perf_counter() - start
    rows.append(compare("step: loss", loss.detach(), loss_ref))
    ours_named = dict(ours.model.named_parameters(remove_duplicate=False))
    worst_a = worst_b = scale_a = scale_b = 0.0
    for name, grad in grads_ref.items():
        block = int(name.split("blocks.")[1].split(".")[0])
        which = "lora_A" if ".lora_A." in name else "lora_B"
        parts = [
            ours_named[f"base_model.model.model.layer.{block}.attention.{t}.{which}.default.weight"]
            for t in ("q_proj", "k_proj", "v_proj")
        ]
        if which == "lora_A":  # the fused A is shared by q, k and v: its gradient is the sum of theirs
            mine = sum({id(p): p.grad for p in parts}.values())  # a shared A (one parameter) once
            worst_a, scale_a = max(worst_a, float((mine - grad).abs().max())), max(scale_a, float(grad.abs().max()))
        else:
            mine = torch.cat([p.grad for p in parts])
            worst_b, scale_b = max(worst_b, float((mine - grad).abs().max())), max(scale_b, float(grad.abs().max()))
    rows.append(Stage("step: LoRA A gradients (sum over q, k, v)", worst_a, scale_a, f"{len(grads_ref) // 2} blocks"))
    rows.append(Stage("step: LoRA B gradients (q, k, v stacked)", worst_b, scale_b, f"{len(grads_ref) // 2} blocks"))
    torch.manual_seed(SEED)
    loss_train, _, _ = official_step(True)
    rows.append(
        Stage(
            "step: reference loss, train() against eval() mode",
            abs(float(loss_train) - float(loss_ref)),
            abs(float(loss_ref)),
            "train.py runs DINOv3 in train mode, where its RoPE coordinates are rescaled at random (x1/2..x2) on every pass",
        )
    )
    rows.append(
        Stage(f"step: seconds ({views_full} + {views_partial} views), reference / geofeat", seconds_ref, seconds, "times")
    )
    return rows


# ----------------------------------------------------------------------------- our defaults against the reference


#: Each deliberate difference of the default recipe: (name, the reference recipe's field set to the default's value, why).
DIFFERENCES = (
    (
        "back-projection",
        {"backproject": "ball"},
        "the mean of every pixel within the ball, a true average; the reference keeps one pixel per view and vertex, and its gradients are not those of its result",
    ),
    (
        "pixel grid",
        {"pixel_grid": "centers"},
        "pixel centres, where the rasterizer sampled; the reference's corner-aligned grid shifts pixels by up to half a pixel, in feature lookup and in 3D",
    ),
    (
        "backbone input",
        {"input_size": None},
        "the render as it is (512 is a multiple of 16); the reference resizes 512 to 518 and the patch embedding then drops 6 rows and columns",
    ),
    ("precision", {"precision": "float32"}, "float32 sums; the reference samples and sums in float16"),
    (
        "radius",
        {"radius_basis": "diagonal"},
        "0.004 x the bounding-box diagonal, O(V); the reference's largest vertex distance needs all pairs (a sample above 35,000 vertices)",
    ),
    ("neighbours per pixel", {"max_neighbours": None}, "every vertex in the ball; the reference keeps the first 100 by index"),
)


def difference_stages(ours, mesh: geofeat.Mesh, other: geofeat.Mesh, n_views: int) -> list[Stage]:
    """Effect of each deliberate difference: the reference recipe with that one field set to geofeat's default.

    Each row: the per-vertex cosine between those features and the reference recipe's on
    ``mesh``, and the share of ``mesh`` vertices whose nearest neighbour on ``other`` in
    feature space is the same with both recipes. The reference recipe equals the official
    code (the tables above), so this needs no reference code.
    """
    from dataclasses import replace

    def features(recipe, shape):
        cameras = make_cameras(shape, n_views, image_size=SIZE, device="cpu")
        with torch.no_grad():
            return multiview_features(shape, cameras, ours, recipe=recipe, fill="nearest", batch_size=4)[0]

    reference = RECIPES["reference"]
    base = (features(reference, mesh), features(reference, other))
    rows = []
    variants = [(name, replace(reference, **change), why) for name, change, why in DIFFERENCES]
    variants.append(("all of them (the default recipe)", RECIPES["default"], "geofeat's default"))
    for name, recipe, why in variants:
        changed = (features(recipe, mesh), features(recipe, other))
        cos = cosine_rows(changed[0], base[0])
        agree = nn_agreement(base[1], base[0], changed[1], changed[0])
        rows.append(
            Stage(
                f"default {name}",
                float(1 - cos.mean()),
                1.0,
                f"cosine to the reference: mean {cos.mean():.4f}, min {cos.min():.3f}; same nearest neighbour on "
                f"{other.name}: {agree:.1%}. Why: {why}",
            )
        )
    return rows


# ----------------------------------------------------------------------------- partial shapes


def partial_statistics(verts: np.ndarray, faces: np.ndarray, n_full: int, sqrt_area: float) -> tuple[float, float, int]:
    """Kept-vertex fraction, boundary length / sqrt(full area), and number of connected components of a partial shape."""
    from geofeat.topology import corner_edges, vertex_components

    faces = np.asarray(faces, dtype=np.int64)
    used = np.unique(faces)
    edges, counts = np.unique(corner_edges(faces), axis=0, return_counts=True)
    boundary = edges[counts == 1]  # edges of one face only
    length = float(np.linalg.norm(verts[boundary[:, 0]] - verts[boundary[:, 1]], axis=1).sum()) / sqrt_area
    n_components, labels = vertex_components(len(verts), faces)
    return used.size / n_full, length, int(np.unique(labels[used]).size)


def partial_stages(geolora_repo: Path, mesh: geofeat.Mesh, draws: int) -> list[Stage]:
    """CUTS, HOLES and RAY of both codes over ``draws`` draws: the two codes cannot share a seed, so compare distributions."""
    import open3d as o3d

    from geofeat.geometry.geodesic import geodesic_matrix
    from geofeat.topology import triangle_areas

    full_area = float(triangle_areas(mesh.verts, mesh.faces).sum())
    sqrt_area = full_area**0.5
    with reference_path(geolora_repo):
        shape_dataset = importlib.import_module("utils.shape_dataset")
        dataset = object.__new__(shape_dataset.PartialShapeDataset)  # only its generators are used
        o3d_mesh = o3d.geometry.TriangleMesh()
        o3d_mesh.vertices = o3d.utility.Vector3dVector(mesh.verts.copy())
        o3d_mesh.triangles = o3d.utility.Vector3iVector(mesh.faces.copy())
        distances = torch.as_tensor(geodesic_matrix(mesh, normalize=True, cache=False), dtype=torch.float32)
        generators = {
            "cuts": lambda: dataset.generate_random_cut(o3d_mesh),
            "holes": lambda: dataset.generate_random_holes(o3d_mesh, distances),
            "ray": lambda: dataset.generate_random_view_ray(o3d_mesh),
        }
        np.random.seed(SEED)
        torch.manual_seed(SEED)
        theirs = {
            kind: [partial_statistics(*fn(), len(mesh.verts), sqrt_area) for _ in range(draws)] for kind, fn in generators.items()
        }
    ours = {}
    for kind in generators:
        stats = []
        for i in range(draws):
            partial = make_partial(mesh, kind, seed=i).mesh
            stats.append(partial_statistics(partial.verts, partial.faces, len(mesh.verts), sqrt_area))
        ours[kind] = stats
    rows = []
    for kind in generators:
        for j, what in enumerate(("kept-vertex fraction", "boundary length / sqrt(area)", "components")):
            a = np.array([s[j] for s in ours[kind]], dtype=float)
            b = np.array([s[j] for s in theirs[kind]], dtype=float)
            note = (
                f"geofeat mean {a.mean():.3f} (10-90%: {np.percentile(a, 10):.3f}-{np.percentile(a, 90):.3f}); "
                f"reference mean {b.mean():.3f} (10-90%: {np.percentile(b, 10):.3f}-{np.percentile(b, 90):.3f})"
            )
            rows.append(
                Stage(
                    f"{kind.upper()}: {what}, {draws} draws (difference of means)", abs(a.mean() - b.mean()), abs(b.mean()), note
                )
            )
    return rows


# ----------------------------------------------------------------------------- recorded outputs for the tests

#: Render size, views and shape of the recorded feature stages (small, so that the arrays stay small).
RECORD_SIZE, RECORD_VIEWS, RECORD_EVERY = 64, 4, 10


def record_reference(args) -> None:
    """Run the official code on a tiny official-layout DINOv3 + LoRA and save its stage outputs for ``tests/``.

    Writes ``geolora_reference.npz`` (weights, inputs and outputs, under 200 KB) and
    ``geolora_reference_lora.pth`` (the LoRA as the official ``get_state_dict_lora`` saves it)
    into ``args.record``. The tests (``tests/multiview/test_reference_recipe.py``) rebuild the
    official weights in geofeat's loaders and compare each stage with these arrays.
    """
    out = Path(args.record)
    out.mkdir(parents=True, exist_ok=True)
    mesh = geofeat.load_mesh(args.data_root / "FAUST_r" / "off" / f"{args.shape}.off")
    arrays: dict[str, np.ndarray] = {}
    with reference_path(args.geolora_repo):
        dino_utils = importlib.import_module("utils.dino_utils")
        utils_module = importlib.import_module("utils.utils")
        official = tiny_official_vit(args.dinov3_repo, "dinov3")
        for key, value in official.state_dict().items():
            arrays[f"weights/{key}"] = value.numpy()
        peft_model = official_lora(official, scale=0.3)
        torch.save(utils_module.get_state_dict_lora(peft_model), out / "geolora_reference_lora.pth")

        # tokens of one image, without and with LoRA
        image = torch.rand(1, 32, 32, 3, generator=torch.Generator().manual_seed(SEED)).half().float()
        arrays["tokens/image"] = image.numpy()
        with torch.no_grad():
            with peft_model.disable_adapter():
                arrays["tokens/plain"] = peft_model.get_intermediate_layers(imagenet_normalized(image), n=1)[0].numpy()
            arrays["tokens/lora"] = peft_model.get_intermediate_layers(imagenet_normalized(image), n=1)[0].numpy()

        # the feature path on a small render
        run = ReferenceRun()
        with recording(dino_utils, run), torch.no_grad():
            features = dino_utils.get_features_per_vertex(
                torch.device("cpu"),
                RecordingModel(peft_model),
                _p3d_mesh(utils_module, mesh),
                num_views=RECORD_VIEWS,
                H=RECORD_SIZE,
                W=RECORD_SIZE,
                tolerance=0.004,
                set_missing_features=True,
            )
        foreground = run.depth[..., 0] != -1
        cameras = cameras_from_pytorch3d(run.camera, RECORD_SIZE)
        arrays["path/rotation"], arrays["path/position"] = cameras.rotation.numpy(), cameras.position.numpy()
        arrays["path/foreground"] = foreground.numpy()
        arrays["path/depth"] = run.depth[..., 0][foreground].numpy()
        view0 = foreground[0].reshape(-1)
        arrays["path/image_view0"] = run.renderings[0, ..., :3].reshape(-1, 3)[view0].numpy()
        arrays["path/pixel_features_view0"] = run.pixel_features[0][0].T[view0].numpy()
        arrays["path/points_view0"] = run.points[0].numpy()
        arrays["path/features"] = features[::RECORD_EVERY].numpy()

        # one training step (the official compute_features renders at 512)
        stack = contextlib.ExitStack()
        stack.enter_context(contiguous_grid_sample())
        full, partial, gt = training_pair(mesh)
        geodesics = torch.as_tensor(utils_module.geodesic_dist_echo(full.verts.copy(), full.faces.copy()), dtype=torch.float32)
        peft_model.zero_grad(set_to_none=True)
        feat_full = dino_utils.compute_features(
            torch.device("cpu"),
            peft_model,
            torch.tensor(full.verts, dtype=torch.float32),
            torch.tensor(full.faces).int(),
            num_views=args.views_full,
        ).float()
        feat_partial = dino_utils.compute_features(
            torch.device("cpu"),
            peft_model,
            torch.tensor(partial.verts, dtype=torch.float32),
            torch.tensor(partial.faces).int(),
            num_views=args.views_partial,
        ).float()
        observed = feat_partial.sum(dim=1) != 0
        loss = utils_module.weighted_contrastive_loss(
            feat_partial[gt != -1][observed], feat_full[gt[gt != -1]][observed], feat_full, gt[gt != -1][observed], geodesics
        )
        loss.backward()
        arrays["step/views"] = np.array([args.views_full, args.views_partial])
        arrays["step/loss"] = loss.detach().numpy()
        arrays["step/geodesics_row0"] = geodesics[0].numpy()
        for name, param in peft_model.named_parameters():
            if "lora_" in name:
                arrays[f"step/grad/{name}"] = param.grad.numpy()
        stack.close()
    np.savez_compressed(out / "geolora_reference.npz", **arrays)
    size = (out / "geolora_reference.npz").stat().st_size + (out / "geolora_reference_lora.pth").stat().st_size
    print(f"recorded {len(arrays)} arrays into {out} ({size / 1024:.0f} KB)")


# ----------------------------------------------------------------------------- driver


def geolora_sections(args) -> Iterator[str]:
    """The parity sections asked for by ``args``, each a Markdown table, as they are done."""
    mesh = geofeat.load_mesh(args.data_root / "FAUST_r" / "off" / f"{args.shape}.off")
    torch.set_num_threads(1)  # see ONE_THREAD
    with tempfile.TemporaryDirectory() as tmp, reference_path(args.geolora_repo):
        folder = Path(tmp)
        dino_utils = importlib.import_module("utils.dino_utils")
        utils_module = importlib.import_module("utils.utils")
        if args.dinov3_repo:
            official = official_vit(args.dinov3_repo, "dinov3")
            ours = our_backbone(official, "dinov3", folder)
            peft_model = official_lora(official)
            lora_path = folder / "lora.pth"
            torch.save(utils_module.get_state_dict_lora(peft_model), lora_path)  # the official save format
            load_official_lora(ours, lora_path)
            if args.views:
                rows, _, _ = feature_stages(
                    dino_utils, utils_module, peft_model, ours, mesh, args.views, "reference", lora=True, label="DINOv3+LoRA"
                )
                yield markdown(rows, f"DINOv3 ViT-B/16 + LoRA, GeoLoRA code ({args.shape}, {args.views} views)")
            if args.differences:
                other = geofeat.load_mesh(args.data_root / "FAUST_r" / "off" / f"{args.other}.off")
                rows = difference_stages(ours, mesh, other, args.differences)
                yield markdown(
                    rows,
                    f"geofeat's default recipe against the reference, one difference at a time ({args.shape} -> {args.other}, "
                    f"{args.differences} views; max abs diff = 1 - mean cosine)",
                )
            if args.full_views:
                yield markdown(
                    full_view_stages(dino_utils, utils_module, peft_model, ours, mesh, args.full_views),
                    f"DINOv3 ViT-B/16 + LoRA, {args.full_views} views ({args.shape})",
                )
            if args.step:
                rows = step_stages(dino_utils, utils_module, peft_model, ours, mesh, args.views_full, args.views_partial)
                yield markdown(rows, f"One GeoLoRA training step ({args.shape}, CUTS partial)")
        if args.dinov2_repo:
            official2 = official_vit(args.dinov2_repo, "dinov2")
            ours2 = our_backbone(official2, "dinov2", folder)
            if args.views:
                rows, _, _ = feature_stages(
                    dino_utils, utils_module, official2, ours2, mesh, args.views, "reference", lora=False, label="DINOv2"
                )
                yield markdown(rows, f"DINOv2 ViT-B/14, GeoLoRA code ({args.shape}, {args.views} views)")
    if args.dsmk_repo and args.dinov2_repo:
        with reference_path(args.dsmk_repo):
            dsmk = importlib.import_module("utils.dino_util")
            utils_module = types.SimpleNamespace(convert_verts_faces_to_torch_mesh=_dsmk_mesh)
            rows, _, _ = feature_stages(
                dsmk, utils_module, official2, ours2, mesh, args.dsmk_views, "dsmk", lora=False, label="DSMK"
            )
            yield markdown(rows, f"DINOv2 ViT-B/14, DeepShapeMatchingKit code ({args.shape}, {args.dsmk_views} views)")
    if args.partials:
        yield markdown(partial_stages(args.geolora_repo, mesh, args.partials), f"Partial shapes ({args.shape})")


def _dsmk_mesh(verts, faces, device):
    """DeepShapeMatchingKit's mesh: vertex colours 0.8, as its ``compute_shape_dino_features`` builds it."""
    from pytorch3d.renderer import TexturesVertex
    from pytorch3d.structures import Meshes

    return Meshes(verts=[verts.float()], faces=[faces], textures=TexturesVertex(torch.ones_like(verts.float())[None] * 0.8)).to(
        device
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of this check (shared with ``python -m benchmarks.parity``)."""
    parser.add_argument("--geolora-repo", type=Path, default=None, help="copy of vikiehm/geo-lora")
    parser.add_argument("--dinov3-repo", type=Path, default=None, help="copy of facebookresearch/dinov3")
    parser.add_argument("--dinov2-repo", type=Path, default=None, help="copy of facebookresearch/dinov2")
    parser.add_argument(
        "--dsmk-repo", type=Path, default=None, help="copy of xieyizheng/DeepShapeMatchingKit (needs --dinov2-repo)"
    )
    parser.add_argument("--shape", default="tr_reg_080", help="FAUST_r shape")
    parser.add_argument(
        "--views", type=int, default=4, help="views of the DINOv3 and DINOv2 feature stages (a perfect square; 0: skip them)"
    )
    parser.add_argument("--dsmk-views", type=int, default=4, help="views of the DeepShapeMatchingKit stages (100 in its code)")
    parser.add_argument("--no-step", dest="step", action="store_false", help="skip the training step")
    parser.add_argument("--differences", type=int, default=0, help="views of the default-vs-reference table (0: none)")
    parser.add_argument("--other", default="tr_reg_081", help="second FAUST_r shape of the nearest-neighbour agreement")
    parser.add_argument("--full-views", type=int, default=0, help="views of the end-to-end cosine check (49; 0: none)")
    parser.add_argument("--partials", type=int, default=0, help="draws of each partial-shape generator to compare (0: none)")
    parser.add_argument("--views-full", type=int, default=9)
    parser.add_argument("--views-partial", type=int, default=4)


def main(argv=None) -> int:

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    parser.add_argument(
        "--data-root", type=Path, default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)"
    )
    parser.add_argument("--out", type=Path, default=RESULTS / "parity" / "parity_geolora.md")
    parser.add_argument("--record", type=Path, default=None, help="instead: record the tests' arrays into this folder")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # see ONE_THREAD
    if not args.geolora_repo:
        parser.error("give --geolora-repo (and --dinov3-repo and/or --dinov2-repo)")
    args.data_root = data_folder(args.data_root, "--data-root")
    if args.record:
        if not args.dinov3_repo:
            parser.error("--record needs --dinov3-repo")
        record_reference(args)
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sections = [f"Run {datetime.date.today().isoformat()} on {machine()}, one thread. {ONE_THREAD}\n"]
    for section in geolora_sections(args):  # the file is rewritten after each section: a later failure loses nothing
        print(section, flush=True)
        sections.append(section)
        args.out.write_text("\n".join(sections))
    text = "\n".join(sections)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
