"""Step time of GeoLoRA training, phase by phase.

Runs training steps of `geofeat.train.GeoLoraTrainer` on FAUST_r shapes with a randomly
initialised DINOv3 and reports the median seconds per phase (partial-shape generation,
geodesics, rendering, backbone forward, back-projection, loss, backward, optimizer) over the
steps after the first (warm-up). Random weights cost the same time as trained ones.

    python -m benchmarks.speed.geolora --model small --image-size 128 --steps 20          # the CPU experiment
    python -m benchmarks.speed.geolora --model vitb16 --image-size 512 --steps 3          # paper settings
    python -m benchmarks.speed.geolora --model vitb16 --image-size 512 --device cuda      # on a GPU

Writes ``benchmarks/results/speed_geolora_<model>_<size>_<device>.json`` and ``.md`` (``_reference``
appended under ``--recipe reference``), or ``OUT.json`` and ``OUT.md`` with ``--out OUT``;
``--render-only --out OUT`` rewrites the Markdown from ``OUT.json``, running nothing.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import (
    DEFAULT_DATA,
    RESULTS,
    data_folder,
    machine,
    profile_markdown,
    profile_tables,
    read_results,
    stored_profile_tables,
)
from geofeat.backbones import DinoBackbone
from geofeat.train.config import TrainConfig
from geofeat.train.trainer import PHASES, GeoLoraTrainer

MODELS = {
    # the backbone of benchmarks/geolora_learns.py
    "small": dict(hidden_size=96, intermediate_size=384, num_hidden_layers=4, num_attention_heads=4, patch_size=8),
    # DINOv3 ViT-B/16 (the paper's backbone): width 768, 12 blocks, 12 heads, 4 registers
    "vitb16": dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12, patch_size=16),
}


def random_backbone(model: str, seed: int = 0) -> DinoBackbone:
    """A DINOv3 of the given size with transformers' random initialisation."""
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    torch.manual_seed(seed)
    config = DINOv3ViTConfig(**MODELS[model], num_register_tokens=4, image_size=224)
    return DinoBackbone(DINOv3ViTModel(config), kind="dinov3", source=f"random {model}")


