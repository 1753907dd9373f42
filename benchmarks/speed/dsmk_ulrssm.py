"""Training step time of DeepShapeMatchingKit's own ULRSSM, at its FAUST_r training configuration.

The counterpart of ``speed/heads.py`` (our ULRSSM head): this script times the reference code,
DeepShapeMatchingKit (DSMK, github.com/xieyizheng/DeepShapeMatchingKit), imported from a
checkout given by ``--dsmk``; no DSMK code is copied here. Everything is DSMK's: the options
file ``options/ulrssm/train/faust.yaml`` read by its option parser (only the data root and the
GPU count are set), its ``PairFaustDataset``, whose items compute and cache the spectral
operators with DSMK's ``get_operators`` (its preprocessing), its data loader, and its
``ULRSSM_Model`` built by ``build_model``. One training iteration is what DSMK's ``train.py``
does per batch::

    model.feed_data(batch); model.optimize_parameters(); model.update_model_per_iteration()

Two timings, both after ``--warmup`` untimed iterations, with the device synchronised:

- ``step``: the iteration above on batches already produced by DSMK's loader and held in
  memory (as CPU tensors, as the loader gives them; ``feed_data`` moves them to the device),
  the closest to what ``speed/heads.py`` times for our head;
- ``loader``: DSMK's ``train.py`` loop, the iteration plus waiting for the next batch of its
  data loader (one worker, which reads the meshes and the cached operators), timed like its
  ``iter_timer``.

Data: DSMK reads ULRSSM's preprocessed FAUST_r (each mesh centred and scaled to unit area,
ULRSSM's ``preprocess.py``). That layout is made in ``--work`` from our FAUST_r files with
DSMK's own functions (``read_shape``, ``laplacian_decomposition``, ``write_off``). Only the
first ``--shapes`` training shapes are written; DSMK's FAUST dataset asserts 100 ``.off``
files, so the others are empty placeholders that are never read; the timed pairs are all
ordered pairs of the written shapes (same pairs included, as DSMK's ``include_same_pair``).

Packages DSMK imports but this path never calls are replaced by stand-ins when they are not
installed (``torchvision``, ``wandb``, ``igl``); ``open3d``, whose ``read_triangle_mesh``
DSMK's ``read_shape`` calls, is replaced by a plain OFF reader returning arrays of the same
types (float64 vertices, int32 triangles). Its float64 values can differ from open3d's
parser in the last bit; rounded to float32, as DSMK's dataset uses them (and keys its
operator cache on them), they were equal for tr_reg_000-004. The result records which
stand-ins were used.

Usage::

    python -m benchmarks.speed.dsmk_ulrssm --dsmk /tmp/dsmk --work /tmp/dsmk_work \\
        --data-root ../shared/data --device auto --iters 20

Writes ``OUT.json`` and ``OUT.md`` (default ``benchmarks/results/speed_dsmk_ulrssm``); ``--render-only``
rewrites ``OUT.md`` from ``OUT.json``, running nothing.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import importlib.machinery
import importlib.metadata
import importlib.util
import json
import math
import os
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch

#: Where the benchmark scripts' results land.
RESULTS = Path(__file__).resolve().parents[1] / "results"
#: The default of --data-root: ``$GEOFEAT_DATA``, geofeat's data setting (None when it is not set).
DEFAULT_DATA = os.environ.get("GEOFEAT_DATA")
#: geofeat's machine description, a file that imports nothing of geofeat (see `machine`).
MACHINE_FILE = Path(__file__).resolve().parents[2] / "geofeat" / "apps" / "machine.py"
#: DSMK's ULRSSM training options for FAUST_r, relative to its root
OPTIONS = Path("options") / "ulrssm" / "train" / "faust.yaml"
#: FAUST_r has 100 shapes; DSMK's train split is the first 80
N_FAUST = 100
N_TRAIN = 80
#: what this script uses of DSMK: name -> its module
DSMK_NAMES = {
    "build_dataset": "datasets",
    "build_dataloader": "datasets",
    "EnlargedSampler": "datasets.data_sampler",
    "build_model": "models",
    "laplacian_decomposition": "utils.geometry_util",
    "set_random_seed": "utils.misc",
    "parse": "utils.options",
    "read_shape": "utils.shape_util",
    "write_off": "utils.shape_util",
}


# -- the results (this script runs outside geofeat's environment)


def machine(*extra: str) -> str:
    """`geofeat.apps.machine.machine`, loaded from its file: importing the geofeat package needs its dependencies."""
    spec = importlib.util.spec_from_file_location("geofeat_apps_machine", MACHINE_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.machine(*extra)


def write_results(out: Path, result: dict, table: str) -> None:
    """Write ``OUT.json`` and ``OUT.md``, creating the folder; print the table."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(table + "\n")
    print(table)


