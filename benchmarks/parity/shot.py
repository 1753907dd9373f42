"""geofeat's SHOT against pyshot (the reference DeepShapeMatchingKit calls), shape by shape and parameter set by set.

geofeat side: `geofeat.descriptors.shot.shot_descriptors` with the normals `SHOT` uses
(point clouds: ``cloud_normals="zero"``, as pyshot). Reference side: ``pyshot.get_descriptors``
run by `benchmarks/official/pyshot_harness.py` in pyshot's own environment
(``--reference-python``; pyshot is GPL-3.0 and compiled, so it is built outside this
repository: the harness's docstring says how).

Shapes: FAUST_r tr_reg_080 (``--data``), PSMAL cuts_0_horse_01 (``--data-ext``), a CUTS partial
shape of tr_reg_080 (`geofeat.geometry.partial.make_partial`, seed 0) and the vertices of
tr_reg_081 as a point cloud. Parameter sets: DeepShapeMatchingKit's (`SHOT_RECIPES`) and three
others. Per shape and set the table gives the largest absolute difference per entry, the
same outside the vertices whose frame has a sign tie (as many neighbours on each side of an
axis: pyshot keeps Eigen's arbitrary sign there), the share of vertices differing by more
than 1e-5, the ties, how many tie vertices differ by more than 1e-5 as computed and with the
best of the four signs of X and Z (``flip_axes``: where that is 0, pyshot simply chose the other
sign), the zero rows of each side and both wall times. So that it fits a laptop's width it is
two tables with the shape and the parameter set in each: the differences, then the ties, zero
rows and times; above them, the date and the machine of the run.

    python -m benchmarks.parity.shot --reference-python PYSHOT_VENV/bin/python --data /data --data-ext /data_ext \\
        [--record tests/data]
    python -m benchmarks.parity.shot --render-only     # rewrites OUT.md from OUT.json, runs nothing

``--record DIR`` also writes ``DIR/shot_reference.npz``: pyshot's rows of every 50th vertex of
tr_reg_080 (DeepShapeMatchingKit's parameters and a second set) and of every 10th point of a
642-point bumpy sphere cloud, which ``tests/descriptors/test_shot_reference.py`` compares with
geofeat without pyshot installed.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import geofeat
from benchmarks.common import DEFAULT_DATA, DEFAULT_DATA_EXT, RESULTS, data_folder, machine, rewrite_table, write_results
from geofeat.descriptors.shot import SHOT, SHOT_RECIPES, shot_descriptors
from geofeat.geometry.partial import make_partial

#: Parameter sets compared (pyshot's names); the first is DeepShapeMatchingKit's.
#: The harness pyshot's environment runs (it imports pyshot, nothing of geofeat).
PYSHOT_HARNESS = Path(__file__).resolve().parents[1] / "official" / "pyshot_harness.py"
PARAM_SETS: dict[str, dict] = {
    "dsmk": SHOT_RECIPES["dsmk"],
    "r0.1_b7_16vol": {"radius": 0.1, "min_neighbors": 3, "n_bins": 7, "double_volumes_sectors": False},
    "r0.05_b10_nointerp": {"radius": 0.05, "n_bins": 10, "use_interpolation": False},
    "r0.03_b5_min8_nonorm": {"radius": 0.03, "min_neighbors": 8, "use_normalization": False},
}
#: Entries further apart than this count as a differing vertex.
TOLERANCE = 1e-5
#: Rows recorded for the CI test: every ``RECORD_STEP``-th vertex of tr_reg_080.
RECORD_STEP = 50


def shapes(data: Path, data_ext: Path) -> dict[str, geofeat.Mesh]:
    """The four inputs: FAUST_r, PSMAL, a CUTS partial shape, a point cloud."""
    faust = geofeat.load_mesh(data / "FAUST_r" / "off" / "tr_reg_080.off")
    return {
        "FAUST_r tr_reg_080": faust,
        "PSMAL cuts_0_horse_01": geofeat.load_mesh(
            data_ext / "PSMAL" / "PARTIALSMAL" / "test" / "shapes" / "cuts_0_horse_01.off"
        ),
        "CUTS of tr_reg_080 (seed 0)": make_partial(faust, "cuts", seed=0).mesh,
        "cloud: tr_reg_081 vertices": geofeat.Mesh(geofeat.load_mesh(data / "FAUST_r" / "off" / "tr_reg_081.off").verts),
    }


def reference(python: str, harness: str, mesh: geofeat.Mesh, params: dict, work: Path) -> tuple[np.ndarray, float]:
    """pyshot's descriptors of ``mesh`` (V, L) and its wall time, via the harness."""
    src, out = work / "in.npz", work / "out.npz"
    arrays = {"verts": np.asarray(mesh.verts, dtype=np.float64)}
    if mesh.faces is not None:
        arrays["faces"] = np.asarray(mesh.faces, dtype=np.int64)
    np.savez(src, **arrays)
    subprocess.run([python, harness, str(src), str(out), json.dumps(params)], check=True, capture_output=True, text=True)
    with np.load(out) as result:
        return result["descriptors"], float(result["wall_time"])


