"""Before and after on one GPU: the multi-view DINO path and a GeoLoRA step, stage by stage.

Reads the JSON results that `speed/dino.py` and `speed/geolora.py` wrote for the code as it
was (``<folder>/before/``) and as it is (``<folder>/``), measured on the same kind of GPU, and
writes ``<folder>/before_after.md`` (seconds per stage, peak GPU memory and the ratio) and
``<folder>/before_after_short.md`` (the two headline rows, for the README); with the results of
`speed/heads.py` and `speed/dsmk_ulrssm.py` of one run in the folder, also ``<folder>/heads_vs_dsmk.md``.

    python -m benchmarks.speed.dino --device cuda --repeats 5 --out benchmarks/results/h100/speed_dino_bf16
    python -m benchmarks.speed.geolora --model vitb16 --image-size 512 --device cuda --steps 20 \\
        --out benchmarks/results/h100/speed_geolora_vitb16_512_cuda
    python -m benchmarks.speed.gpu_before_after --folder benchmarks/results/h100

(the ``before/`` files come from the same two scripts run on an earlier version of geofeat).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

#: Where the benchmark scripts' results land.
RESULTS = Path(__file__).resolve().parents[1] / "results"
VIT_B = "ViT-B/16 size (12 layers, width 768)"
DINO_STAGES = ("render", "backbone", "backproject", "total")
GEOLORA_PHASES = ("geodesics", "partial", "render", "forward", "backproject", "loss", "backward", "optimizer")


def _ratio(before: float, after: float) -> str:
    return f"{before / after:.1f}x" if after > 0 else "-"


def dino_table(before: dict, after: dict) -> list[str]:
    """Rows of the ViT-B/16-size backbone, before and after (the pass without stage synchronisations when both have it)."""
    old = next(r for r in before["rows"] if r["name"] == VIT_B)
    new = next(r for r in after["rows"] if r["name"] == VIT_B)
    stages = DINO_STAGES + (("wall",) if "wall" in old and "wall" in new else ())
    lines = [
        f"Multi-view DINO path, one FAUST_r shape ({after['vertices']} vertices), {after['views']} views at "
        f"{after['image_size']} x {after['image_size']}, random DINOv3 of ViT-B/16 size, "
        f"{'bfloat16 autocast' if after['autocast'] else 'float32'}, median of {after['repeats']} passes, "
        f"{after['gpu']}. Before: {before['date']}, views per batch {before['batch_size']}; "
        f"after: {after['date']}, views per batch {after['batch_size']}. Stages are timed with the device "
        "synchronised at their ends (total: their sum); wall: a pass timed as a whole, as the descriptors run it.",
        "",
        "| seconds per shape | " + " | ".join(stages) + " |",
        "|---|" + "---|" * len(stages),
        "| before | " + " | ".join(f"{old[s]:.3f}" for s in stages) + " |",
        "| after | " + " | ".join(f"{new[s]:.3f}" for s in stages) + " |",
        "| speed-up | " + " | ".join(_ratio(old[s], new[s]) for s in stages) + " |",
    ]
    if new.get("peak_gib") is not None:
        lines += ["", f"Peak GPU memory after: {new['peak_gib']:.2f} GiB."]
    return lines


def _wall(result: dict) -> float:
    """Seconds per GeoLoRA step, wall clock (the phase sum for results that lack it)."""
    return result.get("wall_seconds_per_step", result["median_step_seconds"])


def geolora_table(before: dict, after: dict) -> list[str]:
    """Median seconds per phase of a GeoLoRA step, before and after, and the wall-clock steps/s."""
    old, new = before["median_seconds"], after["median_seconds"]
    lines = [
        f"GeoLoRA training step at the paper's settings (DINOv3 ViT-B/16 size, {after['image_size']} x "
        f"{after['image_size']}, {after['views'][0]} + {after['partials_per_step']} x {after['views'][1]} views, "
        f"recipe {after.get('recipe', 'default')}, bfloat16 autocast), median seconds per phase. Before: {before['date']}, "
        f"{before['steps_timed']} steps, {before.get('workers', 0)} sample workers; after: {after['date']}, "
        f"{after['steps_timed']} steps, {after.get('workers', 0)} sample workers. Step: the sum of the phases; "
        "wall: the timed steps end to end.",
        "",
        "| | " + " | ".join(GEOLORA_PHASES) + " | step | wall steps/s | 50,000 steps |",
        "|---|" + "---|" * (len(GEOLORA_PHASES) + 3),
    ]
    for label, result, phases in (("before", before, old), ("after", after, new)):
        wall = _wall(result)
        lines.append(
            f"| {label} | "
            + " | ".join(f"{phases[p]:.3f}" for p in GEOLORA_PHASES)
            + f" | {result['median_step_seconds']:.3f} | {1 / wall:.2f} | {50000 * wall / 3600:.1f} h |"
        )
    lines += ["", f"Wall clock after: {_wall(before) / _wall(after):.1f}x the speed before."]
    return lines


def short_table(load, args) -> list[str]:
    """The two headline rows: seconds per shape of the DINO path, wall-clock steps/s of GeoLoRA."""
    before_dino, after_dino = load("before", args.dino), load(args.dino)
    old_dino = next(r for r in before_dino["rows"] if r["name"] == VIT_B)
    new_dino = next(r for r in after_dino["rows"] if r["name"] == VIT_B)
    key = "wall" if "wall" in old_dino and "wall" in new_dino else "total"
    old_step, new_step = _wall(load("before", args.geolora)), _wall(load(args.geolora))
    return [
        f"| {after_dino['gpu']} | before | after | |",
        "|---|---|---|---|",
        f"| DINOv3 ViT-B/16 features of one 5k-vertex shape, 49 views at 512 x 512 | {old_dino[key]:.3f} s | "
        f"{new_dino[key]:.3f} s | {old_dino[key] / new_dino[key]:.1f}x |",
        f"| GeoLoRA training at the paper's settings | {1 / old_step:.2f} steps/s | {1 / new_step:.2f} steps/s | "
        f"{old_step / new_step:.1f}x |",
        "",
        f"{after_dino['date']}, {after_dino['machine']}; random weights of the paper's backbone size, bfloat16 autocast.",
    ]


def heads_table(ours: dict, dsmk: dict) -> list[str]:
    """Our ULRSSM training step beside DeepShapeMatchingKit's, measured on the same GPU in the same run."""
    ulrssm = next(r for r in ours["rows"] if r["head"] == "ulrssm")
    ours_ms = 1000.0 * ulrssm["seconds"] / ulrssm["steps"]
    theirs_ms = dsmk["step"]["mean_ms"]
    return [
        f"ULRSSM training step at the authors' FAUST_r setting, {ours['gpu']}, {ours['date']}: geofeat's "
        f"(`speed/heads.py`, mean over {ulrssm['steps']} steps of one pass) beside DeepShapeMatchingKit's own iteration "
        f"(`speed/dsmk_ulrssm.py`, {dsmk['dsmk_commit'][:10]}, mean over {dsmk['step']['iterations']} iterations on "
        "batches in memory), one pair per step.",
        "",
        "| ULRSSM step | ms | steps/s |",
        "|---|---|---|",
        f"| DeepShapeMatchingKit | {theirs_ms:.1f} | {1000.0 / theirs_ms:.1f} |",
        f"| geofeat | {ours_ms:.1f} | {1000.0 / ours_ms:.1f} |",
        "",
        f"geofeat's step takes {ours_ms / theirs_ms:.2f} of DeepShapeMatchingKit's time ({theirs_ms / ours_ms:.2f}x its speed).",
    ]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--folder", default=str(RESULTS / "h100"))
    parser.add_argument("--dino", default="speed_dino_bf16.json")
    parser.add_argument("--geolora", default="speed_geolora_vitb16_512_cuda.json")
    parser.add_argument("--heads", default="speed_heads.json", help="speed/heads.py's result (for heads_vs_dsmk.md)")
    parser.add_argument("--dsmk", default="speed_dsmk_ulrssm.json", help="speed/dsmk_ulrssm.py's result, same run")
    args = parser.parse_args(argv)
    folder = Path(args.folder)

    def load(*parts: str) -> dict:
        return json.loads(folder.joinpath(*parts).read_text())

    lines = dino_table(load("before", args.dino), load(args.dino))
    lines += [""] + geolora_table(load("before", args.geolora), load(args.geolora))
    after_dino = load(args.dino)
    lines += ["", f"Machine: {after_dino['machine']}."]
    (folder / "before_after.md").write_text("\n".join(lines) + "\n")
    (folder / "before_after_short.md").write_text("\n".join(short_table(load, args)) + "\n")
    if (folder / args.heads).is_file() and (folder / args.dsmk).is_file():
        heads = heads_table(load(args.heads), load(args.dsmk))
        (folder / "heads_vs_dsmk.md").write_text("\n".join(heads) + "\n")
        lines += ["", *heads]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
