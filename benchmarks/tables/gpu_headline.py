"""The README's GPU figures: two headline rows from the results of one GPU run.

Reads what `speed/dino.py` and `speed/geolora.py` wrote for one GPU (by default into
``benchmarks/results/h100/``) and writes ``<folder>/headline.md``: the seconds of DINOv3
ViT-B/16 features for one shape (a whole pass, as the descriptors run it) and the GeoLoRA
training speed at the paper's settings, with the GPU, the machine and the date::

    python -m benchmarks.speed.dino --device cuda --repeats 5 --profile --bf16-weights --out benchmarks/results/h100/speed_dino_bf16
    python -m benchmarks.speed.geolora --model vitb16 --image-size 512 --device cuda --steps 20 \\
        --out benchmarks/results/h100/speed_geolora_vitb16_512_cuda
    python -m benchmarks.tables.gpu_headline --folder benchmarks/results/h100
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.common import RESULTS

#: The backbone row of speed/dino.py's results that the headline quotes (the paper's backbone size).
VIT_B = "ViT-B/16 size (12 layers, width 768)"


def headline(dino: dict, geolora: dict) -> str:
    """The Markdown of the two rows, their GPU, machine and dates."""
    row = next(r for r in dino["rows"] if r["name"] == VIT_B)
    precision = "bfloat16 autocast" if dino.get("autocast") else "float32"
    dates = ", ".join(sorted({dino["date"], geolora["date"]}))
    machines = list(dict.fromkeys([dino["machine"], geolora["machine"]]))
    lines = [
        f"| {dino['gpu']} | time |",
        "|---|---|",
        f"| DINOv3 ViT-B/16 features of one {dino['vertices']:,}-vertex shape, {dino['views']} views at "
        f"{dino['image_size']} x {dino['image_size']} | {row['wall']:.2f} s |",
        f"| GeoLoRA training at the paper's settings ({geolora['image_size']} x {geolora['image_size']}) | "
        f"{geolora['wall_steps_per_second']:.1f} steps/s, {geolora['hours_for_50000_steps']:.1f} h for 50,000 steps |",
        "",
        f"{dates}, {'; '.join(machines)}; random weights of the paper's backbone size, {precision}, "
        f"{geolora.get('workers', 0)} sample workers for training.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--folder", type=Path, default=RESULTS / "h100", help="the GPU run's results folder")
    args = parser.parse_args(argv)
    dino = json.loads((args.folder / "speed_dino_bf16.json").read_text())
    geolora = json.loads((args.folder / "speed_geolora_vitb16_512_cuda.json").read_text())
    text = headline(dino, geolora)
    (args.folder / "headline.md").write_text(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
