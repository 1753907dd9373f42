"""The learned heads' per-shape preprocessing on a point cloud, against the same shape as a mesh.

For each of N FAUST_r test shapes (5,000 vertices each, from tr_reg_080), the mesh and its
vertices as a point cloud go through what a learned head computes once per shape before its
first training step or match, with every cache empty (the feature cache in a fresh
temporary folder for every run; the spectral-basis, operator and cloud-area caches in memory
cleared):

* ``normalise``: the presets' unit-area transform (a cloud's area: its Laplacian's mass);
* ``features``: the input features (WKS, or the coordinates);
* ``eigenpairs``: the Laplacian and its eigenpairs (`geofeat.geometry.spectral.spectral_basis`);
* ``normals+gradients``: the rest of DiffusionNet's operators (`surface_operators` on the
  basis just computed: normals, frames, gradient matrices, float32 tensors).

Head settings: ULRSSM with geofeat's defaults (robust Laplacian, geofeat's operators with
200 eigenpairs, WKS input from 128, no normalisation) and the ``reference`` presets of ULRSSM
(cotangent Laplacian on meshes, ULRSSM's operators with 200 eigenpairs, WKS from 128), DPFM and
EchoMatch (DiffusionNet's and ULRSSM's operators with 128 eigenpairs, xyz input). On a cloud every preset uses the point-cloud Laplacian. Each figure is the
fastest of the repeats (the run least slowed by other work on the machine), averaged over
the shapes.

Usage::

    python -m benchmarks.speed.cloud_preprocessing --data ../shared/data --shapes 3 --repeats 3
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import tempfile
import time
from pathlib import Path

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, faust_test_shapes, machine, write_results
from geofeat.adapters import inputs as head_inputs
from geofeat.adapters.blocks.operators import clear_operator_cache
from geofeat.adapters.heads import make_head
from geofeat.geometry.spectral import clear_basis_cache, spectral_basis
from geofeat.storage.cache_folder import set_cache_dir

#: label -> (head, preset)
CONFIGURATIONS = {
    "ULRSSM, geofeat defaults": ("ulrssm", None),
    "ULRSSM reference": ("ulrssm", "reference"),
    "DPFM reference": ("dpfm", "reference"),
    "EchoMatch reference": ("echomatch", "reference"),
}
STAGES = ("normalise", "features", "eigenpairs", "normals+gradients")


def clear_caches() -> None:
    """Empty every in-memory cache a head's preprocessing fills."""
    clear_basis_cache()
    clear_operator_cache()
    head_inputs._cloud_areas.clear()


def preprocess(head_name: str, preset: str | None, mesh: geofeat.Mesh) -> dict[str, float]:
    """Seconds of each stage of one shape's preprocessing by a fresh head, every cache empty."""
    clear_caches()
    head = make_head(head_name, preset=preset, progress=False)
    c = head.config
    seconds = {}
    with tempfile.TemporaryDirectory() as features_cache:
        set_cache_dir(Path(features_cache))
        try:
            start = time.perf_counter()
            prepared = head_inputs.normalized_mesh(mesh, c.mesh_normalization)
            seconds["normalise"] = time.perf_counter() - start
            start = time.perf_counter()
            head.features(prepared)
            seconds["features"] = time.perf_counter() - start
        finally:
            set_cache_dir(None)
    start = time.perf_counter()
    spectral_basis(prepared, c.n_eig, head_inputs.laplacian_for(prepared, c.laplacian))
    seconds["eigenpairs"] = time.perf_counter() - start
    start = time.perf_counter()
    head.operators(prepared)
    seconds["normals+gradients"] = time.perf_counter() - start
    return seconds


def measure(shapes: list[geofeat.Mesh], repeats: int) -> dict[str, dict[str, dict[str, float]]]:
    """``{configuration: {"mesh" | "cloud": {stage: seconds}}}``: per shape the fastest run, averaged over the shapes."""
    results: dict[str, dict[str, dict[str, float]]] = {}
    for label, (head_name, preset) in CONFIGURATIONS.items():
        results[label] = {}
        for kind in ("mesh", "cloud"):
            per_shape = []
            for mesh in shapes:
                shape = mesh if kind == "mesh" else geofeat.Mesh(mesh.verts, name=f"{mesh.name}-cloud")
                runs = [preprocess(head_name, preset, shape) for _ in range(repeats)]
                per_shape.append(min(runs, key=lambda run: sum(run.values())))
            results[label][kind] = {stage: statistics.mean(s[stage] for s in per_shape) for stage in STAGES}
            results[label][kind]["total"] = sum(results[label][kind][stage] for stage in STAGES)
    return results


def table(results: dict, n_shapes: int, repeats: int) -> str:
    """Markdown: seconds per stage, mesh / cloud, and the cloud's total against the mesh's."""
    lines = [
        "| head settings | " + " | ".join(f"{s}, mesh / cloud" for s in STAGES) + " | total, mesh / cloud | cloud / mesh |",
        "|---|" + "---|" * (len(STAGES) + 2),
    ]
    for label, kinds in results.items():
        mesh, cloud = kinds["mesh"], kinds["cloud"]
        cells = [f"{mesh[s]:.2f} / {cloud[s]:.2f}" for s in (*STAGES, "total")]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {cloud['total'] / mesh['total']:.2f}x |")
    lines += [
        "",
        f"Seconds per shape: the fastest of {repeats} runs with empty caches, averaged over {n_shapes} FAUST_r shapes "
        f"of 5,000 vertices (from tr_reg_080), each as a mesh and as its vertices' point cloud. "
        f"`python -m benchmarks.speed.cloud_preprocessing`; {datetime.date.today().isoformat()}, {machine()}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--shapes", type=int, default=3, help="number of FAUST_r shapes (from tr_reg_080)")
    parser.add_argument("--repeats", type=int, default=3, help="runs per shape and setting; the fastest counts")
    parser.add_argument("--out", default=str(RESULTS / "speed_cloud_preprocessing"), help="writes OUT.json and OUT.md")
    args = parser.parse_args(argv)
    shapes = faust_test_shapes(args.data, args.shapes)
    results = measure(shapes, args.repeats)
    record = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "shapes": [m.name for m in shapes],
        "repeats": args.repeats,
        "configurations": {label: {"head": h, "preset": p} for label, (h, p) in CONFIGURATIONS.items()},
        "seconds": results,
    }
    write_results(args.out, record, table(results, len(shapes), args.repeats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
