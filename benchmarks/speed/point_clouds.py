"""DINO features of point clouds on the CPU: a 5,000-point cloud against its mesh, and clouds up to 500,000 points.

Both through `geofeat.multiview.multiview_features`, the path of ``geofeat.compute(shape,
"dinov3")``, with a small DINOv3 of random weights (width 64, 4 blocks, patch 16; no weights
can be downloaded here), so the backbone's share is far below a ViT-B's and the rendering and
back-projection stand out:

* **5,000 points.** FAUST_r ``tr_reg_000`` as a mesh and as its vertices alone, 49 views of
  the official layout at 512 x 512 in batches of 4 (the descriptor's defaults on a CPU),
  ``"ball"`` and ``"face"`` back-projection; seconds per phase (render: rasterize or splat,
  shade; forward: the backbone and the patch samples; backproject: plans and sums), the
  best of ``--repeats`` runs, the four runs taking turns. The cloud's one-off work (normals
  from 30 neighbours, disc radii from 8) is in its first batch's render time and is also
  timed alone.
* **Large clouds.** Points drawn uniformly on the surface of ``tr_reg_000`` (seeded), 4
  views at 128 x 128 (``"uniform"`` layout), ``"ball"``: each run is a fresh process, whose
  peak resident memory (``ru_maxrss``) is its own; the memory before the call (the process
  with torch, the backbone and the cloud loaded) is given beside it, and a second process
  times and measures the cloud's one-off work (normals and radii) alone.

Usage::

    python -m benchmarks.speed.point_clouds --data /work/shared/data --sizes 50000 500000
    python -m benchmarks.speed.point_clouds --render-only    # rewrites OUT.md from OUT.json, runs nothing
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, rewrite_table, write_results

_RUN = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[3])
from benchmarks.speed.point_clouds import run_large
print(json.dumps(run_large(np.load(sys.argv[1]), sys.argv[2])))
"""


def surface_samples(mesh: geofeat.Mesh, n_points: int, seed: int = 0) -> np.ndarray:
    """``n_points`` points drawn uniformly on the mesh's surface (area-weighted faces, uniform barycentrics), (n, 3)."""
    rng = np.random.default_rng(seed)
    corners = mesh.verts[mesh.faces]  # (F, 3, 3)
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    face = rng.choice(len(area), size=n_points, p=area / area.sum())
    u, v = rng.uniform(size=(2, n_points))
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    chosen = corners[face]
    return chosen[:, 0] + u[:, None] * (chosen[:, 1] - chosen[:, 0]) + v[:, None] * (chosen[:, 2] - chosen[:, 0])


@contextmanager
def _timed(seconds: dict, phase: str):
    start = time.perf_counter()
    try:
        yield
    finally:
        seconds[phase] += time.perf_counter() - start


def phase_timer() -> tuple[dict, callable]:
    """A `PhaseTimer` and the dict of seconds per phase it fills."""
    seconds: dict = defaultdict(float)
    return seconds, lambda phase: _timed(seconds, phase)


def small_backbone():
    """The small random DINOv3 of the figures (width 64, 4 blocks, patch 16)."""
    from benchmarks.tables.figures import tiny_random_dinov3

    return tiny_random_dinov3()


def mesh_vs_cloud(mesh: geofeat.Mesh, views: int, image_size: int, repeats: int) -> list[dict]:
    """Seconds per phase of the mesh and of its vertices as a cloud, per back-projection mode (best of ``repeats``)."""
    from geofeat.multiview import multiview_features
    from geofeat.render import make_cameras
    from geofeat.render.points import splat_radii
    from geofeat.render.shading import cloud_normals

    backbone = small_backbone()
    cameras = make_cameras(mesh, views, layout="official", image_size=image_size, device="cpu")
    cloud = geofeat.Mesh(mesh.verts, None, name="cloud")
    runs = [(name, shape, mode) for mode in ("ball", "face") for name, shape in (("mesh", mesh), ("cloud", cloud))]
    best: dict[tuple[str, str], dict] = {}
    for _ in range(repeats):  # the runs take turns, so that a change in the machine's load hits them alike
        for name, shape, mode in runs:
            seconds, timer = phase_timer()
            start = time.perf_counter()
            multiview_features(shape, cameras, backbone, backproject=mode, batch_size=4, timer=timer)
            seconds["total"] = time.perf_counter() - start
            if (name, mode) not in best or seconds["total"] < best[name, mode]["total"]:
                best[name, mode] = dict(seconds)
    rows = [{"shape": name, "mode": mode, **best[name, mode]} for name, _, mode in runs]
    start = time.perf_counter()
    cloud_normals(mesh.verts), splat_radii(mesh.verts)
    rows.append({"shape": "cloud", "mode": "one-off: normals and radii", "total": time.perf_counter() - start})
    return rows


