"""The point renderer against the mesh rasterizer, and against pytorch3d's ``PointsRasterizer``.

The shape is FAUST_r ``tr_reg_000`` (``--data``); the cloud is its own vertices, drawn from
the official camera layout (49 views at 512 x 512, as the ``dinov3`` descriptor renders):

* **Mesh vs points.** The mesh through `geofeat.render.rasterize` (back faces culled, as the
  default recipe does), its vertices through `geofeat.render.rasterize_points` (discs of
  0.5 x each point's local spacing). Over all views: the IoU of the two foregrounds and the
  share of the mesh's foreground the discs miss (holes) or add; the depth difference on
  pixels both cover, relative to the bounding-box diagonal; the angle between the normal
  images (the mesh's interpolated vertex normals, the cloud's estimated normals, both turned
  towards the camera, as they are shaded); and the visible points: per view, the points that
  win a pixel and the points the cloud's ball back-projection reaches, against the vertices
  of the visible faces and the vertices the mesh's ball back-projection reaches (precision
  and recall, summed over the views).
* **Features.** ``dinov3`` vertex features of the mesh and of the cloud with one small
  random DINOv3 backbone (no weights can be downloaded here): their cosine similarity per
  vertex, for the ``"ball"`` and ``"face"`` back-projections.
* **pytorch3d.** The same points, cameras and radii through pytorch3d's ``PointsRasterizer``
  (``benchmarks/official/pytorch3d_points.py``, run by ``--pytorch3d-python``; pytorch3d's
  view is ``X @ R + T`` with ``R = R_ours.T diag(-1, -1, 1)``, ``T = -diag(-1, -1, 1) R_ours C``,
  focal length ``1 / tan(fov / 2)`` in NDC and each disc's radius ``f r / z`` pixels times
  ``2 / min(H, W)``): the IoU of the foregrounds, the share of pixels with the same nearest
  point, the depth difference there, and what the other pixels are.

Usage::

    python -m benchmarks.parity.point_renderer --data /work/shared/data \\
        --pytorch3d-python /work/ref/venv/bin/python --pytorch3d-src /work/ref/pytorch3d-src
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, write_results
from geofeat.multiview import multiview_features
from geofeat.multiview.backproject import Backprojector
from geofeat.render import Cameras, make_cameras, rasterize, rasterize_points, splat_points
from geofeat.render.cameras import as_tensor
from geofeat.render.points import splat_radii
from geofeat.render.rasterizer import surface_points
from geofeat.render.shading import cloud_normals, vertex_normals

HARNESS = Path(__file__).resolve().parents[1] / "official" / "pytorch3d_points.py"
_FLIP = np.diag([-1.0, -1.0, 1.0])  # our camera frame to pytorch3d's view frame
#: A pixel centre this close to a disc's edge (|d^2 / r^2 - 1|) is decided by float32 rounding: pytorch3d
#: rounds NDC coordinates of about 1 to 6e-8, which for a disc of 0.01 NDC moves d^2 / r^2 by about 1e-5.
EDGE_MARGIN = 1e-4


def foreground_stats(mesh_fg: torch.Tensor, point_fg: torch.Tensor) -> dict:
    """IoU of two foregrounds and the shares of the first that the second misses and adds."""
    both, either = (mesh_fg & point_fg).sum(), (mesh_fg | point_fg).sum()
    return {
        "iou": float(both / either),
        "holes": float((mesh_fg & ~point_fg).sum() / mesh_fg.sum()),
        "extra": float((point_fg & ~mesh_fg).sum() / mesh_fg.sum()),
    }


def turned_to(normals: torch.Tensor, points: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """Unit normals, each flipped to face ``eye`` (M, 3)."""
    normals = torch.nn.functional.normalize(normals, dim=-1)
    return torch.where(((eye - points) * normals).sum(-1, keepdim=True) < 0, -normals, normals)


def mesh_vs_points(mesh: geofeat.Mesh, cameras: Cameras) -> dict:
    """Foregrounds, depths, normal images and visible sets of the mesh and of its vertices as a cloud."""
    mesh_fr = rasterize(mesh, None, cameras)
    point_fr = rasterize_points(mesh.verts, cameras)
    diagonal = float(np.linalg.norm(np.ptp(mesh.verts, axis=0)))
    both = (mesh_fr.pix_to_face >= 0) & (point_fr.pix_to_point >= 0)
    depth_error = ((point_fr.depth - mesh_fr.depth)[both].abs() / diagonal).double()
    verts, faces = as_tensor(mesh.verts), as_tensor(mesh.faces)
    mesh_normals, point_normals = vertex_normals(verts, faces), cloud_normals(mesh.verts)
    mesh_ball = Backprojector(mesh.verts, mesh.faces, "ball")
    cloud_ball = Backprojector(mesh.verts, None, "ball")
    angles, sets = [], {"drawn": [], "cloud_ball": [], "face_verts": [], "mesh_ball": []}
    for view in range(len(cameras)):
        camera = cameras[view]
        pixels = torch.nonzero(both[view : view + 1])
        face = mesh_fr.pix_to_face[view][pixels[:, 1], pixels[:, 2]]
        bary = mesh_fr.bary[view][pixels[:, 1], pixels[:, 2]]
        corners = faces[face]
        mesh_points = surface_points(verts, corners, bary)
        point = point_fr.pix_to_point[view][pixels[:, 1], pixels[:, 2]]
        eye = camera.position[0]
        n_mesh = turned_to((bary.double()[..., None] * mesh_normals[corners]).sum(1), mesh_points, eye)
        n_point = turned_to(
            point_normals[point], splat_points(mesh.verts, camera, point_fr.pix_to_point[view : view + 1], pixels), eye
        )
        angles.append(torch.rad2deg(torch.acos((n_mesh * n_point).sum(-1).clamp(-1, 1))))
        drawn = point_fr.pix_to_point[view : view + 1]
        fg_points = torch.nonzero(drawn >= 0)
        lifted = splat_points(mesh.verts, camera, drawn, fg_points)
        visible_faces = torch.unique(mesh_fr.pix_to_face[view][mesh_fr.pix_to_face[view] >= 0])
        sets["drawn"].append(set(torch.unique(drawn[drawn >= 0]).tolist()))
        sets["cloud_ball"].append(set(torch.unique(cloud_ball.plan(drawn, None, lifted).rows).tolist()))
        sets["face_verts"].append(set(torch.unique(faces[visible_faces]).tolist()))
        sets["mesh_ball"].append(
            set(torch.unique(mesh_ball.plan(mesh_fr.pix_to_face[view : view + 1], mesh_fr.bary[view : view + 1]).rows).tolist())
        )
    angle = torch.cat(angles)
    return {
        **foreground_stats(mesh_fr.pix_to_face >= 0, point_fr.pix_to_point >= 0),
        "depth_error_median": float(depth_error.median()),
        "depth_error_p95": float(torch.quantile(depth_error, 0.95)),
        "normal_angle_mean": float(angle.mean()),
        "normal_angle_median": float(angle.median()),
        "normal_angle_p95": float(torch.quantile(angle.double(), 0.95)),
        "visible_sets": visible_set_rows(sets),
    }


def precision_recall(found: list[set], truth: list[set]) -> dict:
    """Precision and recall of ``found`` against ``truth``, summed over the views."""
    hits = sum(len(f & t) for f, t in zip(found, truth, strict=True))
    return {"precision": hits / max(1, sum(len(f) for f in found)), "recall": hits / max(1, sum(len(t) for t in truth))}


def visible_set_rows(sets: dict[str, list[set]]) -> list[dict]:
    """The rows of the visible-set table: per view, then over all views together."""
    rows = []
    for found, truth in (("drawn", "face_verts"), ("drawn", "mesh_ball"), ("cloud_ball", "mesh_ball")):
        rows.append({"cloud": found, "mesh": truth, "per": "view", **precision_recall(sets[found], sets[truth])})
    union = {name: [set().union(*views)] for name, views in sets.items()}
    for found, truth in (("drawn", "face_verts"), ("cloud_ball", "mesh_ball")):
        rows.append({"cloud": found, "mesh": truth, "per": "all views", **precision_recall(union[found], union[truth])})
    return rows


def tiny_backbone():
    """A small DINOv3 ViT (patch 16, width 64, 4 blocks) with seeded random weights, as a geofeat backbone."""
    from benchmarks.tables.figures import tiny_random_dinov3

    return tiny_random_dinov3()


def feature_agreement(mesh: geofeat.Mesh, cameras: Cameras) -> list[dict]:
    """Cosine similarity of the mesh's and the cloud's vertex features (same backbone, cameras), per mode."""
    backbone, cloud = tiny_backbone(), geofeat.Mesh(mesh.verts, None, name="cloud")
    rows = []
    for mode in ("ball", "face"):
        timings = {}
        results = []
        for shape in (mesh, cloud):
            start = time.perf_counter()
            results.append(multiview_features(shape, cameras, backbone, backproject=mode, fill="zero", batch_size=4))
            timings["cloud" if shape is cloud else "mesh"] = time.perf_counter() - start
        (f_mesh, seen_mesh), (f_cloud, seen_cloud) = results
        both = seen_mesh & seen_cloud
        centre = f_mesh[both].mean(dim=0)  # the random backbone's features share a large common part
        a, b = f_mesh[both] - centre, f_cloud[both] - centre
        cosine = torch.nn.functional.cosine_similarity(a, b, dim=1).double()
        shuffled = b[torch.randperm(b.shape[0], generator=torch.Generator().manual_seed(0))]
        baseline = torch.nn.functional.cosine_similarity(a, shuffled, dim=1).double()
        rows.append({
            "mode": mode,
            "seen_mesh": int(seen_mesh.sum()),
            "seen_cloud": int(seen_cloud.sum()),
            "seen_both": int(both.sum()),
            "cosine_mean": float(cosine.mean()),
            "cosine_p05": float(torch.quantile(cosine, 0.05)),
            "cosine_other_vertex": float(baseline.mean()),
            "seconds": timings,
        })  # fmt: skip
    return rows


def pytorch3d_inputs(points: np.ndarray, radii: np.ndarray, cameras: Cameras) -> dict:
    """The arrays of ``pytorch3d_points.py``: our cameras and radii in pytorch3d's conventions."""
    rotation, position = cameras.rotation.numpy(), cameras.position.numpy()
    depth = cameras.world_to_camera(points)[..., 2].numpy()  # (N, P)
    ndc_per_pixel = 2.0 / min(cameras.image_size)
    return {
        "points": points.astype(np.float32),
        "R": np.einsum("nji,jk->nik", rotation, _FLIP).astype(np.float32),
        "T": -np.einsum("ij,njk,nk->ni", _FLIP, rotation, position).astype(np.float32),
        "focal_length": np.float32(cameras.focal_length * ndc_per_pixel),
        "image_size": np.array(cameras.image_size),
        "radius": (cameras.focal_length * radii[None] / depth * ndc_per_pixel).astype(np.float32),
    }


