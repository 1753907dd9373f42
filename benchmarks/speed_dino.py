"""Time one shape through the multi-view DINO path, stage by stage, and draw what it makes.

The path is `geofeat.render.multiview_features`, the one of the DINO descriptors and the
GeoLoRA trainer. Stages, each summed over the batches of views: render (rasterize + gray
Phong shading), backbone (ImageNet normalisation, ViT forward, bilinear samples of the patch
grid at the foreground pixels, per-pixel L2 norm) and back-projection (ball mode: KD-tree
neighbours and a sparse product). Backbones are randomly
initialised DINOv3 architectures (no weights can be downloaded here): a tiny one and one of
ViT-B/16 size (12 layers, width 768, 12 heads, 4 register tokens).

Also writes a PNG grid of the rendered views and a PCA colouring of the back-projected
features of the ViT-B-sized backbone.

Usage::

    python benchmarks/speed_dino.py --data ../shared/data --views 49 --image-size 512
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
from common import DEFAULT_DATA, faust_test_shapes, machine, write_results

from geofeat.backbones import DinoBackbone
from geofeat.evaluation.report import plot_mesh_colors
from geofeat.render import make_cameras, multiview_features, render_phong

HERE = Path(__file__).resolve().parent

BACKBONES = {
    "tiny (2 layers, width 32)": dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2),
    "ViT-B/16 size (12 layers, width 768)": dict(
        hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12
    ),
}


def random_dinov3(seed: int, **sizes) -> DinoBackbone:
    """A DINOv3-architecture backbone with random weights (patch 16, 4 register tokens)."""
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    torch.manual_seed(seed)
    config = DINOv3ViTConfig(patch_size=16, image_size=224, num_register_tokens=4, **sizes)
    return DinoBackbone(DINOv3ViTModel(config), kind="dinov3")


def run_stages(mesh, cameras, backbone: DinoBackbone, batch_size: int, autocast: bool = False) -> tuple[dict, np.ndarray]:
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

    features, _ = multiview_features(
        mesh, cameras, backbone, backproject="ball", batch_size=batch_size, autocast=autocast, timer=timer
    )
    return {"render": seconds["render"], "backbone": seconds["forward"], "backproject": seconds["backproject"]}, (
        features.cpu().numpy()
    )


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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA)
    parser.add_argument("--views", type=int, default=49)
    parser.add_argument("--image-size", type=int, default=512)
    parser.add_argument("--batch-size", type=int, default=7)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--autocast", action="store_true", help="bfloat16 autocast of the backbone (the trainer's CUDA setting)")
    parser.add_argument("--repeats", type=int, default=1, help="timed passes per backbone; the median is reported")
    parser.add_argument(
        "--out", default=str(HERE / "results" / "speed_dino"), help="writes OUT.json, OUT.md, OUT_views.png, OUT_pca.png"
    )
    args = parser.parse_args(argv)

    mesh = faust_test_shapes(args.data, 1)[0]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows, features_for_figure = [], None
    for label, sizes in BACKBONES.items():
        backbone = random_dinov3(0, **sizes)
        backbone.model.to(
            torch.device(args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu"))
        )
        cameras = make_cameras(mesh, args.views, layout="official", image_size=args.image_size, device=backbone.device)
        run_stages(mesh, cameras[:1], backbone, 1, args.autocast)  # warm-up: first-call allocations
        passes = [run_stages(mesh, cameras, backbone, args.batch_size, args.autocast) for _ in range(args.repeats)]
        features = passes[-1][1]
        seconds = {stage: float(np.median([p[0][stage] for p in passes])) for stage in passes[0][0]}
        rows.append({"name": label, **seconds, "total": float(np.median([sum(p[0].values()) for p in passes]))})
        print(f"{label}: " + ", ".join(f"{k} {v:.2f} s" for k, v in rows[-1].items() if k != "name"), flush=True)
        features_for_figure = features
    images_for_figure = list(render_phong(mesh, None, cameras).images.cpu().numpy())  # for the figure, not timed

    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "device": str(backbone.device),
        "shape": mesh.name,
        "vertices": mesh.n_vertices,
        "views": args.views,
        "image_size": args.image_size,
        "batch_size": args.batch_size,
        "autocast": args.autocast,
        "repeats": args.repeats,
        "gpu": torch.cuda.get_device_name(backbone.device) if backbone.device.type == "cuda" else None,
        "rows": rows,
    }
    lines = [
        f"One FAUST_r shape ({mesh.name}, {mesh.n_vertices} vertices), {args.views} views at {args.image_size} x {args.image_size}, "
        f"batches of {args.batch_size} views, device {result['device']} ({result['gpu'] or 'CPU'}), "
        f"{'bfloat16 autocast' if args.autocast else 'float32'}, median of {args.repeats} pass(es), {result['date']}, {result['machine']}",
        "",
        "| backbone (random DINOv3 weights) | render | backbone | back-project (ball) | render + back-project | total |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['name']} | {row['render']:.2f} s | {row['backbone']:.2f} s | {row['backproject']:.2f} s | "
            f"{row['render'] + row['backproject']:.2f} s | {row['total']:.2f} s |"
        )
    write_results(out, result, "\n".join(lines))
    save_view_grid(images_for_figure, out.parent / f"{out.name}_views.png")
    plot_mesh_colors(
        mesh, pca_colors(features_for_figure), out.parent / f"{out.name}_pca.png", "PCA of back-projected features (random ViT-B)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
