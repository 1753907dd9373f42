"""Training steps per second of the learned heads (ULRSSM, DPFM, EchoMatch) at their reference settings.

Each head is built with a preset of the authors' settings (sizes and losses) and trained on
FAUST_r pairs: ULRSSM (``reference``) on full pairs (``faust_r``), DPFM
(``reference_shrec16_cuts``, its partial-to-full setting) and EchoMatch (``reference``) on
partial-to-full pairs (``faust_r_cuts``). A first pass over the pairs
computes and caches every input (descriptors, surface operators) and builds the model; a
second pass is timed: it holds only training steps (forward, loss, backward, Adam), one
step per pair. On CUDA the timer synchronises the device.

Usage::

    python -m benchmarks.speed.heads --data-root ../shared/data --pairs 8 --device auto
    python -m benchmarks.speed.heads --render-only --out benchmarks/results/h100/speed_heads   # OUT.md from OUT.json
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time

import torch

from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, rewrite_table, write_results
from geofeat.adapters.heads import make_head
from geofeat.datasets import load_dataset
from geofeat.runtime.devices import resolve_device

#: head -> (training dataset, preset): the authors' settings for full (ULRSSM) and partial-to-full pairs
SETTINGS = {
    "ulrssm": ("faust_r", "reference"),
    "dpfm": ("faust_r_cuts", "reference_shrec16_cuts"),
    "echomatch": ("faust_r_cuts", "reference"),
}


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work, so that wall time covers it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_head(name: str, data_root: str, n_pairs: int, device: torch.device) -> dict:
    """Seconds of a timed training pass over ``n_pairs`` pairs, after an untimed pass that fills the caches."""
    dataset_name, preset = SETTINGS[name]
    dataset = load_dataset(dataset_name, root=data_root, split="train", seed=0)
    pairs = [dataset[i] for i in range(min(n_pairs, len(dataset)))]
    head = make_head(name, preset=preset, device=str(device), progress=False, epochs=1)
    start = time.perf_counter()
    head.fit(pairs)  # inputs, operators, model, first-call allocations
    synchronize(device)
    warm_up = time.perf_counter() - start
    start = time.perf_counter()
    losses = head.fit(pairs)
    synchronize(device)
    seconds = time.perf_counter() - start
    parameters = sum(p.numel() for p in head.model.parameters() if p.requires_grad)
    return {
        "head": name,
        "dataset": dataset_name,
        "preset": preset,
        "steps": len(losses),
        "seconds": seconds,
        "steps_per_second": len(losses) / seconds,
        "first_pass_seconds": warm_up,
        "parameters": parameters,
        "peak_cuda_memory_gib": torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None,
    }


def table(result: dict) -> str:
    """The Markdown of a result: the steps per second, then the first pass, parameters and memory, each head a row."""
    where = result.get("gpu", result["machine"])
    lines = [
        f"Head training at the authors' settings, FAUST_r train pairs (about 5k vertices), one pair per step, "
        f"device {result['device']} ({where}), {result['date']}",
        "",
        "| head | preset | training pairs | steps timed | steps/s |",
        "|---|---|---|---|---|",
    ]
    costs = ["| head | first pass (inputs + steps) | trainable parameters | peak CUDA memory |", "|---|---|---|---|"]
    for row in result["rows"]:
        memory = f"{row['peak_cuda_memory_gib']:.2f} GiB" if row["peak_cuda_memory_gib"] is not None else "-"
        lines.append(f"| {row['head']} | {row['preset']} | {row['dataset']} | {row['steps']} | {row['steps_per_second']:.2f} |")
        costs.append(f"| {row['head']} | {row['first_pass_seconds']:.1f} s | {row['parameters']:,} | {memory} |")
    return "\n".join([*lines, "", *costs])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)")
    parser.add_argument("--heads", nargs="+", default=sorted(SETTINGS), choices=sorted(SETTINGS))
    parser.add_argument("--pairs", type=int, default=8, help="training pairs per timed pass (one step each)")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--out", default=str(RESULTS / "speed_heads"), help="writes OUT.json and OUT.md")
    parser.add_argument("--render-only", action="store_true", help="rewrite OUT.md from OUT.json without running anything")
    args = parser.parse_args(argv)
    if args.render_only:
        rewrite_table(args.out, table)
        return 0

    device = resolve_device(args.device)
    data_root = str(data_folder(args.data_root, "--data-root"))
    rows = []
    for name in args.heads:
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        rows.append(time_head(name, data_root, args.pairs, device))
        row = rows[-1]
        print(f"{name}: {row['steps']} steps in {row['seconds']:.2f} s = {row['steps_per_second']:.2f} steps/s", flush=True)
    result = {"date": datetime.date.today().isoformat(), "machine": machine(), "device": str(device), "rows": rows}
    if device.type == "cuda":
        result["gpu"] = torch.cuda.get_device_name(device)
    write_results(args.out, result, table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
