"""Sample-stream parity: 50 GeoLoRA training steps of geofeat's trainer against the official loop on one recorded stream.

    python -m benchmarks.parity.training_stream --stream DIR --geolora-repo PATH --dinov3-repo PATH
        [--steps 50] [--image-size 128] [--out benchmarks/results/parity/training_stream.md]
        [--official-python /work/ref/venv/bin/python --harness /work/ref/stream/record_stream.py]

(pytorch3d must be importable: a CPU build from source where no wheel fits, e.g. on PYTHONPATH.)

``--stream`` is a folder of ``step_NNN.npz`` files recorded from the official data loader
(vikiehm/geo-lora ``utils/shape_dataset.py``: ``PartialShapeDataset`` in train.py's
``DataLoader`` and ``generate_partial_shape``, seeded as train.py seeds them) by a harness kept
outside this repository, in the official code's environment (open3d, libigl; see
`STREAM_KEYS`). When ``DIR`` holds no recording and ``--official-python`` and ``--harness``
are given, the harness is run first (``HARNESS DIR --steps N --seed S --workers W
--partials 2 --data DATA/FAUST_r/off``; train.py's seed 42 and 5 loader workers by default). Each step holds the full shape as the loader returns it (turned about y, its
vertices divided by sqrt(area) in place by ``geodesic_dist_echo``), its float32 geodesic
matrix, and per partial shape its vertices (turned again), faces and ground truth.

Both sides start from the same weights: the official DINOv3 model class at test size (width
16, 2 blocks, 2 heads; `benchmarks.parity.geolora.tiny_official_vit`) with random weights, and a random
peft LoRA on the fused ``qkv`` as train.py configures it (r=16, alpha=32), saved as the
official ``get_state_dict_lora`` saves it and read by `geofeat.backbones.load_official_lora`.
geofeat's backbone is the same state dict through geofeat's loader. Then, per step:

* official: train.py's loop body (lines ~256-330): ``compute_features`` of
  ``utils/dino_utils.py`` for the full shape (9 views) and each partial shape (4 views), the
  observed-vertex masks, ``weighted_contrastive_loss`` of ``utils/utils.py``, the NaN skip,
  Adam (lr 1e-4) on ``dino_model.parameters()``, ``clip_grad_norm_(max_norm=1.0)``;
* geofeat: ``GeoLoraTrainer.train_step`` (recipe "reference", ``rope_augmentation=False``,
  ``amp="off"``), its sample source replaced by `geofeat.train.samples.PreparedSample`
  records of the same stream (the float32 geodesic matrix as recorded).

Settings held equal on purpose, and why:

* render size ``--image-size`` (128) instead of the official 512: pytorch3d rasterizes by brute
  force on a CPU (every face for every pixel), so 512 costs minutes per step. The official
  ``compute_features`` is called unchanged; only the ``H``/``W`` it passes to
  ``get_features_per_vertex`` are replaced. Both sides then resize each render to 518 for the
  backbone as the official transform does.
* DINOv3 in ``eval()`` on both sides: train.py runs it in ``train()`` mode, where its RoPE
  coordinates are rescaled by a random factor at every forward pass. The official code makes
  one forward (one draw) per view, geofeat one forward for all views of a step, so the
  draws cannot be matched one for one; with the jitter off both compute the same function.
* one thread: the official back-projection's indexed in-place addition races between CPU
  threads (see `benchmarks.parity.geolora.ONE_THREAD`).

The per-vertex features are float16 on both sides (the official ``get_dino_features`` casts the
tokens to half and sums in half; geofeat's "reference" recipe does the same), so the expected
agreement of the losses is that of features equal to about one float16 unit in the last place
(1.2e-4 at feature magnitude 0.15), not float32 round-off.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import geofeat
from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine
from benchmarks.parity.geolora import (
    ONE_THREAD,
    contiguous_grid_sample,
    official_lora,
    our_backbone,
    reference_path,
    tiny_official_vit,
)
from geofeat.backbones.lora import load_official_lora

#: Arrays of one recorded step (``step_NNN.npz``); ``_j`` per partial shape j.
STREAM_KEYS = ("verts_2", "faces_2", "dist_full", "verts_1_j", "faces_1_j", "gt01_j", "kind_j")
#: Scale of the random initial LoRA A and B (float16 values; `benchmarks.parity.geolora.official_lora`).
LORA_SCALE = 0.1


def load_step(folder: Path, step: int) -> dict:
    """One recorded step: the full shape, its geodesics and its partial shapes with their ground truth."""
    with np.load(folder / f"step_{step:03d}.npz") as data:
        record = {key: data[key] for key in data.files}
    n = sum(1 for key in record if key.startswith("verts_1_"))
    record["partials"] = [
        (record[f"verts_1_{j}"], record[f"faces_1_{j}"], record[f"gt01_{j}"], str(record[f"kind_{j}"])) for j in range(n)
    ]
    return record


def repeated_faces(faces: np.ndarray) -> int:
    """Faces that name the same three vertices as an earlier face (`geofeat.Mesh` drops them; the official code keeps them)."""
    corners = np.sort(np.asarray(faces, dtype=np.int64), axis=1)
    return len(corners) - len(np.unique(corners, axis=0))


@contextlib.contextmanager
def render_size(dino_utils, size: int):
    """The official ``compute_features`` unchanged, its fixed 512 x 512 render replaced by ``size``."""
    original = dino_utils.get_features_per_vertex

    def get_features_per_vertex(*args, **kwargs):
        kwargs.update(H=size, W=size)
        return original(*args, **kwargs)

    dino_utils.get_features_per_vertex = get_features_per_vertex
    try:
        yield
    finally:
        dino_utils.get_features_per_vertex = original


@contextlib.contextmanager
def recording_grad_norms(norms: list):
    """``torch.nn.utils.clip_grad_norm_`` as it is, with each total norm (before clipping) appended to ``norms``."""
    original = torch.nn.utils.clip_grad_norm_

    def clip_grad_norm_(*args, **kwargs):
        total = original(*args, **kwargs)
        norms.append(float(total))
        return total

    torch.nn.utils.clip_grad_norm_ = clip_grad_norm_
    try:
        yield
    finally:
        torch.nn.utils.clip_grad_norm_ = original


def official_steps(dino_utils, utils_module, peft_model, stream: Path, steps: int, args) -> list[dict]:
    """train.py's loop body on the recorded stream (DINOv3 in eval(), CPU); one dict per step."""
    cpu = torch.device("cpu")
    peft_model.eval()  # see the module notes: no RoPE jitter
    optimizer = torch.optim.Adam(list(peft_model.parameters()), lr=1e-4)
    snapshots = args.snapshots
    out = []
    norms: list[float] = []
    with contiguous_grid_sample(), render_size(dino_utils, args.image_size), recording_grad_norms(norms):
        for step in range(steps):
            start = time.perf_counter()
            snapshots.append(official_lora_tensors(peft_model))  # the weights this step starts from
            rec = load_step(stream, step)
            verts_2 = torch.from_numpy(rec["verts_2"])
            faces_2 = torch.from_numpy(rec["faces_2"])
            dist_full = torch.from_numpy(rec["dist_full"])
            feat_full = dino_utils.compute_features(cpu, peft_model, verts_2, faces_2.int(), num_views=args.views_full).float()
            losses, deduplicated = [], []
            seen = [(feat_full.sum(dim=1) != 0).numpy()]  # train.py's observed masks: full, then each partial
            for verts, faces, gt, _ in rec["partials"]:
                verts_1, faces_1, gt01 = torch.from_numpy(verts), torch.from_numpy(faces), torch.from_numpy(gt)

                def partial_loss(faces_1, feat_full, verts_1=verts_1, gt01=gt01, dist_full=dist_full):
                    feat_partial = dino_utils.compute_features(
                        cpu, peft_model, verts_1, faces_1, num_views=args.views_partial
                    ).float()
                    observed = feat_partial.sum(dim=1) != 0
                    positive_1 = feat_partial[gt01 != -1][observed]
                    positive_2 = feat_full[gt01[gt01 != -1]][observed]
                    used_gt = gt01[gt01 != -1][observed]
                    loss = utils_module.weighted_contrastive_loss(positive_1, positive_2, feat_full, used_gt, dist_full)
                    return loss, observed

                loss, observed = partial_loss(faces_1, feat_full)
                losses.append(loss)
                seen.append(observed.numpy())
                if repeated_faces(faces):  # diagnosis: the same partial with the faces geofeat.Mesh keeps
                    kept = geofeat.Mesh(verts.astype(np.float64), faces.astype(np.int64)).faces
                    with torch.no_grad():
                        deduplicated.append(float(partial_loss(torch.from_numpy(kept).int(), feat_full.detach())[0]))
                else:
                    deduplicated.append(float(losses[-1].detach()))
            loss = torch.stack(losses)
            row = {"step": step, "partial_losses": [float(v) for v in loss.detach()], "skipped": False, "seen": seen}
            row["loss_without_repeated_faces"] = float(np.mean(deduplicated))
            if torch.isnan(loss).any():
                row.update(loss=float("nan"), skipped=True, grad_norm=float("nan"))
            else:
                loss = loss.mean()
                optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(peft_model.parameters(), max_norm=1.0)
                optimizer.step()
                row.update(loss=float(loss.detach()), grad_norm=norms[-1])
            row["seconds"] = time.perf_counter() - start
            out.append(row)
            print(f"official step {step}: loss {row['loss']:.7f} ({row['seconds']:.1f} s)", flush=True)
    return out