def ours(mesh: geofeat.Mesh, params: dict, queries: np.ndarray | None = None, **options) -> tuple[np.ndarray, dict, float]:
    """geofeat's descriptors (pyshot's conventions: zero normals on clouds), the report and the wall time."""
    normals = SHOT(cloud_normals="zero").normals(mesh)
    start = time.perf_counter()
    features, report = shot_descriptors(mesh.verts, normals, queries=queries, **params, **options)
    return features, report, time.perf_counter() - start


def ties_flipped(mesh: geofeat.Mesh, params: dict, theirs: np.ndarray, tie: np.ndarray) -> np.ndarray:
    """Per sign-tie vertex, the smallest largest difference to pyshot's row over the four signs of X and Z, shape (T,)."""
    rows = np.flatnonzero(tie)
    best = np.full(len(rows), np.inf)
    for flip in range(4):
        mine, _, _ = ours(mesh, params, rows, flip_axes=np.full(len(rows), flip))
        best = np.minimum(best, np.abs(mine - theirs[rows]).max(axis=1))
    return best


def compare(mesh: geofeat.Mesh, params: dict, python: str, harness: str, work: Path) -> dict:
    """One row of the table."""
    theirs, t_ref = reference(python, harness, mesh, params, work)
    mine, report, t_ours = ours(mesh, params)
    finite = np.isfinite(theirs).all(axis=1)
    diff = np.where(finite[:, None], np.abs(mine - np.nan_to_num(theirs)), 0.0).max(axis=1)
    tie = report["sign_tie"]
    flipped = ties_flipped(mesh, params, np.nan_to_num(theirs), tie)
    return {
        "vertices": mesh.n_vertices,
        "max_abs": float(diff.max()),
        "max_abs_without_ties": float(diff[~tie].max()) if (~tie).any() else 0.0,
        "max_abs_reference": float(np.abs(np.nan_to_num(theirs)).max()),
        "share_over_tol": float(np.mean(diff > TOLERANCE)),
        "over_tol_without_ties": int(np.count_nonzero((diff > TOLERANCE) & ~tie)),
        "sign_ties": int(tie.sum()),
        "ties_over_tol": int(np.count_nonzero(diff[tie] > TOLERANCE)),
        "ties_over_tol_flipped": int(np.count_nonzero(flipped > TOLERANCE)),
        "nan_rows_reference": int(np.count_nonzero(~finite)),
        "zero_rows_ours": int(np.count_nonzero(~mine.any(axis=1))),
        "zero_rows_reference": int(np.count_nonzero(~np.nan_to_num(theirs).any(axis=1))),
        "seconds_ours": t_ours,
        "seconds_reference": t_ref,
    }


