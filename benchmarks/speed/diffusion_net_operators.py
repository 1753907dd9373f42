"""DiffusionNet's per-shape operators: geofeat against the reference code, side by side in one run.

What a DiffusionNet head (DPFM, ULRSSM, EchoMatch) computes for every new shape before its
first training step: the mass, 128 Laplacian eigenpairs and the two gradient matrices. For
each shape, in this order:

* the reference: ``compute_operators`` of nmwsharp/diffusion-net (cotan Laplacian, scipy's
  ``eigsh``, its per-vertex gradient fit), run by `benchmarks/official/diffusion_net_harness.py`
  in the reference's own environment; its time is that of the call alone;
* geofeat: `surface_operators` with the reference's construction (``laplacian_kind="cotan"``,
  ``construction="diffusionnet"``), the in-memory caches emptied first, twice: with the
  eigensolver's defaults (CHOLMOD's factorisation where scikit-sparse is installed, its
  own Lanczos iteration from 2,000 vertices) and with ARPACK alone, SuperLU and ``2k + 1``
  Lanczos vectors.

The shapes are those the heads see: FAUST_r test shapes and the PSMAL sample, each scaled to
unit area (`geofeat.adapters.inputs.normalized_mesh`), so both sides get the same arrays.
Agreement per shape: mass, eigenvalues (the reference's shift ``1e-8 |phi|^2`` removed),
eigenspaces (eigenvalues closer than 1e-3 form one space) and the gradient matrices; the
Laplacian against the float64 one the reference's ``eigsh`` saw (the harness returns it),
and our eigensolver on exactly the reference's problem (that Laplacian plus ``1e-8 I``, its
mass), which isolates the solver from the Laplacian's construction.

    python -m benchmarks.speed.diffusion_net_operators --reference-python DN_VENV/bin/python \\
        --diffusion-net-repo PATH/TO/diffusion-net --data /data
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, write_results
from benchmarks.parity.diffusion_net_cloud import (
    HARNESS,
    REFERENCE_SHIFT,
    as_scipy,
    dense_stage,
    eigenspace_stage,
    reference,
    sparse_stage,
)
from geofeat.adapters.blocks.operators import clear_operator_cache, surface_operators
from geofeat.adapters.inputs import normalized_mesh
from geofeat.geometry import spectral
from geofeat.geometry.laplacian import laplacian
from geofeat.geometry.spectral import clear_basis_cache, solve_eigenpairs

K_EIG = 128
#: A gradient row counts as different where it is this far from the reference's (relative to the largest entry).
GRADIENT_ROW_TOLERANCE = 1e-3
#: The eigensolver settings timed: the defaults, and ARPACK alone with SuperLU and its usual ``2k + 1`` vectors.
SETTINGS = {
    "defaults": {
        "FACTORIZATION": "auto",
        "SUBSPACE_EXTRA": spectral.SUBSPACE_EXTRA,
        "LANCZOS_FROM_VERTICES": spectral.LANCZOS_FROM_VERTICES,
    },
    "ARPACK, SuperLU, 2k+1 vectors": {"FACTORIZATION": "superlu", "SUBSPACE_EXTRA": K_EIG + 1, "LANCZOS_FROM_VERTICES": 10**9},
}


def shapes(data: Path, n_faust: int, n_psmal: int) -> list[tuple[str, geofeat.Mesh]]:
    """``(dataset, mesh)`` of the first FAUST_r test shapes and PSMAL sample shapes, at unit area."""
    faust = [data / "FAUST_r" / "off" / f"tr_reg_{i:03d}.off" for i in range(80, 80 + n_faust)]
    psmal = sorted((data / "PSMAL_sample" / "PARTIALSMAL" / "train" / "shapes").glob("*.off"))[:n_psmal]
    missing = [p for p in faust if not p.is_file()]
    if missing or len(psmal) < n_psmal:
        raise SystemExit(f"shapes not found under {data} (FAUST_r/off and PSMAL_sample); pass --data")
    named = [("FAUST_r", p) for p in faust] + [("PSMAL", p) for p in psmal]
    return [(dataset, normalized_mesh(geofeat.load_mesh(p), "unit_area")) for dataset, p in named]


def ours(mesh: geofeat.Mesh, settings: dict) -> tuple[object, float]:
    """geofeat's operators of ``mesh`` under the eigensolver ``settings``, from empty caches, and their seconds."""
    saved = {name: getattr(spectral, name) for name in settings}
    for name, value in settings.items():
        setattr(spectral, name, value)
    try:
        clear_basis_cache()
        clear_operator_cache()
        start = time.perf_counter()
        ops = surface_operators(mesh, K_EIG, laplacian_kind="cotan", construction="diffusionnet", cache=False)
        return ops, time.perf_counter() - start
    finally:
        for name, value in saved.items():
            setattr(spectral, name, value)


