"""Time one shape through the multi-view DINO path, stage by stage, and draw what it makes.

The path is `geofeat.multiview.multiview_features`, the one of the DINO descriptors and the
GeoLoRA trainer. Stages, each summed over the batches of views, the device synchronised at
each stage's start and end: render (rasterize + gray Phong shading), backbone (ImageNet
normalisation, ViT forward, bilinear samples of the patch grid at the pixels that reach a
vertex, per-pixel L2 norm) and back-projection (ball mode: the plan of which pixels reach
which vertices, face-candidate neighbours, then a sparse product). "wall" is a whole pass
timed without those synchronisations, as the descriptors run it. The first pass of each
backbone (allocations, and compilation with ``--compile``) is timed apart.

``--profile`` also records one pass of the ViT-B/16-size backbone with torch.profiler and
writes ``OUT_profile.md``: the pass's wall time against the time the device spent in
kernels, and the kernels that took most of it. ``--bf16-weights`` adds a row with the
backbone's weights cast to bfloat16 (under autocast), and the mean cosine similarity of its
vertex features, and of autocast's, to float32 ones. Backbones are randomly
initialised DINOv3 architectures (no weights can be downloaded here): a tiny one and one of
ViT-B/16 size (12 layers, width 768, 12 heads, 4 register tokens).

Also writes a PNG grid of the rendered views and a PCA colouring of the back-projected
features of the ViT-B-sized backbone.

Usage::

    python -m benchmarks.speed.dino --data ../shared/data --views 49 --image-size 512
    python -m benchmarks.speed.dino --device cuda --repeats 5 --compile --out results/h100/speed_dino
    python -m benchmarks.speed.dino --device cuda --repeats 5 --profile --bf16-weights --out results/h100/speed_dino_bf16
    python -m benchmarks.speed.dino --render-only --out results/h100/speed_dino_bf16   # the Markdown from OUT.json
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (
    DEFAULT_DATA,
    RESULTS,
    faust_test_shapes,
    machine,
    profile_markdown,
    profile_tables,
    read_results,
    stored_profile_tables,
    write_results,
)
from geofeat.backbones import DinoBackbone
from geofeat.evaluation.report import plot_mesh_colors
from geofeat.multiview import multiview_features
from geofeat.multiview.pipeline import CPU_BATCH_SIZE, auto_batch_size
from geofeat.render import make_cameras, render_phong

VIT_B = "ViT-B/16 size (12 layers, width 768)"
BACKBONES = {
    "tiny (2 layers, width 32)": dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2),
    VIT_B: dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12),
}


def random_dinov3(seed: int, **sizes) -> DinoBackbone:
    """A DINOv3-architecture backbone with random weights (patch 16, 4 register tokens)."""
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    torch.manual_seed(seed)
    config = DINOv3ViTConfig(patch_size=16, image_size=224, num_register_tokens=4, **sizes)
    return DinoBackbone(DINOv3ViTModel(config), kind="dinov3")


def run_stages(mesh, cameras, backbone: DinoBackbone, batch_size: int | None, autocast: bool) -> tuple[dict, np.ndarray]:
    """Seconds per stage and the vertex features (V, C) of one pass through the multi-view path."""
    seconds = {"render": 0.0, "forward": 0.0, "backproject": 0.0}

    def synchronize() -> None:  # CUDA work is queued: wait for it so that each stage owns its time
        if backbone.device.type == "cuda":
            torch.cuda.synchronize(backbone.device)

    @contextlib.contextmanager
    def timer(phase: str):
        synchronize()
        start = time.perf_counter()
        try:
            yield
        finally:
            synchronize()
            seconds[phase] += time.perf_counter() - start

    if batch_size is None:
        batch_size = auto_batch_size(len(cameras), cameras.height, cameras.width, backbone)
    features, _ = multiview_features(
        mesh, cameras, backbone, backproject="ball", batch_size=batch_size, autocast=autocast, timer=timer
    )
    return {"render": seconds["render"], "backbone": seconds["forward"], "backproject": seconds["backproject"]}, (
        features.cpu().numpy()
    )


def wall_pass(mesh, cameras, backbone: DinoBackbone, batch_size: int | None, autocast: bool) -> float:
    """Seconds of one pass with no synchronisation inside it (the device waited for at the end)."""
    if batch_size is None:
        batch_size = auto_batch_size(len(cameras), cameras.height, cameras.width, backbone)
    cuda = backbone.device.type == "cuda"
    if cuda:
        torch.cuda.synchronize(backbone.device)
    start = time.perf_counter()
    features, _ = multiview_features(mesh, cameras, backbone, backproject="ball", batch_size=batch_size, autocast=autocast)
    if cuda:
        torch.cuda.synchronize(backbone.device)
    return time.perf_counter() - start


def timed_passes(mesh, cameras, backbone, args, autocast: bool) -> tuple[dict, np.ndarray]:
    """A warm-up pass, then ``args.repeats`` timed passes: the median seconds per stage and per pass, peak GPU memory, the features."""
    start = time.perf_counter()
    run_stages(mesh, cameras, backbone, args.batch_size, autocast)  # warm-up: first-call allocations (and compilation)
    first = time.perf_counter() - start
    if backbone.device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(backbone.device)
    passes = [run_stages(mesh, cameras, backbone, args.batch_size, autocast) for _ in range(args.repeats)]
    walls = [wall_pass(mesh, cameras, backbone, args.batch_size, autocast) for _ in range(args.repeats)]
    seconds = {stage: float(np.median([p[0][stage] for p in passes])) for stage in passes[0][0]}
    row = {**seconds, "total": float(np.median([sum(p[0].values()) for p in passes])), "wall": float(np.median(walls))}
    row["first_pass"] = first
    row["peak_gib"] = torch.cuda.max_memory_allocated(backbone.device) / 2**30 if backbone.device.type == "cuda" else None
    return row, passes[-1][1]


def profile_pass(mesh, cameras, backbone: DinoBackbone, args, autocast: bool) -> tuple[dict, list[str]]:
    """One pass under torch.profiler: wall and kernel seconds, and the costliest kernels and host operations (`profile_tables`)."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if backbone.device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        wall = wall_pass(mesh, cameras, backbone, args.batch_size, autocast)
    return profile_tables(prof, wall)


