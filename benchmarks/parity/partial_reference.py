"""geofeat's reference CUTS and HOLES partial shapes against GeoLoRA's official generators, draw by draw.

geofeat side: `geofeat.geometry.partial_reference` (`cut_partial_reference`,
`holes_partial_reference`, the draws `draw_cut_normal` / `draw_holes`) and its plane clip
`geofeat.geometry.clip.clip_plane`. Official side: ``PartialShapeDataset.generate_random_cut``,
``generate_random_holes`` and ``get_gt_corres`` of ``vikiehm/geo-lora`` (``utils/shape_dataset.py``),
run unmodified by a small harness in the official environment (``--official-python``, with
open3d 0.20, libigl, torch). The harness is kept outside this repository (``--harness``); it
has three commands, which this script calls:

* ``prepare MESH OUT.npz``: the full shape as the official dataset makes it (trimesh
  ``process=False``, float32 ``verts_2``, no rotation) and ``get_geodesic_distmat(normalize=True)``,
  which divides ``verts_2`` in place by the square root of the area; writes ``verts``,
  ``faces`` and the float32 geodesic matrix ``dist``. Both sides use these arrays.
* ``run PREPARED {cuts,holes} {seeded,stream} SEED N OUT.npz``: N calls; ``seeded`` reseeds
  ``np.random`` and torch with ``SEED + i`` before call i, ``stream`` seeds once. For every
  call it writes what was drawn (``d{i}_normals``; ``d{i}_m``, ``d{i}_centres``), the input of
  every ``keep_largest_component`` call (``d{i}_raw{k}_verts/faces``: the raw clip of try k, or
  the selection), the result ``d{i}_verts/faces`` and ``d{i}_gt`` (``get_gt_corres`` on the CPU),
  and the seconds of each generator call and of each ``get_gt_corres`` call (``draw_seconds``,
  ``draw_seconds_gt``).

The shapes are those of ``parity/ray_reference.py``: FAUST_r tr_reg_080, PSMAL cuts_0_horse_01
(PSMAL holds partial shapes only) and BeCoS-TOSCA 0_michael0.

Per method and shape, every seeded draw is made on both sides from the same seed and compared:
identical means the same vertices (to 1e-6), the same triangles (up to face order and the
cyclic order of corners) and the same ground truth; every raw clip of the official side is
also compared with `clip_plane` (vertex and face order included). Then ``--free`` draws from
one seeded stream on each side (different seeds) give the distributions of the kept fraction,
the boundary length over the square root of the area and the number of components before the
largest is kept. Time per partial shape: the median over the seeded draws, of the
official generator, of its ground truth and of geofeat's draw (both in one call).

    python -m benchmarks.parity.partial_reference --official-python /ref/venv/bin/python --data-ext /data_ext \\
        --harness /ref/partial_harness.py --out benchmarks/results/partial_reference/parity
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.stats import ks_2samp

from benchmarks.common import DATA_EXT_ENV, DEFAULT_DATA, DEFAULT_DATA_EXT, RESULTS, data_folder, machine, write_results
from geofeat import Mesh
from geofeat.geometry.clip import clip_plane
from geofeat.geometry.partial_reference import cut_partial_reference, draw_holes, holes_partial_reference
from geofeat.topology import face_components, triangle_areas

#: Vertices farther apart than this count as different.
TOLERANCE = 1e-6
METHODS = ("cuts", "holes")
SEEDED_BASE = 1000  # seeded draw i uses seed SEEDED_BASE + i on both sides
FREE_SEED_OFFICIAL, FREE_SEED_OURS = 7, 8


def default_shapes(data: str, ext: str) -> list[tuple[str, str, str]]:
    """(label, kind of shape, path) of the three shapes."""
    return [
        ("FAUST_r tr_reg_080", "human, full", f"{data}/FAUST_r/off/tr_reg_080.off"),
        (
            "PSMAL cuts_0_horse_01",
            "SMAL horse, a PARTIALSMAL shape (PSMAL holds no full shapes; 49 boundary edges)",
            f"{ext}/PSMAL/PARTIALSMAL/test/shapes/cuts_0_horse_01.off",
        ),
        ("BeCoS-TOSCA 0_michael0", "TOSCA human, full (20 boundary edges)", f"{ext}/BeCoS/partial_full/test/0/0_michael0.off"),
    ]


def harness(args, *command) -> None:
    """Run the official-side harness; its environment gets no PYTHONPATH of this one."""
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    subprocess.run([args.official_python, args.harness, *map(str, command)], check=True, stdout=subprocess.DEVNULL, env=env)


# --------------------------------------------------------------------------- comparison


def canonical_faces(faces: np.ndarray) -> np.ndarray:
    """Each triangle rotated to start at its smallest index (orientation kept), rows sorted."""
    start = np.argmin(faces, axis=1)
    rolled = np.stack([faces[np.arange(len(faces)), (start + k) % 3] for k in range(3)], axis=1)
    return rolled[np.lexsort(rolled.T[::-1])]


def first_of_each_triangle(faces: np.ndarray) -> np.ndarray:
    """``faces`` with a triangle named again (any corner order) dropped, the first kept."""
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    return faces[np.sort(first)]


def compare(ours, verts, faces, gt) -> tuple[str, bool]:
    """How a geofeat shape relates to the official (verts, faces, gt): (category, same order).

    Categories: ``identical``; ``repeated triangles`` (identical once the official shape's
    repeated triangles are dropped); ``vertex count``, ``positions``, ``faces``, ``ground truth``.
    Same order: the vertices in the official order and the faces too, corners included (for
    ``repeated triangles``: the official faces with each repeat dropped, the first kept).
    """
    mine = ours.mesh.verts
    verts = np.asarray(verts, dtype=np.float64)
    if len(mine) != len(verts):
        return "vertex count", False
    in_order = bool(np.abs(mine - verts).max() <= TOLERANCE) if len(mine) else True
    if in_order:
        match = np.arange(len(mine))
    else:
        dist, match = cKDTree(verts).query(mine)
        if dist.max() > TOLERANCE or np.unique(match).size != len(match):
            return "positions", False
    category, expected = "identical", faces
    if not np.array_equal(canonical_faces(match[ours.mesh.faces]), canonical_faces(faces)):
        expected = first_of_each_triangle(faces)
        if len(expected) < len(faces) and np.array_equal(canonical_faces(match[ours.mesh.faces]), canonical_faces(expected)):
            category = "repeated triangles"
        else:
            return "faces", False
    if not np.array_equal(ours.vertex_map, np.asarray(gt)[match]):
        return "ground truth", False
    # in order: the same vertex order and the same faces in the same order (the repeats dropped)
    return category, in_order and np.array_equal(ours.mesh.faces, expected)


def clip_parity(record, n: int, verts: np.ndarray, faces: np.ndarray) -> dict:
    """Every raw clip the official side made (each try of each draw) against `clip_plane`."""
    coords = verts.astype(np.float64)
    centre = (coords.min(axis=0) + coords.max(axis=0)) * 0.5
    counts = {"clips": 0, "identical_in_order": 0, "identical_to_tolerance": 0, "largest_difference": 0.0}
    for i in range(n):
        normals = record[f"d{i}_normals"]
        for k in range(int(record[f"d{i}_n_raw"])):
            raw_verts, raw_faces = record[f"d{i}_raw{k}_verts"], record[f"d{i}_raw{k}_faces"]
            mine, my_faces, _ = clip_plane(verts, faces, centre, normals[k])
            counts["clips"] += 1
            if mine.shape == raw_verts.shape and np.array_equal(my_faces, raw_faces):
                difference = float(np.abs(mine.astype(np.float64) - raw_verts).max()) if len(mine) else 0.0
                counts["largest_difference"] = max(counts["largest_difference"], difference)
                counts["identical_in_order"] += int(difference == 0.0)
                counts["identical_to_tolerance"] += int(difference <= TOLERANCE)
    return counts


def draws_match(method: str, ours, record, i: int) -> bool:
    if method == "cuts":
        return np.array_equal(ours.info["normals"], record[f"d{i}_normals"])
    return np.array_equal(ours.info["centres"], record[f"d{i}_centres"])


def geofeat_draw(method: str, mesh: Mesh, dist: np.ndarray, rng, generator):
    if method == "cuts":
        return cut_partial_reference(mesh, rng)
    draw = draw_holes(mesh.n_vertices, generator)
    return holes_partial_reference(mesh, draw.centres, draw.radius, dist)


# --------------------------------------------------------------------------- statistics


def shape_stats(verts: np.ndarray, faces: np.ndarray, n_source: int) -> tuple[float, float]:
    """Kept fraction ``V_p / V`` and boundary length over the square root of the partial area."""
    verts = np.asarray(verts, dtype=np.float64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    length = float(np.linalg.norm(verts[boundary[:, 0]] - verts[boundary[:, 1]], axis=1).sum())
    return len(verts) / n_source, length / float(np.sqrt(triangle_areas(verts, faces).sum()))


def official_components(record, i: int, method: str, full_faces: np.ndarray) -> int:
    """Components before the largest is kept, from the official raw input of keep_largest_component."""
    if method == "cuts" and len(record[f"d{i}_normals"]) == 10:  # whole-mesh fallback
        return int(face_components(full_faces).max()) + 1
    raw = record[f"d{i}_raw{int(record[f'd{i}_n_raw']) - 1}_faces"]
    return int(face_components(raw).max()) + 1


def describe(values) -> dict:
    values = np.asarray(values, dtype=np.float64)
    p5, p50, p95 = np.percentile(values, [5, 50, 95])
    return {"mean": float(values.mean()), "std": float(values.std()), "p5": float(p5), "p50": float(p50), "p95": float(p95)}


# --------------------------------------------------------------------------- main


def run_shape(args, label: str, path: str, work: Path) -> dict:
    stem = Path(path).stem
    prepared = work / f"{stem}.npz"
    if not prepared.is_file():
        harness(args, "prepare", path, prepared)
    data = np.load(prepared)
    verts, faces, dist = data["verts"], data["faces"], data["dist"]
    mesh = Mesh(verts, faces, name=stem)
    result = {"path": path, "vertices": int(len(verts)), "faces": int(len(faces))}
    _, position = np.unique(verts, axis=0, return_inverse=True)
    result["duplicate_positions"] = int(len(verts) - position.max() - 1)
    # faces whose three corners lie at the positions of another face's corners: the clip merges them into one triangle
    result["coinciding_faces"] = int(len(faces) - len(np.unique(np.sort(position.reshape(-1)[faces], axis=1), axis=0)))
    for method in METHODS:
        seeded = work / f"{stem}_{method}_seeded{SEEDED_BASE}x{args.draws}.npz"
        free = work / f"{stem}_{method}_stream{FREE_SEED_OFFICIAL}x{args.free}.npz"
        if not seeded.is_file():
            harness(args, "run", prepared, method, "seeded", SEEDED_BASE, args.draws, seeded)
        if not free.is_file():
            harness(args, "run", prepared, method, "stream", FREE_SEED_OFFICIAL, args.free, free)
        record = np.load(seeded)
        categories: dict[str, list[int]] = {}
        in_order = draw_mismatch = 0
        repeated: list[int] = []  # repeated triangles of the official shape, per draw that has some
        seconds = []  # geofeat's draws alone (the partial shape and its ground truth), not the comparison
        for i in range(args.draws):
            seed = SEEDED_BASE + i
            start = time.perf_counter()
            ours = geofeat_draw(method, mesh, dist, np.random.RandomState(seed), torch.Generator().manual_seed(seed))
            seconds.append(time.perf_counter() - start)
            if not draws_match(method, ours, record, i):
                draw_mismatch += 1
                categories.setdefault("draw", []).append(i)
                continue
            category, ordered = compare(ours, record[f"d{i}_verts"], record[f"d{i}_faces"], record[f"d{i}_gt"])
            categories.setdefault(category, []).append(i)
            in_order += int(ordered)
            if category == "repeated triangles":
                repeated.append(ours.info["repeated_faces"])
        entry = {
            "draws": args.draws,
            "identical": len(categories.get("identical", [])),
            "in_official_order": in_order,
            "repeated_triangles_per_draw": {"min": min(repeated), "max": max(repeated)} if repeated else None,
            "differing": {key: value for key, value in categories.items() if key != "identical"},
            "seconds_per_draw": draw_times(record, seconds),
        }
        if method == "cuts":
            entry["clip"] = clip_parity(record, args.draws, verts, faces)
            entry["whole_mesh_draws"] = [i for i in range(args.draws) if len(record[f"d{i}_normals"]) == 10]
            entry["retried_draws"] = [i for i in range(args.draws) if len(record[f"d{i}_normals"]) > 1]
        entry["free"] = free_draws(args, method, mesh, dist, np.load(free), faces)
        result[method] = entry
        print(f"{label} {method}: {entry['identical']} / {args.draws} identical, differing {entry['differing']}", flush=True)
    return result


def draw_times(record, geofeat_seconds: list[float]) -> dict:
    """Mean and median seconds per draw: the official generator, its ground truth, both, and geofeat's draw."""
    official, official_gt = record["draw_seconds"], record["draw_seconds_gt"]
    out = {}
    for key, values in {
        "official_generator": official,
        "official_ground_truth": official_gt,
        "official_total": official + official_gt,
        "geofeat": np.asarray(geofeat_seconds),
    }.items():
        out[key] = {"mean": float(np.mean(values)), "median": float(np.median(values))}
    return out


