"""DiffusionNet's operators of a point cloud: geofeat against the reference code, stage by stage.

geofeat side: `geofeat.adapters.blocks.operators.surface_operators` with
``construction="diffusionnet"`` on a point cloud (the point-cloud Laplacian, the normals
of `neighborhood_normals`, the gradient fit over the 30 nearest points) and, for the
Laplacian itself, `geofeat.geometry.laplacian.laplacian`. Reference side: ``compute_operators``
of nmwsharp/diffusion-net (``src/diffusion_net/geometry.py``, its point-cloud path), run by
`benchmarks/official/diffusion_net_harness.py` in the reference's own environment
(``--reference-python``; its docstring says what to install) from your clone
(``--diffusion-net-repo``).

Clouds: the vertices of FAUST_r tr_reg_080 (``--data``), centred and scaled to unit area as
the heads' reference presets see a cloud (`geofeat.adapters.inputs.normalized_mesh`); 1,000
random points on a bumpy sphere; 300 points of a Gaussian blob. Per cloud and stage the
table gives the largest absolute difference, the largest magnitude of the reference's
values and their ratio:

* mass, Laplacian (stiffness), eigenvalues (also with the reference's shift removed: it
  solves ``(L + 1e-8 I) phi = lambda M phi``, which raises each eigenvalue by about
  ``1e-8 |phi|^2``);
* eigenvectors, compared as eigenspaces: eigenvalues closer than `CLUSTER_GAP` (relative)
  form one space, and the row gives the sine of the largest principal angle between ours
  and the reference's over all spaces (signs, and bases inside a repeated eigenvalue, are
  arbitrary); the last space is left out, since it may go on past the k computed. A
  second row solves the reference's shifted problem with our solver: what remains of the
  first row is the shift;
* normals, up to sign (the reference keeps the sign of its SVD; the note gives the share
  of points where ours has the same one), tangent frames (``Y = n x X`` follows the
  normal's sign), gradient X and gradient Y (row ``i`` of Y times the sign of normal ``i``).

    python -m benchmarks.parity.diffusion_net_cloud --reference-python DN_VENV/bin/python \\
        --diffusion-net-repo PATH/TO/diffusion-net --data /data [--record tests/data]

``--record DIR`` also writes ``DIR/diffusion_net_cloud_reference.npz``, the reference's
operators of a 200-point cloud in small form, which
``tests/adapters/blocks/test_diffusion_net_cloud_reference.py`` compares with geofeat without
the reference installed (``tests/data/README.md`` describes the file).
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, write_results
from benchmarks.parity.common import Stage, markdown
from benchmarks.parity.shot import bumpy_cloud
from geofeat.adapters.blocks.operators import SurfaceOperators, surface_operators
from geofeat.adapters.inputs import normalized_mesh
from geofeat.geometry.laplacian import laplacian
from geofeat.geometry.spectral import clear_basis_cache, solve_eigenpairs

#: The harness the reference's environment runs (it imports diffusion_net, nothing of geofeat).
HARNESS = Path(__file__).resolve().parents[1] / "official" / "diffusion_net_harness.py"
#: Eigenpairs compared (DiffusionNet's default ``k_eig``), and for the small Gaussian blob.
K_EIG = 128
K_EIG_SMALL = 32
#: Eigenvalues closer than this (relative to the larger) span one eigenspace in the comparison.
CLUSTER_GAP = 1e-3
#: The identity shift of the reference's eigensolve, ``(L + REFERENCE_SHIFT I)``.
REFERENCE_SHIFT = 1e-8
#: The recorded cloud of the CI test: points, eigenpairs, every RECORD_ROW_STEP-th gradient row.
RECORD_POINTS = 200
RECORD_K = 16
RECORD_ROW_STEP = 20
RECORD_FILE = "diffusion_net_cloud_reference.npz"


def clouds(data: Path) -> dict[str, tuple[geofeat.Mesh, int]]:
    """The compared clouds with their number of eigenpairs."""
    faust = geofeat.load_mesh(data / "FAUST_r" / "off" / "tr_reg_080.off")
    faust_cloud = normalized_mesh(geofeat.Mesh(faust.verts, name="tr_reg_080-cloud"), "unit_area")
    blob = np.random.default_rng(0).standard_normal((300, 3))
    return {
        "FAUST_r tr_reg_080 vertices, unit area": (faust_cloud, K_EIG),
        "bumpy sphere, 1,000 random points": (geofeat.Mesh(bumpy_cloud(1000), name="bumpy1000"), K_EIG),
        "Gaussian blob, 300 random points": (geofeat.Mesh(blob, name="blob300"), K_EIG_SMALL),
    }


def reference(
    python: str, repo: str, harness: str, verts: np.ndarray, k: int, work: Path, faces: np.ndarray | None = None
) -> dict:
    """The reference's operators of a cloud, or of a mesh with ``faces`` (arrays named as the harness writes them; sparse matrices as scipy CSR)."""
    source, target = work / "in.npz", work / "out.npz"
    extra = {} if faces is None else {"faces": np.asarray(faces, dtype=np.int64)}
    np.savez(source, verts=np.asarray(verts, dtype=np.float64), k_eig=k, **extra)
    subprocess.run([python, harness, repo, str(source), str(target)], check=True, capture_output=True, text=True)
    n = len(verts)
    with np.load(target) as out:
        result = {name: out[name] for name in ("frames", "mass", "evals", "evecs")}
        names = ("L", "gradX", "gradY") + (("L_exact",) if "L_exact_data" in out else ())
        for name in names:
            coo = (out[f"{name}_data"], (out[f"{name}_row"], out[f"{name}_col"]))
            result[name] = sp.csr_matrix(coo, shape=(n, n))
        result["wall_time"] = float(out["wall_time"])
    return result


