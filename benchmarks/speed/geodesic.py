"""All-pairs geodesic matrices: geofeat against GeoLoRA's ``geodesic_dist_echo``, side by side.

For each of N FAUST_r shapes, and for each repeat, these run one after the other on the same
vertex and face arrays already in memory, each producing the full (V, V) matrix divided by
the square root of the surface area:

* baseline: GeoLoRA's ``geodesic_dist_echo`` (github.com/vikiehm/geo-lora, utils/utils.py),
  re-implemented here from what it does (see `baseline_geodesic_dist_echo`);
* scipy Dijkstra from every vertex on the same edge graph (the textbook way, for scale);
* ``geofeat.geometry.geodesic.geodesic_matrix(method="dijkstra")`` (cache off);
* ``geodesic_matrix(method="heat")`` (cache off).

Accuracy: exact polyhedral geodesics (MMP algorithm, package pygeodesic) from a seeded sample
of source vertices to every vertex are the reference; each method's rows for those sources
are compared with them (mean relative error over all source-target pairs, source excluded).

Times are wall-clock medians over the repeats, summed over the shapes; the CPU time of this
process is recorded beside them because the machine may be shared (the load average is
recorded too).

Usage::

    python -m benchmarks.speed.geodesic --data ../shared/data --shapes 5 --repeats 3
"""

from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, faust_test_shapes, machine, write_results
from geofeat.geometry.geodesic import edge_graph, geodesic_matrix

METHODS = ("baseline", "scipy_all_sources", "geofeat_dijkstra", "geofeat_heat")
LABELS = {
    "baseline": "GeoLoRA `geodesic_dist_echo` (k-NN k=500 masked to edges + scipy `shortest_path`)",
    "baseline_shortest_path": "&nbsp;&nbsp;of which its `shortest_path` call alone",
    "scipy_all_sources": "scipy `dijkstra` from every vertex on the edge graph",
    "geofeat_dijkstra": "geofeat `geodesic_matrix(method='dijkstra')`",
    "geofeat_heat": "geofeat `geodesic_matrix(method='heat')`",
}


def baseline_geodesic_dist_echo(verts: np.ndarray, faces: np.ndarray, n_neighbors: int = 500) -> tuple[np.ndarray, dict]:
    """GeoLoRA's all-pairs geodesics, re-implemented from the behaviour of its code.

    What the original does, step by step: the vertices arrive as float32 (its dataset casts
    them); it divides them by the square root of the summed vertex areas, which it obtains
    from a one-eigenpair Laplace-Beltrami decomposition (cotan Laplacian and vertex areas from
    potpourri3d, ARPACK shift-invert); it builds trimesh's networkx vertex-adjacency graph and
    asserts that it is connected; it computes scikit-learn's k-nearest-neighbour distance
    graph with k = min(500, V - 1); it copies those k-NN distances into an empty LIL matrix
    at the positions of the mesh edges; it runs scipy's ``shortest_path`` on that matrix as
    an undirected graph (method 'auto'). The edge weights are therefore Euclidean edge
    lengths, as in geofeat's Dijkstra.

    Returns
    -------
    dist : numpy.ndarray, shape (V, V), float64
    seconds : dict
        Time of its shortest-path call ("shortest_path").
    """
    import networkx as nx
    import potpourri3d as pp3d
    import scipy.sparse.linalg as sla
    import trimesh
    from scipy.sparse.csgraph import shortest_path
    from sklearn.neighbors import kneighbors_graph

    verts = np.array(verts, dtype=np.float32)
    n = len(verts)
    stiffness = pp3d.cotan_laplacian(verts, faces, denom_eps=1e-10)
    mass = pp3d.vertex_areas(verts, faces)
    mass += 1e-8 * np.mean(mass)
    shifted = (stiffness + 1e-8 * sp.identity(n)).tocsc()
    sla.eigsh(shifted, k=1, M=sp.diags(mass), sigma=1e-8)
    verts /= np.sqrt(mass.sum())

    adjacency_graph = trimesh.Trimesh(vertices=verts, faces=faces, process=False).vertex_adjacency_graph
    if not nx.is_connected(adjacency_graph):
        raise ValueError("graph not connected")
    on_edge = nx.adjacency_matrix(adjacency_graph, range(n)) != 0
    knn = kneighbors_graph(verts, n_neighbors=min(n_neighbors, n - 1), mode="distance", include_self=False)
    weights = sp.csr_matrix((n, n)).tolil()
    weights[on_edge] = knn[on_edge]
    start = time.perf_counter()
    dist = shortest_path(weights, directed=False)
    return dist, {"shortest_path": time.perf_counter() - start}