def free_draws(args, method: str, mesh: Mesh, dist: np.ndarray, record, full_faces: np.ndarray) -> dict:
    """Distributions over ``args.free`` consecutive draws of one seeded stream on each side."""
    official = {"keep_fraction": [], "boundary_over_sqrt_area": [], "components": []}
    ours = {key: [] for key in official}
    for i in range(args.free):
        fraction, boundary = shape_stats(record[f"d{i}_verts"], record[f"d{i}_faces"], mesh.n_vertices)
        official["keep_fraction"].append(fraction)
        official["boundary_over_sqrt_area"].append(boundary)
        official["components"].append(official_components(record, i, method, full_faces))
    rng = np.random.RandomState(FREE_SEED_OURS)
    generator = torch.Generator().manual_seed(FREE_SEED_OURS)
    for _ in range(args.free):
        shape = geofeat_draw(method, mesh, dist, rng, generator)
        fraction, boundary = shape_stats(shape.mesh.verts, shape.mesh.faces, mesh.n_vertices)
        ours["keep_fraction"].append(fraction)
        ours["boundary_over_sqrt_area"].append(boundary)
        ours["components"].append(shape.info["components"])
    out = {"draws": args.free, "seed_official": FREE_SEED_OFFICIAL, "seed_geofeat": FREE_SEED_OURS}
    for key in official:
        out[key] = {
            "official": describe(official[key]),
            "geofeat": describe(ours[key]),
            "ks_pvalue": float(ks_2samp(official[key], ours[key]).pvalue),
        }
    return out