def mean_cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Mean over rows of the cosine similarity of two (V, C) feature arrays."""
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    return float(np.mean((a * b).sum(axis=1) / np.maximum(na * nb, 1e-12)))


def pca_colors(features: np.ndarray) -> np.ndarray:
    """First three principal components of the features, each scaled to [0, 1], shape (V, 3)."""
    centered = features - features.mean(axis=0)
    _, _, vt = np.linalg.svd(centered, full_matrices=False)
    components = centered @ vt[:3].T
    lo, hi = np.percentile(components, 2, axis=0), np.percentile(components, 98, axis=0)
    return np.clip((components - lo) / np.where(hi > lo, hi - lo, 1.0), 0, 1)


def save_view_grid(images: list, path: Path) -> None:
    """All rendered views in a square grid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    side = int(np.ceil(np.sqrt(len(images))))
    fig, axes = plt.subplots(side, side, figsize=(1.6 * side, 1.6 * side))
    for ax, image in zip(axes.ravel(), images + [None] * (side * side - len(images)), strict=True):
        ax.set_axis_off()
        if image is not None:
            ax.imshow(np.clip(image, 0, 1))
    fig.tight_layout(pad=0.1)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def caption(result: dict) -> str:
    """The first line of the table: shape, views, batches, device, precision, passes, date and machine."""
    if result["batch_size"] != "auto":
        batches = f"batches of {result['batch_size']} views"
    elif result["device"].startswith("cuda"):
        batches = "views per batch as memory allows"
    else:
        batches = f"batches of {CPU_BATCH_SIZE} views (the CPU's automatic batch)"
    return (
        f"One FAUST_r shape ({result['shape']}, {result['vertices']} vertices), {result['views']} views at "
        f"{result['image_size']} x {result['image_size']}, {batches}, device {result['device']} ({result['gpu'] or 'CPU'}), "
        f"{'bfloat16 autocast' if result['autocast'] else 'float32'}, median of {result['repeats']} pass(es), "
        f"{result['date']}, {result['machine']}"
    )


