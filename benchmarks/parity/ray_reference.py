"""geofeat's reference RAY partial shapes against the official GeoLoRA ray caster, draw by draw.

For each shape, a seeded stream of ``numpy.random`` draws is replayed on both sides:

- the official side: a harness run with ``--official-python`` (an environment with open3d,
  libigl and trimesh and a clone of ``vikiehm/geo-lora``) that calls
  ``utils/ray_caster.py`` ``cam_generator("low", 1)`` and ``RayCaster.get_partial_shape``
  (kept outside this repository; it writes, per draw, the camera, the hit triangles, the
  partial shape, its ground truth and open3d's per-ray triangle ids and ``t_hit``);
- geofeat: `geofeat.render.raycast.official_ray_eye` and `ray_partial_reference`.

Both sides get the same float32 vertices (the harness writes the arrays it used). A draw
is *identical* when the partial vertices agree to 1e-6, the faces agree up to their order
(and the rotation of a face's corners) and the ground truth agrees. Where the hit triangles
differ, every ray whose first triangle differs is classified. The same draws give the
distributions of the official RAY (kept vertex fraction, boundary length / sqrt(area),
components of the hit faces), beside geofeat's own RAY (`geofeat.geometry.partial.ray_partial`,
seeds 0 .. N-1, one free draw each). Last, the time per partial shape on the first shape.

    python -m benchmarks.parity.ray_reference --official-python /ref/venv/bin/python --data-ext /data_ext \\
        --harness /ref/ray_harness.py --out benchmarks/results/partial_reference/ray
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import geofeat
from benchmarks.common import DATA_EXT_ENV, DEFAULT_DATA, DEFAULT_DATA_EXT, data_folder, machine, rewrite_table, write_results
from geofeat.geometry.partial import ray_partial
from geofeat.geometry.visibility import visible_faces
from geofeat.render.rasterizer import RasterSettings
from geofeat.render.raycast import first_hits, official_ray_eye, pinhole_camera, ray_partial_reference
from geofeat.topology import face_components

POSITION_TOLERANCE = 1e-6
GRAZE = 1e-3  # a ray this close (in pixels) to a triangle's boundary grazes it
MISS = 65535  # the harness's triangle id of a ray that hits nothing


def compared_shapes(data: Path, data_ext: Path) -> dict[str, Path]:
    """The shapes compared, by name: FAUST_r tr_reg_080 of ``--data``, a PSMAL and a BeCoS-TOSCA shape of ``--data-ext``."""
    return {
        "FAUST_r tr_reg_080": data / "FAUST_r" / "off" / "tr_reg_080.off",
        "PSMAL cuts_0_horse_01": data_ext / "PSMAL" / "PARTIALSMAL" / "test" / "shapes" / "cuts_0_horse_01.off",
        "BeCoS-TOSCA 0_michael0": data_ext / "BeCoS" / "partial_full" / "test" / "0" / "0_michael0.off",
    }


def official_env() -> dict:
    """This environment without ``PYTHONPATH`` (which may point at this geofeat)."""
    return {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}


def run_harness(args, path: Path, out: Path) -> dict:
    """The official side's draws for one shape, as arrays (see the harness)."""
    command = [
        args.official_python,
        args.harness,
        "draws",
        str(path),
        "--seed",
        str(args.seed),
        "--draws",
        str(args.draws),
        "--out",
        str(out),
    ]
    subprocess.run(command, check=True, env=official_env())
    with np.load(out) as data:
        return {key: data[key] for key in data.files}


def piece(data: dict, key: str, index: int) -> np.ndarray:
    offsets = data[key + "_offsets"]
    return data[key][offsets[index] : offsets[index + 1]]