def ours(mesh: geofeat.Mesh, k: int) -> tuple[SurfaceOperators, sp.csr_matrix, float]:
    """geofeat's operators (with empty caches), its Laplacian's stiffness, and the wall time of the operators."""
    clear_basis_cache()
    start = time.perf_counter()
    ops = surface_operators(mesh, k, laplacian_kind="robust", construction="diffusionnet", cache=False)
    seconds = time.perf_counter() - start
    return ops, laplacian(mesh, "robust").stiffness, seconds


def as_scipy(matrix) -> sp.csr_matrix:
    """A torch sparse COO matrix as scipy CSR float64."""
    coalesced = matrix.coalesce()
    rows, cols = coalesced.indices().numpy()
    return sp.csr_matrix((coalesced.values().double().numpy(), (rows, cols)), shape=tuple(coalesced.shape))


def sparse_stage(stage: str, ours_matrix: sp.spmatrix, theirs: sp.spmatrix, note: str = "") -> Stage:
    """`Stage` of two sparse matrices (every entry, structural zeros included)."""
    diff = abs(sp.csr_matrix(ours_matrix) - sp.csr_matrix(theirs))
    return Stage(stage, float(diff.max()) if diff.nnz else 0.0, float(abs(theirs).max()), note)


def dense_stage(stage: str, ours_array: np.ndarray, theirs: np.ndarray, note: str = "") -> Stage:
    """`Stage` of two dense arrays of the same shape (compared in float64)."""
    a, b = np.asarray(ours_array, dtype=np.float64), np.asarray(theirs, dtype=np.float64)
    return Stage(stage, float(np.abs(a - b).max()), float(np.abs(b).max()), note)


def eigenspaces(evals: np.ndarray, gap: float = CLUSTER_GAP) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of ascending eigenvalues closer than ``gap`` (relative to the larger)."""
    spaces, start = [], 0
    for i in range(1, len(evals) + 1):
        if i == len(evals) or evals[i] - evals[i - 1] > gap * max(abs(evals[i]), 1e-12):
            spaces.append((start, i))
            start = i
    return spaces


def own_scale_note(ours_evals: np.ndarray, theirs: np.ndarray) -> str:
    """The largest difference relative to the eigenvalue itself (the first, zero eigenvalue left out)."""
    relative = np.abs(ours_evals[1:] - theirs[1:]) / np.abs(theirs[1:])
    return f"relative to each eigenvalue: at most {relative.max():.2e} (index {int(relative.argmax()) + 1})"


def shifted_evecs(stiffness: sp.spmatrix, mass: np.ndarray, k: int) -> np.ndarray:
    """Our eigensolver on the reference's shifted problem ``(L + REFERENCE_SHIFT I) phi = lambda M phi``, (V, k)."""
    shifted = stiffness + REFERENCE_SHIFT * sp.identity(stiffness.shape[0])
    return solve_eigenpairs(shifted, mass, k, progress=False)[1]