def geofeat_steps(ours, stream: Path, steps: int, args, folder: Path) -> tuple[list[dict], dict]:
    """geofeat's ``GeoLoraTrainer.train_step`` on the same stream: one dict per step, and the LoRA at the end.

    Then, with ``args.snapshots`` (the official LoRA at the start of each step), each step's
    loss again from the official's weights of that step (no gradient; ``synced_loss``), which
    separates what a step itself contributes from what the weights carried over.
    """
    from geofeat.train.config import TrainConfig
    from geofeat.train.run_log import PhaseTimer
    from geofeat.train.samples import PreparedSample
    from geofeat.train.trainer import GeoLoraTrainer

    config = TrainConfig(
        data="unused",
        out=str(folder / "run"),
        recipe="reference",
        rope_augmentation=False,
        views_full=args.views_full,
        views_partial=args.views_partial,
        image_size=args.image_size,
        device="cpu",
        amp="off",
        progress=False,
        partials_per_shape=2,
        lr=1e-4,
        grad_clip=1.0,
        workers=0,
        geodesic_cache=str(folder / "geodesics"),
    )
    first = load_step(stream, 0)
    placeholder = geofeat.Mesh(first["verts_2"].astype(np.float64), first["faces_2"], "stream")
    trainer = GeoLoraTrainer(config, backbone=ours, shapes=[placeholder])
    trainer._make_optimizer()  # Adam over the parameters that require gradients: the LoRA ones
    names = [n for n, p in ours.model.named_parameters() if p.requires_grad]
    if not names or not all("lora_" in n for n in names):
        raise SystemExit(f"geofeat's trainable parameters are not the LoRA ones: {names[:4]}")

    partial_losses: list[float] = []
    half_losses: list[float] = []
    seen: list[np.ndarray] = []  # seen masks of the step: full, then each partial
    loss_of = trainer._loss

    def loss_and_record(feat_partial, feat_full, gt, dist, seen_partial, seen_full):
        if not seen:
            seen.append(seen_full.numpy().copy())
        seen.append(seen_partial.numpy().copy())
        loss = loss_of(feat_partial, feat_full, gt, dist, seen_partial, seen_full)
        partial_losses.append(float(loss.detach()))
        with torch.no_grad():  # the effect of the trainer's float16 geodesic store, on the loss only
            half = loss_of(feat_partial, feat_full, gt, dist.half().float(), seen_partial, seen_full)
        half_losses.append(float(half))
        return loss

    trainer._loss = loss_and_record
    current: list[PreparedSample] = []
    trainer.sample_stream.next_samples = lambda step, timer: current
    out = []
    norms: list[float] = []
    with recording_grad_norms(norms):
        for step in range(steps):
            start = time.perf_counter()
            rec = load_step(stream, step)
            full = geofeat.Mesh(rec["verts_2"].astype(np.float64), rec["faces_2"].astype(np.int64), str(rec["filename"]))
            partials = [
                (geofeat.Mesh(v.astype(np.float64), f.astype(np.int64), f"{full.name}-{k}"), torch.from_numpy(g).long())
                for v, f, g, k in rec["partials"]
            ]
            current[:] = [PreparedSample(step, 0, full, partials, torch.from_numpy(rec["dist_full"]))]
            partial_losses.clear()
            half_losses.clear()
            seen.clear()
            n_norms = len(norms)
            record = trainer.train_step()
            row = {
                "step": step,
                "loss": record.loss,
                "partial_losses": list(partial_losses),
                "loss_float16_geodesics": float(np.mean(half_losses)) if half_losses else float("nan"),
                "n_partials": record.n_partials,
                "seen": list(seen),
                "grad_norm": norms[-1] if len(norms) > n_norms else float("nan"),
                "seconds": time.perf_counter() - start,
            }
            out.append(row)
            print(f"geofeat  step {step}: loss {row['loss']:.7f} ({row['seconds']:.1f} s)", flush=True)
    final = geofeat_lora_tensors(ours)
    for step, snapshot in enumerate(args.snapshots[:steps]):
        set_geofeat_lora(ours, snapshot)
        rec = load_step(stream, step)
        full = geofeat.Mesh(rec["verts_2"].astype(np.float64), rec["faces_2"].astype(np.int64), str(rec["filename"]))
        partials = [
            (geofeat.Mesh(v.astype(np.float64), f.astype(np.int64), f"{full.name}-{k}"), torch.from_numpy(g).long())
            for v, f, g, k in rec["partials"]
        ]
        sample = PreparedSample(step, 0, full, partials, torch.from_numpy(rec["dist_full"]))
        seen.clear()
        with torch.no_grad():
            loss, _ = trainer._sample_loss(sample, PhaseTimer(torch.device("cpu")))
        out[step]["synced_loss"] = float("nan") if loss is None else float(loss)
    return out, final