def oriented_faces(faces: np.ndarray) -> list[tuple[int, int, int]]:
    """Faces as a sorted list of corner triples, each rotated to start at its smallest corner.

    A later triangle with the same three vertices as an earlier one is left out (a geofeat
    `Mesh` holds it once).
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces = faces[np.sort(first)]
    start = np.argmin(faces, axis=1)
    rotated = np.stack([np.roll(face, -k) for face, k in zip(faces, start, strict=True)]) if len(faces) else faces
    return sorted(map(tuple, rotated.tolist()))


def boundary_ratio(verts: np.ndarray, faces: np.ndarray) -> float:
    """Length of the boundary (edges of one face) over the square root of the area."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    length = np.linalg.norm(verts[boundary[:, 0]] - verts[boundary[:, 1]], axis=1).sum()
    corners = verts[faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum() / 2
    return float(length / np.sqrt(area))


def classify_rays(mesh: geofeat.Mesh, official: dict, index: int, scale: float, eye: np.ndarray) -> dict:
    """Why the first triangle of some rays differs: counts of the differing rays by cause.

    A ray whose pixel centre lies within ``GRAZE`` pixels of the image of either triangle's
    boundary grazes an edge or a vertex; otherwise, two hits at the same depth (within 1e-5)
    are a tie between coincident triangles (triangles on repeated positions).
    """
    cast = np.float32(scale) * mesh.verts.astype(np.float32)
    camera = pinhole_camera(eye)
    ours = first_hits(cast, mesh.faces, camera)
    theirs = official["pix"][index].astype(np.int64)
    theirs[theirs == MISS] = -1
    t_hit = official["t_hit"][index]
    pixels = camera.project(cast.astype(np.float64)).pixels[0].numpy()
    causes = {"silhouette (one side misses)": 0, "grazes an edge or vertex": 0, "depth tie (coincident triangles)": 0, "other": 0}
    margin = 0.0
    for row, col in zip(*np.nonzero(ours.face != theirs), strict=True):
        a, b = ours.face[row, col], theirs[row, col]
        centre = np.array([col + 0.5, row + 0.5])
        gap = min(boundary_distance(pixels[mesh.faces[face]], centre) for face in (a, b) if face >= 0)
        if gap < GRAZE:
            causes["silhouette (one side misses)" if min(a, b) < 0 else "grazes an edge or vertex"] += 1
            margin = max(margin, gap)
        elif min(a, b) >= 0 and abs(ours.depth[row, col] - t_hit[row, col]) < 1e-5:
            causes["depth tie (coincident triangles)"] += 1
        else:
            causes["other"] += 1
    causes = {key: value for key, value in causes.items() if value}
    if margin:
        causes["largest distance of a grazing ray to the boundary, px"] = margin
    return causes


def boundary_distance(corners: np.ndarray, point: np.ndarray) -> float:
    """Distance in pixels from a point to the boundary of a projected triangle, corners (3, 2)."""
    distances = []
    for k in range(3):
        a, b = corners[k], corners[(k + 1) % 3]
        along = np.clip((point - a) @ (b - a) / max((b - a) @ (b - a), 1e-300), 0.0, 1.0)
        distances.append(np.linalg.norm(point - (a + along * (b - a))))
    return float(min(distances))


def crosses_camera_plane(mesh: geofeat.Mesh, scale: float, eye: np.ndarray) -> bool:
    """Whether some face has a corner at or behind the camera's plane (the exact ray-test path)."""
    cast = (np.float32(scale) * mesh.verts.astype(np.float32)).astype(np.float64)
    depth = pinhole_camera(eye).project(cast).depth[0].numpy()[mesh.faces]
    return bool(((depth.min(axis=1) <= RasterSettings().z_near) & (depth.max(axis=1) > 0)).any())


def summary(values) -> dict:
    values = np.asarray(values, dtype=np.float64)
    return {
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "p10": float(np.percentile(values, 10)),
        "p90": float(np.percentile(values, 90)),
    }


def compare_shape(args, name: str, path: Path, workdir: Path) -> dict:
    official = run_harness(args, path, workdir / f"{path.stem}.npz")
    mesh = geofeat.Mesh(official["full_verts"], official["full_faces"], name=path.stem)
    np.random.seed(args.seed)
    rows, reasons = [], {}
    sides = {
        "official": {"keep": [], "boundary": [], "components": []},
        "reference": {"keep": [], "boundary": [], "components": []},
    }
    for index in range(args.draws):
        eye = official_ray_eye()
        partial = ray_partial_reference(mesh, eye)
        scale = float(partial.info["scale"])
        their_verts = piece(official, "verts", index)
        their_faces = piece(official, "faces", index)
        their_gt = piece(official, "gt", index)
        their_hits = piece(official, "hits", index)
        same_hits = np.array_equal(partial.info["hit_faces"], their_hits)
        same_verts = (
            partial.mesh.n_vertices == len(their_verts) and np.abs(partial.mesh.verts - their_verts).max() <= POSITION_TOLERANCE
        )
        same_faces = same_verts and oriented_faces(partial.mesh.faces) == oriented_faces(their_faces)
        same_gt = same_verts and np.array_equal(partial.vertex_map, their_gt)
        row = {
            "draw": index,
            "eye_equal": bool(np.array_equal(eye, official["eye"][index])),
            "identical": bool(same_verts and same_faces and same_gt),
            "same_hits": bool(same_hits),
            "hits_only_ours": int(np.setdiff1d(partial.info["hit_faces"], their_hits).size),
            "hits_only_official": int(np.setdiff1d(their_hits, partial.info["hit_faces"]).size),
            "gt_differs_from_source_index": int((partial.vertex_map != partial.info["source_vertices"]).sum()),
            "filled": int(partial.info["n_filled"]),
            "filled_repeated": int(partial.info["n_filled_repeated"]),
            "crosses_camera_plane": crosses_camera_plane(mesh, partial.info["scale"], eye),
        }
        if not same_hits:
            row["rays"] = classify_rays(mesh, official, index, partial.info["scale"], eye)
        if not row["identical"]:
            cause = "hit triangles differ" if not same_hits else "same hits, partial differs"
            reasons[cause] = reasons.get(cause, 0) + 1
        rows.append(row)
        sides["reference"]["keep"].append(partial.info["keep_fraction"])
        sides["reference"]["boundary"].append(boundary_ratio(partial.mesh.verts, partial.mesh.faces))
        sides["reference"]["components"].append(partial.info["n_components"])
        sides["official"]["keep"].append(len(their_verts) / mesh.n_vertices)
        sides["official"]["boundary"].append(boundary_ratio(their_verts, their_faces))
        sides["official"]["components"].append(int(official["n_comp"][index]))

    own = {"keep": [], "boundary": [], "components": []}
    for seed in range(args.draws):
        partial = ray_partial(mesh, seed, keep_range=(0.0, 1.0), max_tries=1)
        seen = np.flatnonzero(visible_faces(mesh, partial.info["eye"], partial.info["target"]))
        own["keep"].append(partial.info["keep_fraction"])
        own["boundary"].append(boundary_ratio(partial.mesh.verts, partial.mesh.faces))
        own["components"].append(int(face_components(mesh.faces[seen]).max()) + 1)
    sides["geofeat ray_partial"] = own

    differing = [row for row in rows if not row["identical"] or not row["same_hits"]]
    rays = {}
    for row in differing:
        for cause, count in row.get("rays", {}).items():
            rays[cause] = max(rays.get(cause, 0), count) if cause.startswith("largest") else rays.get(cause, 0) + count
    return {
        "shape": name,
        "path": str(path),
        "n_vertices": mesh.n_vertices,
        "n_faces": len(mesh.faces),
        "scale": scale,
        "duplicate_positions": int(mesh.n_vertices - len(np.unique(official["full_verts"], axis=0))),
        "draws": args.draws,
        "eyes_equal": sum(row["eye_equal"] for row in rows),
        "identical": sum(row["identical"] for row in rows),
        "same_hits": sum(row["same_hits"] for row in rows),
        "differing": len([row for row in rows if not row["identical"]]),
        "reasons": reasons,
        "differing_rays_by_cause": rays,
        "draws_gt_differs_from_source_index": sum(row["gt_differs_from_source_index"] > 0 for row in rows),
        "vertices_gt_differs_from_source_index": sum(row["gt_differs_from_source_index"] for row in rows),
        "draws_crossing_camera_plane": sum(row["crosses_camera_plane"] for row in rows),
        "draws_with_filled_holes": sum(row["filled"] > 0 for row in rows),
        "draws_with_repeated_filled_triangle": sum(row["filled_repeated"] > 0 for row in rows),
        "distributions": {
            side: {metric: summary(values) for metric, values in metrics.items()} for side, metrics in sides.items()
        },
        "differing_draws": differing,
    }


def timing(args, path: Path) -> dict:
    """Seconds per RAY partial shape: official ``get_partial_shape`` and `ray_partial_reference`, same draws."""
    command = [args.official_python, args.harness, "time", str(path), "--seed", str(args.seed), "--repeats", str(args.repeats)]
    official = json.loads(subprocess.run(command, check=True, capture_output=True, text=True, env=official_env()).stdout)
    with tempfile.TemporaryDirectory() as tmp:
        data = run_harness(argparse.Namespace(**{**vars(args), "draws": 1}), path, Path(tmp) / "one.npz")
    mesh = geofeat.Mesh(data["full_verts"], data["full_faces"], name=path.stem)
    np.random.seed(args.seed)
    ours = []
    for _ in range(args.repeats):
        eye = official_ray_eye()
        start = time.perf_counter()
        ray_partial_reference(mesh, eye)
        ours.append(time.perf_counter() - start)
    return {
        "shape": path.stem,
        "repeats": args.repeats,
        "load_average_1min": os.getloadavg()[0],
        "official_median_s": float(np.median(official["seconds"])),
        "reference_median_s": float(np.median(ours)),
        "official_versions": {key: official[key] for key in ("open3d", "trimesh", "numpy")},
    }


def fmt(stats: dict) -> str:
    return f"{stats['mean']:.3f} ({stats['p10']:.3f}-{stats['p90']:.3f})"


def table(result: dict) -> str:
    """The Markdown of a result: date and machine first, then tables of at most seven columns."""
    lines = [
        "# Reference RAY partial shapes against the official ray caster",
        "",
        f"{result['date']}; {result['machine']}. Seed {result['seed']}: `numpy.random.seed({result['seed']})`, then one "
        '`cam_generator("low", 1)` per draw on both sides; the same float32 vertices on both sides.',
        "",
        "| shape | V | cast scale | draws | same camera |",
        "|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        lines.append(
            f"| {shape['shape']} | {shape['n_vertices']} | {shape['scale']:g} | {shape['draws']} | {shape['eyes_equal']} |"
        )
    lines += [
        "",
        "Of those draws, the partial shapes of both sides:",
        "",
        "| shape | identical | same hit triangles | differing | why |",
        "|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        why = "; ".join(f"{k}: {v}" for k, v in shape["reasons"].items()) or "-"
        lines.append(f"| {shape['shape']} | {shape['identical']} | {shape['same_hits']} | {shape['differing']} | {why} |")
    lines += ["", "Rays whose first triangle differs (all draws), by cause:", ""]
    for shape in result["shapes"]:
        causes = ", ".join(
            f"{k}: {v:.2g}" if isinstance(v, float) else f"{k}: {v}" for k, v in shape["differing_rays_by_cause"].items()
        )
        lines.append(
            f"- {shape['shape']}: {causes or 'none'}. Draws with a face crossing the camera's plane: "
            f"{shape['draws_crossing_camera_plane']}; with filled holes: {shape['draws_with_filled_holes']} "
            f"(a filled triangle repeating a face, kept once: {shape['draws_with_repeated_filled_triangle']}); "
            f"source positions repeated: {shape['duplicate_positions']}, ground truth != source index in "
            f"{shape['draws_gt_differs_from_source_index']} draws ({shape['vertices_gt_differs_from_source_index']} vertices)."
        )
    lines += [
        "",
        "Distributions over the draws: mean (10th-90th percentile). Official and reference: the draws above; "
        "geofeat ray_partial: seeds 0 .. N-1, one free draw each (keep_range (0, 1)). Components: of the hit "
        "(visible) faces, before the largest is kept.",
        "",
        "| shape | side | kept vertex fraction | boundary / sqrt(area) | components |",
        "|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        for side, stats in shape["distributions"].items():
            lines.append(
                f"| {shape['shape']} | {side} | {fmt(stats['keep'])} | {fmt(stats['boundary'])} | {fmt(stats['components'])} |"
            )
    speed = result["speed"]
    lines += [
        "",
        f"Time per RAY partial shape on {speed['shape']} (median of {speed['repeats']}, same draws, this machine): "
        f"official (open3d {speed['official_versions']['open3d']} + trimesh {speed['official_versions']['trimesh']}) "
        f"{1000 * speed['official_median_s']:.0f} ms, geofeat reference {1000 * speed['reference_median_s']:.0f} ms"
        + (f" (load average {speed['load_average_1min']:.1f} when timed)." if "load_average_1min" in speed else "."),
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--official-python", help="python of the environment with open3d, libigl and trimesh")
    parser.add_argument("--harness", help="the official-side harness script")
    parser.add_argument("--draws", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=50, help="draws timed on the first shape")
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder that holds FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument(
        "--data-ext", default=DEFAULT_DATA_EXT, help="the folder that holds PSMAL/ and BeCoS/ (default $GEOFEAT_DATA_EXT)"
    )
    parser.add_argument("--out", default="benchmarks/results/partial_reference/ray")
    parser.add_argument("--render-only", action="store_true", help="rewrite OUT.md from OUT.json without running anything")
    args = parser.parse_args(argv)
    if args.render_only:
        rewrite_table(args.out, table)
        return 0
    if not (args.official_python and args.harness):
        parser.error("--official-python and --harness are required (or --render-only)")
    paths = compared_shapes(data_folder(args.data), data_folder(args.data_ext, "--data-ext", DATA_EXT_ENV, "PSMAL/ and BeCoS/"))
    missing = [str(path) for path in paths.values() if not path.is_file()]
    if missing:
        raise SystemExit(f"shapes not found: {missing}")
    with tempfile.TemporaryDirectory() as tmp:
        shapes = [compare_shape(args, name, path, Path(tmp)) for name, path in paths.items()]
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "seed": args.seed,
        "shapes": shapes,
        "speed": timing(args, next(iter(paths.values()))),
    }
    write_results(args.out, result, table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
