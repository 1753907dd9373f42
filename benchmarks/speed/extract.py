"""Time ``geofeat extract`` over a dataset: 1 process, ``torchrun --nproc_per_node=N``, and a rerun (all skipped).

Every timed run starts from a fresh store in a temporary folder (``GEOFEAT_CACHE_DIR``), the
rerun reuses the single-process store. torchrun sets ``OMP_NUM_THREADS=1`` in its workers, so
a single process is timed twice: with the BLAS threads it would get, and with one thread. Runs are separate processes, timed from launch to
exit (Python and torch imports included), so the numbers are what a user waits for.

    GEOFEAT_DATA=../shared/data python -m benchmarks.speed.extract --descriptor wks --dataset faust_r --nproc 2 \
        --out benchmarks/results/speed_extract/results.json

With ``--out OUT.json`` it also writes ``OUT.md``, the table; ``--render-only`` rewrites that
table from an existing ``OUT.json`` without running anything.

``--dinov3`` times the GPU case instead: ``geofeat extract --descriptor dinov3`` over the
FAUST_r shapes of ``--data`` (``FAUST_r/off``) with a randomly initialised DINOv3 backbone
saved as a Hugging Face folder (``--backbone vitb``: ViT-B/16 size, the default; ``tiny``:
2 layers of width 32, for a check on a CPU), once per ``--prefetch`` value (shapes read and
rendered on a background thread ahead of the one being encoded; 0: none), each run a fresh
process and a fresh store. It reports the extract loop's shapes/s and seconds from the
manifest (the backbone's loading excluded), the process's wall time and the device, in
``results/speed_extract/dinov3_<device type>.json`` and ``.md`` unless ``--out`` says otherwise::

    python -m benchmarks.speed.extract --dinov3 --data ../shared/data --device cuda
    python -m benchmarks.speed.extract --dinov3 --backbone tiny --device cpu --first 3 \
        --param views=4 --param image_size=64 --out /tmp/dinov3_cpu.json      # a quick check on a CPU
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

from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine

#: ``--backbone`` choices: keys of `speed_dino.BACKBONES` (random DINOv3 architectures).
DINOV3_BACKBONES = {"vitb": "ViT-B/16 size (12 layers, width 768)", "tiny": "tiny (2 layers, width 32)"}


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
        f"imports included; {report['machine']}, {report['date']}",
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


def faust_folder(data: Path, first: int | None, tmp: Path) -> tuple[Path, int]:
    """``<data>/FAUST_r/off``, or a folder of links to its first ``first`` shapes (sorted by name); and the count."""
    folder = data / "FAUST_r" / "off"
    files = sorted(folder.glob("*.off"))
    if not files:
        sys.exit(f"no FAUST_r shapes in {folder}; pass --data, the folder that holds FAUST_r")
    if first is None or first >= len(files):
        return folder, len(files)
    subset = tmp / "shapes"
    subset.mkdir()
    for path in files[:first]:
        (subset / path.name).symlink_to(path.resolve())
    return subset, first


def device_name(device: str) -> str:
    """The GPU's name for a CUDA device, else the CPU model."""
    import torch

    if device.startswith("cuda") or (device == "auto" and torch.cuda.is_available()):
        return torch.cuda.get_device_name(torch.device("cuda" if device == "auto" else device))
    return machine().split(",")[0]


def dinov3_markdown(report: dict) -> str:
    """The table of a ``--dinov3`` report: one row per run, then what was run and where."""
    params = " ".join(report["params"]) or "default parameters"
    amp = report.get("descriptor_params", {}).get("amp")
    precision = {"on": ", bfloat16 autocast", "off": ", float32"}.get(amp, "")
    lines = [
        f"`geofeat extract --descriptor dinov3` ({params}; otherwise 49 views of 512 x 512{precision}) "
        f"over {report['shapes']} FAUST_r shapes, random DINOv3 backbone of {report['backbone']} from a Hugging Face "
        f"folder, `--device {report['device']}` ({report['device_name']}); each run a fresh process and store. "
        "Loop: the extract loop over the shapes, the backbone's loading excluded; process: launch to exit. "
        f"torch {report['torch']}, transformers {report['transformers']}; {report['machine']}, {report['date']}",
        "",
        "| prefetch | shapes computed | loop | shapes/s | vs prefetch 0 | process |",
        "|---|---|---|---|---|---|",
    ]
    base = [r["shapes_per_second"] for r in report["rows"] if r["prefetch"] == 0 and r["shapes_per_second"]]
    for r in report["rows"]:
        ratio = f"{r['shapes_per_second'] / (sum(base) / len(base)):.2f}x" if base and r["shapes_per_second"] else "-"
        rate = f"{r['shapes_per_second']:.3g}" if r["shapes_per_second"] else "-"
        lines.append(
            f"| {r['prefetch']} | {r['computed']} | {r['wall_seconds']:.2f} s | {rate} | {ratio} | {r['process_seconds']:.2f} s |"
        )
    return "\n".join(lines) + "\n"