def versus_pytorch3d(mesh: geofeat.Mesh, cameras: Cameras, python: str, source: str | None) -> dict:
    """Our point renderer against pytorch3d's on the same points, cameras and radii."""
    radii = splat_radii(mesh.verts)
    start = time.perf_counter()
    ours = rasterize_points(mesh.verts, cameras, radii=radii)
    seconds = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **pytorch3d_inputs(mesh.verts, radii, cameras))
        subprocess.run([python, str(HARNESS), str(src), str(out), *([source] if source else [])], check=True)
        with np.load(out) as theirs:
            idx, zbuf, seconds_theirs = theirs["idx"], theirs["zbuf"], theirs["seconds"]
    mine = ours.pix_to_point.numpy()
    fg_mine, fg_theirs = mine >= 0, idx >= 0
    same = fg_mine & fg_theirs & (mine == idx)
    differ = (fg_mine | fg_theirs) & ~same
    return {
        "views": len(cameras),
        "iou": float((fg_mine & fg_theirs).sum() / (fg_mine | fg_theirs).sum()),
        "covered": int((fg_mine | fg_theirs).sum()),
        "same_point_share": float(same.sum() / (fg_mine | fg_theirs).sum()),
        "differing": differing_pixels(mesh.verts, radii, cameras, mine, idx, differ),
        "depth_abs_max_same_point": float(np.abs(ours.depth.numpy()[same] - zbuf[same]).max()),
        "seconds_ours": seconds,
        "seconds_pytorch3d": float(seconds_theirs.sum()),
    }


