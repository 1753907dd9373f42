"""Geodesics on point clouds against the mesh they sample: FAUST_r vertices without their faces.

For each of N FAUST_r test shapes, the vertices alone (a point cloud) get their all-pairs
geodesic matrix from the heat method on points
(``geofeat.geometry.geodesic.geodesic_matrix(cloud, normalize=False)``, what an evaluation
on a point cloud reads, symmetrised). Its rows at a seeded sample of source vertices are
compared with distances on the mesh itself:

* exact polyhedral geodesics (MMP, package pygeodesic): the accuracy reference;
* the heat method on the mesh (``distances_from(mesh, sources, "heat")``);
* edge Dijkstra on the mesh (``distances_from(mesh, sources, "dijkstra")``, what the
  published protocols use).

The mesh's own methods are compared with the exact distances too, for scale. Relative
errors are taken over every (source, vertex) pair but the sources themselves. The area of
the point cloud (the masses of its robust Laplacian, which normalise the distances of an
evaluation on points) is compared with the mesh's area.

Usage::

    python -m benchmarks.cloud_geodesic --data ../shared/data --shapes 5 --sources 20
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import time

import numpy as np

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, faust_test_shapes, machine, write_results
from benchmarks.speed.geodesic import exact_rows
from geofeat.geometry.geodesic import distances_from, geodesic_matrix
from geofeat.geometry.geodesic_cloud import cloud_area

#: (key, label): each comparison, "a vs b".
COMPARISONS = (
    ("points_vs_exact", "heat method on the points vs exact polyhedral geodesics (MMP)"),
    ("points_vs_mesh_heat", "heat method on the points vs the heat method on the mesh"),
    ("points_vs_mesh_dijkstra", "heat method on the points vs edge Dijkstra on the mesh"),
    ("mesh_heat_vs_exact", "for scale: heat method on the mesh vs exact"),
    ("mesh_dijkstra_vs_exact", "for scale: edge Dijkstra on the mesh vs exact"),
)
#: A relative error above this counts as a shortcut (the points of two body parts joined).
FAR_OFF = 0.2


def relative_errors(found: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """|found - reference| / reference over every pair whose reference is not 0."""
    away = reference > 0
    return np.abs(found.astype(np.float64) - reference)[away] / reference[away]


def compare_shape(mesh: geofeat.Mesh, n_sources: int, seed: int) -> tuple[dict[str, np.ndarray], dict]:
    """Relative errors of every comparison on one shape, and its area ratio and timing."""
    cloud = geofeat.Mesh(mesh.verts, name=f"{mesh.name}_points")
    sources = np.random.default_rng(seed).choice(mesh.n_vertices, n_sources, replace=False)
    start = time.perf_counter()
    on_points = geodesic_matrix(cloud, normalize=False, cache=False)[sources]
    seconds = time.perf_counter() - start
    exact = exact_rows(mesh, sources) * np.sqrt(mesh.area())  # exact_rows divides by sqrt(area)
    heat, dijkstra = distances_from(mesh, sources, "heat"), distances_from(mesh, sources, "dijkstra")
    errors = {
        "points_vs_exact": relative_errors(on_points, exact),
        "points_vs_mesh_heat": relative_errors(on_points, heat),
        "points_vs_mesh_dijkstra": relative_errors(on_points, dijkstra),
        "mesh_heat_vs_exact": relative_errors(heat, exact),
        "mesh_dijkstra_vs_exact": relative_errors(dijkstra, exact),
    }
    return errors, {"shape": mesh.name, "area_ratio": cloud_area(cloud) / mesh.area(), "all_pairs_seconds": seconds}


def summary(errors: np.ndarray) -> dict:
    return {
        "median": float(np.median(errors)),
        "mean": float(errors.mean()),
        "p95": float(np.percentile(errors, 95)),
        "far_off": float((errors > FAR_OFF).mean()),
    }


def table(result: dict) -> str:
    lines = [
        f"Geodesic distances on the vertices of {result['n_shapes']} FAUST_r test shapes taken as point clouds (about "
        f"{result['n_points']:,} points each), {result['n_sources']} seeded sources per shape to every vertex; "
        "relative error over every (source, vertex) pair.",
        "",
        f"| compared | median relative error | mean | 95th percentile | pairs off by more than {FAR_OFF:.0%} |",
        "|---|---|---|---|---|",
    ]
    for key, label in COMPARISONS:
        row = result["comparisons"][key]
        lines.append(f"| {label} | {row['median']:.2%} | {row['mean']:.2%} | {row['p95']:.1%} | {row['far_off']:.1%} |")
    ratios = [shape["area_ratio"] for shape in result["shapes"]]
    lines += [
        "",
        f"Area of a cloud (its point-cloud Laplacian's masses) over the mesh's area: {min(ratios):.3f} to {max(ratios):.3f}. "
        f"All-pairs matrix on the points: {result['median_all_pairs_seconds']:.1f} s per shape (median).  ",
        f"`python -m benchmarks.cloud_geodesic`, {result['date']}, {result['machine']}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--shapes", type=int, default=5, help="number of FAUST_r test shapes (from tr_reg_080)")
    parser.add_argument("--sources", type=int, default=20, help="source vertices per shape")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(RESULTS / "cloud_geodesic"), help="output path without suffix (.json, .md)")
    args = parser.parse_args(argv)
    shapes = faust_test_shapes(args.data, args.shapes)
    pooled: dict[str, list[np.ndarray]] = {key: [] for key, _ in COMPARISONS}
    per_shape = []
    for index, mesh in enumerate(shapes):
        errors, info = compare_shape(mesh, args.sources, args.seed + index)
        for key, values in errors.items():
            pooled[key].append(values)
        per_shape.append(info | {key: summary(values) for key, values in errors.items()})
    result = {
        "n_shapes": len(shapes),
        "n_points": int(np.mean([mesh.n_vertices for mesh in shapes])),
        "n_sources": args.sources,
        "seed": args.seed,
        "comparisons": {key: summary(np.concatenate(values)) for key, values in pooled.items()},
        "median_all_pairs_seconds": statistics.median(shape["all_pairs_seconds"] for shape in per_shape),
        "shapes": per_shape,
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
    }
    write_results(args.out, result, table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