def set_geofeat_lora(ours, tensors: dict[str, torch.Tensor]) -> None:
    """Write LoRA tensors in the official layout (`official_lora_tensors`) into geofeat's per-projection LoRA."""
    named = dict(ours.model.named_parameters(remove_duplicate=False))
    keys = sorted({n.split(".attention.")[0] for n in named if "lora_" in n})
    with torch.no_grad():
        for key in keys:
            block = int(key.rsplit(".", 1)[1])
            b_parts = tensors[f"blocks.{block}.lora_B"].chunk(3)
            for t, b in zip(("q_proj", "k_proj", "v_proj"), b_parts, strict=True):
                named[f"{key}.attention.{t}.lora_A.default.weight"].copy_(tensors[f"blocks.{block}.lora_A"])
                named[f"{key}.attention.{t}.lora_B.default.weight"].copy_(b)


def official_lora_tensors(peft_model) -> dict[str, torch.Tensor]:
    """``blocks.N.lora_A`` (r, C) and ``blocks.N.lora_B`` (3C, r) of the official peft model."""
    out = {}
    for name, param in peft_model.named_parameters():
        if "lora_" in name:
            block = int(name.split("blocks.")[1].split(".")[0])
            out[f"blocks.{block}.{'lora_A' if '.lora_A.' in name else 'lora_B'}"] = param.detach().clone()
    return out


