"""WKS on large meshes: time and peak memory of geofeat against pyFM on the same meshes.

The meshes are made from a FAUST_r shape: subdivided three times (about 320k vertices; four
times, about 1.3M, for larger sizes), then decimated with fast-simplification to each target size (which leaves some degenerate
faces, as real scans have). Every run is a fresh Python process, so that its peak resident
memory (``ru_maxrss``) is its own:

* geofeat: ``geofeat.compute(mesh, "wks", cache=False)`` (robust Laplacian, 128
  eigenpairs, 128 energies: the defaults) and the same with ``laplacian="cotan"``;
* pyFM: ``TriMesh(verts, faces).process(k=128)`` then ``mesh_WKS(mesh, 128)`` (cotangent
  Laplacian), only up to ``--pyfm-max`` vertices.

Usage::

    python -m benchmarks.speed.large_mesh --sizes 20000 80000 200000 --out benchmarks/results/speed_large_mesh
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine

_RUN = """
import json, resource, sys, time
import numpy as np
data = np.load(sys.argv[1]); which = sys.argv[2]
verts, faces = data["verts"], data["faces"]
start = time.perf_counter()
if which == "pyfm":
    from pyFM.mesh import TriMesh
    from pyFM.signatures import mesh_WKS
    out = mesh_WKS(TriMesh(verts, faces).process(k=128), 128)
else:
    import geofeat
    mesh = geofeat.Mesh(verts, faces)
    out = geofeat.compute(mesh, "wks", cache=False, laplacian=which)
seconds = time.perf_counter() - start
peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
print(json.dumps({"seconds": seconds, "peak_gb": peak_gb, "finite": bool(np.isfinite(out).all()), "shape": list(out.shape)}))
"""


def make_mesh(data_root: Path, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """FAUST_r ``tr_reg_000`` subdivided three times (more where needed) and decimated to about ``n_vertices`` vertices."""
    import fast_simplification
    import trimesh

    import geofeat

    base = geofeat.load_mesh(data_root / "FAUST_r" / "off" / "tr_reg_000.off")
    verts, faces = base.verts, base.faces
    subdivisions = 0
    while subdivisions < 3 or len(verts) < n_vertices:
        verts, faces = trimesh.remesh.subdivide(verts, faces)
        subdivisions += 1
    reduction = 1.0 - n_vertices / len(verts)
    if reduction > 0:
        verts, faces = fast_simplification.simplify(verts.astype(np.float32), faces.astype(np.int32), target_reduction=reduction)
    return np.asarray(verts, dtype=np.float64), np.asarray(faces, dtype=np.int64)


def run(path: Path, which: str, timeout: float) -> dict:
    """One fresh process; a failed run records its error and how long it took to fail."""
    start = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, "-c", _RUN, str(path), which], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"seconds": None, "error": f"did not finish within {timeout:.0f} s"}
    if done.returncode != 0:
        error = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "failed"
        return {"seconds": None, "failed_after": time.perf_counter() - start, "error": error}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[20000, 80000, 200000])
    parser.add_argument("--pyfm-max", type=int, default=200000, help="run pyFM only up to this many vertices")
    parser.add_argument("--cotan-max", type=int, default=None, help="run geofeat's cotan row only up to this many vertices")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per run")
    parser.add_argument("--out", type=Path, default=RESULTS / "speed_large_mesh")
    parser.add_argument("--table-only", action="store_true", help="only rewrite OUT/results.md from OUT/results.json")
    args = parser.parse_args(argv)
    if args.table_only:
        write_table(args.out)
        return 0
    data = data_folder(args.data)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            verts, faces = make_mesh(data, size)
            tri = verts[faces]
            degenerate = int((np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) == 0).sum())
            path = Path(tmp) / f"mesh{size}.npz"
            np.savez(path, verts=verts, faces=faces)
            row = {"vertices": len(verts), "faces": len(faces), "zero_area_faces": degenerate}
            for which in ("robust", "cotan", "pyfm"):
                if which == "pyfm" and len(verts) > args.pyfm_max:
                    continue
                if which == "cotan" and args.cotan_max is not None and len(verts) > args.cotan_max:
                    continue
                row[which] = run(path, which, args.timeout)
                print(json.dumps({"vertices": len(verts), which: row[which]}), flush=True)
            rows.append(row)
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"date": datetime.date.today().isoformat(), "machine": machine(), "rows": rows}
    (args.out / "results.json").write_text(json.dumps(record, indent=1) + "\n")
    write_table(args.out)
    return 0


def write_table(out: Path) -> str:
    """Write ``out/results.md`` from ``out/results.json`` and return it."""
    record = json.loads((out / "results.json").read_text())
    lines = [
        f"WKS (128 eigenpairs, 128 energies), {record['machine']}, {record['date']}; seconds / peak GB per fresh process",
        "",
        "| vertices | zero-area faces | geofeat robust | geofeat cotan | pyFM (cotan) | pyFM / geofeat robust |",
        "|---|---|---|---|---|---|",
    ]

    def cell(result):
        if result is None:
            return "-"
        if result.get("seconds") is None:
            error = result.get("error", "failed").split(":")[0].rsplit(".", 1)[-1]  # the exception's name
            after = f" after {result['failed_after']:.0f} s" if "failed_after" in result else ""
            return f"{error}{after} (see results.json)"
        return f"{result['seconds']:.1f} s / {result['peak_gb']:.2f} GB"

    def ratio(row):
        robust, pyfm = row.get("robust") or {}, row.get("pyfm") or {}
        if robust.get("seconds") and pyfm.get("seconds"):
            return f"{pyfm['seconds'] / robust['seconds']:.2f}x"
        return "-"

    for row in record["rows"]:
        lines.append(
            f"| {row['vertices']} | {row['zero_area_faces']} | {cell(row.get('robust'))} | {cell(row.get('cotan'))} | "
            f"{cell(row.get('pyfm'))} | {ratio(row)} |"
        )
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    sys.exit(main())
