"""Pictures for the documentation: per-vertex features drawn as colours on a mesh.

Everything is built in code (the synthetic humans of `geofeat.datasets.SyntheticHumans`), so
the script runs offline with no data and no weights:

* ``features_on_mesh.png``: HKS and WKS on one synthetic human, WKS on another individual in
  another pose, and WKS on a CUTS partial shape of that second human. A descriptor of
  C channels becomes a colour by its first three principal components (fitted on the first
  shape, area-weighted, and applied unchanged to the others), so equal colours mean similar
  features.
* ``multiview_features.png``: the multi-view path of the ``dinov2``/``dinov3``/``geolora``
  descriptors: three of the views the backbone sees (geofeat's rasterizer and gray Phong
  shading), and the features back-projected to the vertices. No DINO weights can be
  downloaded here, so the backbone is a small DINOv3 with random weights: the picture shows
  the machinery, not what trained features look like.

The meshes are drawn with geofeat's own rasterizer (`geofeat.render.render_phong` with
per-vertex colours). A ``README.md`` beside the pictures records the machine, the date and
the command.

    .venv/bin/python -m benchmarks.tables.figures               # writes benchmarks/results/figures/
    .venv/bin/python -m benchmarks.tables.figures --out /tmp/figs
"""

from __future__ import annotations

import argparse
import datetime
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import geofeat
from benchmarks.common import REPO, RESULTS, machine
from geofeat.datasets import SyntheticHumans
from geofeat.geometry import spectral_basis
from geofeat.geometry.partial import make_partial
from geofeat.multiview import multiview_features
from geofeat.render import Cameras, make_cameras, orbit_cameras, render_phong

DEFAULT_OUT = RESULTS / "figures"
#: Pixels of one drawn mesh, and the PNG resolution (small files for the docs).
IMAGE_SIZE = 384
DPI = 80


def pca_basis(features: np.ndarray, weights: np.ndarray | None = None, n: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Mean (C,) and the first ``n`` principal axes (C, n) of ``features`` (V, C), rows weighted by ``weights``."""
    w = np.ones(len(features)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mean = w @ features
    centred = (features - mean) * np.sqrt(w)[:, None]
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    axes = vt[:n].T
    # a sign per axis, fixed by the data (an SVD may return either sign)
    signs = np.sign(((features - mean) @ axes)[np.argmax(np.abs((features - mean) @ axes), axis=0), np.arange(n)])
    return mean, axes * np.where(signs == 0, 1.0, signs)


def to_rgb(features: np.ndarray, mean: np.ndarray, axes: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Features (V, C) projected on ``axes`` and scaled from [low, high] to [0, 1] per component: (V, 3) RGB."""
    projected = (features - mean) @ axes
    return np.clip((projected - low) / np.where(high > low, high - low, 1.0), 0.0, 1.0)


def rgb_of(reference: np.ndarray, weights: np.ndarray, *others: np.ndarray) -> list[np.ndarray]:
    """RGB of ``reference`` and of every array of ``others`` with the reference's PCA and colour range."""
    mean, axes = pca_basis(reference, weights)
    projected = (reference - mean) @ axes
    low, high = np.percentile(projected, 1, axis=0), np.percentile(projected, 99, axis=0)
    return [to_rgb(f, mean, axes, low, high) for f in (reference, *others)]


def front_camera(mesh: geofeat.Mesh, azimuth: float = 20.0) -> Cameras:
    """One camera looking at the mesh's bounding-box centre from the front (+z), slightly from the side."""
    lo, hi = mesh.verts.min(axis=0), mesh.verts.max(axis=0)
    centre = (lo + hi) / 2
    return orbit_cameras(centre, 1.1 * np.linalg.norm(hi - lo), [10.0], [azimuth], IMAGE_SIZE, fov_degrees=40.0, device="cpu")


def draw(mesh: geofeat.Mesh, colors: np.ndarray | None, cameras: Cameras, crop=True) -> tuple[np.ndarray, tuple]:
    """The shaded image (H, W, 3) in [0, 1] of the first camera, vertices coloured by ``colors`` (V, 3), and its crop box.

    ``crop``: True cuts the image to the pixels the mesh covers (with a margin), a box
    ``(top, bottom, left, right)`` cuts it there, False keeps the whole image.
    """
    images, fragments = render_phong(mesh, None, cameras, vertex_colors=colors)
    image = np.clip(images[0].cpu().numpy(), 0.0, 1.0)
    if crop is False:
        return image, (0, image.shape[0], 0, image.shape[1])
    if crop is True:
        rows, cols = np.nonzero(fragments.pix_to_face[0].cpu().numpy() >= 0)
        margin = 6
        crop = (max(rows.min() - margin, 0), rows.max() + margin + 1, max(cols.min() - margin, 0), cols.max() + margin + 1)
    top, bottom, left, right = crop
    return image[top:bottom, left:right], crop


def features_on_mesh(out: Path) -> tuple[Path, str]:
    """HKS and WKS of a synthetic human, WKS of another one and of a CUTS partial shape of it."""
    humans = SyntheticHumans(n_individuals=2, n_poses=3, seed=0)
    a, b = humans.shape(0), humans.shape(5)  # individual 0 near rest, individual 1 in its third pose
    partial = make_partial(b, "cuts", seed=3)
    # geofeat.compute takes a Mesh, a path, (verts, faces) or a trimesh; (V, C) float32
    hks_a = geofeat.compute(a, "hks", cache=False)
    wks_a, wks_b, wks_p = (geofeat.compute(m, "wks", cache=False) for m in (a, b, partial.mesh))
    area_a = spectral_basis(a, 128, "robust").mass
    (hks_rgb,) = rgb_of(hks_a, area_a)
    wks_rgb_a, wks_rgb_b, wks_rgb_p = rgb_of(wks_a, area_a, wks_b, wks_p)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        (a, hks_rgb, f"HKS ({hks_a.shape[1]} channels)\nshape A"),
        (a, wks_rgb_a, f"WKS ({wks_a.shape[1]} channels)\nshape A"),
        (b, wks_rgb_b, "WKS, shape B:\nanother body, another pose"),
        (partial.mesh, wks_rgb_p, f"WKS of a CUTS partial of B\n({partial.mesh.n_vertices} of {b.n_vertices} vertices)"),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.3 * len(panels), 3.6), dpi=DPI)
    boxes = {}
    for ax, (mesh, rgb, title) in zip(axes, panels, strict=True):
        if mesh is partial.mesh:  # seen from B's camera, framed as B: where the partial shape lies on B
            image, _ = draw(mesh, rgb, front_camera(b), crop=boxes["b"])
        else:
            image, boxes["b" if mesh is b else "a"] = draw(mesh, rgb, front_camera(mesh))
        ax.imshow(image)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    path = out / "features_on_mesh.png"
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=0.05)
    plt.close(fig)
    caption = (
        "Colour = the first three principal components of the features as red, green, blue, fitted on shape A "
        "(area-weighted) and applied unchanged to B and to the partial shape. HKS and WKS depend only on the "
        "intrinsic geometry, so corresponding points of A and B get similar colours although the pose differs. "
        "On the partial shape the Laplacian's spectrum changes, and so do the colours: the reason spectral "
        "descriptors alone match partial shapes poorly."
    )
    return path, caption