def tables(result: dict) -> str:
    lines = [
        "# Reference CUTS and HOLES partial shapes against the official generators",
        "",
        f"{result['date']}; {result['machine']}.",
        "",
        "geofeat's reference CUTS and HOLES (`geofeat.geometry.partial_reference`) beside GeoLoRA's "
        "`generate_random_cut` / `generate_random_holes` / `get_gt_corres`, run unmodified with open3d "
        f"0.20 in its own environment. {result['draws']} seeded draws per method and shape (seed "
        f"{SEEDED_BASE} + i on both sides); identical: vertices within {TOLERANCE:g}, the same triangles "
        "up to face order and cyclic corner order, the same ground truth; in the official order: besides, the "
        "vertices in the official order and the faces in the official order, corners included (with repeated "
        "triangles: the official faces with each repeat dropped). Both sides get the float32 vertices "
        "the official dataset passes on (divided in place by the square root of the area) and its float32 "
        f"geodesic matrix (the shapes of `parity/ray_reference.py`). Official environment: {result['official']}. "
        f"`python -m benchmarks.parity.partial_reference`, {result['seconds'] / 60:.0f} minutes in all.",
        "",
        "| method | shape | draws | identical | in the official order | differing (kind: count) |",
        "|---|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        for method in METHODS:
            entry = shape[method]
            differing = ", ".join(f"{k}: {len(v)}" for k, v in entry["differing"].items()) or "none"
            if entry["repeated_triangles_per_draw"]:
                counts = entry["repeated_triangles_per_draw"]
                differing += f" ({counts['min']} to {counts['max']} repeated triangles a shape)"
            lines.append(
                f"| {method} | {shape['label']} | {entry['draws']} | {entry['identical']} | {entry['in_official_order']} | {differing} |"
            )
    lines += [
        "",
        "Kinds of difference: *repeated triangles*: the official shape holds a triangle twice (the clip merges "
        "vertices at equal positions, so two source faces whose corners lie at the same positions become one "
        "triangle twice; see the coinciding faces of each shape below); a geofeat `Mesh` holds each triangle once, so "
        "the reference drops the repeat; vertices, the other triangles and the ground truth are the same. "
        "*draw*: the two sides drew different normals or centres; *vertex count*, *positions*, *faces*, "
        "*ground truth*: the first check that failed.",
        "",
        "`clip_plane` against every raw `clip_plane` of the official cuts (each try, before the largest component):",
        "",
        "| shape | clips | identical in order, bit for bit | within 1e-6 | largest difference |",
        "|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        clip = shape["cuts"]["clip"]
        lines.append(
            f"| {shape['label']} | {clip['clips']} | {clip['identical_in_order']} | {clip['identical_to_tolerance']} | {clip['largest_difference']:.1e} |"
        )
    lines += [
        "",
        f"{result['free']} free draws per method and shape (one stream each; official seed {FREE_SEED_OFFICIAL}, "
        f"geofeat seed {FREE_SEED_OURS}): mean ± std [5 %, 50 %, 95 %], and the two-sample KS p-value. Kept "
        "fraction: V_p / V; boundary: length of the edges of one face over the square root of the partial "
        "shape's area; components: edge-connected components before the largest is kept.",
        "",
        "| method | shape | quantity | official | geofeat | KS p |",
        "|---|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        for method in METHODS:
            free = shape[method]["free"]
            for key in ("keep_fraction", "boundary_over_sqrt_area", "components"):
                row = free[key]
                cells = [
                    f"{d['mean']:.3f} ± {d['std']:.3f} [{d['p5']:.3f}, {d['p50']:.3f}, {d['p95']:.3f}]"
                    for d in (row["official"], row["geofeat"])
                ]
                lines.append(f"| {method} | {shape['label']} | {key} | {cells[0]} | {cells[1]} | {row['ks_pvalue']:.2f} |")
    lines += [
        "",
        "Time per partial shape, the median over the seeded draws (means in the JSON), one CPU thread (`OMP_NUM_THREADS=1`), on 2 cores shared "
        f"with other jobs (load average {result['load_average'][0]:.1f} at the start, {result['load_average'][1]:.1f} "
        "at the end): the two sides ran at different moments, so the ratios carry the noise of that load. Official: "
        "`generate_random_cut` / `generate_random_holes` (Open3D) and `get_gt_corres` (torch, CPU) timed apart; "
        "geofeat: `cut_partial_reference` / `draw_holes` + `holes_partial_reference`, which make the ground truth too "
        "(the same `torch.cdist` and `min`, which take most of the time on both sides).",
        "",
        "| method | shape | official generator | official ground truth | official total | geofeat (with ground truth) | geofeat / official |",
        "|---|---|---|---|---|---|---|",
    ]
    for shape in result["shapes"]:
        for method in METHODS:
            entry = shape[method]
            times = {key: value["median"] for key, value in entry["seconds_per_draw"].items()}
            cells = [
                f"{times[key] * 1e3:.1f} ms"
                for key in ("official_generator", "official_ground_truth", "official_total", "geofeat")
            ]
            lines.append(
                f"| {method} | {shape['label']} | {' | '.join(cells)} | {times['geofeat'] / times['official_total']:.2f} |"
            )
    lines += ["", "Shapes:", ""]
    for shape in result["shapes"]:
        lines.append(
            f"- {shape['label']}: {shape['kind']} ({shape['vertices']} vertices, {shape['faces']} faces, "
            f"{shape['duplicate_positions']} vertices at a position another vertex has, {shape['coinciding_faces']} "
            "faces with their corners at the positions of another face's corners); cuts retried in "
            f"{len(shape['cuts']['retried_draws'])} and fell back to the whole mesh in "
            f"{len(shape['cuts']['whole_mesh_draws'])} of the seeded draws."
        )
    return "\n".join(lines)


def official_versions(args) -> str:
    """The versions of the official environment's libraries, as one string."""
    names = ("open3d", "libigl", "torch", "numpy")
    code = f"from importlib.metadata import version; print(', '.join(n + ' ' + version(n) for n in {names!r}))"
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    return subprocess.run([args.official_python, "-c", code], check=True, capture_output=True, text=True, env=env).stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--official-python", required=True, help="python of the official environment (open3d, libigl, torch)")
    parser.add_argument("--harness", required=True, help="the official-side harness (kept outside this repository)")
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--data-ext", default=DEFAULT_DATA_EXT, help="folder with PSMAL/ and BeCoS/ (default $GEOFEAT_DATA_EXT)")
    parser.add_argument("--draws", type=int, default=200, help="seeded draws per method and shape")
    parser.add_argument("--free", type=int, default=500, help="free draws per method and shape")
    parser.add_argument("--work", help="folder for the official side's arrays (kept; reused when present)")
    parser.add_argument("--out", default=str(RESULTS / "partial_reference" / "parity"))
    args = parser.parse_args()
    if args.draws < 1 or args.free < 2:
        parser.error(f"--draws must be at least 1 and --free at least 2 (a distribution); found {args.draws} and {args.free}")
    args.data = str(data_folder(args.data))
    args.data_ext = str(data_folder(args.data_ext, "--data-ext", DATA_EXT_ENV, "PSMAL/ and BeCoS/"))
    # the official shapes have what Mesh warns about (non-manifold edges where the clip merged
    # vertices, zero-area triangles beside a vertex near the plane): expected here, not news
    logging.getLogger("geofeat.mesh").setLevel(logging.ERROR)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="parity_partial_"))
    work.mkdir(parents=True, exist_ok=True)
    shapes = []
    missing = [path for _, _, path in default_shapes(args.data, args.data_ext) if not Path(path).is_file()]
    if missing:
        raise SystemExit(f"shapes not found: {missing}; pass --data / --data-ext")
    load_before, start = os.getloadavg()[0], time.perf_counter()
    for label, kind, path in default_shapes(args.data, args.data_ext):
        shapes.append({"label": label, "kind": kind, **run_shape(args, label, path, work)})
    result = {
        "draws": args.draws,
        "free": args.free,
        "official": f"vikiehm/geo-lora utils/shape_dataset.py at ed2a541, {official_versions(args)}",
        "seconds": time.perf_counter() - start,
        "load_average": [load_before, os.getloadavg()[0]],
        "harness": args.harness,
        "shapes": shapes,
        "date": datetime.date.today().isoformat(),
        "machine": machine(f"torch {torch.__version__}"),
    }
    write_results(args.out, result, tables(result))


if __name__ == "__main__":
    main()