def eigenspace_stage(ours_evecs: np.ndarray, theirs: np.ndarray, evals: np.ndarray, mass: np.ndarray, what: str = "") -> Stage:
    """Largest sine of a principal angle between our and the reference's eigenspaces (mass inner product)."""
    spaces = eigenspaces(evals)[:-1]
    worst, where = 0.0, (0, 0)
    for start, stop in spaces:
        overlap = ours_evecs[:, start:stop].T @ (mass[:, None] * theirs[:, start:stop])
        smallest = float(np.linalg.svd(overlap, compute_uv=False).min())
        sine = float(np.sqrt(max(0.0, 1.0 - min(smallest, 1.0) ** 2)))
        if sine >= worst:
            worst, where = sine, (start, stop)
    repeated = sum(stop - start > 1 for start, stop in spaces)
    last = len(evals) - (spaces[-1][1] if spaces else 0)
    note = (
        f"{len(spaces)} spaces ({repeated} of several eigenvalues), worst {where[0]}..{where[1] - 1}; "
        f"last {last} eigenvector(s) left out"
    )
    stage = f"eigenvectors 0..{len(evals) - last - 1}{', ' + what if what else ''}: sine of the largest angle between eigenspaces"
    return Stage(stage, worst, 1.0, note)


def compare(mesh: geofeat.Mesh, k: int, ref: dict) -> tuple[list[Stage], dict]:
    """Every stage of one cloud, and its figures for the JSON record."""
    ops, stiffness, seconds = ours(mesh, k)
    normals, ref_normals = ops.frames[:, 2].double().numpy(), ref["frames"][:, 2]
    sign = np.where(np.einsum("vd,vd->v", normals, ref_normals) < 0, -1.0, 1.0)
    evals, evecs = ops.evals.double().numpy(), ops.evecs.double().numpy()
    shift = REFERENCE_SHIFT * np.square(ref["evecs"]).sum(axis=0)
    rows = [
        dense_stage("mass", ops.mass.numpy(), ref["mass"], "ours in float32, as the heads use it"),
        sparse_stage("Laplacian L (stiffness)", stiffness, ref["L"], "the reference's values pass through float32"),
        dense_stage("eigenvalues", evals, ref["evals"], own_scale_note(evals, ref["evals"])),
        dense_stage(
            "eigenvalues, the reference's shift 1e-8 |phi|^2 removed",
            evals,
            ref["evals"] - shift,
            own_scale_note(evals, ref["evals"] - shift),
        ),
        eigenspace_stage(evecs, ref["evecs"], ref["evals"], ref["mass"]),
        eigenspace_stage(
            shifted_evecs(stiffness, ref["mass"], k), ref["evecs"], ref["evals"], ref["mass"], "ours solving (L + 1e-8 I)"
        ),
        dense_stage("normals, up to sign", normals, sign[:, None] * ref_normals, f"same sign at {np.mean(sign > 0):.2%}"),
        dense_stage("tangent frames: X", ops.frames[:, 0].numpy(), ref["frames"][:, 0]),
        dense_stage("tangent frames: Y (the normal's sign)", ops.frames[:, 1].numpy(), sign[:, None] * ref["frames"][:, 1]),
        sparse_stage("gradient X", as_scipy(ops.grad_x), ref["gradX"]),
        sparse_stage("gradient Y (row i times the sign of normal i)", as_scipy(ops.grad_y), sp.diags(sign) @ ref["gradY"]),
    ]
    figures = {
        "points": mesh.n_vertices,
        "k_eig": k,
        "normals_same_sign": float(np.mean(sign > 0)),
        "seconds_ours": seconds,
        "seconds_reference": ref["wall_time"],
        "stages": [
            {"stage": r.stage, "max_abs": r.max_abs, "scale": r.scale, "relative": r.relative, "note": r.note} for r in rows
        ],
    }
    return rows, figures