def differing_pixels(verts, radii, cameras, mine, idx, differ) -> dict:
    """What the pixels where the two renderers disagree are: a disc edge met within rounding, or something else.

    Where one renderer shows a point and the other a farther point or nothing, the nearer
    point's disc reaches the pixel centre in one and not in the other: an *edge* pixel when
    the centre's squared distance from the point lies within `EDGE_MARGIN` of the squared
    radius (relative), where float32 rounding decides. ``float64_agrees`` counts the edge
    pixels where geofeat's choice is the one the test in float64 makes. Where the two points
    lie at one depth (within 1e-6), the pixel is a *depth tie*.
    """
    view, row, col = np.nonzero(differ)
    out = {"pixels": int(len(view)), "edge": 0, "float64_agrees": 0, "depth_tie": 0, "other": 0, "largest_edge_margin": 0.0}
    for v, r, c in zip(view.tolist(), row.tolist(), col.tolist(), strict=True):
        shown = [int(i) for i in (mine[v, r, c], idx[v, r, c]) if i >= 0]
        depth = cameras[v].world_to_camera(verts[shown])[0, :, 2].numpy()
        if len(shown) == 2 and abs(depth[0] - depth[1]) <= 1e-6 * depth.max():
            out["depth_tie"] += 1
            continue
        point = shown[int(np.argmin(depth))]  # the nearer point: its disc reaches the pixel in one renderer only
        projected = cameras[v].project(verts[point : point + 1])
        offset = projected.pixels[0, 0].numpy() - (c + 0.5, r + 0.5)
        screen_radius = cameras.focal_length * radii[point] / float(projected.depth[0, 0])
        ratio = float(offset @ offset) / screen_radius**2
        if abs(ratio - 1.0) < EDGE_MARGIN:
            out["edge"] += 1
            out["float64_agrees"] += int((ratio <= 1.0) == (int(mine[v, r, c]) == point))
            out["largest_edge_margin"] = max(out["largest_edge_margin"], abs(ratio - 1.0))
        else:
            out["other"] += 1
    return out


