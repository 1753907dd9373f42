"""SHOT: geofeat against pyshot on a FAUST_r shape, then geofeat alone on a 200,000-vertex mesh.

1. FAUST_r tr_reg_080 (5,000 vertices) with DeepShapeMatchingKit's parameters (radius 0.3,
   about 2,200 neighbours per vertex): pyshot through its harness in its own environment
   (``--reference-python``, ``--harness``: see `benchmarks.parity.shot`; it times its own
   ``get_descriptors`` call, min over the repeats) against geofeat's `shot_descriptors` on
   one thread and on every core (min over the repeats); the ratio is pyshot's time over
   geofeat's. Without ``--harness`` only geofeat runs.
2. ``--large`` vertices (default 200,000: FAUST_r subdivided and decimated, as
   `benchmarks.speed.large_mesh` makes it) at ``--large-radius`` (default 0.03, about 2,700
   neighbours per vertex), through ``geofeat.compute`` (progress bar on a terminal): wall time
   and the peak of the memory NumPy allocated (tracemalloc), which the chunks bound.

    python -m benchmarks.speed.shot --data /data --reference-python /ref/shot/venv/bin/python --harness /ref/shot/harness.py
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, write_results
from benchmarks.parity.shot import PARAM_SETS
from benchmarks.speed.large_mesh import make_mesh
from geofeat.descriptors.shot import PAIRS_PER_CHUNK, SHOT, shot_descriptors


def time_ours(mesh: geofeat.Mesh, params: dict, workers: int, repeats: int) -> float:
    """Min wall time of `shot_descriptors` over ``repeats`` calls (normals excluded, as pyshot's harness times only the call)."""
    normals = SHOT().normals(mesh)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        shot_descriptors(mesh.verts, normals, workers=workers, **params)
        times.append(time.perf_counter() - start)
    return min(times)


def time_reference(python: str, harness: str, mesh: geofeat.Mesh, params: dict, repeats: int) -> float:
    """pyshot's min wall time over ``repeats`` calls, as its harness measures it."""
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, verts=np.asarray(mesh.verts), faces=np.asarray(mesh.faces))
        subprocess.run(
            [python, harness, str(src), str(out), json.dumps({**params, "repeats": repeats})], check=True, capture_output=True
        )
        with np.load(out) as result:
            return float(result["wall_time"])


def large_run(data: Path, n_vertices: int, radius: float) -> dict:
    """Wall time and NumPy's peak allocation of ``geofeat.compute`` on a mesh of about ``n_vertices`` vertices."""
    verts, faces = make_mesh(data, n_vertices)
    mesh = geofeat.Mesh(verts, faces, name=f"faust_{len(verts)}")
    tracemalloc.start()
    start = time.perf_counter()
    features = geofeat.compute(mesh, "shot", cache=False, radius=radius)
    seconds = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {
        "vertices": mesh.n_vertices,
        "radius": radius,
        "seconds": seconds,
        "peak_mib": peak / 2**20,
        "output_mib": features.nbytes / 2**20,
        "zero_rows": int(np.count_nonzero(~features.any(axis=1))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--reference-python", help="python of pyshot's environment")
    parser.add_argument("--harness", help="the pyshot harness (kept outside this repository)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--large", type=int, default=200_000, help="vertices of the large mesh (0: skip)")
    parser.add_argument("--large-radius", type=float, default=0.03)
    parser.add_argument("--out", default=str(RESULTS / "speed_shot"))
    args = parser.parse_args()
    data = data_folder(args.data)
    mesh = geofeat.load_mesh(data / "FAUST_r" / "off" / "tr_reg_080.off")
    params = PARAM_SETS["dsmk"]
    cores = os.cpu_count() or 1
    row = {
        "geofeat_1_thread": time_ours(mesh, params, 1, args.repeats),
        f"geofeat_{cores}_threads": time_ours(mesh, params, cores, args.repeats),
    }
    if args.harness and args.reference_python:
        row["pyshot"] = time_reference(args.reference_python, args.harness, mesh, params, args.repeats)
    large = large_run(data, args.large, args.large_radius) if args.large else None
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    lines = [
        f"{machine()}; {stamp}; min of {args.repeats}",
        "",
        "| FAUST_r tr_reg_080, DSMK parameters | seconds | pyshot / this |",
        "|---|---|---|",
    ]
    for name, seconds in row.items():
        ratio = f"{row['pyshot'] / seconds:.2f}" if "pyshot" in row else "-"
        lines.append(f"| {name.replace('_', ' ')} | {seconds:.2f} | {ratio} |")
    if large:
        lines += [
            "",
            f"| large mesh (geofeat.compute, {cores} threads, {PAIRS_PER_CHUNK:,} pairs per chunk) | vertices | radius "
            "| seconds | NumPy peak MiB (output MiB) | zero rows |",
            "|---|---|---|---|---|---|",
            f"| FAUST_r subdivided and decimated | {large['vertices']} | {large['radius']} | {large['seconds']:.1f} | "
            f"{large['peak_mib']:.0f} ({large['output_mib']:.0f}) | {large['zero_rows']} |",
        ]
    result = {"date": stamp, "machine": machine(), "faust_dsmk": row, "large": large, "repeats": args.repeats}
    write_results(args.out, result, "\n".join(lines))


if __name__ == "__main__":
    main()