def agreement(mesh: geofeat.Mesh, ops, ref: dict) -> dict:
    """Largest differences of one shape's operators, relative to the reference's largest value."""
    evals, evecs = ops.evals.double().numpy(), ops.evecs.double().numpy()
    grads = {"gradX": as_scipy(ops.grad_x), "gradY": as_scipy(ops.grad_y)}
    shift = REFERENCE_SHIFT * np.square(ref["evecs"]).sum(axis=0)
    mass = dense_stage("mass", ops.mass.numpy(), ref["mass"])
    eigenspaces = eigenspace_stage(evecs, ref["evecs"], ref["evals"], ref["mass"])
    grad_x, grad_y = (sparse_stage(f"gradient {axis}", grads[f"grad{axis}"], ref[f"grad{axis}"]) for axis in "XY")
    relative_evals = np.abs(evals[1:] - (ref["evals"] - shift)[1:]) / np.abs((ref["evals"] - shift)[1:])
    rows_apart = {}
    for name, ours_matrix in grads.items():
        apart = abs(ours_matrix - ref[name]).max(axis=1).toarray().ravel()
        rows_apart[name] = int((apart > GRADIENT_ROW_TOLERANCE * abs(ref[name]).max()).sum())
    problem = ref["L_exact"] + REFERENCE_SHIFT * sp.identity(mesh.n_vertices)
    solved_evals, solved_evecs = solve_eigenpairs(problem, ref["mass"], len(ref["evals"]), progress=False)
    solved = np.abs(solved_evals[1:] - ref["evals"][1:]) / np.abs(ref["evals"][1:])
    return {
        "solver_eigenvalues_relative_each": float(solved.max()),
        "solver_eigenspace_sine": eigenspace_stage(solved_evecs, ref["evecs"], ref["evals"], ref["mass"]).max_abs,
        "gradient_rows_apart": max(rows_apart.values()),
        "laplacian": float(abs(laplacian(mesh, "cotan").stiffness - ref["L_exact"]).max() / abs(ref["L_exact"]).max()),
        "mass": mass.relative,
        "eigenvalues_relative_each": float(relative_evals.max()),
        "eigenspace_sine": eigenspaces.max_abs,
        "grad_x": grad_x.relative,
        "grad_y": grad_y.relative,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reference-python", required=True, help="python of the reference's environment")
    parser.add_argument("--diffusion-net-repo", required=True, help="your clone of nmwsharp/diffusion-net")
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ and PSMAL_sample/ (default $GEOFEAT_DATA)")
    parser.add_argument("--faust", type=int, default=5, help="FAUST_r test shapes")
    parser.add_argument("--psmal", type=int, default=5, help="PSMAL sample shapes")
    parser.add_argument("--out", default=str(RESULTS / "speed_diffusion_net_operators"))
    args = parser.parse_args(argv)
    rows = []
    meshes = shapes(data_folder(args.data), args.faust, args.psmal)
    ours(meshes[0][1], SETTINGS["defaults"])  # one untimed call: imports and compiled code are loaded once
    with tempfile.TemporaryDirectory() as tmp:
        for dataset, mesh in meshes:
            ref = reference(
                args.reference_python, args.diffusion_net_repo, str(HARNESS), mesh.verts, K_EIG, Path(tmp), mesh.faces
            )
            row = {"dataset": dataset, "shape": mesh.name, "vertices": mesh.n_vertices, "reference": ref["wall_time"]}
            for label, settings in SETTINGS.items():
                ops, seconds = ours(mesh, settings)
                row[label] = seconds
                if label == "defaults":
                    row["agreement"] = agreement(mesh, ops, ref)
            rows.append(row)
            print(row, flush=True)
    record = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "cholmod": spectral.cholmod_available(),
        "rows": rows,
    }
    write_results(args.out, record, table(record))
    return 0


def table(record: dict) -> str:
    """Markdown: per dataset, the median seconds per shape, the ratios and the worst agreement."""
    lines = [
        f"DiffusionNet operators (mass, 128 eigenpairs, gradients) per shape, median over the shapes; "
        f"{record['machine']}, {record['date']}; CHOLMOD {'installed' if record['cholmod'] else 'not installed'}",
        "",
        "| shapes | vertices | reference | geofeat | reference / geofeat | geofeat with ARPACK alone, SuperLU, 2k+1 vectors |",
        "|---|---|---|---|---|---|",
    ]
    for dataset in dict.fromkeys(r["dataset"] for r in record["rows"]):
        rows = [r for r in record["rows"] if r["dataset"] == dataset]
        ref = statistics.median(r["reference"] for r in rows)
        new = statistics.median(r["defaults"] for r in rows)
        old = statistics.median(r["ARPACK, SuperLU, 2k+1 vectors"] for r in rows)
        verts = statistics.median(r["vertices"] for r in rows)
        lines.append(f"| {dataset} ({len(rows)}) | {verts:.0f} | {ref:.2f} s | {new:.2f} s | {ref / new:.2f}x | {old:.2f} s |")
    worst = {key: max(r["agreement"][key] for r in record["rows"]) for key in record["rows"][0]["agreement"]}
    apart = [f"{r['shape']} ({r['agreement']['gradient_rows_apart']} of {r['vertices']})" for r in record["rows"]]
    apart = [a for a, r in zip(apart, record["rows"], strict=True) if r["agreement"]["gradient_rows_apart"]]
    lines += [
        "",
        "Agreement with the reference, worst over the shapes: "
        f"mass {worst['mass']:.1e}, eigenvalues {worst['eigenvalues_relative_each']:.1e} (each relative to itself, "
        f"the reference's 1e-8 shift removed), eigenspaces {worst['eigenspace_sine']:.1e} (sine of the largest angle), "
        f"gradient X {worst['grad_x']:.1e}, gradient Y {worst['grad_y']:.1e} (relative to the largest entry). "
        f"Our cotan Laplacian differs from the reference's (potpourri3d's) by {worst['laplacian']:.1e} of its largest entry, "
        "and the reference adds 1e-8 I to it and 1e-8 of the mean to the mass; "
        "our eigensolver on the reference's own problem (its float64 Laplacian and mass) gives its eigenvalues to "
        f"{worst['solver_eigenvalues_relative_each']:.1e} (relative) and its eigenspaces to a sine of "
        f"{worst['solver_eigenspace_sine']:.1e}. "
        f"Gradient rows more than {GRADIENT_ROW_TOLERANCE:g} apart: "
        + (", ".join(apart) if apart else "none")
        + "; every other row agrees to rounding.",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