def table(result: dict) -> str:
    """Markdown of a result: the date and machine of the run, then two tables (differences; ties, zero rows and times)."""
    date = result["date"][:10]
    where = f"{date}, {result['machine']}" if result.get("machine") else date
    lines = [
        f"Run of {where}; tolerance {result['tolerance']:g}. The differences per entry:",
        "",
        "| shape | parameters | V | max abs | max abs w/o ties (largest value) | share > 1e-5 | > 1e-5 w/o ties |",
        "|---|---|---|---|---|---|---|",
    ]
    rows = result["rows"]
    for r in rows:
        lines.append(
            f"| {r['shape']} | {r['params']} | {r['vertices']} | {r['max_abs']:.2e} | {r['max_abs_without_ties']:.2e} ({r['max_abs_reference']:.3g}) | "
            f"{100 * r['share_over_tol']:.2f}% | {r['over_tol_without_ties']} |"
        )
    lines += [
        "",
        "Sign ties, zero rows and wall times of the same runs:",
        "",
        "| shape | parameters | ties | ties > 1e-5: as computed / best other sign | zero rows ours / pyshot | NaN rows pyshot "
        "| s ours / pyshot |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['shape']} | {r['params']} | {r['sign_ties']} | {r['ties_over_tol']} / {r['ties_over_tol_flipped']} | "
            f"{r['zero_rows_ours']} / {r['zero_rows_reference']} | {r['nan_rows_reference']} | "
            f"{r['seconds_ours']:.2f} / {r['seconds_reference']:.2f} |"
        )
    return "\n".join(lines)


def bumpy_cloud(n: int = 642, seed: int = 0) -> np.ndarray:
    """``n`` random points on a bumpy sphere, shape (n, 3): the recorded point cloud (no symmetry, so few sign ties)."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    return points * (1 + 0.1 * np.sin(3 * points[:, :1]) * np.cos(2 * points[:, 1:2]))


#: What the CI test checks: (name, params, shape key, row step).
RECORDED = (
    ("faust_dsmk", PARAM_SETS["dsmk"], "faust", RECORD_STEP),
    ("faust_r0.1_b7_16vol", PARAM_SETS["r0.1_b7_16vol"], "faust", RECORD_STEP),
    ("cloud_r0.5_b5_nonorm", {"radius": 0.5, "n_bins": 5, "use_normalization": False}, "cloud", 10),
)


def record_reference(folder: Path, faust: geofeat.Mesh, python: str, harness: str, work: Path) -> Path:
    """Write ``shot_reference.npz``, the reference rows of `RECORDED`, for the CI test; returns the file."""
    cloud = geofeat.Mesh(bumpy_cloud())
    inputs = {"faust": faust, "cloud": cloud}
    arrays: dict[str, np.ndarray] = {"cloud_verts": np.asarray(cloud.verts), "faust_verts_sum": np.asarray(faust.verts).sum(0)}
    for name, params, key, step in RECORDED:
        theirs, _ = reference(python, harness, inputs[key], params, work)
        rows = np.arange(0, inputs[key].n_vertices, step)
        arrays[f"{name}_rows"] = rows
        arrays[f"{name}_descriptors"] = theirs[rows].astype(np.float32)  # pyshot's values are float32
        arrays[f"{name}_params"] = np.array(json.dumps(params))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "shot_reference.npz"
    np.savez_compressed(path, **arrays)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--reference-python", help="python of pyshot's environment (required unless --render-only)")
    parser.add_argument("--harness", default=str(PYSHOT_HARNESS), help="the harness pyshot's python runs (default: ours)")
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--data-ext", default=DEFAULT_DATA_EXT, help="folder with PSMAL/ (default $GEOFEAT_DATA_EXT)")
    parser.add_argument("--record", help="also write shot_reference.npz (the CI test's reference rows) to this folder")
    parser.add_argument("--out", default=str(RESULTS / "parity" / "parity_shot"))
    parser.add_argument("--render-only", action="store_true", help="rewrite OUT.md from OUT.json without running anything")
    args = parser.parse_args()
    if args.render_only:
        rewrite_table(args.out, table)
        return
    if not args.reference_python:
        parser.error("--reference-python is required (or --render-only)")
    meshes = shapes(data_folder(args.data), data_folder(args.data_ext, "--data-ext"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for shape, mesh in meshes.items():
            for name, params in PARAM_SETS.items():
                rows.append({"shape": shape, "params": name, **compare(mesh, params, args.reference_python, args.harness, work)})
        if args.record:
            record_reference(Path(args.record), meshes["FAUST_r tr_reg_080"], args.reference_python, args.harness, work)
    result = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "param_sets": PARAM_SETS,
        "tolerance": TOLERANCE,
        "rows": rows,
    }
    write_results(args.out, result, table(result))


if __name__ == "__main__":
    main()