def varied_backbone(result: dict) -> str:
    """The backbone whose variants (torch.compile, bfloat16 weights) were timed: the largest."""
    names = [row["name"] for row in result["rows"]]
    variants = [name for name in names if name.endswith((", torch.compile", ", bfloat16 weights"))]
    return variants[0].rsplit(", ", 1)[0] if variants else names[-1]


def table(result: dict) -> str:
    """The Markdown of a result: the seconds per stage, then the first pass and memory, each backbone a row."""
    wall = all("wall" in row for row in result["rows"])  # runs before the wall column kept none
    lines = [
        caption(result),
        "",
        "| backbone (random DINOv3 weights) | render | backbone | back-project (ball) | total |" + (" wall |" if wall else ""),
        "|---|---|---|---|---|" + ("---|" if wall else ""),
    ]
    memory = any(row["peak_gib"] is not None for row in result["rows"])  # none on the CPU
    costs = [
        "| backbone (random DINOv3 weights) | first pass |" + (" peak GPU memory |" if memory else ""),
        "|---|---|" + ("---|" if memory else ""),
    ]
    for row in result["rows"]:
        peak = f"{row['peak_gib']:.2f} GiB" if row["peak_gib"] is not None else "-"
        lines.append(
            f"| {row['name']} | {row['render']:.3f} s | {row['backbone']:.3f} s | {row['backproject']:.3f} s | "
            f"{row['total']:.3f} s |" + (f" {row['wall']:.3f} s |" if wall else "")
        )
        costs.append(f"| {row['name']} | {row['first_pass']:.2f} s |" + (f" {peak} |" if memory else ""))
    lines += ["", *costs]
    if "compile" in result:
        cost, saved = result["compile"]["compile_s"], result["compile"]["saved_per_shape_s"]
        lines += [
            "",
            f"torch.compile: {cost:.1f} s to compile, {saved * 1000:.1f} ms saved per shape, so over 100 shapes it "
            + ("pays" if 100 * saved > cost else "does not pay")
            + f" ({100 * saved:.1f} s saved against {cost:.1f} s).",
        ]
    if "cosine_to_float32" in result:
        similarity = result["cosine_to_float32"]
        lines += [
            "",
            f"Mean cosine similarity of the vertex features to float32 ones (same weights): "
            f"{'bfloat16 autocast' if result['autocast'] else 'float32'} {similarity['autocast']:.5f}, "
            f"bfloat16 weights {similarity['bfloat16_weights']:.5f}.",
        ]
    return "\n".join(lines)


def write_profile(out: Path, result: dict) -> None:
    """``OUT_profile.md`` of a result holding ``profile``: date, machine and GPU above the summary and tables."""
    path = out.parent / f"{out.name}_profile.md"
    tables = stored_profile_tables(result, path)
    what = f"One pass of the {varied_backbone(result)} backbone under torch.profiler ({caption(result).split(', median')[0]})"
    path.write_text(profile_markdown(what, result, tables, where=result.get("gpu")))


