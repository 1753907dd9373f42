"""Pictures of the first pairs of a depth-scan benchmark: what the camera saw, and the point cloud it made.

For each of the first N pairs of ``faust_r_scans`` (or another scan benchmark), two panels:

* the depth image the virtual camera took of the scanned shape: depth along the optical
  axis, near points dark, no point in white (background, and points dropped at grazing
  angles);
* the point cloud seen from the side (the camera's view turned by 90 degrees about the
  vertical), each point in the colour of its ground-truth counterpart on the target shape
  (the position colours of the pair pictures of ``run.py``), grey where it has none.

Usage::

    python -m benchmarks.scan_pictures --data ../shared/data --pairs 4
"""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

import numpy as np

from benchmarks.common import DEFAULT_DATA, RESULTS, machine
from geofeat.datasets import load_dataset
from geofeat.datasets.depth_camera import Scan
from geofeat.evaluation.report import position_colors, transferred_colors


def depth_image(scan: Scan, image_size: tuple[int, int]) -> np.ndarray:
    """Depth along the optical axis at each pixel, NaN where the scan has no point; shape (H, W)."""
    forward = (scan.target - scan.eye) / np.linalg.norm(scan.target - scan.eye)
    image = np.full(image_size, np.nan)
    image[scan.pixels[:, 0], scan.pixels[:, 1]] = (scan.cloud.verts - scan.eye) @ forward
    return image


def side_view(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """Points seen from the camera's side: horizontal and vertical screen coordinates, and depth order."""
    forward = scan.target - scan.eye
    forward[1] = 0.0  # turn about the vertical (+y) axis
    forward /= np.linalg.norm(forward)
    side = np.cross([0.0, 1.0, 0.0], forward)  # looking along it, the camera's view axis runs across the picture
    relative = scan.cloud.verts - scan.target
    return np.stack([relative @ forward, relative[:, 1]], axis=1), relative @ side


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--dataset", default="faust_r_scans")
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(RESULTS / "scans" / "scans.png"))
    args = parser.parse_args(argv)
    from matplotlib.figure import Figure

    dataset = load_dataset(args.dataset, args.data, split="test", seed=args.seed)
    camera = dataset.camera
    fig = Figure(figsize=(2.6 * args.pairs, 6.4))
    axes = fig.subplots(2, args.pairs, squeeze=False)
    for i in range(args.pairs):
        pair, scan = dataset[i], dataset.scan(i)
        has = pair.map_yx >= 0
        top, bottom = axes[0, i], axes[1, i]
        top.imshow(depth_image(scan, camera.image_size), cmap="viridis", interpolation="nearest")
        top.set_title(f"{scan.surface.mesh.name}: depth image\n{scan.cloud.n_vertices:,} points", fontsize=8)
        xy, order = side_view(scan)
        colors = transferred_colors(position_colors(pair.x), pair.map_yx)
        draw = np.argsort(order)  # far points first
        bottom.scatter(xy[draw, 0], xy[draw, 1], c=colors[draw], s=1.2, linewidths=0)
        bottom.set_aspect("equal")
        bottom.set_title(f"seen from the side, coloured\nthrough the truth on {pair.x.name} ({has.mean():.0%})", fontsize=8)
        top.set_xticks([])
        top.set_yticks([])
        bottom.set_axis_off()
    start = camera.dropout_start_degrees
    dropout = "no dropout" if start is None else f"dropout from {start:g} degrees of incidence"
    caption = (
        f"The first {args.pairs} pairs of {args.dataset} (seed {args.seed}): a {camera.image_size[0]} x {camera.image_size[1]} "
        f"depth camera, {camera.fov_degrees:g} degree field of view, noise {camera.depth_noise:g} of the bounding-box "
        f"diagonal along each ray, {dropout}. Top: depth (near dark, "
        "no point white). Bottom: the cloud seen from the side, each point in the colour of its counterpart on the target "
        f"(position colours), grey without one (the percentage has one). python -m benchmarks.scan_pictures; {machine()}."
    )
    fig.text(0.01, 0.01, "\n".join(textwrap.wrap(caption, width=int(2.6 * args.pairs * 16))), fontsize=7, va="bottom")
    fig.subplots_adjust(left=0.01, right=0.99, top=0.93, bottom=0.14, wspace=0.05, hspace=0.25)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"written to {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