def tiny_random_dinov3(seed: int = 1):
    """A small DINOv3 ViT (patch 16, width 64, 4 blocks) with seeded random weights, wrapped as a geofeat backbone."""
    import torch
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    from geofeat.backbones import DinoBackbone

    torch.manual_seed(seed)
    config = DINOv3ViTConfig(
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=4,
        num_attention_heads=4,
        patch_size=16,
        image_size=224,
        num_register_tokens=4,
    )
    model = DINOv3ViTModel(config)
    with torch.no_grad():
        for param in model.parameters():
            param.copy_(torch.randn_like(param) * 0.2)
    return DinoBackbone(model.eval(), kind="dinov3")


def multiview(out: Path) -> tuple[Path, str]:
    """Three of the nine official views of a synthetic human and its back-projected (random-weight) DINOv3 features."""
    import torch

    torch.manual_seed(0)
    mesh = SyntheticHumans(n_individuals=1, n_poses=1, seed=0).shape(0)
    cameras = make_cameras(mesh, 9, layout="official", image_size=224, device="cpu")
    views, _ = render_phong(mesh, None, cameras)
    features = multiview_features(mesh, cameras, tiny_random_dinov3(), backproject="ball", batch_size=3).features
    features = features.cpu().numpy().astype(np.float64)
    (rgb,) = rgb_of(features, np.ones(len(features)))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [0, 4, 7]
    fig, axes = plt.subplots(1, len(shown) + 1, figsize=(2.3 * (len(shown) + 1), 3.6), dpi=DPI)
    for ax, view in zip(axes[: len(shown)], shown, strict=True):
        ax.imshow(np.clip(views[view].cpu().numpy(), 0, 1))
        ax.set_title(f"view {view + 1} of 9\n(what the backbone sees)", fontsize=9)
        ax.axis("off")
    axes[-1].imshow(draw(mesh, rgb, front_camera(mesh))[0])
    axes[-1].set_title(f"back-projected features ({features.shape[1]} ch.)\nRANDOM weights: machinery only", fontsize=9)
    axes[-1].axis("off")
    path = out / "multiview_features.png"
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=0.05)
    plt.close(fig)
    caption = (
        "Left: three of the nine views of the official camera grid, rendered with geofeat's rasterizer and the gray "
        "Phong shading GeoLoRA feeds to DINO. Right: the per-vertex features after back-projection, as colours "
        "(first three principal components). The backbone here is a small DINOv3 with random weights, because no "
        "weights can be downloaded where this picture is made: it shows the path, not what trained DINO features look like."
    )
    return path, caption


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(DEFAULT_OUT), help=f"output folder (default {DEFAULT_OUT.relative_to(REPO)})")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="geofeat-figures-") as tmp:
        geofeat.set_cache_dir(tmp)  # nothing is left in the user's cache
        made = [features_on_mesh(out), multiview(out)]
    seconds = time.perf_counter() - start
    lines = [
        "# Pictures of the documentation",
        "",
        f"Written by `python -m benchmarks.tables.figures` on {datetime.date.today().isoformat()}, "
        f"{machine()}, geofeat {geofeat.__version__}, in {seconds:.0f} s.",
        "",
    ]
    for path, caption in made:
        lines += [f"- `{path.name}` ({path.stat().st_size // 1024} KB): {caption}", ""]
    (out / "README.md").write_text("\n".join(lines), encoding="utf-8")
    for path, _ in made:
        print(f"wrote {path} ({path.stat().st_size // 1024} KB)")
    print(f"wrote {out / 'README.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