def geofeat_lora_tensors(ours) -> dict[str, torch.Tensor]:
    """geofeat's per-projection LoRA in the official layout: the shared A, and B of q, k, v stacked."""
    named = dict(ours.model.named_parameters(remove_duplicate=False))
    out = {}
    for key in sorted({n.split(".attention.")[0] for n in named if "lora_" in n}):
        block = int(key.rsplit(".", 1)[1])

        def part(t, which, key=key):
            return named[f"{key}.attention.{t}.{which}.default.weight"].detach()

        a = [part(t, "lora_A") for t in ("q_proj", "k_proj", "v_proj")]
        if not (torch.equal(a[0], a[1]) and torch.equal(a[0], a[2])):
            raise SystemExit(f"geofeat's LoRA A of block {block} is not shared by q, k and v")
        out[f"blocks.{block}.lora_A"] = a[0].clone()
        out[f"blocks.{block}.lora_B"] = torch.cat([part(t, "lora_B") for t in ("q_proj", "k_proj", "v_proj")])
    return out


def lora_difference(ours: dict, theirs: dict, initial: dict) -> dict:
    """Largest |geofeat - official| over all LoRA entries, the official's largest magnitude and largest change from the start."""
    if set(ours) != set(theirs):
        raise SystemExit(f"LoRA tensors differ: {sorted(set(ours) ^ set(theirs))}")
    diff = max(float((ours[k].double() - theirs[k].double()).abs().max()) for k in theirs)
    scale = max(float(theirs[k].abs().max()) for k in theirs)
    moved = max(float((theirs[k].double() - initial[k].double()).abs().max()) for k in theirs)
    return {"max_abs_diff": diff, "official_max_abs": scale, "official_max_change": moved}