def record_cloud() -> geofeat.Mesh:
    """The 200-point cloud of the CI test: random points on a bumpy sphere (seed 1)."""
    return geofeat.Mesh(bumpy_cloud(RECORD_POINTS, seed=1), name="bumpy200")


def probe_functions(verts: np.ndarray) -> np.ndarray:
    """Per-point functions the recorded matrices are applied to, shape (V, 4): x, y z, and two smooth waves."""
    x, y, z = verts.T
    return np.stack((x, y * z, np.sin(3 * x) * np.cos(2 * y), np.cos(4 * z + y)), axis=1)


def record_reference(folder: Path, python: str, repo: str, harness: str, work: Path) -> Path:
    """Write `RECORD_FILE`: the reference's operators of `record_cloud` in small form; returns the file."""
    cloud = record_cloud()
    ref = reference(python, repo, harness, cloud.verts, RECORD_K, work)
    probes = probe_functions(cloud.verts)
    rows = np.arange(0, cloud.n_vertices, RECORD_ROW_STEP)
    arrays = {
        "verts": cloud.verts,
        "k_eig": np.array(RECORD_K),
        "mass": ref["mass"],
        "evals": ref["evals"],
        "evecs": ref["evecs"].astype(np.float32),
        "normals": ref["frames"][:, 2].astype(np.float32),
        "frames_x": ref["frames"][:, 0].astype(np.float32),
        "probes": probes,
        "L_probes": (ref["L"] @ probes).astype(np.float32),
        "rows": rows,
    }
    for name in ("gradX", "gradY"):
        arrays[f"{name}_probes"] = (ref[name] @ probes).astype(np.float32)
        arrays[f"{name}_rows"] = ref[name][rows].toarray().astype(np.float32)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / RECORD_FILE
    np.savez_compressed(path, **arrays)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--reference-python", required=True, help="python of the reference's environment")
    parser.add_argument("--diffusion-net-repo", required=True, help="your clone of nmwsharp/diffusion-net")
    parser.add_argument("--harness", default=str(HARNESS), help="the harness the reference's python runs (default: ours)")
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--record", help="also write the CI test's reference file to this folder")
    parser.add_argument("--out", default=str(RESULTS / "parity" / "diffusion_net_cloud"))
    args = parser.parse_args()
    repo = str(Path(args.diffusion_net_repo).expanduser().resolve())
    sections, records = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for name, (mesh, k) in clouds(data_folder(args.data)).items():
            ref = reference(args.reference_python, repo, args.harness, mesh.verts, k, work)
            rows, records[name] = compare(mesh, k, ref)
            f = records[name]
            title = (
                f"{name}: {f['points']} points, k = {k}; {f['seconds_ours']:.2f} s ours, {f['seconds_reference']:.2f} s reference"
            )
            sections.append(markdown(rows, title))
        if args.record:
            record_reference(Path(args.record), args.reference_python, repo, args.harness, work)
    commit, day = subprocess.run(
        ["git", "-C", repo, "log", "-1", "--format=%H %cs"], capture_output=True, text=True
    ).stdout.split() or ("", "")
    header = (
        f"Run {datetime.date.today().isoformat()} on {machine()}; reference: nmwsharp/diffusion-net as of "
        f"{day or '(date unknown)'} (the commit is in the .json), `compute_operators` on the CPU. Times: the "
        "operators of one cloud (Laplacian, eigenpairs, normals, gradients), each side in its own process.\n"
    )
    result = {"date": datetime.date.today().isoformat(), "machine": machine(), "reference_commit": commit, "clouds": records}
    write_results(args.out, result, "\n".join([header, *sections]))


if __name__ == "__main__":
    main()
