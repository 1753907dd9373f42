"""SHOT: geofeat against pyshot on a FAUST_r shape, then geofeat alone on a 200,000-vertex mesh.

1. FAUST_r tr_reg_080 (5,000 vertices) with DeepShapeMatchingKit's parameters (radius 0.3,
   about 2,200 neighbours per vertex): pyshot through its harness in its own environment
   (``--reference-python``: see `benchmarks/official/pyshot_harness.py`; it times its own
   ``get_descriptors`` call, min over the repeats) against geofeat's `shot_descriptors` on
   one thread and on every core (min over the repeats); the ratio is pyshot's time over
   geofeat's. The first geofeat call of the run is timed on its own: it loads the compiled
   kernels (or compiles them, about 10 s, the first time after an install). Without
   ``--reference-python`` only geofeat runs.
2. ``--large`` vertices (default 200,000: FAUST_r subdivided and decimated, as
   `benchmarks.speed.large_mesh` makes it) at ``--large-radius`` (default 0.03, about 2,700
   neighbours per vertex), through ``geofeat.compute`` (progress bar on a terminal) in a child
   process: wall time, the peak of the memory NumPy allocated (tracemalloc) and the child's
   peak resident memory (everything: Python, libraries, mesh, output).

    python -m benchmarks.speed.shot --data /data --reference-python PYSHOT_VENV/bin/python
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, write_results
from benchmarks.parity.shot import PARAM_SETS, PYSHOT_HARNESS
from benchmarks.speed.large_mesh import make_mesh
from geofeat.descriptors.shot import QUERIES_PER_CHUNK, SHOT, shot_descriptors


def time_ours(mesh: geofeat.Mesh, params: dict, workers: int, repeats: int) -> float:
    """Min wall time of `shot_descriptors` over ``repeats`` calls (normals excluded, as pyshot's harness times only the call).

    ``repeats=1`` as the first call of a process: the time it takes to load the compiled kernels too.
    """
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
    """Wall time and NumPy's peak allocation of ``geofeat.compute`` on a mesh of about ``n_vertices`` vertices.

    Run it in a process of its own (`large_in_child`): the resident peak it reports is the process's.
    """
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
        "resident_peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10,
        "zero_rows": int(np.count_nonzero(~features.any(axis=1))),
    }


def large_in_child(data: Path, n_vertices: int, radius: float) -> dict:
    """`large_run` in a fresh Python process (its output streams pass through: the progress bar shows)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "large.json"
        code = (
            "import json, sys; from pathlib import Path; from benchmarks.speed.shot import large_run; "
            "Path(sys.argv[4]).write_text(json.dumps(large_run(Path(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]))))"
        )
        subprocess.run([sys.executable, "-c", code, str(data), str(n_vertices), str(radius), str(out)], check=True)
        return json.loads(out.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--reference-python", help="python of pyshot's environment")
    parser.add_argument("--harness", default=str(PYSHOT_HARNESS), help="the harness pyshot's python runs (default: ours)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--large", type=int, default=200_000, help="vertices of the large mesh (0: skip)")
    parser.add_argument("--large-radius", type=float, default=0.03)
    parser.add_argument("--out", default=str(RESULTS / "speed_shot"))
    args = parser.parse_args()
    data = data_folder(args.data)
    mesh = geofeat.load_mesh(data / "FAUST_r" / "off" / "tr_reg_080.off")
    params = PARAM_SETS["dsmk"]
    cores = len(os.sched_getaffinity(0))
    row = {
        "geofeat_first_call_1_thread": time_ours(mesh, params, 1, 1),
        "geofeat_1_thread": time_ours(mesh, params, 1, args.repeats),
        f"geofeat_{cores}_threads": time_ours(mesh, params, cores, args.repeats),
    }
    if args.reference_python:
        row["pyshot"] = time_reference(args.reference_python, args.harness, mesh, params, args.repeats)
    large = large_in_child(data, args.large, args.large_radius) if args.large else None
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
            f"| large mesh (geofeat.compute, {cores} threads, {QUERIES_PER_CHUNK} vertices per task) | vertices | radius "
            "| seconds | NumPy peak MiB (output MiB) | process peak MiB | zero rows |",
            "|---|---|---|---|---|---|---|",
            f"| FAUST_r subdivided and decimated | {large['vertices']} | {large['radius']} | {large['seconds']:.1f} | "
            f"{large['peak_mib']:.0f} ({large['output_mib']:.0f}) | {large['resident_peak_mib']:.0f} | {large['zero_rows']} |",
        ]
    result = {"date": stamp, "machine": machine(), "faust_dsmk": row, "large": large, "repeats": args.repeats}
    write_results(args.out, result, "\n".join(lines))


if __name__ == "__main__":
    main()