def record_stream(args) -> None:
    """Run the official-side harness into ``args.stream``; its environment gets no PYTHONPATH of this one."""
    if not (args.official_python and args.harness):
        raise SystemExit(f"{args.stream} holds no recorded steps; record them or pass --official-python and --harness")
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    data = data_folder(args.data_root, "--data-root") / "FAUST_r" / "off"
    command = [args.official_python, args.harness, args.stream, "--steps", args.steps, "--seed", args.seed]
    command += ["--workers", args.workers, "--partials", 2, "--data", data]
    subprocess.run([str(c) for c in command], check=True, env=env)


def run(args) -> dict:
    torch.set_num_threads(1)  # see benchmarks.parity.geolora.ONE_THREAD
    stream = args.stream
    if not sorted(stream.glob("step_*.npz")):
        record_stream(args)
    meta = json.loads((stream / "meta.json").read_text()) if (stream / "meta.json").is_file() else {}
    steps = min(args.steps, len(sorted(stream.glob("step_*.npz"))))
    result: dict = {"steps": steps, "image_size": args.image_size, "views": [args.views_full, args.views_partial]}
    result["stream"] = {"folder": str(stream), **{k: meta.get(k) for k in ("seed", "workers", "partials", "shapes")}}
    with tempfile.TemporaryDirectory() as tmp, reference_path(args.geolora_repo):
        folder = Path(tmp)
        dino_utils = importlib.import_module("utils.dino_utils")
        utils_module = importlib.import_module("utils.utils")
        official = tiny_official_vit(args.dinov3_repo, "dinov3")
        ours = our_backbone(official, "dinov3", folder)
        peft_model = official_lora(official, scale=LORA_SCALE)
        lora_path = folder / "lora.pth"
        torch.save(utils_module.get_state_dict_lora(peft_model), lora_path)  # the official save format
        load_official_lora(ours, lora_path)
        initial = official_lora_tensors(peft_model)
        result["lora_at_start"] = lora_difference(geofeat_lora_tensors(ours), initial, initial)

        start = time.perf_counter()
        args.snapshots = []
        theirs = official_steps(dino_utils, utils_module, peft_model, stream, steps, args)
        result["seconds_official"] = time.perf_counter() - start
        start = time.perf_counter()
        mine, final = geofeat_steps(ours, stream, steps, args, folder)
        result["seconds_geofeat"] = time.perf_counter() - start
        result["lora_at_end"] = lora_difference(final, official_lora_tensors(peft_model), initial)

    rows = []
    for a, b in zip(theirs, mine, strict=True):
        rec = load_step(stream, a["step"])
        rows.append(
            {
                "step": a["step"],
                "shape": str(rec["filename"]),
                "kinds": [k for *_, k in rec["partials"]],
                "partial_vertices": [len(v) for v, *_ in rec["partials"]],
                "repeated_faces": [repeated_faces(f) for _, f, *_ in rec["partials"]],
                "official_loss": a["loss"],
                "geofeat_loss": b["loss"],
                "abs_diff": abs(a["loss"] - b["loss"]),
                "official_partial_losses": a["partial_losses"],
                "geofeat_partial_losses": b["partial_losses"],
                "official_skipped": a["skipped"],
                "geofeat_partials": b["n_partials"],
                "official_grad_norm": a["grad_norm"],
                "geofeat_loss_at_official_weights": b.get("synced_loss", float("nan")),
                "synced_abs_diff": abs(a["loss"] - b.get("synced_loss", float("nan"))),
                "official_loss_without_repeated_faces": a["loss_without_repeated_faces"],
                "seen_vertices": [int(m.sum()) for m in a["seen"]],
                "seen_mismatch": [int((x != y).sum()) for x, y in zip(a["seen"], b["seen"], strict=True)],
                "geofeat_grad_norm": b["grad_norm"],
                "geofeat_loss_float16_geodesics": b["loss_float16_geodesics"],
                "official_seconds": a["seconds"],
                "geofeat_seconds": b["seconds"],
            }
        )
    result["rows"] = rows
    finite = [r for r in rows if math.isfinite(r["official_loss"]) and math.isfinite(r["geofeat_loss"])]
    result["max_abs_loss_diff"] = max((r["abs_diff"] for r in finite), default=float("nan"))
    result["max_rel_loss_diff"] = max((r["abs_diff"] / abs(r["official_loss"]) for r in finite), default=float("nan"))
    result["max_rel_grad_norm_diff"] = max(
        (abs(r["official_grad_norm"] - r["geofeat_grad_norm"]) / r["official_grad_norm"] for r in finite), default=float("nan")
    )
    result["max_abs_float16_geodesic_effect"] = max(
        (abs(r["geofeat_loss_float16_geodesics"] - r["geofeat_loss"]) for r in finite), default=float("nan")
    )
    result["skipped_steps"] = [r["step"] for r in rows if r["official_skipped"] or r["geofeat_partials"] < len(r["kinds"])]
    result["steps_with_repeated_faces"] = [r["step"] for r in rows if any(r["repeated_faces"])]
    clean = [r for r in finite if not any(r["repeated_faces"])]
    matched = [r for r in finite if not any(r["seen_mismatch"])]
    result["max_abs_synced_loss_diff"] = max((r["synced_abs_diff"] for r in finite), default=float("nan"))
    result["max_abs_synced_loss_diff_same_seen_vertices"] = max((r["synced_abs_diff"] for r in matched), default=float("nan"))
    result["steps_with_seen_mismatch"] = [r["step"] for r in rows if any(r["seen_mismatch"])]
    result["max_abs_loss_diff_same_seen_vertices"] = max((r["abs_diff"] for r in matched), default=float("nan"))
    result["max_rel_loss_diff_same_seen_vertices"] = max(
        (r["abs_diff"] / abs(r["official_loss"]) for r in matched), default=float("nan")
    )
    result["max_abs_loss_diff_without_repeated_faces"] = max((r["abs_diff"] for r in clean), default=float("nan"))
    result["max_abs_loss_diff_repeated_faces_dropped_in_both"] = max(
        (abs(r["official_loss_without_repeated_faces"] - r["geofeat_loss"]) for r in finite), default=float("nan")
    )
    return result


