"""HKS and WKS from mesh to features: geofeat against pyFM, side by side in one run.

For each of N FAUST_r shapes, and for each repeat, the two libraries run one after the
other on the same vertex and face arrays already in memory:

* pyFM: ``TriMesh(verts, faces).process(k)`` then ``mesh_WKS`` and ``mesh_HKS``;
* geofeat: ``Mesh(verts, faces)`` then ``compute(..., "wks")`` and ``compute(..., "hks")``
  with the feature cache off and the in-memory spectral cache cleared before each shape
  (the two calls share one eigen-solve, as pyFM's share one ``process``).

geofeat runs twice: with the cotangent Laplacian (the operator pyFM uses; its values are
compared with pyFM's) and with its default robust Laplacian. The cache-hit time is the
median of 5 consecutive ``compute`` calls that find their entry in an HDF5 cache. Median over repeats, summed over shapes.
Last, WKS for the whole collection: pyFM in a loop against ``geofeat.compute_many`` with
two worker processes (this uses both cores; the start of the workers is counted).

Usage::

    python -m benchmarks.speed.spectral --data ../shared/data --shapes 10 --k 128
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import sys
import tempfile
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, faust_test_shapes, machine, write_results
from benchmarks.parity.diffusion_net_cloud import eigenspace_stage
from geofeat.geometry import laplacian, spectral
from geofeat.geometry.spectral import clear_basis_cache, solve_eigenpairs


def run_pyfm(verts, faces, k, n_wks, n_hks):
    from pyFM.mesh import TriMesh
    from pyFM.signatures import mesh_HKS, mesh_WKS

    mesh = TriMesh(verts, faces).process(k=k)
    return mesh_WKS(mesh, n_wks), mesh_HKS(mesh, n_hks)


def run_pyfm_wks(verts, faces, k, n_wks):
    from pyFM.mesh import TriMesh
    from pyFM.signatures import mesh_WKS

    return mesh_WKS(TriMesh(verts, faces).process(k=k), n_wks)


def run_geofeat(verts, faces, k, n_wks, n_hks, laplacian, normalize=True):
    clear_basis_cache()
    mesh = geofeat.Mesh(verts, faces)
    wks = geofeat.compute(mesh, "wks", cache=False, n_eig=k, n_descr=n_wks, laplacian=laplacian, normalize=normalize)
    hks = geofeat.compute(mesh, "hks", cache=False, n_eig=k, n_descr=n_hks, laplacian=laplacian, normalize=normalize)
    return wks, hks


def timed(fn, *args, **kwargs):
    start = time.perf_counter()
    out = fn(*args, **kwargs)
    return time.perf_counter() - start, out


def relative_error(ours: np.ndarray, ref: np.ndarray) -> float:
    """Largest absolute difference divided by the largest reference magnitude."""
    return float(np.abs(ours.astype(np.float64) - ref).max() / np.abs(ref).max())


def eigsh_agreement(mesh: geofeat.Mesh, k: int) -> tuple[float, float]:
    """Our eigenpairs of the robust Laplacian against scipy's ``eigsh`` (generalised problem, default tolerance).

    Returns the largest eigenvalue difference relative to the eigenvalue (the zero one left
    out) and the largest sine between eigenspaces (eigenvalues closer than 1e-3 form one).
    """
    lap = laplacian(mesh, kind="robust")
    stiffness = sp.csc_matrix(lap.stiffness)
    evals, evecs = solve_eigenpairs(stiffness, lap.mass, k, progress=False)
    ref_evals, ref_evecs = sla.eigsh(stiffness, k=k, M=sp.diags(lap.mass), sigma=-1e-6 * stiffness.diagonal().sum())
    relative = np.abs(evals[1:] - ref_evals[1:]) / np.abs(ref_evals[1:])
    return float(relative.max()), eigenspace_stage(evecs, ref_evecs, ref_evals, lap.mass).max_abs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--shapes", type=int, default=10, help="number of FAUST_r shapes (from tr_reg_080)")
    parser.add_argument("--k", type=int, default=128, help="eigenpairs, the same for both libraries")
    parser.add_argument("--n-wks", type=int, default=128)
    parser.add_argument("--n-hks", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(RESULTS / "speed_spectral"), help="writes OUT.json and OUT.md")
    args = parser.parse_args(argv)

    shapes = faust_test_shapes(args.data, args.shapes)

    times = {"pyfm": [], "geofeat_cotan": [], "geofeat_robust": [], "cache_hit": [], "compute_wks": []}
    errors_wks, errors_hks, eigsh_errors = [], [], []
    with tempfile.TemporaryDirectory(prefix="geofeat-bench-") as tmp:
        store = geofeat.FeatureCache(tmp)
        for mesh in shapes:
            verts, faces = np.array(mesh.verts), np.array(mesh.faces)
            per = {key: [] for key in times}
            for _ in range(args.repeats):
                t, (w_ref, h_ref) = timed(run_pyfm, verts, faces, args.k, args.n_wks, args.n_hks)
                per["pyfm"].append(t)
                t, _ = timed(run_geofeat, verts, faces, args.k, args.n_wks, args.n_hks, "cotan")
                per["geofeat_cotan"].append(t)
                t, _ = timed(run_geofeat, verts, faces, args.k, args.n_wks, args.n_hks, "robust")
                per["geofeat_robust"].append(t)
                clear_basis_cache()
                t, _ = timed(geofeat.compute, mesh, "wks", cache=False, n_eig=args.k, n_descr=args.n_wks)
                per["compute_wks"].append(t)
                geofeat.compute(mesh, "wks", cache=store, n_eig=args.k, n_descr=args.n_wks)
                hits = [timed(geofeat.compute, mesh, "wks", cache=store, n_eig=args.k, n_descr=args.n_wks)[0] for _ in range(5)]
                per["cache_hit"].append(statistics.median(hits))
            for key, values in per.items():
                times[key].append(statistics.median(values))
            w_ours, h_ours = run_geofeat(verts, faces, args.k, args.n_wks, args.n_hks, "cotan", normalize=False)
            errors_wks.append(relative_error(w_ours, w_ref))
            errors_hks.append(relative_error(h_ours, h_ref))
            eigsh_errors.append(eigsh_agreement(mesh, args.k))
            print(
                f"{mesh.name}: pyFM {per['pyfm'][0]:.3f}s, geofeat cotan {per['geofeat_cotan'][0]:.3f}s, "
                f"robust {per['geofeat_robust'][0]:.3f}s, cache hit {per['cache_hit'][0] * 1e3:.2f}ms",
                flush=True,
            )

    # A whole collection, WKS only: pyFM in a loop against compute_many in two worker processes.
    arrays = [(np.array(m.verts), np.array(m.faces)) for m in shapes]
    batch_pyfm, batch_geofeat = [], []
    for _ in range(args.repeats):
        t, _ = timed(lambda: [run_pyfm_wks(v, f, args.k, args.n_wks) for v, f in arrays])
        batch_pyfm.append(t)
        t, _ = timed(geofeat.compute_many, shapes, "wks", cache=False, n_jobs=2, progress=False, n_eig=args.k, n_descr=args.n_wks)
        batch_geofeat.append(t)
    total = {key: sum(values) for key, values in times.items()}
    total["batch_pyfm"] = statistics.median(batch_pyfm)
    total["batch_geofeat_2_jobs"] = statistics.median(batch_geofeat)
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "geofeat": geofeat.__version__,
        "shapes": [m.name for m in shapes],
        "vertices_mean": float(np.mean([m.n_vertices for m in shapes])),
        "k": args.k,
        "n_wks": args.n_wks,
        "n_hks": args.n_hks,
        "repeats": args.repeats,
        "seconds_total": total,
        "speedup_cotan": total["pyfm"] / total["geofeat_cotan"],
        "speedup_robust": total["pyfm"] / total["geofeat_robust"],
        "cache_hit_speedup": total["compute_wks"] / total["cache_hit"],
        "batch_speedup_2_jobs": total["batch_pyfm"] / total["batch_geofeat_2_jobs"],
        "max_relative_error_wks": max(errors_wks),
        "max_relative_error_hks": max(errors_hks),
        "eigsh_eigenvalues_relative": max(e for e, _ in eigsh_errors),
        "eigsh_eigenspace_sine": max(s for _, s in eigsh_errors),
        "cholmod": spectral.cholmod_available(),
    }
    n = len(shapes)
    table = [
        f"HKS ({args.n_hks}) + WKS ({args.n_wks}) from mesh to features, k = {args.k} eigenpairs, "
        f"{n} FAUST_r shapes (~{result['vertices_mean']:.0f} vertices), median of {args.repeats} runs, "
        f"{result['date']}, {result['machine']}; eigensolver factorisation: "
        f"{'CHOLMOD' if result['cholmod'] else 'SuperLU (scikit-sparse not installed)'}",
        "",
        "| pipeline | total for the shapes | per shape | speed-up vs pyFM |",
        "|---|---|---|---|",
        f"| pyFM `TriMesh.process` + `mesh_WKS` + `mesh_HKS` | {total['pyfm']:.2f} s | {total['pyfm'] / n * 1e3:.0f} ms | 1.00x |",
        f"| geofeat, cotan Laplacian (pyFM's operator) | {total['geofeat_cotan']:.2f} s | "
        f"{total['geofeat_cotan'] / n * 1e3:.0f} ms | {result['speedup_cotan']:.2f}x |",
        f"| geofeat, robust Laplacian (default) | {total['geofeat_robust']:.2f} s | "
        f"{total['geofeat_robust'] / n * 1e3:.0f} ms | {result['speedup_robust']:.2f}x |",
        f"| geofeat WKS, cache hit (HDF5) | {total['cache_hit'] * 1e3:.1f} ms | {total['cache_hit'] / n * 1e3:.2f} ms | "
        f"{result['cache_hit_speedup']:.0f}x faster than computing WKS |",
        f"| WKS for all {n} shapes: pyFM loop vs `compute_many(n_jobs=2)` (both cores, process start included) | "
        f"{total['batch_pyfm']:.2f} s vs {total['batch_geofeat_2_jobs']:.2f} s | | {result['batch_speedup_2_jobs']:.2f}x |",
        "",
        f"Agreement with pyFM (cotan, channels not normalised): largest difference / largest value = "
        f"{result['max_relative_error_wks']:.1e} (WKS), {result['max_relative_error_hks']:.1e} (HKS). "
        f"Eigenpairs against scipy's `eigsh` (robust Laplacian, every shape): eigenvalues within "
        f"{result['eigsh_eigenvalues_relative']:.1e} of each other (relative), eigenspaces within a sine of "
        f"{result['eigsh_eigenspace_sine']:.1e}.",
    ]
    write_results(args.out, result, "\n".join(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
