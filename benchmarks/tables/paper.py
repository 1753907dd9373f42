"""The GeoLoRA paper's tables in one command: nearest neighbour on DINOv3 and GeoLoRA features, and the heads.

For each benchmark of the paper's nearest-neighbour table (BeCoS P2F, SHREC'16 CUTS, PFAUST-H
P2F, BeCoS P2P, PSMAL P2P; ``--benchmarks`` takes any of the eight of
`geofeat.evaluation.paper_benchmarks.PAPER_BENCHMARKS`), with the official evaluation protocol
(its pairs, frames, evaluated points, distances and pooling):

1. the features of every shape, computed once and kept in a feature store (``--cache``):
   DINOv3 and GeoLoRA (the release LoRA file the benchmark's test configuration names, from
   ``--lora-dir``), both with the official recipe (``recipe="reference"``: 49 views at 512 x
   512), in the frame the official code renders the shapes in;
2. each partial vertex matched to its nearest full vertex in feature space (``torch.cdist``,
   then the smallest, as the official code);
3. with ``--head FOLDER`` (a head saved by ``Head.save``: ULRSSM, DPFM or EchoMatch, on the
   input its configuration names), the head's matches on the same pairs; ULRSSM also after
   test-time adaptation (``--tta-steps``, default its configuration's, or 15).

Each row's errors are pooled over the evaluated points of all its pairs, x100, beside the
published figure (``benchmarks/results/real_files/published_figures.json``, entries with a
``paper_rows`` field) and the difference. A row whose results exist in ``OUT`` is not
repeated (``--force``), and features in the store are never recomputed, so an interrupted run
continues where it stopped (``--cache``: where the features and geodesic matrices are kept,
default ``OUT/cache``). Before computing, the run says how many shapes are left and how
long they should take, from the speed of the first shape.

Data: ``--data NAME=FOLDER``, NAME a benchmark or a group (``becos``: both BeCoS settings,
``pfaust``: PFAUST-M and -H, ``shrec16``: CUTS and HOLES, ``psmal``, ``cp2p``). A benchmark
without data is listed with where its files come from, not run.

    python -m benchmarks.tables.paper --weights dinov3-vitb16 --lora-dir geo-lora/saved_models \\
        --data becos=BeCoS --data psmal=PARTIALSMAL/test --data pfaust=FAUST_r --data shrec16=SHREC16_test \\
        --head heads/ulrssm_geolora --out runs/paper

``--random-weights DIR`` writes a DINOv3 of the paper's size (``--backbone vitb``, or ``tiny``
for a quick check) and four LoRA files in the release layout, all random, into DIR and uses
them: the run then shows the commands, pair counts and timings, not meaningful errors.
``--views`` and ``--image-size`` override the recipe's 49 views at 512 (for such checks only).
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import geofeat
from benchmarks.common import RESULTS, machine
from geofeat.datasets.records import Match
from geofeat.descriptors import make_descriptor
from geofeat.descriptors.collection import compute_each
from geofeat.errors import GeofeatError
from geofeat.evaluation import evaluate_dataset, summarize
from geofeat.evaluation.paper_benchmarks import (
    FLIP_X_180,
    PAPER_BENCHMARKS,
    ROTATE_X_90,
    PaperBenchmark,
    framed,
    paper_pairs,
)
from geofeat.geometry.geodesic_store import GeodesicStore

PUBLISHED = RESULTS / "real_files" / "published_figures.json"
#: The paper's nearest-neighbour table, in its order.
PAPER_TABLE = ("becos_p2f", "shrec16_cuts", "pfaust_hard", "becos_p2p", "psmal")
GROUPS = {
    "becos": ("becos_p2f", "becos_p2p"),
    "pfaust": ("pfaust_medium", "pfaust_hard"),
    "shrec16": ("shrec16_cuts", "shrec16_holes"),
}
INPUTS = ("dinov3", "geolora")
#: Sizes of the random DINOv3 of ``--random-weights``.
RANDOM_BACKBONES = {
    "vitb": dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12),
    "tiny": dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2),
}
#: Rank of the release LoRA checkpoints (alpha 32).
RELEASE_RANK = 16

log = logging.getLogger("paper")


# ----------------------------------------------------------------------------- inputs


def data_folders(given: list[str]) -> dict[str, Path]:
    """``NAME=FOLDER`` arguments as ``{benchmark: folder}`` (groups spread over their benchmarks)."""
    folders: dict[str, Path] = {}
    for item in given:
        name, sep, folder = item.partition("=")
        if not sep or not folder:
            raise SystemExit(f"--data takes NAME=FOLDER; found {item!r}")
        names = GROUPS.get(name, (name,))
        unknown = [n for n in names if n not in PAPER_BENCHMARKS]
        if unknown:
            raise SystemExit(f"--data: unknown benchmark {name!r}; known: {', '.join([*GROUPS, *PAPER_BENCHMARKS])}")
        for n in names:
            folders[n] = Path(folder)
    return folders


def write_random_release(folder: Path, backbone: str) -> tuple[Path, Path]:
    """A random DINOv3 (Hugging Face folder) and random LoRA files in the release layout; returns (weights, lora dir)."""
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    weights, lora_dir = folder / f"dinov3_{backbone}", folder / "saved_models"
    sizes = RANDOM_BACKBONES[backbone]
    if not (weights / "config.json").is_file():
        torch.manual_seed(0)
        config = DINOv3ViTConfig(patch_size=16, image_size=224, num_register_tokens=4, **sizes)
        DINOv3ViTModel(config).save_pretrained(weights)
    lora_dir.mkdir(parents=True, exist_ok=True)
    width, depth = sizes["hidden_size"], sizes["num_hidden_layers"]
    for index, name in enumerate(sorted({b.lora for b in PAPER_BENCHMARKS.values()})):
        if (lora_dir / name).is_file():
            continue
        generator = torch.Generator().manual_seed(index)
        state = {}
        for block in range(depth):
            prefix = f"base_model.model.blocks.{block}.attn.qkv"
            state[f"{prefix}.lora_A.default.weight"] = 0.02 * torch.randn(RELEASE_RANK, width, generator=generator)
            state[f"{prefix}.lora_B.default.weight"] = 0.02 * torch.randn(3 * width, RELEASE_RANK, generator=generator)
        torch.save(state, lora_dir / name)
    return weights, lora_dir


def published_rows() -> dict[str, tuple[float, str]]:
    """``{row id: (figure, source)}`` from the ``paper_rows`` of the published-figures file."""
    rows = {}
    for entry in json.loads(PUBLISHED.read_text()):
        for row in entry.get("paper_rows", []):
            rows[row["row"]] = (float(row["value"]), entry["source"])
    return rows


# ----------------------------------------------------------------------------- one benchmark


def shape_features(pairs, benchmark: PaperBenchmark, descriptor, store, progress: bool) -> dict[str, np.ndarray]:
    """Features of every shape of the pairs, in the benchmark's frame: ``{mesh hash (as stored): (V, C)}``.

    Shapes in the store are read; after the first shape computed, the time the others should
    take is logged.
    """
    meshes: dict[str, geofeat.Mesh] = {}
    for index in range(len(pairs)):
        pair = pairs[index]
        for mesh in (pair.x, pair.y):
            meshes.setdefault(mesh.hash, mesh)
    shapes = list(meshes.values())
    features, estimated = {}, False
    start = time.perf_counter()
    label = f"{benchmark.title}, {descriptor.name}"
    for outcome in compute_each([framed(m, benchmark) for m in shapes], descriptor, store, progress=progress, desc=label):
        if outcome.status == "failed":
            raise outcome.error
        features[shapes[outcome.index].hash] = outcome.features
        if outcome.status == "computed" and not estimated:
            seconds, left = time.perf_counter() - start, len(shapes) - outcome.index - 1
            log.info(
                "%s: %d shapes; the first computed took %.1f s, so about %.0f s for the %d left",
                label,
                len(shapes),
                seconds,
                seconds * left,
                left,
            )
            estimated = True
        start = time.perf_counter()
    return features


def nearest_match(features: dict[str, np.ndarray]):
    """The matcher of the official code: each vertex of y to the full vertex of least feature distance."""

    def match(index, pair) -> Match:
        fx = torch.from_numpy(features[pair.x.hash]).float()
        fy = torch.from_numpy(features[pair.y.hash]).float()
        predicted = torch.min(torch.cdist(fy, fx), dim=1).indices.numpy().astype(np.int64)
        return Match(predicted, np.ones(predicted.size, dtype=bool))

    return match


def head_match(head, benchmark: PaperBenchmark):
    """A saved head's matcher, on the pair in the benchmark's frame."""

    def match(index, pair) -> Match:
        return head.match(replace(pair, x=framed(pair.x, benchmark), y=framed(pair.y, benchmark)))

    return match


def run_benchmark(benchmark: PaperBenchmark, folder: Path, args, store, geodesics) -> list[dict]:
    """The rows of one benchmark: ``{"row", "benchmark", "pipeline", "n_pairs", "n_points", "error", "seconds"}``."""
    cuts_list = args.cuts_list if benchmark.name == "shrec16_cuts" else None
    pairs = paper_pairs(benchmark, folder, split=args.split, cuts_list=cuts_list)
    common = {"recipe": "reference", "weights": str(args.weights), "device": args.device}
    common.update({k: v for k, v in (("views", args.views), ("image_size", args.image_size)) if v is not None})
    matchers, feature_seconds = {}, {}
    for name in INPUTS:
        params = dict(common)
        if name == "geolora":
            params["checkpoint"] = str(args.lora_dir / benchmark.lora)
        descriptor = make_descriptor(name, **params)
        start = time.perf_counter()
        features = shape_features(pairs, benchmark, descriptor, store, args.progress)
        feature_seconds[name] = time.perf_counter() - start
        matchers[f"nn/{name}"] = nearest_match(features)
    for head_folder in args.head:
        from geofeat.adapters.heads import load_head

        head = load_head(head_folder)
        matchers[f"{head.name}/{head.config.descriptor}"] = head_match(head, benchmark)
        if head.name == "ulrssm":
            tta = load_head(head_folder)
            tta.config = replace(tta.config, tta_steps=args.tta_steps or head.config.tta_steps or 15)
            matchers[f"ulrssm_tta/{head.config.descriptor}"] = head_match(tta, benchmark)
    start = time.perf_counter()
    records, _ = evaluate_dataset(
        pairs, matchers, protocol=benchmark.points, store=geodesics, progress=args.progress, desc=benchmark.title
    )
    seconds = time.perf_counter() - start
    rows = []
    for pipeline, recs in records.items():
        summary = summarize(recs)
        rows.append(
            {
                "row": f"{benchmark.name}/{pipeline}",
                "benchmark": benchmark.name,
                "title": benchmark.title,
                "pipeline": pipeline,
                "n_pairs": summary.n_pairs,
                "n_points": summary.n_evaluated_vertices,
                "error": summary.geodesic_error,
                "miou": summary.miou,
                "n_shapes": len(features),
                "feature_seconds": feature_seconds.get(pipeline.split("/")[1]) if pipeline.startswith("nn/") else None,
                "match_and_evaluate_seconds": seconds,
            }
        )
    if args.random_weights:  # errors of random weights mean nothing: not kept
        rows = [{k: v for k, v in r.items() if k not in ("error", "miou")} for r in rows]
    return rows


# ----------------------------------------------------------------------------- the table


def expected_seconds(n_shapes: int) -> tuple[float | None, float | None]:
    """Seconds to compute the features of ``n_shapes`` shapes twice (DINOv3, GeoLoRA) at 49 views of 512 x 512.

    From the measured seconds per shape of a ViT-B/16-size DINOv3 (`speed/dino.py`): on the
    2-core CPU (float32) and on an H100 (float32, the reference recipe's precision); None
    where no measurement is there.
    """

    def per_shape(path: Path, column: str) -> float | None:
        if not path.is_file():
            return None
        row = next((r for r in json.loads(path.read_text())["rows"] if r["name"].startswith("ViT-B/16 size (")), None)
        return None if row is None else row.get(column, row["total"])

    cpu = per_shape(RESULTS / "speed_dino.json", "total")
    gpu = per_shape(RESULTS / "h100" / "speed_dino_fp32.json", "wall")
    return tuple(None if s is None else 2 * n_shapes * s for s in (cpu, gpu))


def duration(seconds: float) -> str:
    """``"45 s"``, ``"3.2 min"`` or ``"2.2 h"``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def table(rows: list[dict], missing: list[PaperBenchmark], failed: list, published: dict, setting: str, meaningful: bool) -> str:
    """The Markdown table of the rows, the published figures beside them, the benchmarks without data or that failed.

    With random weights (``meaningful`` False) the errors are left out: the table then shows
    what the run did (pairs, points, shapes, seconds).
    """
    lines = [
        f"The GeoLoRA paper's benchmarks with the official evaluation protocol: {setting}. "
        + (
            "Mean geodesic error x100, pooled over the evaluated points of all pairs, beside the published figure."
            if meaningful
            else "Random weights: the errors mean nothing and are left out; features (s): that input's features of every shape."
        )
        + " `python -m benchmarks.tables.paper`.",
        "",
    ]
    if meaningful:
        lines += [
            "| benchmark | pipeline | pairs | points | error x100 | published | difference |",
            "|---|---|---|---|---|---|---|",
        ]
    else:
        lines += [
            "| benchmark | pipeline | pairs | points | shapes | features (s) | matching and evaluation (s) |",
            "|---|---|---|---|---|---|---|",
        ]
    sources: list[str] = []
    for r in rows:
        head = f"| {r['title']} | {r['pipeline']} | {r['n_pairs']} | {r['n_points']} |"
        if not meaningful:
            seconds = "-" if r.get("feature_seconds") is None else f"{r['feature_seconds']:.1f}"
            lines.append(f"{head} {r.get('n_shapes', '-')} | {seconds} | {r['match_and_evaluate_seconds']:.1f} |")
            continue
        figure = published.get(r["row"])
        if figure is None:
            cells = "- | -"
        else:
            if figure[1] not in sources:
                sources.append(figure[1])
            cells = f"{figure[0]:.2f} [{sources.index(figure[1]) + 1}] | {r['error'] - figure[0]:+.2f}"
        lines.append(f"{head} {r['error']:.2f} | {cells} |")
    if sources:
        lines += ["", *[f"[{n}] {s}" for n, s in enumerate(sources, 1)]]
    shapes = {r["benchmark"]: (r["title"], r.get("n_shapes")) for r in rows if r.get("n_shapes")}
    if shapes:
        lines += ["", "Features at the paper's setting (49 views at 512 x 512, DINOv3 and GeoLoRA), from measured speeds:", ""]
        for title, n in shapes.values():
            cpu, gpu = expected_seconds(n)
            where = [f"{duration(cpu)} on the 2-core CPU" if cpu else None, f"{duration(gpu)} on an H100" if gpu else None]
            lines.append(f"- {title}: {n} shapes, about {' and '.join(w for w in where if w) or 'no measurement'}.")
    if missing:
        lines += ["", "Not run, no data given (`--data NAME=FOLDER`):", ""]
        lines += [f"- {b.title}: {b.data}." for b in missing]
    if failed:
        lines += ["", "Not run, the data could not be read:", ""]
        lines += [f"- {b.title}: {why}" for b, why in failed]
    return "\n".join(lines)


FRAMES = {None: "as stored", ROTATE_X_90: "90 degrees about x", FLIP_X_180: "180 degrees about x"}
DISTANCE_WORDS = {
    "sqrt_area": "over sqrt(area) of x",
    "recorded": "over BeCoS's recorded sqrt(area) of x's full shape",
    "raw": "raw (mesh units)",
}


def describe() -> str:
    """The benchmarks as the official protocol evaluates them, with the published nearest-neighbour figures."""
    published = published_rows()
    lines = [
        "| benchmark | dataset (`--data`) | evaluated points | geodesic errors | features' frame | LoRA file | "
        "published nn, DINOv3 / GeoLoRA |",
        "|---|---|---|---|---|---|---|",
    ]
    for b in PAPER_BENCHMARKS.values():
        points = "each kept template point" if b.points == "template" else "each partial vertex with a counterpart"
        figures = [published.get(f"{b.name}/nn/{name}") for name in INPUTS]
        shown = " / ".join("-" if f is None else f"{f[0]:.2f}" for f in figures)
        group = next((g for g, names in GROUPS.items() if b.name in names), b.name)
        lines.append(
            f"| {b.title} | `{b.dataset}` (`{group}`) | {points} | {DISTANCE_WORDS[b.distances]} | {FRAMES[b.frame]} | "
            f"`{b.lora}` | {shown} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", type=Path, help="DINOv3 ViT-B/16 weights (a Hugging Face folder or Meta's .pth)")
    parser.add_argument("--lora-dir", type=Path, help="the release's saved_models/ (becos.pth, faust.pth, smal.pth, ...)")
    parser.add_argument("--random-weights", type=Path, metavar="DIR", help="write and use random weights (see above)")
    parser.add_argument("--backbone", choices=sorted(RANDOM_BACKBONES), default="vitb", help="size of --random-weights")
    parser.add_argument("--data", action="append", default=[], metavar="NAME=FOLDER")
    parser.add_argument("--benchmarks", nargs="+", choices=sorted(PAPER_BENCHMARKS), default=list(PAPER_TABLE))
    parser.add_argument("--head", action="append", default=[], metavar="FOLDER", help="a saved head (repeatable)")
    parser.add_argument("--tta-steps", type=int, help="ULRSSM's test-time adaptation steps (default its config's, or 15)")
    parser.add_argument("--cuts-list", type=Path, help="SHREC'16 CUTS: the partial shapes to evaluate (one file name a line)")
    parser.add_argument("--split", default="test", help="the datasets' split (the paper's: test; others for checks only)")
    parser.add_argument("--views", type=int, help="override the recipe's 49 views (checks only)")
    parser.add_argument("--image-size", type=int, help="override the recipe's 512 x 512 (checks only)")
    parser.add_argument("--device", default="auto")
    parser.add_argument(
        "--out", type=Path, default=Path("runs/paper"), help="results (paper.md, paper.json, one JSON a benchmark)"
    )
    parser.add_argument("--cache", type=Path, help="features and geodesic matrices (default OUT/cache)")
    parser.add_argument("--force", action="store_true", help="repeat rows whose results exist")
    parser.add_argument("--no-progress", dest="progress", action="store_false")
    parser.add_argument("--describe", type=Path, metavar="OUT.md", help="only write the table of the benchmarks")
    args = parser.parse_args(argv)
    if args.describe:
        args.describe.parent.mkdir(parents=True, exist_ok=True)
        args.describe.write_text(describe() + "\n")
        print(describe())
        return 0
    if args.random_weights:
        args.weights, args.lora_dir = write_random_release(args.random_weights, args.backbone)
    if not (args.weights and args.lora_dir):
        parser.error("give --weights and --lora-dir, or --random-weights DIR")
    folders = data_folders(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    cache = args.cache or args.out / "cache"
    store = geofeat.FeatureCache(cache / "features")
    geodesics = GeodesicStore(cache / "geodesics")
    rows, missing, failed = [], [], []
    for name in args.benchmarks:
        benchmark = PAPER_BENCHMARKS[name]
        if name not in folders:
            missing.append(benchmark)
            continue
        done = args.out / f"{name}.json"
        if done.is_file() and not args.force:
            rows += json.loads(done.read_text())["rows"]
            continue
        try:
            found = run_benchmark(benchmark, folders[name], args, store, geodesics)
        except GeofeatError as err:
            log.error("%s: %s", benchmark.title, err)
            why = str(err).splitlines()[0].replace(str(folders[name].resolve()), "the folder given")
            failed.append((benchmark, why.replace(str(folders[name]), "the folder given")))
            continue
        done.write_text(json.dumps({"rows": found, "date": datetime.date.today().isoformat()}, indent=1) + "\n")
        rows += found
    views = args.views or 49
    size = args.image_size or 512
    setting = f"{views} views at {size} x {size}, {'random weights (' + args.backbone + ')' if args.random_weights else 'the given weights'}"
    text = table(rows, missing, failed, published_rows(), setting, meaningful=not args.random_weights)
    text += f"\n\n{datetime.date.today().isoformat()}, {machine()}.\n"
    (args.out / "paper.md").write_text(text)
    (args.out / "paper.json").write_text(
        json.dumps(
            {
                "rows": rows,
                "missing": [b.name for b in missing],
                "failed": {b.name: why for b, why in failed},
                "split": args.split,
                "setting": setting,
                "machine": machine(),
            },
            indent=1,
        )
        + "\n"
    )
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