def render_only(out: Path) -> None:
    """Rewrite ``OUT.md`` (and ``OUT_profile.md`` where the run was profiled) from ``OUT.json``."""
    result = read_results(out)
    out.with_name(f"{out.name}.md").write_text(table(result) + "\n")
    if "profile" in result:
        write_profile(out, result)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--views", type=int, default=49)
    parser.add_argument("--image-size", type=int, default=512)
    parser.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help="views per backbone call; default: as many as GPU memory allows (4 on the CPU)",
    )
    parser.add_argument("--device", default="auto")
    parser.add_argument(
        "--precision",
        choices=("auto", "bfloat16", "float32"),
        default="auto",
        help="the backbone's: bfloat16 autocast or float32; auto: bfloat16 on CUDA (the descriptors' default), float32 on the CPU",
    )
    parser.add_argument("--backbones", choices=("all", "tiny"), default="all", help="tiny: the small backbone only")
    parser.add_argument(
        "--compile", action="store_true", help="also time the ViT-B/16-size backbone under torch.compile (first pass = compile)"
    )
    parser.add_argument(
        "--bf16-weights", action="store_true", help="also time the ViT-B/16-size backbone with its weights in bfloat16"
    )
    parser.add_argument("--profile", action="store_true", help="profile one pass of the ViT-B/16-size backbone (OUT_profile.md)")
    parser.add_argument("--repeats", type=int, default=1, help="timed passes per backbone; the median is reported")
    parser.add_argument("--out", default=str(RESULTS / "speed_dino"), help="writes OUT.json, OUT.md, OUT_views.png, OUT_pca.png")
    parser.add_argument(
        "--render-only", action="store_true", help="rewrite OUT.md (and OUT_profile.md) from OUT.json without running anything"
    )
    args = parser.parse_args(argv)
    if args.render_only:
        render_only(Path(args.out))
        return 0

    device = torch.device(args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu"))
    autocast = args.precision == "bfloat16" or (args.precision == "auto" and device.type == "cuda")
    mesh = faust_test_shapes(args.data, 1)[0]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows, features_for_figure = [], None
    backbones = dict(list(BACKBONES.items())[:1]) if args.backbones == "tiny" else dict(BACKBONES)
    main_label = list(backbones)[-1]  # the variants are of the largest backbone timed
    compiled, bf16_weights = f"{main_label}, torch.compile", f"{main_label}, bfloat16 weights"
    if args.compile:
        backbones[compiled] = backbones[main_label]
    if args.bf16_weights:
        backbones[bf16_weights] = backbones[main_label]
    features_by_label, profile = {}, None
    for label, sizes in backbones.items():
        backbone = random_dinov3(0, **sizes)
        backbone.model.to(device)
        if label == compiled:
            backbone.model = torch.compile(backbone.model)
        if label == bf16_weights:
            backbone.model.to(torch.bfloat16)
        cameras = make_cameras(mesh, args.views, layout="official", image_size=args.image_size, device=backbone.device)
        row, features = timed_passes(mesh, cameras, backbone, args, autocast or label == bf16_weights)
        rows.append({"name": label, **row})
        features_by_label[label] = features
        print(f"{label}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items() if v is not None), flush=True)
        if label == main_label:
            features_for_figure = features
            if args.profile:
                profile = profile_pass(mesh, cameras, backbone, args, autocast)
            if args.bf16_weights:  # the reference for the feature comparison: the same weights in float32
                _, features_by_label["float32"] = run_stages(mesh, cameras, backbone, args.batch_size, False)
    images_for_figure = list(render_phong(mesh, None, cameras).images.cpu().numpy())  # for the figure, not timed

    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "device": str(backbone.device),
        "shape": mesh.name,
        "vertices": mesh.n_vertices,
        "views": args.views,
        "image_size": args.image_size,
        "batch_size": args.batch_size or "auto",
        "autocast": autocast,
        "repeats": args.repeats,
        "gpu": torch.cuda.get_device_name(backbone.device) if backbone.device.type == "cuda" else None,
        "rows": rows,
    }
    if args.compile:
        eager = next(r for r in rows if r["name"] == main_label)
        timed = next(r for r in rows if r["name"] == compiled)
        saved = eager["total"] - timed["total"]
        cost = timed["first_pass"] - timed["total"] - (eager["first_pass"] - eager["total"])
        result["compile"] = {"saved_per_shape_s": saved, "compile_s": cost, "pays_over_100_shapes": 100 * saved > cost}
    if args.bf16_weights:
        reference = features_by_label["float32"]
        result["cosine_to_float32"] = {
            "autocast": mean_cosine(features_by_label[main_label], reference),
            "bfloat16_weights": mean_cosine(features_by_label[bf16_weights], reference),
        }
    if profile is not None:
        result["profile"], result["profile_tables"] = profile
    write_results(out, result, table(result))
    if profile is not None:
        write_profile(out, result)
    save_view_grid(images_for_figure, out.parent / f"{out.name}_views.png")
    plot_mesh_colors(
        mesh, pca_colors(features_for_figure), out.parent / f"{out.name}_pca.png", "PCA of back-projected features (random ViT-B)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