# -- stand-ins for packages DSMK imports but the ULRSSM training path does not call


class _Unused(types.ModuleType):
    """A module that exists so that ``import`` succeeds; any attribute it lacks raises."""

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        raise AttributeError(
            f"{self.__name__}.{name}: {self.__name__} is not installed here; this stand-in only lets DSMK's modules import "
            "(its ULRSSM training path does not use it)."
        )


def _module(name: str, cls: type = _Unused) -> types.ModuleType:
    module = cls(name)
    module.__spec__ = importlib.machinery.ModuleSpec(name, None)
    module.__dict__["__stand_in__"] = True
    return module


def read_off(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (F, 3) int32 of an OFF file, as ``open3d.io.read_triangle_mesh`` gives them."""
    lines = []
    with open(path) as handle:
        for line in handle:
            line = line.split("#", 1)[0].strip()
            if line:
                lines.append(line)
    if not lines or not lines[0].startswith("OFF"):
        raise ValueError(f"{path}: not an OFF file")
    head = lines[0][3:].split() or lines[1].split()
    first = 1 if lines[0][3:].split() else 2
    n_verts, n_faces = int(head[0]), int(head[1])
    verts = np.array(" ".join(lines[first : first + n_verts]).split(), dtype=np.float64).reshape(n_verts, 3)
    faces = np.array(" ".join(lines[first + n_verts : first + n_verts + n_faces]).split(), dtype=np.int64).reshape(n_faces, -1)
    if faces.shape[1] != 4 or np.any(faces[:, 0] != 3):
        raise ValueError(f"{path}: only triangle meshes are read by this stand-in")
    return verts, faces[:, 1:].astype(np.int32)


def _open3d_stand_in() -> types.ModuleType:
    """``open3d`` with ``io.read_triangle_mesh`` for OFF files (the only call on DSMK's ULRSSM path)."""
    o3d = _module("open3d")
    io = _module("open3d.io")

    def read_triangle_mesh(path: str):
        verts, faces = read_off(str(path))
        return types.SimpleNamespace(vertices=verts, triangles=faces)

    io.__dict__["read_triangle_mesh"] = read_triangle_mesh
    o3d.__dict__["io"] = io
    return o3d


def install_stand_ins() -> list[str]:
    """Put stand-ins in ``sys.modules`` for the missing packages; returns their names."""
    used = []
    for name in ("open3d", "wandb", "igl", "torchvision"):
        try:
            importlib.import_module(name)
            continue
        except Exception:  # not installed, or installed but broken (e.g. built for another torch)
            for key in [k for k in sys.modules if k == name or k.startswith(name + ".")]:
                del sys.modules[key]
        if name == "open3d":
            module = _open3d_stand_in()
            sys.modules["open3d.io"] = module.io
        else:
            module = _module(name)
        if name == "torchvision":  # datasets/__init__.py: import torchvision.transforms as transforms
            transforms = _module("torchvision.transforms")
            module.__dict__["transforms"] = transforms
            sys.modules["torchvision.transforms"] = transforms
        sys.modules[name] = module
        used.append(name)
    return used


# -- DSMK


def import_dsmk(root: Path) -> types.SimpleNamespace:
    """DSMK's modules, imported from ``root`` (its top-level packages are ``datasets``, ``models``, ``utils``...)."""
    if not (root / OPTIONS).is_file():
        raise SystemExit(f"{root} is not a DeepShapeMatchingKit checkout ({OPTIONS} missing); pass --dsmk")
    clash = [name for name in ("datasets", "models", "networks", "losses", "metrics", "utils") if name in sys.modules]
    if clash:
        raise SystemExit(f"modules named {clash} are already imported; DSMK's packages of the same names cannot load")
    sys.path.insert(0, str(root))
    return types.SimpleNamespace(**{name: getattr(importlib.import_module(module), name) for name, module in DSMK_NAMES.items()})


def dsmk_commit(root: Path) -> str:
    """The DSMK commit: ``DSMK_COMMIT`` in the checkout, else its git HEAD, else ``"unknown"``.

    A folder that is not itself the top of a git work tree (files copied out of one) is
    "unknown" unless it holds ``DSMK_COMMIT``: git would otherwise answer for a repository
    above it.
    """
    marker = root / "DSMK_COMMIT"
    if marker.is_file():
        return marker.read_text().strip()

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True).stdout.strip()

    try:
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root.resolve():
            return "unknown"
        return git("rev-parse", "HEAD")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def prepare_layout(dsmk: types.SimpleNamespace, data_root: Path, work: Path, n_shapes: int) -> Path:
    """``work/FAUST_r/off`` as DSMK reads it: the first ``n_shapes`` shapes preprocessed as ULRSSM's, the rest placeholders.

    Each written shape is read with DSMK's ``read_shape``, centred at its mean vertex,
    divided by the square root of its area (``laplacian_decomposition(k=1)``'s last output)
    and written with ``write_off``: ULRSSM's ``preprocess.py`` without its eigenpairs and
    geodesics (DSMK's dataset computes and caches the eigenpairs on first access). Shapes
    already written are kept.
    """
    folder = work / "FAUST_r" / "off"
    folder.mkdir(parents=True, exist_ok=True)
    for index in range(N_FAUST):
        target = folder / f"tr_reg_{index:03d}.off"
        if index >= n_shapes:
            if not target.exists():
                target.touch()  # never read: only its name is globbed by DSMK's dataset
            continue
        if target.is_file() and target.stat().st_size > 0:
            continue
        source = data_root / "FAUST_r" / "off" / target.name
        if not source.is_file():
            raise SystemExit(f"{source} not found: pass --data-root (the folder holding FAUST_r/off)")
        verts, faces = dsmk.read_shape(str(source))
        verts = verts - np.mean(verts, axis=0)
        verts = verts / dsmk.laplacian_decomposition(verts=verts, faces=faces, k=1)[-1]
        dsmk.write_off(str(target), verts, faces)
    return work / "FAUST_r"


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work, so that wall time covers it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def iterate(model, batch) -> float:
    """One DSMK training iteration (``train.py``'s body without logging); returns the total loss."""
    model.curr_iter += 1
    model.feed_data(batch)
    model.optimize_parameters()
    model.update_model_per_iteration()
    return float(model.loss_metrics["l_total"])


def summary(seconds: list[float]) -> dict:
    """Median, mean, min and max of per-iteration times, in milliseconds."""
    ms = [1000.0 * s for s in seconds]
    return {
        "iterations": len(ms),
        "median_ms": statistics.median(ms),
        "mean_ms": statistics.fmean(ms),
        "min_ms": min(ms),
        "max_ms": max(ms),
    }


def run(args: argparse.Namespace, save) -> None:
    """Build DSMK's ULRSSM training at its FAUST_r options, time its iterations, ``save(result)`` after each timing."""
    if args.device == "auto":
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    else:
        device = torch.device(args.device)
    if device.type == "cuda" and device.index not in (None, 0):
        raise SystemExit(
            "DSMK puts its model on the default CUDA device: use --device cuda (set CUDA_VISIBLE_DEVICES to pick one)"
        )
    stand_ins = install_stand_ins()
    root = Path(args.dsmk).resolve()
    dsmk = import_dsmk(root)
    start = time.perf_counter()
    data_root = prepare_layout(dsmk, Path(args.data_root), Path(args.work).resolve(), args.shapes)
    layout_seconds = time.perf_counter() - start

    # DSMK's options, as train.py's parse_options makes them (no experiment folders, no wandb)
    opt = dsmk.parse(str(root / OPTIONS), str(root), is_train=True)
    opt["num_gpu"] = 1 if device.type == "cuda" else 0  # BaseModel: 'cuda' if num_gpu != 0 else 'cpu'
    opt["dist"], opt["rank"], opt["world_size"] = False, 0, 1
    opt["datasets"]["train_dataset"]["data_root"] = str(data_root)
    dsmk.set_random_seed(opt["manual_seed"])

    train_set = dsmk.build_dataset(opt["datasets"]["train_dataset"])
    shapes = train_set.dataset
    names = [Path(f).stem for f in shapes.off_files[: args.shapes]]
    expected = [f"tr_reg_{i:03d}" for i in range(args.shapes)]
    if names != expected:
        raise SystemExit(
            f"DSMK's dataset orders the shapes as {names}, expected {expected}: use a --work path without 'digits.' in it"
        )
    opt["train"]["total_iter"] = int(opt["train"]["total_epochs"]) * math.ceil(len(train_set) / opt["datasets"]["batch_size"])

    # DSMK's preprocessing: the first access of each shape computes and caches its operators
    cache = data_root / "diffusion"
    cached_before = len(list(cache.glob("*.npz"))) if cache.is_dir() else 0
    start = time.perf_counter()
    vertices = [int(shapes[i]["verts"].shape[0]) for i in range(args.shapes)]
    preprocessing_seconds = time.perf_counter() - start
    computed = len(list(cache.glob("*.npz"))) - cached_before

    # all ordered pairs of the written shapes, in DSMK's pair indexing (first * 80 + second)
    pair_indices = [i * len(shapes) + j for i in range(args.shapes) for j in range(args.shapes)]
    subset = torch.utils.data.Subset(train_set, pair_indices)
    sampler = dsmk.EnlargedSampler(subset, opt["world_size"], opt["rank"], 1)
    loader = dsmk.build_dataloader(
        subset, opt["datasets"], "train", num_gpu=opt["num_gpu"], dist=False, sampler=sampler, seed=opt["manual_seed"]
    )

    model = dsmk.build_model(opt)
    parameters = sum(p.numel() for net in model.networks.values() for p in net.parameters() if p.requires_grad)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)

    # step: loader batches held in memory
    sampler.set_epoch(1)
    batches = list(loader)
    losses = [iterate(model, batches[i % len(batches)]) for i in range(args.warmup)]
    step_seconds = []
    for i in range(args.iters):
        synchronize(device)
        start = time.perf_counter()
        losses.append(iterate(model, batches[(args.warmup + i) % len(batches)]))
        synchronize(device)
        step_seconds.append(time.perf_counter() - start)
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None

    train = opt["datasets"]["train_dataset"]
    feature = opt["networks"]["feature_extractor"]
    result = {
        "date": datetime.date.today().isoformat(),
        "machine": machine(f"torch {torch.__version__}"),
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "dsmk_commit": dsmk_commit(root),
        "options": str(OPTIONS),
        "setting": {
            "model": opt["type"],
            "batch_size": opt["datasets"]["batch_size"],
            "num_worker": opt["datasets"]["num_worker"],
            "num_evecs": train["num_evecs"],
            "feature_extractor": dict(feature),
            "fmap_net": dict(opt["networks"]["fmap_net"]),
            "permutation": dict(opt["networks"]["permutation"]),
            "losses": {k: dict(v) for k, v in opt["train"]["losses"].items()},
            "optimizer": {k: dict(v) for k, v in opt["train"]["optims"].items()},
            "scheduler": {k: dict(v) for k, v in opt["train"]["schedulers"].items()},
        },
        "shapes": args.shapes,
        "vertices": vertices,
        "pairs": len(pair_indices),
        "warmup_iterations": args.warmup,
        "parameters": parameters,
        "layout_seconds": layout_seconds,
        "preprocessing_seconds": preprocessing_seconds,
        "operators_computed": computed,
        "step": summary(step_seconds),
        "loader": None,
        "peak_cuda_memory_gib": peak,
        "losses": losses,
        "stand_ins": stand_ins,
        "versions": {
            name: _version(name)
            for name in ("torch", "numpy", "scipy", "scikit-learn", "potpourri3d", "robust_laplacian", "trimesh")
        },
    }
    if device.type == "cuda":
        result["gpu"] = torch.cuda.get_device_name(device)
    save(result)  # kept if the loader timing does not finish

    # loader: train.py's loop, waiting for the loader included (its iter_timer)
    loader_seconds = []
    sampler.set_epoch(2)
    count = 0
    synchronize(device)
    last = time.perf_counter()
    for batch in loader:
        losses.append(iterate(model, batch))
        synchronize(device)
        now = time.perf_counter()
        if count >= args.warmup:
            loader_seconds.append(now - last)
        last = now
        count += 1
        if count >= args.warmup + args.iters:
            break
    result["loader"] = summary(loader_seconds) if loader_seconds else None
    result["losses"] = losses
    save(result)


