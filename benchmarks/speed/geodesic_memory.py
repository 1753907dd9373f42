"""Evaluating a partial shape against a large full target: time, peak memory and disk, under the memory bound.

A full target with tens of thousands of vertices has an all-pairs geodesic matrix of 4 V^2
bytes (6.4 GB at 40,000 vertices, 25.6 GB at 80,000). The evaluation estimates that before
computing: within the bound (default half the available memory) it forms the matrix; above
it, it computes only the distances it reads, a few rows at a time
(`geofeat.geometry.geodesic_memory.GeodesicEntries`). The geodesic store keeps no entry larger than
its limit (default 4 GiB).

Targets: the template of `geofeat.datasets.synthetic` meshed at a fine grid spacing (about
40,000 and 80,000 vertices). Pair: a CUTS partial of the target (`geofeat.geometry.make_partial`)
against the whole target, with the ground truth and its left-right mirror (chirality); the
prediction is the nearest target vertex of each partial vertex after moving it by a random
offset (about two edge lengths), so that errors are not all zero. Each run is a fresh
process under ``/usr/bin/time -v`` (peak resident memory), with an empty cache folder; the
disk column is what that folder holds afterwards. The machine may be shared: the process's
CPU time (user + system) and the one-minute load average at its end are recorded beside the
wall-clock times.

Runs: ``default`` (the bound in force: half the available memory), ``streamed`` (the bound
set to 1 GB with ``GEOFEAT_GEODESIC_MEMORY``: the streamed entries), ``stored`` (the bound
and the store limit raised: what the evaluation did before there was either, the matrix
formed and written into the store).

Usage::

    python -m benchmarks.speed.geodesic_memory --sizes 40000 --runs default streamed
    python -m benchmarks.speed.geodesic_memory --sizes 80000 --runs default --merge

The results are written after every run (``--merge`` keeps those of other sizes and runs);
``--render-only`` rewrites ``OUT.md`` from ``OUT.json``, running nothing.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, RESULTS, machine, read_results, write_results

#: Grid spacing of the synthetic template for a target of about this many vertices (5,000 at 0.022).
SPACING = {5000: 0.022, 40000: 0.0078, 80000: 0.0055}
RUNS = {
    "default": {},
    "streamed": {"GEOFEAT_GEODESIC_MEMORY": "1G"},
    "stored": {"GEOFEAT_GEODESIC_MEMORY": "1T", "GEOFEAT_GEODESIC_STORE_LIMIT": "1T"},
}
LABELS = {
    "default": "default bound (half the available memory)",
    "streamed": "bound 1 GB: streamed entries",
    "stored": "no bound, no store limit (the matrix formed and stored)",
}


def make_target(size: int, folder: Path) -> Path:
    """The synthetic template at the spacing for ``size`` vertices, with its mirror map, saved as ``.npz``."""
    from geofeat.datasets.synthetic import template

    path = folder / f"target_{size}.npz"
    if not path.exists():
        mesh, mirror = template(SPACING[size])
        np.savez(path, verts=mesh.verts, faces=mesh.faces, mirror=mirror)
    return path


def child(target: Path) -> None:
    """Evaluate one pair on the saved target (in a fresh process); print one JSON line."""
    from scipy.spatial import cKDTree

    from geofeat.datasets.records import Match, ShapePair
    from geofeat.evaluation.protocol import evaluate_dataset, summarize
    from geofeat.geometry.geodesic_store import GeodesicStore
    from geofeat.geometry.partial import make_partial
    from geofeat.mesh import Mesh

    data = np.load(target)
    x = Mesh(data["verts"], data["faces"], name=target.stem)
    partial = make_partial(x, "cuts", seed=0)
    y, gt = partial.mesh, partial.vertex_map
    rng = np.random.default_rng(0)
    edge = float(np.linalg.norm(x.verts[x.faces[:, 0]] - x.verts[x.faces[:, 1]], axis=1).mean())
    moved = y.verts + rng.normal(scale=2 * edge, size=y.verts.shape)
    pred = cKDTree(x.verts).query(moved)[1].astype(np.int64)
    overlap = np.zeros(x.n_vertices, dtype=bool)
    overlap[gt] = True
    pair = ShapePair(x=x, y=y, map_yx=gt, overlap_x=overlap, map_yx_sym=data["mirror"][gt])
    match = Match(map_yx=pred, overlap_y=np.ones(y.n_vertices, dtype=bool))
    start = time.perf_counter()
    records, _ = evaluate_dataset([pair], lambda i, p: match, store=GeodesicStore(), progress=False)
    seconds = time.perf_counter() - start
    summary = summarize(records)
    print(
        "RESULT "
        + json.dumps(
            {
                "n_vertices": x.n_vertices,
                "n_partial": y.n_vertices,
                "seconds": seconds,
                "geodesic_error": summary.geodesic_error,
                "chirality_accuracy": summary.chirality_accuracy,
            }
        )
    )


def folder_bytes(folder: Path) -> int:
    """Bytes of the files under a folder, whatever they are (0 when it does not exist; links not followed).

    The whole cache folder of a run, temporary files included; `EntryFolder.info` of the
    feature cache or the geodesic store counts their entries only.
    """
    if not folder.is_dir():
        return 0
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file() and not path.is_symlink())


def measure(target: Path, run: str, work: Path) -> dict:
    """One evaluation in a fresh process under /usr/bin/time -v; its record."""
    cache = Path(tempfile.mkdtemp(prefix=f"cache_{run}_", dir=work))
    env = {**os.environ, "GEOFEAT_CACHE_DIR": str(cache), **RUNS[run]}
    command = ["/usr/bin/time", "-v", sys.executable, "-m", "benchmarks.speed.geodesic_memory", "--child", str(target)]
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - start
    record = {"run": run, "returncode": done.returncode, "process_seconds": wall, "disk_bytes": folder_bytes(cache)}
    record["cpu_seconds"] = 0.0
    for line in done.stderr.splitlines():
        if "Maximum resident set size" in line:
            record["peak_rss_bytes"] = int(line.split(":")[1]) * 1024
        elif "User time (seconds)" in line or "System time (seconds)" in line:
            record["cpu_seconds"] += float(line.split(":")[1])
    record["load_average"] = os.getloadavg()[0]
    result = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if result:
        record.update(json.loads(result[-1][len("RESULT ") :]))
    if "Computing only the distances" in done.stderr:
        record["path"] = "streamed, nothing stored"
    elif "is not kept in the geodesic store" in done.stderr:
        record["path"] = "matrix, not stored (above the store limit)"
    else:
        record["path"] = "matrix, stored"
    record["warnings"] = [line.strip() for line in done.stderr.splitlines() if "WARNING" in line or "Error" in line][-3:]
    return record


def table(records: list[dict], header: str) -> str:
    """The header, then two tables sharing the target and run columns: the times, and memory, disk and accuracy."""
    lines = [
        header,
        "",
        "| target vertices | run | what it did | evaluation s | process s | process CPU s | load |",
        "|---:|---|---|---:|---:|---:|---:|",
    ]
    costs = [
        "| target vertices | run | peak memory | written to the store | geodesic error x100 | chirality |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for r in records:
        if r["returncode"] != 0:
            lines.append(f"| {r.get('n_vertices', '?')} | {LABELS[r['run']]} | failed | {'; '.join(r['warnings'])} | | | |")
            costs.append(f"| {r.get('n_vertices', '?')} | {LABELS[r['run']]} | | | | |")
            continue
        lines.append(
            f"| {r['n_vertices']:,} | {LABELS[r['run']]} | {r['path']} | {r['seconds']:.0f} | {r['process_seconds']:.0f} | "
            f"{r['cpu_seconds']:.0f} | {r['load_average']:.1f} |"
        )
        costs.append(
            f"| {r['n_vertices']:,} | {LABELS[r['run']]} | {r['peak_rss_bytes'] / 1e9:.2f} GB | {r['disk_bytes'] / 1e9:.2f} GB | "
            f"{r['geodesic_error']:.4f} | {r['chirality_accuracy']:.4f} |"
        )
    return "\n".join([*lines, "", *costs])


def header(result: dict) -> str:
    """The line above the tables: machine, memory, date and time of the last run."""
    memory = f"; memory {result['memory_gb']:.0f} GB" if result.get("memory_gb") is not None else ""
    return f"Machine: {result['machine']}{memory}; {result['date']}. Written by `benchmarks/speed/geodesic_memory.py`."


def stored_memory_gb(out: Path) -> float | None:
    """The machine's memory as the Markdown written with an older record gives it (those records kept none)."""
    path = out.with_suffix(".md")
    found = re.search(r"; memory (\d+) GB;", path.read_text()) if path.exists() else None
    return float(found.group(1)) if found else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[40000, 80000], choices=sorted(SPACING))
    parser.add_argument("--runs", nargs="+", default=["default", "streamed"], choices=list(RUNS))
    parser.add_argument("--work", default=None, help="folder for the targets and the cache folders (default: a temporary one)")
    parser.add_argument("--out", default=str(RESULTS / "geodesic_memory"))
    parser.add_argument("--merge", action="store_true", help="keep the records of other sizes and runs already in OUT.json")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--render-only", action="store_true", help="rewrite OUT.md from OUT.json without running anything")
    args = parser.parse_args()
    if args.child:
        child(Path(args.child))
        return
    if args.render_only:
        out = Path(args.out)
        result = read_results(out)
        if "memory_gb" not in result:
            result["memory_gb"] = stored_memory_gb(out)
        out.with_suffix(".md").write_text(table(result["records"], header(result)) + "\n")
        return
    work = Path(args.work or tempfile.mkdtemp(prefix="geodesic_memory_"))
    work.mkdir(parents=True, exist_ok=True)
    out = Path(args.out)
    records = []
    if args.merge and out.with_suffix(".json").exists():
        records = read_results(out)["records"]
    for size in args.sizes:
        target = make_target(size, work)
        for run in args.runs:
            if size == 80000 and run == "stored":
                continue  # 25.6 GB: more than this machine has
            record = measure(target, run, work)
            record["size"] = size
            print(json.dumps(record), flush=True)
            records = [r for r in records if (r.get("size"), r["run"]) != (size, run)] + [record]
            records.sort(key=lambda r: (r.get("size", 0), list(RUNS).index(r["run"])))
            result = {
                "machine": machine(),
                "memory_gb": os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 1e9,
                "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
                "records": records,
            }
            write_results(out, result, table(records, header(result)))


if __name__ == "__main__":
    main()
