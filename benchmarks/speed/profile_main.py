"""Where the main job's time goes: ``benchmarks/run.py`` under cProfile, cold then warm, stage by stage.

    python -m benchmarks.speed.profile_main --out benchmarks/results/profile_main/results

Runs the main job (defaults of ``benchmarks/run.py``) twice in fresh processes with one
worker and one BLAS thread, so that the stages add up: first with an empty geofeat cache
(cold), then again on the cache the first run filled (warm). The stages are cumulative
cProfile seconds of the functions that own them; cProfile itself adds some time, so the
total is above a plain run's. Writes ``OUT.json`` and ``OUT.md`` (the stage table).
"""

from __future__ import annotations

import argparse
import datetime
import os
import pstats
import subprocess
import sys
import tempfile
from pathlib import Path

from benchmarks.common import BENCHMARKS, RESULTS, machine, write_results

#: stage -> (file suffix, function name) of the function whose cumulative time is the stage;
#: a stage given as "A - B" is A's time less B's.
STAGES = {
    "synthetic full shapes (template + skinning)": [("datasets/derived.py", "_full")],
    "partial shapes + ground-truth maps": [("datasets/derived.py", "__getitem__"), "-", ("datasets/derived.py", "_full")],
    "WKS (Laplacian + 128 eigenpairs)": [("descriptors/spectral.py", "compute")],
    "feature cache (HDF5 read/write)": [("descriptors/compute.py", "compute"), "-", ("descriptors/base.py", "__call__")],
    "nearest-neighbour matching": [("adapters/matchers.py", "nn_match")],
    "geodesic matrices (compute)": [("geometry/geodesic.py", "geodesic_matrix")],
    "geodesic store (read/write + checksum)": [
        ("geometry/geodesic_store.py", "load"),
        "-",
        ("geometry/geodesic.py", "geodesic_matrix"),
    ],
    "plots (pck.png, pairs.png)": [
        ("geofeat/evaluation/report.py", "plot_pck"),
        "+",
        ("geofeat/evaluation/report.py", "plot_pairs"),
    ],
}


def cumulative(stats: pstats.Stats, suffix: str, name: str) -> float:
    """Cumulative seconds of the functions ``name`` defined in a file ending with ``suffix``."""
    return sum(
        row[3] for (path, _, func), row in stats.stats.items() if func == name and path.replace(os.sep, "/").endswith(suffix)
    )


def stage_seconds(profile: Path) -> dict[str, float]:
    """Seconds per stage, plus imports (the module level of run.py less its ``main``) and the total."""
    stats = pstats.Stats(str(profile))
    seconds = {}
    for stage, terms in STAGES.items():
        value, sign = 0.0, 1.0
        for term in terms:
            if term in ("+", "-"):
                sign = 1.0 if term == "+" else -1.0
            else:
                value += sign * cumulative(stats, *term)
        seconds[stage] = value
    total = cumulative(stats, "benchmarks/run.py", "<module>")
    seconds = {"imports (run.py's module level)": total - cumulative(stats, "geofeat/apps/benchmark.py", "main"), **seconds}
    seconds["total (the profiled process)"] = total
    return seconds


def profile_run(cache: str, out: Path, profile: Path) -> None:
    env = dict(os.environ, GEOFEAT_CACHE_DIR=cache, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    command = [sys.executable, "-m", "cProfile", "-o", str(profile), str(BENCHMARKS / "run.py")]
    subprocess.run([*command, "--workers", "1", "--no-progress", "--out", str(out)], env=env, check=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(RESULTS / "profile_main" / "results"), help="OUT.json and OUT.md")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="geofeat_profile_") as scratch:
        runs = {}
        for run in ("cold", "warm"):
            profile = Path(scratch) / f"{run}.prof"
            profile_run(str(Path(scratch) / "cache"), Path(scratch) / "out", profile)
            runs[run] = stage_seconds(profile)
    rows = [f"| {stage} | {runs['cold'][stage]:.1f} | {runs['warm'][stage]:.1f} |" for stage in runs["cold"]]
    table = "\n".join(["| stage | cold (s) | warm (s) |", "|---|---|---|", *rows])
    result = {"machine": machine(), "date": datetime.date.today().isoformat(), "seconds": runs}
    write_results(args.out, result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
