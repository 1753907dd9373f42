"""The DPFM reference code's own pipeline on the FAUST_r test pairs, for comparison with geofeat's.

Runs the authors' model (imported at run time from the user's clone of ``pvnieo/DPFM``,
never copied) with a release checkpoint on the 190 pairs ``i < j`` of the 20 FAUST_r test
shapes, with the reference's own preprocessing: meshes read by potpourri3d as float32,
centred and scaled to unit area by its loader functions, its DiffusionNet operators
(128 eigenpairs), its farthest-point sample record (start drawn from torch's generator,
seeded here). The repository has no FAUST_r evaluation script; the point map is the nearest
neighbour of every row of ``Phi_y`` among the rows of ``Phi_x C^T`` (float64 kd-tree) and the
errors are geofeat's template protocol (Dijkstra geodesics of the unit-area shape).

    python -m benchmarks.reference_dpfm_faust_r --repo PATH/TO/DPFM [--checkpoint faust.pth]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

from benchmarks.common import DEFAULT_DATA, data_folder, machine
from benchmarks.parity.common import reference_import
from geofeat.datasets import load_dataset
from geofeat.evaluation import metrics
from geofeat.geometry.geodesic import geodesic_matrix


def reference_faust_r(
    repo: Path,
    checkpoint: Path,
    data_root: Path,
    seed: int = 0,
    limit: int | None = None,
    n_fmap: int = 50,
    k_eig: int = 128,
    ratio: float = 0.7,
    progress: bool = True,
) -> dict:
    """Mean template geodesic error x100 and PCK AUC of the reference pipeline on the 190 test pairs.

    Returns
    -------
    dict
        ``geodesic_error``, ``geodesic_error_cdist`` (nearest neighbours by float32
        ``torch.cdist`` instead), ``pck_auc``, ``head``, ``dataset``, ``n_pairs``, ``seconds``, ``checkpoint``
        (its file name), ``threads``, ``machine``, ``date``, per-pair errors.
    """
    dataset = load_dataset("faust_r", root=data_root, split="test", pairs="combinations")
    n_pairs = len(dataset) if limit is None else min(limit, len(dataset))
    start = time.perf_counter()
    with reference_import(repo, "dpfm") as load:
        model_mod, utils, geometry = load("model"), load("utils"), load("diffusion_net.geometry")
        cfg = {
            "fmap": {
                "C_in": 3,
                "n_feat": 128,
                "n_fmap": n_fmap,
                "k_eig": k_eig,
                "lambda_": 100,
                "resolvant_gamma": 0.5,
                "robust": False,
            },
            "attention": {
                "num_head": 4,
                "gnn_dim": 128,
                "ref_n_layers": 1,
                "cross_sampling_ratio": ratio,
                "attention_type": "normal",
            },
            "overlap": {"overlap_feat_dim": 32},
        }
        net = model_mod.DPFMNet(cfg)
        net.load_state_dict(torch.load(checkpoint, map_location="cpu", weights_only=True))
        net.eval()
        torch.manual_seed(seed)
        shapes: dict[str, dict] = {}

        def shape(mesh) -> dict:
            if mesh.name not in shapes:
                verts = torch.from_numpy(mesh.verts.astype(np.float32))
                faces = torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64))
                verts = utils.normalize_area_scale(geometry.normalize_positions(verts), faces)
                frames, mass, lap, evals, evecs, grad_x, grad_y = geometry.compute_operators(verts, faces, k_eig)
                order = utils.farthest_point_sample(verts.t(), ratio=0.9)
                dists, ranks = utils.square_distance(verts.unsqueeze(0), verts[order].unsqueeze(0)).sort(dim=-1)
                shapes[mesh.name] = {
                    "xyz": verts,
                    "faces": faces,
                    "mass": mass,
                    "L": lap,
                    "evals": evals,
                    "evecs": evecs,
                    "gradX": grad_x,
                    "gradY": grad_y,
                    "sample_idx": (order, ranks[:, :, :130].clone(), dists[:, :, :130].clone()),
                }
            return shapes[mesh.name]

        errors, errors_cdist, names = [], [], []
        for i in tqdm(range(n_pairs), desc="DPFM reference on faust_r", unit="pair", disable=not progress):
            pair = dataset[i]
            sx, sy = shape(pair.x), shape(pair.y)
            with torch.no_grad():
                c_pred = net({"shape1": sx, "shape2": sy})[0][0]
            emb_x = sx["evecs"][:, :n_fmap] @ c_pred.T
            emb_y = sy["evecs"][:, :n_fmap]
            p2p = cKDTree(emb_x.double().numpy()).query(emb_y.double().numpy())[1]
            p2p_cdist = torch.cdist(emb_y, emb_x).argmin(dim=1).numpy()
            dist_x = geodesic_matrix(pair.x, method="dijkstra", normalize=True)
            errors.append(metrics.template_geodesic_errors(p2p, pair.corr_x, pair.corr_y, dist_x))
            errors_cdist.append(metrics.template_geodesic_errors(p2p_cdist, pair.corr_x, pair.corr_y, dist_x))
            names.append(pair.name)
    return {
        "head": "dpfm",
        "dataset": "faust_r",
        "n_pairs": n_pairs,
        "geodesic_error": metrics.mean_geodesic_error(errors),
        "geodesic_error_cdist": metrics.mean_geodesic_error(errors_cdist),
        "pck_auc": metrics.pck_auc(np.concatenate(errors)),
        "seconds": time.perf_counter() - start,
        "seed": seed,
        "checkpoint": checkpoint.name,
        "threads": torch.get_num_threads(),
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "pairs": [{"pair": n, "geodesic_error": 100 * float(e.mean())} for n, e in zip(names, errors, strict=True)],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", required=True, help="your clone of the DPFM reference repository (pvnieo/DPFM)")
    parser.add_argument("--checkpoint", default=None, help="default: <repo>/dpfm/data/saved_models/faust.pth")
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)")
    parser.add_argument("--seed", type=int, default=0, help="seed of torch's generator (the reference's sampling start)")
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument(
        "--out", default=None, help="write the result as JSON here (benchmarks/tables/release.py reads reference.json)"
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    checkpoint = Path(args.checkpoint or Path(args.repo) / "dpfm" / "data" / "saved_models" / "faust.pth")
    data_root = data_folder(args.data_root, "--data-root")
    result = reference_faust_r(Path(args.repo), checkpoint, data_root, args.seed, args.limit, progress=not args.no_progress)
    print(
        f"DPFM reference ({checkpoint.name}) on {result['n_pairs']} FAUST_r pairs: geodesic error x100 "
        f"{result['geodesic_error']:.3f} (float32 cdist NN: {result['geodesic_error_cdist']:.3f}), "
        f"PCK AUC {result['pck_auc']:.4f}, {result['seconds']:.0f} s"
    )
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
