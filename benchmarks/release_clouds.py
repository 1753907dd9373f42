"""The authors' FAUST_r release checkpoints on point clouds: the same pairs as meshes and as clouds.

ULRSSM ``faust_scape.pth`` and DPFM ``faust.pth`` (passed by path, not part of geofeat) are
loaded with their reference presets and match the first N pairs ``i < j`` of the FAUST_r
test shapes four ways: as meshes; with ``y`` as the point cloud of its vertices; with both
shapes as clouds; and with both as clouds whose normals (and so tangent Y axes and Y
gradient rows) take the sign of the mesh's vertex normals, to show what the unoriented
normals of the reference's point-cloud operators cost. Every match is scored on the mesh
pair (same vertices, so the same ground truth and geodesics), every vertex with a
counterpart evaluated.

    python -m benchmarks.release_clouds --checkpoints ../shared/checkpoints --data ../shared/data --pairs 10
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import time
from pathlib import Path

import numpy as np
import torch

import geofeat
from benchmarks.common import DEFAULT_DATA, REPO, RESULTS, data_folder, machine, write_results
from geofeat.adapters.blocks.operators import SurfaceOperators
from geofeat.adapters.heads import load_head
from geofeat.adapters.learned import LearnedHead
from geofeat.datasets import ShapePair, load_dataset
from geofeat.evaluation.protocol import evaluate_pair, summarize
from geofeat.geometry.normals import vertex_normals

#: head -> checkpoint file under --checkpoints
CHECKPOINTS = {"ulrssm": "ulrssm/faust_scape.pth", "dpfm": "dpfm/faust.pth"}
WAYS = ("meshes", "y as a cloud", "both clouds", "both clouds, normals signed like the mesh's")


def cloud_of(mesh: geofeat.Mesh) -> geofeat.Mesh:
    """The point cloud of a mesh's vertices."""
    return geofeat.Mesh(mesh.verts, name=f"{mesh.name}-cloud")


def signed_like(ops: SurfaceOperators, normals: np.ndarray) -> SurfaceOperators:
    """``ops`` with every normal turned to the side of ``normals`` (V, 3): its Y axis and Y gradient row follow."""
    sign = torch.from_numpy(np.where(np.einsum("vd,vd->v", ops.frames[:, 2].double().numpy(), normals) < 0, -1.0, 1.0))
    sign = sign.to(ops.frames.dtype)
    frames = ops.frames.clone()
    frames[:, 1:] *= sign[:, None, None]
    grad_y = ops.grad_y.coalesce()
    values = grad_y.values() * sign[grad_y.indices()[0]]
    grad_y = torch.sparse_coo_tensor(grad_y.indices(), values, grad_y.shape, check_invariants=True).coalesce()
    return dataclasses.replace(ops, frames=frames, grad_y=grad_y)


def match_way(head: LearnedHead, pair: ShapePair, way: str):
    """The head's match of ``pair`` given the way its shapes are passed (see `WAYS`)."""
    if way == "meshes":
        return head.match(pair)
    clouds = dataclasses.replace(pair, x=pair.x if way == "y as a cloud" else cloud_of(pair.x), y=cloud_of(pair.y))
    if way == WAYS[3]:
        prepared, meshes = head.prepare(clouds), head.prepare(pair)
        for cloud, mesh in ((prepared.x, meshes.x), (prepared.y, meshes.y)):
            features, ops = head.shape_inputs(cloud)
            head.use_inputs(cloud, features, signed_like(ops.to("cpu"), vertex_normals(mesh)))
    return head.match(clouds)


def run(checkpoints: Path, data: Path, n_pairs: int) -> dict:
    """``{head: {way: summary and seconds}}`` over the first ``n_pairs`` pairs i < j of the test split."""
    dataset = load_dataset("faust_r", root=data, split="test", pairs="combinations")
    pairs = [dataset[i] for i in range(min(n_pairs, len(dataset)))]
    results: dict = {}
    for name, file in CHECKPOINTS.items():
        results[name] = {}
        for way in WAYS:
            head = load_head(name, checkpoint=checkpoints / file, progress=False)
            start = time.perf_counter()
            evaluations = [evaluate_pair(pair, match_way(head, pair, way)) for pair in pairs]
            summary = summarize(evaluations)
            results[name][way] = {
                "geodesic_error_x100": summary.geodesic_error,
                "pck_auc": summary.pck_auc,
                "seconds": time.perf_counter() - start,
            }
    return {"pairs": [p.name for p in pairs], "results": results}


def table(record: dict) -> str:
    """Markdown: one row per checkpoint, one column per way."""
    lines = ["| checkpoint | " + " | ".join(WAYS) + " |", "|---|" + "---|" * len(WAYS)]
    for name, ways in record["results"].items():
        cells = [f"{ways[w]['geodesic_error_x100']:.2f} ({ways[w]['pck_auc']:.3f})" for w in WAYS]
        lines.append(f"| {name} `{Path(CHECKPOINTS[name]).name}` | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Mean geodesic error x100 (PCK AUC) on the first {len(record['pairs'])} FAUST_r test pairs i < j, every vertex "
        "with a counterpart, scored on the meshes; reference presets, no test-time adaptation. "
        f"`python -m benchmarks.release_clouds`; {record['date']}, {record['machine']}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--checkpoints",
        type=Path,
        default=Path(os.environ.get("GEOFEAT_CHECKPOINTS", REPO.parent / "shared" / "checkpoints")),
        help="folder with ulrssm/faust_scape.pth and dpfm/faust.pth",
    )
    parser.add_argument("--data", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--pairs", type=int, default=10)
    parser.add_argument("--out", default=str(RESULTS / "release" / "clouds"), help="writes OUT.json and OUT.md")
    args = parser.parse_args(argv)
    record = run(args.checkpoints, data_folder(args.data), args.pairs)
    record |= {"date": datetime.date.today().isoformat(), "machine": machine(), "checkpoints": CHECKPOINTS}
    write_results(args.out, record, table(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