def run_method(name: str, mesh: geofeat.Mesh) -> tuple[np.ndarray, dict]:
    """One all-pairs matrix, normalised by sqrt(area), with the wall and CPU seconds it took."""
    wall, cpu = time.perf_counter(), time.process_time()
    extra = {}
    if name == "baseline":
        dist, extra = baseline_geodesic_dist_echo(np.array(mesh.verts), np.array(mesh.faces))
    elif name == "scipy_all_sources":
        dist = dijkstra(edge_graph(mesh) / np.sqrt(mesh.area()), directed=False)
    elif name == "geofeat_dijkstra":
        dist = geodesic_matrix(mesh, "dijkstra", cache=False)
    else:
        dist = geodesic_matrix(mesh, "heat", cache=False)
    seconds = {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}
    seconds.update(extra)
    return dist, seconds


def exact_rows(mesh: geofeat.Mesh, sources: np.ndarray) -> np.ndarray:
    """Exact polyhedral geodesic distances (S, V) from the sources, divided by sqrt(area)."""
    try:
        from pygeodesic import geodesic as pygeodesic
    except ImportError:
        sys.exit("the accuracy reference needs pygeodesic (exact MMP geodesics): pip install pygeodesic")
    solver = pygeodesic.PyGeodesicAlgorithmExact(np.array(mesh.verts), np.array(mesh.faces, dtype=np.int32))
    rows = [solver.geodesicDistances(np.array([s], dtype=np.int32), None)[0] for s in sources]
    return np.stack(rows) / np.sqrt(mesh.area())