def run_dinov3(args: argparse.Namespace) -> None:
    """``--dinov3``: the same extract with each ``--prefetch`` value, from a fresh store each time."""
    import torch
    import transformers

    from benchmarks.speed.dino import BACKBONES, random_dinov3

    rows, descriptor_params = [], None
    data = data_folder(args.data)
    with tempfile.TemporaryDirectory(prefix="geofeat-speed-extract-dinov3-") as tmp:
        tmp = Path(tmp)
        folder, n_shapes = faust_folder(data, args.first, tmp)
        weights = tmp / "backbone"
        random_dinov3(0, **BACKBONES[DINOV3_BACKBONES[args.backbone]]).model.save_pretrained(weights)
        extract = [sys.executable, "-m", "geofeat", "extract", "--descriptor", "dinov3", "--data", str(folder)]
        extract += ["--param", f"weights={json.dumps(str(weights))}", "--device", args.device, "--no-progress"]
        for item in args.param:
            extract += ["--param", item]
        env = {**os.environ, "GEOFEAT_CACHE_DIR": str(tmp / "cache")}
        for run, prefetch in enumerate(args.prefetch * args.repeats):
            manifest = tmp / f"{run}.json"
            command = extract + ["--prefetch", str(prefetch), "--out", str(tmp / f"store{run}"), "--manifest", str(manifest)]
            seconds, result = timed(command, env)
            row = {
                "prefetch": prefetch,
                "computed": result["n_computed"],
                "failed": result["n_failed"],
                "wall_seconds": result["wall_seconds"],
                "shapes_per_second": result["shapes_per_second"],
                "process_seconds": round(seconds, 2),
            }
            rows.append(row)
            descriptor_params = {k: v for k, v in result["params"].items() if k != "weights"}  # as resolved (amp)
            print(
                f"prefetch {prefetch}: {row['computed']} shapes in {row['wall_seconds']:.2f} s, "
                f"{row['shapes_per_second'] or 0:.3g} shapes/s (process {seconds:.2f} s)",
                flush=True,
            )
            if row["failed"]:
                failed = next(r for r in result["shapes"] if r["status"] == "failed")
                sys.exit(f"{row['failed']} shape(s) failed, e.g. {failed['shape']}: {failed['error']}")
    report = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "device": args.device,
        "device_name": device_name(args.device),
        "torch": torch.__version__,
        "transformers": transformers.__version__,
        "backbone": DINOV3_BACKBONES[args.backbone],
        "shapes": n_shapes,
        "data": str(data.resolve()),
        "params": args.param,
        "descriptor_params": descriptor_params,
        "rows": rows,
    }
    kind = "cuda" if args.device.startswith("cuda") or (args.device == "auto" and torch.cuda.is_available()) else "cpu"
    out = Path(args.out) if args.out else RESULTS / "speed_extract" / f"dinov3_{kind}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")
    out.with_suffix(".md").write_text(dinov3_markdown(report))
    print(dinov3_markdown(report))
    print(f"written: {out} and {out.with_suffix('.md')}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--descriptor", default="wks")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--dataset", default="faust_r")
    parser.add_argument("--split", default="all")
    parser.add_argument("--nproc", type=int, default=2, help="torchrun processes")
    parser.add_argument("--out", help="write the results as JSON here (and the table beside it, .md)")
    parser.add_argument("--render-only", action="store_true", help="rewrite the table from the JSON of --out; run nothing")
    dino = parser.add_argument_group("--dinov3: the GPU case, with and without read-ahead")
    dino.add_argument("--dinov3", action="store_true", help="time geofeat extract --descriptor dinov3 per --prefetch value")
    dino.add_argument("--backbone", choices=sorted(DINOV3_BACKBONES), default="vitb", help="random DINOv3 size (default vitb)")
    dino.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r (default $GEOFEAT_DATA)")
    dino.add_argument("--first", type=int, help="only the first N FAUST_r shapes (sorted by name)")
    dino.add_argument("--device", default="auto", help="geofeat extract's --device (default auto)")
    dino.add_argument("--prefetch", type=int, nargs="+", default=[0, 2], help="values to compare (default 0 2)")
    dino.add_argument("--repeats", type=int, default=1, help="runs of the whole --prefetch list (default 1)")
    args = parser.parse_args()
    if args.render_only:
        if not args.out or not Path(args.out).is_file():
            parser.error("--render-only needs --out, the results JSON of an earlier run")
        report = json.loads(Path(args.out).read_text())
        Path(args.out).with_suffix(".md").write_text(dinov3_markdown(report) if "backbone" in report else markdown(report))
        return
    if args.dinov3:
        if args.first is not None and args.first < 1:
            parser.error("--first must be at least 1")
        run_dinov3(args)
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
    report = {
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "cpu_count": os.cpu_count(),
        "descriptor": args.descriptor,
        "params": args.param,
        "dataset": args.dataset,
        "split": args.split,
        "rows": rows,
    }
    print(markdown(report))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
        Path(args.out).with_suffix(".md").write_text(markdown(report))


if __name__ == "__main__":
    main()