def run_large(points: np.ndarray, what: str) -> dict:
    """In a fresh process: the features of a cloud (``what="features"``) or its one-off work alone (``"prepare"``)."""
    import resource

    import torch

    from geofeat.multiview import multiview_features
    from geofeat.render import make_cameras
    from geofeat.render.points import splat_radii
    from geofeat.render.shading import cloud_normals

    cloud = geofeat.Mesh(points, None, name=f"cloud{len(points)}")
    backbone = small_backbone()
    cameras = make_cameras(cloud, 4, layout="uniform", image_size=128, device="cpu")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    seconds, timer = phase_timer()
    start = time.perf_counter()
    if what == "prepare":
        with timer("normals"):
            cloud_normals(points)
        with timer("radii"):
            splat_radii(points)
        extra = {}
    else:
        result = multiview_features(cloud, cameras, backbone, backproject="ball", batch_size=4, timer=timer)
        extra = {"seen": float(result.seen.float().mean()), "finite": bool(torch.isfinite(result.features).all())}
    seconds["total"] = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    return {
        "points": len(points),
        "what": what,
        "seconds": dict(seconds),
        "rss_before_mib": before,
        "rss_peak_mib": peak,
        **extra,
    }


def large_clouds(mesh: geofeat.Mesh, sizes: list[int]) -> list[dict]:
    """`run_large` for each size, features and one-off work, each in a fresh Python process."""
    repo = str(Path(__file__).resolve().parents[2])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in sizes:
            path = Path(tmp) / f"cloud{size}.npy"
            np.save(path, surface_samples(mesh, size))
            for what in ("features", "prepare"):
                out = subprocess.run(
                    [sys.executable, "-c", _RUN, str(path), what, repo], check=True, capture_output=True, text=True
                )
                rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return rows


def table(result: dict) -> str:
    """The Markdown report: mesh against cloud, then the large clouds' seconds and their memory as two tables."""
    lines = [
        f"{result['views']} views of the official layout at {result['image_size']} x {result['image_size']}, batches of 4, "
        "small random DINOv3 (width 64, 4 blocks), CPU; FAUST_r `tr_reg_000` (4,999 vertices) as a mesh and as a cloud of "
        f"its vertices; best of {result['repeats']} runs.",
        "",
        "| shape | back-projection | render s | forward s | backproject s | total s |",
        "|---|---|---|---|---|---|",
    ]
    for r in result["mesh_vs_cloud"]:
        if "render" not in r:
            lines.append(f"| {r['shape']} | {r['mode']} | | | | {r['total']:.2f} |")
            continue
        lines.append(
            f"| {r['shape']} | `{r['mode']}` | {r['render']:.2f} | {r['forward']:.2f} | {r['backproject']:.2f} | {r['total']:.2f} |"
        )
    lines += [
        "",
        "Large clouds (points drawn uniformly on `tr_reg_000`'s surface), 4 views at 128 x 128, `ball`, each in a fresh "
        "process: peak resident memory, and the memory before the call (torch, the backbone and the cloud loaded).",
        "",
        "| points | work | render s | forward s | backproject s | total s |",
        "|---|---|---|---|---|---|",
    ]
    memory = ["| points | work | memory before MiB | peak MiB |", "|---|---|---|---|"]
    for r in result["large"]:
        s = r["seconds"]
        work = "features" if r["what"] == "features" else f"normals ({s['normals']:.1f} s) and radii ({s['radii']:.1f} s) alone"
        phases = " | ".join(f"{s[p]:.1f}" if p in s else "" for p in ("render", "forward", "backproject"))
        lines.append(f"| {r['points']:,} | {work} | {phases} | {s['total']:.1f} |")
        memory.append(f"| {r['points']:,} | {work} | {r['rss_before_mib']:.0f} | {r['rss_peak_mib']:.0f} |")
    lines += ["", *memory]
    load = result["load_average"]
    lines += [
        "",
        f"The machine is shared: its load average (1 minute) was {load[0]:.1f} at the start and {load[1]:.1f} at the end, "
        "so the seconds vary from run to run; the runs of the first table take turns and each row is its best.",
        "",
        f"`python -m benchmarks.speed.point_clouds`; {result['date']}, {result['machine']}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--views", type=int, default=49)
    parser.add_argument("--image-size", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--sizes", type=int, nargs="*", default=[50_000, 500_000])
    parser.add_argument("--out", default=str(RESULTS / "speed_point_clouds"), help="writes OUT.json and OUT.md")
    parser.add_argument("--render-only", action="store_true", help="rewrite OUT.md from OUT.json without running anything")
    args = parser.parse_args(argv)
    if args.render_only:
        rewrite_table(args.out, table)
        return
    mesh = geofeat.load_mesh(data_folder(args.data) / "FAUST_r" / "off" / "tr_reg_000.off")
    load_before = os.getloadavg()[0]
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "views": args.views,
        "image_size": args.image_size,
        "repeats": args.repeats,
        "mesh_vs_cloud": mesh_vs_cloud(mesh, args.views, args.image_size, args.repeats),
        "large": large_clouds(mesh, args.sizes),
    }
    result["load_average"] = [load_before, os.getloadavg()[0]]
    write_results(args.out, result, table(result))


if __name__ == "__main__":
    main()