def table(result: dict) -> str:
    """The Markdown report."""
    m, p = result["mesh_vs_points"], result["pytorch3d"]
    lines = [
        f"FAUST_r `tr_reg_000` ({result['vertices']} vertices), {result['views']} views of the official layout at "
        f"{result['image_size']} x {result['image_size']}; the cloud is the mesh's vertices, discs of 0.5 x each point's "
        "local spacing.",
        "",
        "| mesh rasterizer vs point renderer | value |",
        "|---|---|",
        f"| foreground IoU | {m['iou']:.4f} |",
        f"| mesh foreground the discs miss (holes) | {100 * m['holes']:.3f} % |",
        f"| foreground the discs add (outline grown by a disc) | {100 * m['extra']:.2f} % |",
        f"| depth difference on pixels both cover, / bbox diagonal: median, 95th percentile | {m['depth_error_median']:.2e}, "
        f"{m['depth_error_p95']:.2e} |",
        f"| normal-image angle (degrees): mean, median, 95th percentile | {m['normal_angle_mean']:.1f}, "
        f"{m['normal_angle_median']:.1f}, {m['normal_angle_p95']:.1f} |",
        "",
        "| cloud's set | mesh's set | over | precision | recall |",
        "|---|---|---|---|---|",
    ]
    names = {
        "drawn": "points winning a pixel",
        "cloud_ball": "points the cloud's ball reaches",
        "face_verts": "vertices of visible faces",
        "mesh_ball": "vertices the mesh's ball reaches",
    }
    for row in m["visible_sets"]:
        lines.append(
            f"| {names[row['cloud']]} | {names[row['mesh']]} | {row['per']} | {row['precision']:.3f} | {row['recall']:.3f} |"
        )
    lines += [
        "",
        "| features, small random DINOv3, centred | vertices seen: mesh / cloud / both | cosine, same vertex: mean "
        "| 5th percentile | cosine, a random other vertex: mean |",
        "|---|---|---|---|---|",
    ]
    for row in result["features"]:
        lines.append(
            f"| `{row['mode']}` | {row['seen_mesh']} / {row['seen_cloud']} / {row['seen_both']} | {row['cosine_mean']:.3f} | "
            f"{row['cosine_p05']:.3f} | {row['cosine_other_vertex']:.3f} |"
        )
    d = p["differing"]
    lines += [
        "",
        "| geofeat vs pytorch3d `PointsRasterizer` (same points, cameras, radii) | value |",
        "|---|---|",
        f"| foreground IoU | {p['iou']:.6f} |",
        f"| pixels with the same nearest point (of {p['covered']} covered) | {100 * p['same_point_share']:.4f} % |",
        f"| pixels that differ: at the nearer disc's edge (within {d['largest_edge_margin']:.1e} of r^2; geofeat's choice "
        f"the float64 test's in {d['float64_agrees']}) / depth tie / other | {d['edge']} / {d['depth_tie']} / {d['other']} |",
        f"| largest depth difference where the point is the same | {p['depth_abs_max_same_point']:.2e} |",
        f"| seconds, geofeat / pytorch3d (CPU, naive rasterizer) | {p['seconds_ours']:.1f} / {p['seconds_pytorch3d']:.1f} |",
        "",
        "pytorch3d draws the same camera-facing discs at their points' depths and keeps the nearest, ties to the lower "
        "index, as geofeat does; its radii are in NDC units, converted here from geofeat's per point and view. It tests "
        "a pixel centre against a disc in float32 NDC coordinates (strictly inside), geofeat in float32 pixel offsets "
        "from the disc's box (inside or on the edge), so the two part only where a centre lies on a disc's edge to "
        "within rounding.",
        "",
        f"`python -m benchmarks.parity.point_renderer`; {result['date']}, {result['machine']}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--views", type=int, default=49)
    parser.add_argument("--image-size", type=int, default=512)
    parser.add_argument("--pytorch3d-python", default="/work/ref/venv/bin/python", help="python of an environment with pytorch3d")
    parser.add_argument("--pytorch3d-src", default="/work/ref/pytorch3d-src", help="pytorch3d source tree built in place, or ''")
    parser.add_argument("--out", default=str(RESULTS / "parity" / "point_renderer"))
    args = parser.parse_args(argv)
    mesh = geofeat.load_mesh(data_folder(args.data) / "FAUST_r" / "off" / "tr_reg_000.off")
    cameras = make_cameras(mesh, args.views, layout="official", image_size=args.image_size, device="cpu")
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "vertices": mesh.n_vertices,
        "views": args.views,
        "image_size": args.image_size,
        "mesh_vs_points": mesh_vs_points(mesh, cameras),
        "features": feature_agreement(mesh, cameras),
        "pytorch3d": versus_pytorch3d(mesh, cameras, args.pytorch3d_python, args.pytorch3d_src or None),
    }
    write_results(args.out, result, table(result))


if __name__ == "__main__":
    main()
