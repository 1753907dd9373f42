"""Time ``geofeat extract`` over a dataset: 1 process, ``torchrun --nproc_per_node=N``, and a rerun (all skipped).

Every timed run starts from a fresh store in a temporary folder (``GEOFEAT_CACHE_DIR``), the
rerun reuses the single-process store. torchrun sets ``OMP_NUM_THREADS=1`` in its workers, so
a single process is timed twice: with the BLAS threads it would get, and with one thread. Runs are separate processes, timed from launch to
exit (Python and torch imports included), so the numbers are what a user waits for.

    GEOFEAT_DATA=../shared/data python benchmarks/speed_extract.py --descriptor wks --dataset faust_r --nproc 2 \
        --out benchmarks/results/speed_extract/results.json

With ``--out OUT.json`` it also writes ``OUT.md``, the table; ``--render-only`` rewrites that
table from an existing ``OUT.json`` without running anything.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import machine


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def timed(command: list[str], env: dict) -> tuple[float, dict]:
    """Run ``command`` (it writes the manifest named in it); seconds from launch to exit and the manifest."""
    start = time.perf_counter()
    result = subprocess.run(command, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        sys.exit(f"failed ({result.returncode}): {' '.join(command)}\n{result.stderr[-3000:]}")
    return seconds, json.loads(Path(command[command.index("--manifest") + 1]).read_text())


def markdown(report: dict) -> str:
    """The table of a report: one row per timed run, then the machine and the date."""
    params = " ".join(report["params"]) or "default parameters"
    lines = [
        f"`geofeat extract --descriptor {report['descriptor']}` ({params}) over the {report['rows'][0]['shapes']} shapes "
        f"of `{report['dataset']}` (split {report['split']}), each run a fresh process from launch to exit, "
        f"imports included; {report['machine']}, {report.get('date', 'date not recorded')}",
        "",
        "| run | wall time | shapes computed | already in the store | sum of per-shape compute times | 1-min load before / after |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["rows"]:
        lines.append(
            f"| {r['run']} | {r['seconds']:.2f} s | {r['computed']} | {r['present']} | {r['sum_of_per_shape_seconds']:.2f} s "
            f"| {r['load_1min_before']:.2f} / {r['load_1min_after']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--descriptor", default="wks")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--dataset", default="faust_r")
    parser.add_argument("--split", default="all")
    parser.add_argument("--nproc", type=int, default=2, help="torchrun processes")
    parser.add_argument("--out", help="write the results as JSON here (and the table beside it, .md)")
    parser.add_argument("--render-only", action="store_true", help="rewrite the table from the JSON of --out; run nothing")
    args = parser.parse_args()
    if args.render_only:
        if not args.out or not Path(args.out).is_file():
            parser.error("--render-only needs --out, the results JSON of an earlier run")
        Path(args.out).with_suffix(".md").write_text(markdown(json.loads(Path(args.out).read_text())))
        return
    rows = []
    with tempfile.TemporaryDirectory(prefix="geofeat-speed-extract-") as tmp:
        tmp = Path(tmp)
        extract = ["extract", "--descriptor", args.descriptor, "--dataset", args.dataset, "--split", args.split, "--no-progress"]
        for item in args.param:
            extract += ["--param", item]
        one_thread = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
        runs = [
            ("1 process", [sys.executable, "-m", "geofeat"], "one", {}),
            ("1 process, 1 BLAS thread", [sys.executable, "-m", "geofeat"], "one_thread", one_thread),
            (
                f"torchrun --nproc_per_node={args.nproc}",
                [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={args.nproc}", f"--master_port={free_port()}"]
                + ["-m", "geofeat"],
                "many",
                {},
            ),
            ("rerun, 1 process (all present)", [sys.executable, "-m", "geofeat"], "one", {}),
        ]
        for label, launcher, cache, extra_env in runs:
            env = {**os.environ, "GEOFEAT_CACHE_DIR": str(tmp / cache), **extra_env}
            load_before = os.getloadavg()[0]
            manifest = tmp / f"{len(rows)}.json"
            seconds, result = timed(launcher + extract + ["--manifest", str(manifest)], env)
            compute_s = sum(r["seconds"] for r in result["shapes"])
            row = {
                "run": label,
                "seconds": round(seconds, 2),
                "shapes": result["n_shapes"],
                "computed": result["n_computed"],
                "present": result["n_present"],
                "sum_of_per_shape_seconds": round(compute_s, 2),
                "load_1min_before": round(load_before, 2),
                "load_1min_after": round(os.getloadavg()[0], 2),
            }
            rows.append(row)
            print(f"{label:36s} {seconds:7.2f} s  {row['computed']:4d} computed {row['present']:4d} present", flush=True)
    report = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "cpu_count": os.cpu_count(),
              "descriptor": args.descriptor, "params": args.param, "dataset": args.dataset, "split": args.split,
              "rows": rows}  # fmt: skip
    print(markdown(report))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        Path(args.out).with_suffix(".md").write_text(markdown(report))


if __name__ == "__main__":
    main()