def profile_steps(trainer: GeoLoraTrainer, steps: int) -> tuple[dict, list[str]]:
    """``steps`` training steps under torch.profiler: `common.profile_tables` of them."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if trainer.device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        start = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        if trainer.device.type == "cuda":
            torch.cuda.synchronize()
        wall = time.perf_counter() - start
    return profile_tables(prof, wall)


def caption(result: dict) -> str:
    """What was timed, where and when: the line above the tables.

    Older records lack some of the settings (workers, recipe, precision, wall time); the
    caption names only those the record holds.
    """
    cuda = result["device"].startswith("cuda")
    full, partial = result["views"]
    parts = [
        f"GeoLoRA step time: random DINOv3 {result['model']}",
        f"{result['image_size']} x {result['image_size']}",
        f"{full} + {result['partials_per_step']} x {partial} views",
        result["device"] + (f" ({result['gpu']})" if result.get("gpu") else ""),
    ]
    if "workers" in result:
        parts.append(f"{result['workers']} sample worker(s)")
    autocast = result.get("autocast")
    if autocast is None and "workers" in result:  # recorded before "autocast": the trainer's rule then and now
        autocast = result["amp"] == "on" or (result["amp"] == "auto" and cuda)
    if autocast is not None:
        parts.append("bfloat16 autocast" if autocast else "float32")
    recipe = result.get("recipe", result.get("preset"))
    if recipe is not None:
        parts += [f"recipe {recipe}", f"back-projection {result.get('backproject') or 'of the recipe'}"]
    timing = f"median seconds of {result['steps_timed']} steps"
    if "wall_steps_per_second" in result:
        timing += (
            f" (step: the sum of the phases, {'device time between CUDA events' if cuda else 'wall time'}; wall: the timed "
            f"steps' wall clock, {result['hours_for_50000_steps']:.1f} h for 50,000 steps)"
        )
    parts.append(timing)
    return ", ".join(parts) + f"; {result['machine']}, {result['date']}"


def table(result: dict) -> str:
    """The caption, then two tables: the phases up to the back-projection, and the rest with the step's totals.

    The wall rate and the GPU memory are columns only where the record holds them.
    """
    seconds = result["median_seconds"]
    first, second = PHASES[: PHASES.index("backproject") + 1], PHASES[PHASES.index("backproject") + 1 :]
    heads, cells = list(second) + ["step", "steps/s"], [f"{seconds[p]:.3f}" for p in second]
    cells += [f"{result['median_step_seconds']:.3f}", f"{result['steps_per_second']:.2f}"]
    if "wall_steps_per_second" in result:
        heads.append("wall steps/s")
        cells.append(f"{result['wall_steps_per_second']:.2f}")
    if result.get("peak_cuda_memory_gib") is not None:
        heads.append("peak GPU memory")
        cells.append(f"{result['peak_cuda_memory_gib']:.2f} GiB")
    return "\n".join(
        [
            caption(result),
            "",
            "| " + " | ".join(first) + " |",
            "|" + "---|" * len(first),
            "| " + " | ".join(f"{seconds[p]:.3f}" for p in first) + " |",
            "",
            "| " + " | ".join(heads) + " |",
            "|" + "---|" * len(heads),
            "| " + " | ".join(cells) + " |",
        ]
    )


def write_markdown(out: Path, result: dict) -> None:
    """``OUT.md``, and ``OUT_profile.md`` where the run was profiled (date, machine and GPU above it)."""
    out.with_name(f"{out.name}.md").write_text(table(result) + "\n")
    if "profile" in result:
        path = out.with_name(f"{out.name}_profile.md")
        what = f"3 GeoLoRA steps under torch.profiler ({caption(result).split(', median')[0]})"
        path.write_text(profile_markdown(what, result, stored_profile_tables(result, path), where=result.get("gpu")))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", choices=sorted(MODELS), default="small")
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--views-full", type=int, default=9)
    parser.add_argument("--views-partial", type=int, default=4)
    parser.add_argument("--recipe", choices=("default", "reference"), default="default", help="TrainConfig.recipe")
    parser.add_argument("--backproject", default=None, help="default: the recipe's (ball; ball_last under reference)")
    parser.add_argument(
        "--out", help="writes OUT.json and OUT.md (default benchmarks/results/speed_geolora_<model>_<size>_<device>[_<recipe>])"
    )
    parser.add_argument("--steps", type=int, default=20, help="timed steps (plus one warm-up)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--amp", default="auto")
    parser.add_argument(
        "--workers",
        type=lambda text: text if text == "auto" else int(text),
        default="auto",
        help="sample worker processes (TrainConfig.workers): 0 prepares each sample inside the step; "
        "with workers the partial column is the time a step waited for them (default auto: 0 on the CPU)",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help="profile 3 more steps with torch.profiler (OUT_profile.md: kernels and host operations)",
    )
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument(
        "--render-only", action="store_true", help="rewrite OUT.md (and OUT_profile.md) from OUT.json; run nothing (needs --out)"
    )
    args = parser.parse_args(argv)
    if args.render_only:
        if not args.out:
            parser.error("--render-only needs --out, the OUT of an earlier run")
        out = Path(args.out)
        write_markdown(out, read_results(out))
        return 0
    data_root = str(data_folder(args.data_root, "--data-root"))

    with tempfile.TemporaryDirectory() as tmp:
        config = TrainConfig(
            data="faust_r",
            data_root=data_root,
            split="train",
            first=10,
            out=tmp,
            image_size=args.image_size,
            views_full=args.views_full,
            views_partial=args.views_partial,
            recipe=args.recipe,
            backproject=args.backproject,
            steps=args.steps + 1,
            device=args.device,
            amp=args.amp,
            workers=args.workers,
            progress=False,
        )
        trainer = GeoLoraTrainer(config, backbone=random_backbone(args.model))
        trainer._start_or_resume()
        for mesh in trainer.shapes:
            trainer.geodesics.ensure(mesh)  # computed once per shape, outside the timed steps
        if trainer.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        records = [trainer.train_step()]  # warm-up (allocations; the sample workers start)
        start = time.perf_counter()
        records = [trainer.train_step() for _ in range(args.steps)]
        wall = (time.perf_counter() - start) / args.steps
        profile = profile_steps(trainer, 3) if args.profile else None
        trainer.close()  # the sample workers, if any
    seconds = {p: float(np.median([r.seconds.get(p, 0.0) for r in records])) for p in PHASES}
    step = float(np.median([sum(r.seconds.values()) for r in records]))
    result = {
        "model": args.model,
        "image_size": args.image_size,
        "views": [args.views_full, args.views_partial],
        "partials_per_step": config.partials_per_shape,
        "recipe": config.recipe,
        "device": str(trainer.device),
        "amp": config.amp,
        "workers": trainer.workers,
        "steps_timed": len(records),
        "median_seconds": seconds,
        "median_step_seconds": step,
        "steps_per_second": 1.0 / step,
        "wall_seconds_per_step": wall,
        "wall_steps_per_second": 1.0 / wall,
        "hours_for_50000_steps": 50000 * wall / 3600,
        "peak_cuda_memory_gib": torch.cuda.max_memory_allocated() / 2**30 if trainer.device.type == "cuda" else None,
        "machine": machine(),
        "date": datetime.date.today().isoformat(),
        "backproject": config.backproject,
        "autocast": trainer._autocast(),
    }
    if trainer.device.type == "cuda":
        result["gpu"] = torch.cuda.get_device_name(trainer.device)
    if profile is not None:
        result["profile"], result["profile_tables"] = profile
    recipe = "" if config.recipe == "default" else f"_{config.recipe}"
    out = Path(args.out or RESULTS / f"speed_geolora_{args.model}_{args.image_size}_{trainer.device.type}{recipe}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_name(f"{out.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    write_markdown(out, result)
    print(table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