def markdown_report(result: dict, header: str) -> str:
    end, start = result["lora_at_end"], result["lora_at_start"]
    rows = [r for r in result["rows"] if math.isfinite(r["abs_diff"]) and not any(r["seen_mismatch"])]
    plain = max((r["abs_diff"] for r in rows if not any(r["repeated_faces"])), default=float("nan"))
    kept = max((abs(r["official_loss_without_repeated_faces"] - r["geofeat_loss"]) for r in rows), default=float("nan"))
    lines = [
        header,
        "",
        f"### Sample-stream parity: {result['steps']} GeoLoRA training steps, official loop vs geofeat's trainer",
        "",
        f"Stream: {result['stream']['folder']} (official DataLoader, seed {result['stream'].get('seed')}, "
        f"{result['stream'].get('workers')} workers, {result['stream'].get('partials')} partial shapes a step). "
        f"Render {result['image_size']} px, {result['views'][0]} + {result['views'][1]} views; tiny official DINOv3 "
        "(width 16, 2 blocks) in eval() on both sides; LoRA r=16, alpha=32, random start; Adam lr 1e-4, clip 1.0; "
        "float32 geodesics on both sides; amp off.",
        "",
        "| summary | value |",
        "|---|---|",
        f"| max abs loss diff over {result['steps']} steps | {result['max_abs_loss_diff']:.3g} |",
        f"| max relative loss diff | {result['max_rel_loss_diff']:.3g} |",
        f"| steps where a vertex is seen by one side only (ball-radius ties) | {result['steps_with_seen_mismatch'] or 'none'} |",
        f"| max abs / relative loss diff, steps where both see the same vertices | "
        f"{result['max_abs_loss_diff_same_seen_vertices']:.3g} / {result['max_rel_loss_diff_same_seen_vertices']:.3g} |",
        f"| geofeat's loss from the official's weights of each step: max abs diff, all steps / steps where both see "
        f"the same vertices | {result['max_abs_synced_loss_diff']:.3g} / "
        f"{result['max_abs_synced_loss_diff_same_seen_vertices']:.3g} |",
        f"| max abs loss diff, steps with neither a vertex seen by one side only nor a repeated face | {plain:.3g} |",
        f"| max abs diff of geofeat's loss and the official loss on the faces geofeat keeps, steps where both see the "
        f"same vertices | {kept:.3g} |",
        f"| max abs loss diff, steps whose partial shapes have no repeated face | "
        f"{result['max_abs_loss_diff_without_repeated_faces']:.3g} |",
        f"| max abs loss diff, official loss recomputed (no_grad) on the faces geofeat keeps | "
        f"{result['max_abs_loss_diff_repeated_faces_dropped_in_both']:.3g} |",
        f"| max relative diff of the gradient norm (before clipping) | {result['max_rel_grad_norm_diff']:.3g} |",
        f"| LoRA at the start: max abs diff | {start['max_abs_diff']:.3g} |",
        f"| LoRA at the end: max abs diff | {end['max_abs_diff']:.3g} |",
        f"| LoRA at the end: official max abs entry / largest change from the start | {end['official_max_abs']:.3g} / "
        f"{end['official_max_change']:.3g} |",
        f"| LoRA at the end: diff relative to the largest entry / to the largest change | "
        f"{end['max_abs_diff'] / end['official_max_abs']:.3g} / {end['max_abs_diff'] / max(end['official_max_change'], 1e-30):.3g} |",
        f"| steps skipped (official: any NaN partial loss; geofeat: a partial without queries) | {result['skipped_steps'] or 'none'} |",
        f"| steps with a partial shape holding repeated faces (dropped by geofeat.Mesh, kept by the official code) | "
        f"{result['steps_with_repeated_faces'] or 'none'} |",
        f"| geofeat: max abs loss change with float16 geodesics (its store's precision) | "
        f"{result['max_abs_float16_geodesic_effect']:.3g} |",
        f"| seconds, official / geofeat | {result['seconds_official']:.0f} / {result['seconds_geofeat']:.0f} |",
        "",
        "Where the two can differ, and how each is measured:",
        "",
        "* a vertex seen by one side only: the official code lifts each foreground pixel to 3D from pytorch3d's depth "
        "and cameras, geofeat from its own rasterizer's, equal to float32 rounding (about 1e-7; `parity/geolora.py`'s "
        "depth and camera rows). A vertex whose only pixel lies that close to the edge of its ball (radius 0.004 x the "
        "shape's diameter) is inside on one side and outside on the other: it is a query (or a non-zero key) on one "
        "side only, which moves the loss by about (its loss - the mean) / (number of queries) and the gradient with it. "
        "The 'seen by one side only' column counts these vertices per shape (full, then each partial). For a vertex "
        "seen from several pixels, the same tie can change which pixel is its last candidate (the official code keeps "
        "one pixel per view and vertex): the seen masks then agree and that vertex's feature differs;",
        "* float16: both sides cast the tokens to float16 and sum in float16; summation order leaves features one "
        "float16 unit in the last place apart (1.2e-4 at magnitude 0.15);",
        "* repeated faces: `geofeat.Mesh` drops a face that names the same three vertices as an earlier one (the "
        "official CUTS can leave two copies of a face, one per orientation); the last column recomputes the official "
        "loss (no gradient) on the faces geofeat keeps;",
        "* NaN: train.py skips the whole step when any partial loss is NaN (a partial shape with no observed vertex); "
        "geofeat's trainer skips only that partial shape and trains on the others;",
        "* after the first such event the weights differ, so the later losses differ at the level the weights do.",
        "",
        "| step | shape | partials (vertices) | official loss | geofeat loss | abs diff | grad norm official / geofeat | "
        "seen vertices official (full, partials) | seen by one side only | official loss, repeated faces dropped | "
        "geofeat loss from the official's weights | its abs diff |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        partials = ", ".join(
            f"{k} ({n}{f'; {d} repeated faces' if d else ''})"
            for k, n, d in zip(r["kinds"], r["partial_vertices"], r["repeated_faces"], strict=True)
        )
        lines.append(
            f"| {r['step']} | {r['shape']} | {partials} | {r['official_loss']:.7f} | {r['geofeat_loss']:.7f} | "
            f"{r['abs_diff']:.2e} | {r['official_grad_norm']:.5f} / {r['geofeat_grad_norm']:.5f} | "
            f"{', '.join(map(str, r['seen_vertices']))} | {', '.join(map(str, r['seen_mismatch']))} | "
            + (f"{r['official_loss_without_repeated_faces']:.7f} |" if any(r["repeated_faces"]) else "(none repeated) |")
            + f" {r['geofeat_loss_at_official_weights']:.7f} | {r['synced_abs_diff']:.2e} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--stream", type=Path, default=None, help="folder of the recorded step_NNN.npz files")
    parser.add_argument("--geolora-repo", type=Path, default=None, help="copy of vikiehm/geo-lora")
    parser.add_argument("--dinov3-repo", type=Path, default=None, help="copy of facebookresearch/dinov3")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--views-full", type=int, default=9)
    parser.add_argument("--views-partial", type=int, default=4)
    parser.add_argument("--out", type=Path, default=RESULTS / "parity" / "training_stream.md")
    parser.add_argument("--from-json", type=Path, default=None, help="only rewrite the Markdown of a result file")
    parser.add_argument("--official-python", type=Path, default=None, help="python of the official environment (recording)")
    parser.add_argument("--harness", type=Path, default=None, help="the recording harness (kept outside this repository)")
    parser.add_argument("--seed", type=int, default=42, help="recording: train.py's seed")
    parser.add_argument("--workers", type=int, default=5, help="recording: train.py's DataLoader workers")
    parser.add_argument(
        "--data-root", type=Path, default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)"
    )
    args = parser.parse_args(argv)
    if not args.from_json and not (args.stream and args.geolora_repo and args.dinov3_repo):
        parser.error("give --stream, --geolora-repo and --dinov3-repo (or --from-json)")
    if args.from_json:
        result = json.loads(args.from_json.read_text())
    else:
        result = run(args)
        result["machine"], result["date"] = machine(), datetime.date.today().isoformat()
    header = f"Run {result['date']} on {result['machine']}, one thread. {ONE_THREAD}"
    text = markdown_report(result, header)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    if not args.from_json:
        args.out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