def _version(name: str) -> str | None:
    """The installed version of distribution ``name``, or None."""
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def table(result: dict) -> str:
    """The Markdown of a result: the milliseconds per iteration, then the rate and memory, each timing a row."""
    where = result.get("gpu", result["machine"])
    memory = f"{result['peak_cuda_memory_gib']:.2f} GiB" if result["peak_cuda_memory_gib"] is not None else "-"
    lines = [
        f"DeepShapeMatchingKit's ULRSSM training iteration ({result['dsmk_commit'][:10]}, {result['options']}), "
        f"FAUST_r pairs of {result['shapes']} training shapes ({min(result['vertices'])}-{max(result['vertices'])} vertices), "
        f"batch {result['setting']['batch_size']}, device {result['device']} ({where}), {result['date']}",
        "",
    ]
    times = ["| timing | iterations | median ms/iteration | mean | min | max |", "|---|---|---|---|---|---|"]
    rates = ["| timing | iterations/s (from mean) | peak CUDA memory |", "|---|---|---|"]
    for key, label in (("step", "step (batches in memory)"), ("loader", "train.py loop (with its data loader)")):
        row = result[key]
        if row is None:
            continue
        times.append(
            f"| {label} | {row['iterations']} | {row['median_ms']:.1f} | {row['mean_ms']:.1f} | {row['min_ms']:.1f} | "
            f"{row['max_ms']:.1f} |"
        )
        rates.append(f"| {label} | {1000.0 / row['mean_ms']:.2f} | {memory if key == 'step' else '-'} |")
    lines += [*times, "", *rates]
    lines += [
        "",
        f"Trainable parameters {result['parameters']:,}; {result['warmup_iterations']} warm-up iterations excluded; "
        f"DSMK's preprocessing of the {result['shapes']} shapes {result['preprocessing_seconds']:.1f} s "
        f"({result['operators_computed']} operator sets computed, the rest read from its cache). "
        f"Stand-ins: {', '.join(result['stand_ins']) or 'none'}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dsmk", help="root of a DeepShapeMatchingKit checkout (required unless --render-only)")
    parser.add_argument(
        "--work", help="folder for DSMK's data layout and operator cache, outside the repository (required unless --render-only)"
    )
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="folder holding FAUST_r/off (default $GEOFEAT_DATA)")
    parser.add_argument("--shapes", type=int, default=5, help="training shapes whose ordered pairs are used (1-80)")
    parser.add_argument("--iters", type=int, default=20, help="timed iterations of each timing")
    parser.add_argument("--warmup", type=int, default=3, help="untimed iterations before each timing")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--out", default=str(RESULTS / "speed_dsmk_ulrssm"), help="writes OUT.json and OUT.md")
    parser.add_argument("--render-only", action="store_true", help="rewrite OUT.md from OUT.json without running anything")
    args = parser.parse_args(argv)
    if args.render_only:
        out = Path(args.out)
        result = json.loads(out.with_suffix(".json").read_text())
        out.with_suffix(".md").write_text(table(result) + "\n")
        return 0
    if not args.dsmk or not args.work:
        parser.error("--dsmk and --work are required (or --render-only)")
    if not args.data_root:
        parser.error("no data folder: pass --data-root (the folder that holds FAUST_r/) or set $GEOFEAT_DATA")
    if not 1 <= args.shapes <= N_TRAIN:
        parser.error(f"--shapes must be within 1-{N_TRAIN}")
    if args.iters < 1 or args.warmup < 0:
        parser.error("--iters must be positive and --warmup non-negative")
    run(args, lambda result: write_results(Path(args.out), result, table(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