def errors(rows: np.ndarray, reference: np.ndarray) -> dict:
    """Mean relative and mean absolute (x100, normalised units) error over all pairs but the sources."""
    pairs = reference > 0
    diff = np.abs(rows.astype(np.float64) - reference)[pairs]
    return {"mean_relative": float(np.mean(diff / reference[pairs])), "mean_absolute_x100": float(100 * diff.mean())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--shapes", type=int, default=5, help="number of FAUST_r shapes (from tr_reg_080)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sources", type=int, default=20, help="source vertices per shape for the exact reference")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(RESULTS / "speed_geodesic"), help="writes OUT.json and OUT.md")
    args = parser.parse_args(argv)

    shapes = faust_test_shapes(args.data, args.shapes)
    rng = np.random.default_rng(args.seed)
    load_before = os.getloadavg()

    per_shape = []
    for mesh in shapes:
        sources = np.sort(rng.choice(mesh.n_vertices, size=args.sources, replace=False))
        reference = exact_rows(mesh, sources)
        runs = {name: [] for name in METHODS}
        record = {"shape": mesh.name, "vertices": mesh.n_vertices, "error": {}}
        for repeat in range(args.repeats):
            for name in METHODS:
                dist, seconds = run_method(name, mesh)
                runs[name].append(seconds)
                if repeat == 0:
                    record["error"][name] = errors(dist[sources], reference)
                    if name == "baseline":
                        baseline_rows = dist[sources]
                    if name == "geofeat_dijkstra":
                        record["max_abs_difference_baseline_vs_geofeat_dijkstra"] = float(
                            np.abs(dist[sources] - baseline_rows).max()
                        )
                del dist
        record["seconds"] = {
            name: {key: statistics.median(r[key] for r in values) for key in values[0]} for name, values in runs.items()
        }
        per_shape.append(record)
        times = ", ".join(f"{name} {record['seconds'][name]['wall']:.2f}s" for name in METHODS)
        print(f"{mesh.name} ({mesh.n_vertices} vertices): {times}", flush=True)

    result = summarise(args, shapes, per_shape, load_before)
    write_results(args.out, result, markdown(result))
    return 0


def summarise(args, shapes, per_shape, load_before) -> dict:
    total = {}
    for name in METHODS:
        total[name] = {key: sum(r["seconds"][name][key] for r in per_shape) for key in ("wall", "cpu")}
    total["baseline_shortest_path"] = {"wall": sum(r["seconds"]["baseline"]["shortest_path"] for r in per_shape)}
    error = {
        name: {key: float(np.mean([r["error"][name][key] for r in per_shape])) for key in ("mean_relative", "mean_absolute_x100")}
        for name in METHODS
    }
    speedup = {name: total["baseline"]["wall"] / total[name]["wall"] for name in METHODS}
    speedup_cpu = {name: total["baseline"]["cpu"] / total[name]["cpu"] for name in METHODS}
    return {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "load_average_1_5_15min": {"before": list(load_before), "after": list(os.getloadavg())},
        "geofeat": geofeat.__version__,
        "shapes": [m.name for m in shapes],
        "vertices_mean": float(np.mean([m.n_vertices for m in shapes])),
        "repeats": args.repeats,
        "reference": f"exact polyhedral geodesics (pygeodesic MMP), {args.sources} seeded sources per shape to all vertices",
        "seconds_total": total,
        "speedup_vs_baseline_wall": speedup,
        "speedup_vs_baseline_cpu": speedup_cpu,
        "error_vs_exact": error,
        "target_met": bool(
            speedup["geofeat_dijkstra"] >= 5
            and error["geofeat_dijkstra"]["mean_relative"] <= error["baseline"]["mean_relative"] + 1e-6
        ),
        "per_shape": per_shape,
    }


def markdown(result: dict) -> str:
    total, n = result["seconds_total"], len(result["shapes"])
    lines = [
        f"All-pairs geodesic matrices (normalised by sqrt(area)), {n} FAUST_r shapes "
        f"(~{result['vertices_mean']:.0f} vertices), median of {result['repeats']} runs, {result['date']}, {result['machine']}; "
        f"load average before/after: {result['load_average_1_5_15min']['before'][0]:.2f}/"
        f"{result['load_average_1_5_15min']['after'][0]:.2f}",
        "",
        "| method | wall per shape | speed-up vs baseline (wall) | speed-up (CPU time) | mean relative error vs exact | mean abs. error x100 |",
        "|---|---|---|---|---|---|",
    ]
    for name in ("baseline", "baseline_shortest_path", *METHODS[1:]):
        wall = total[name]["wall"] / n
        if name == "baseline_shortest_path":
            lines.append(f"| {LABELS[name]} | {wall:.2f} s | | | | |")
            continue
        err = result["error_vs_exact"][name]
        lines.append(
            f"| {LABELS[name]} | {wall:.2f} s | {result['speedup_vs_baseline_wall'][name]:.2f}x | "
            f"{result['speedup_vs_baseline_cpu'][name]:.2f}x | {100 * err['mean_relative']:.2f} % | {err['mean_absolute_x100']:.3f} |"
        )
    max_diff = max(r["max_abs_difference_baseline_vs_geofeat_dijkstra"] for r in result["per_shape"])
    lines += [
        "",
        f"Reference: {result['reference']}. Largest difference between the baseline's and geofeat's Dijkstra "
        f"rows: {max_diff:.1e} (normalised units; the baseline works on float32 vertices).",
        f"Target (geofeat Dijkstra >= 5x faster than the baseline at no worse accuracy): "
        f"{'met' if result['target_met'] else 'NOT met'}.",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
