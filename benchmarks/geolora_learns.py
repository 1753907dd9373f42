"""Does the GeoLoRA machinery learn? Train on FAUST_r with a small random DINOv3, measure before/after.

No DINOv3 weights exist on a machine without the gated download, so this experiment uses a
small randomly initialised DINOv3-architecture backbone at reduced resolution. It trains one
LoRA adapter with the geodesic-weighted PointInfoNCE and one with the plain PointInfoNCE on
the FAUST_r training shapes (the first 80), each for a bounded wall time, and evaluates the
``geolora`` descriptor (49 views) with nearest-neighbour matching on ``faust_r_cuts`` and
``faust_r_holes`` test pairs before training (step 0: LoRA B = 0, i.e. the raw random
backbone) and after. Stages (all by default, in this order)::

    python benchmarks/geolora_learns.py --stage backbone       # random DINOv3 -> <work>/backbone
    python benchmarks/geolora_learns.py --stage train --loss geodesic --minutes 30
    python benchmarks/geolora_learns.py --stage train --loss plain --minutes 30
    python benchmarks/geolora_learns.py --stage evaluate --pairs 50
    python benchmarks/geolora_learns.py --stage report          # table + training-curve PNG

The two trainings can run at the same time (one thread each: ``--threads 1``).
Results go to ``benchmarks/results/geolora_learns/``; runs and the backbone to ``--work``.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch
from common import machine

from geofeat.evaluation.report import markdown_table

HERE = Path(__file__).resolve().parent

RESULTS = HERE / "results" / "geolora_learns"
LOSSES = ("geodesic", "plain")
DATASETS = ("faust_r_cuts", "faust_r_holes")
#: The small DINOv3: 4 blocks of width 96, patch 8, rendered at 128 x 128 (16 x 16 patches).
BACKBONE = {
    "hidden_size": 96,
    "intermediate_size": 384,
    "num_hidden_layers": 4,
    "num_attention_heads": 4,
    "patch_size": 8,
    "image_size": 128,
    "num_register_tokens": 4,
}
IMAGE_SIZE = 128
#: At 128 x 128 a pixel is wider than the 0.004-diagonal ball, so pixels go to their face's corners.
BACKPROJECT = "face"


def build_backbone(work: Path, seed: int) -> Path:
    """Save a randomly initialised DINOv3 (transformers' own initialisation, seeded) as a model folder."""
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    folder = work / "backbone"
    if (folder / "config.json").is_file():
        return folder
    torch.manual_seed(seed)
    DINOv3ViTModel(DINOv3ViTConfig(**BACKBONE)).save_pretrained(folder)
    return folder


def train(work: Path, loss: str, minutes: float, data_root: str, args) -> Path:
    """One GeoLoRA run on the 80 FAUST_r training shapes; returns the run folder."""
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    config = TrainConfig(
        data="faust_r", data_root=data_root, split="train", out=str(work / f"run_{loss}"),
        weights=str(build_backbone(work, args.seed)), image_size=IMAGE_SIZE, backproject=BACKPROJECT, loss=loss, lr=args.lr,
        steps=args.steps, max_minutes=minutes, checkpoint_every=args.checkpoint_every,
        validate_every=args.validate_every, val_dataset="faust_r_cuts", val_pairs=args.val_pairs,
        seed=args.seed, device="cpu", progress=not args.no_progress,
    )  # fmt: skip
    GeoLoraTrainer(config).fit()
    return Path(config.out)


def evaluate(work: Path, n_pairs: int, data_root: str, no_progress: bool) -> list[dict]:
    """NN P2F error of the geolora descriptor, before (step 0) and after each run, on both benchmarks."""
    import run as benchmark_run

    from geofeat.train.checkpoints import latest_checkpoint

    backbone = work / "backbone"
    adapters = {"before (step 0)": work / "run_geodesic" / "checkpoints" / "step_0000000"}
    for loss in LOSSES:
        final = latest_checkpoint(work / f"run_{loss}")
        if final is None:
            raise SystemExit(f"no checkpoint in {work / f'run_{loss}'}: run --stage train --loss {loss} first")
        adapters[f"after, {loss} loss ({final.name})"] = final
    rows = []
    for label, adapter in adapters.items():
        for dataset in DATASETS:
            out = RESULTS / f"{dataset}_{adapter.parent.parent.name}_{adapter.name}"
            argv = [
                "--pipeline", "nn", "--dataset", dataset, "--descriptor", "geolora", "--data-root", data_root,
                "--limit", str(n_pairs), "--out", str(out),
                "--param", f"checkpoint={adapter}", "--param", f"weights={backbone}",
                "--param", f"image_size={IMAGE_SIZE}", "--param", f"backproject={BACKPROJECT}", "--param", "device=cpu",
            ]  # fmt: skip
            if no_progress:
                argv.append("--no-progress")
            benchmark_run.main(argv)
            result = json.loads((out / "results.json").read_text())
            rows.append(
                {
                    "adapter": label,
                    "dataset": dataset,
                    **{k: result.get(k) for k in ("n_pairs", "geodesic_error", "pck_auc", "chirality_accuracy")},
                }
            )
    (RESULTS / "evaluation.json").write_text(json.dumps(rows, indent=1) + "\n")
    return rows


def _read_log(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(steps, losses) of training rows and (steps, errors) of validation rows."""
    steps, losses, val_steps, val_errors = [], [], [], []
    with open(path, newline="") as handle:
        for row in csv.DictReader(handle):
            if row["val_geodesic_error"]:
                val_steps.append(int(row["step"]))
                val_errors.append(float(row["val_geodesic_error"]))
            elif row["loss"] and row["loss"] != "nan":
                steps.append(int(row["step"]))
                losses.append(float(row["loss"]))
    return np.array(steps), np.array(losses), np.array(val_steps), np.array(val_errors)


def report(work: Path) -> None:
    """Markdown table and the training-curve figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = json.loads((RESULTS / "evaluation.json").read_text())
    columns = [
        ("adapter", "adapter", "s"), ("dataset", "dataset", "s"), ("n_pairs", "pairs", "d"),
        ("geodesic_error", "geodesic error x100", ".2f"), ("pck_auc", "PCK AUC", ".3f"),
        ("chirality_accuracy", "chirality acc.", ".3f"),
    ]  # fmt: skip
    runs = {}
    for loss in LOSSES:
        steps, losses, val_steps, val_errors = _read_log(work / f"run_{loss}" / "log.csv")
        config = json.loads((work / f"run_{loss}" / "config.json").read_text())
        runs[loss] = {"steps": int(steps.max()) if steps.size else 0, "config": config}
        runs[loss]["curve"] = (steps, losses, val_steps, val_errors)
    lines = [
        f"GeoLoRA learns: small random DINOv3 ({BACKBONE}), {IMAGE_SIZE} x {IMAGE_SIZE} renders, "
        f"machine: {machine()}, date {datetime.date.today().isoformat()}.",
        "",
        *(f"- {loss} loss: {r['steps']} steps in at most {r['config']['max_minutes']} min "
          f"(lr {r['config']['lr']}, {r['config']['views_full']} + {r['config']['views_partial']} views)" for loss, r in runs.items()),
        "",
        markdown_table(rows, columns),
    ]  # fmt: skip
    (RESULTS / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(11, 4))
    for loss, r in runs.items():
        steps, losses, val_steps, val_errors = r["curve"]
        window = max(1, len(losses) // 50)
        smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
        ax_loss.plot(steps[window - 1 :], smooth, label=f"{loss} loss (mean of {window} steps)")
        ax_val.plot(val_steps, val_errors, marker="o", label=f"{loss} loss")
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("training loss")
    ax_loss.set_title("training loss (the two losses have different scales)")
    ax_loss.legend()
    ax_val.set_xlabel("step")
    ax_val.set_ylabel("NN P2F geodesic error x100")
    ax_val.set_title("validation: faust_r_cuts test pairs (9 + 4 views)")
    ax_val.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / "training_curve.png", dpi=110)
    print(f"written to {RESULTS}")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--stage", choices=("all", "backbone", "train", "evaluate", "report"), default="all")
    parser.add_argument("--loss", choices=LOSSES, default=None, help="train stage: one loss (default both, one after the other)")
    parser.add_argument("--minutes", type=float, default=25.0, help="wall-time budget per training run")
    parser.add_argument("--steps", type=int, default=100000, help="step limit per run (the time budget usually ends it)")
    parser.add_argument("--lr", type=float, default=1e-3, help="1e-3: the random backbone learns 10x slower at the paper's 1e-4")
    parser.add_argument("--checkpoint-every", type=int, default=200)
    parser.add_argument("--validate-every", type=int, default=200)
    parser.add_argument("--val-pairs", type=int, default=10)
    parser.add_argument("--pairs", type=int, default=50, help="evaluation pairs per benchmark")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (1 when two runs share 2 cores)")
    parser.add_argument("--work", default=str(HERE.parent / "runs" / "geolora_learns"))
    parser.add_argument("--data-root", default=os.environ.get("GEOFEAT_DATA", str(HERE.parent.parent / "shared" / "data")))
    parser.add_argument("--no-progress", action="store_true")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.stage in ("all", "backbone"):
        print(f"backbone: {build_backbone(work, args.seed)}")
    if args.stage in ("all", "train"):
        for loss in [args.loss] if args.loss else LOSSES:
            train(work, loss, args.minutes, args.data_root, args)
    if args.stage in ("all", "evaluate"):
        evaluate(work, args.pairs, args.data_root, args.no_progress)
    if args.stage in ("all", "report"):
        report(work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
