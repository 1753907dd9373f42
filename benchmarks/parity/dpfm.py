"""DPFM parity: geofeat's head against the authors' code, stage by stage, on one FAUST_r pair.

Both implementations get the same unit-area mesh (float32 vertices, as the reference's data
loader makes them) and the weights of the release checkpoint ``faust.pth``. The first rows
compare what each computes by itself (input coordinates, operators, sampling); from the
network on, both get the *reference's* operators, input coordinates and sample record, so
that each later row isolates one stage.

    python -m benchmarks.parity.dpfm --repo PATH/TO/DPFM

(``python -m benchmarks.parity`` runs this with the other heads.) The reference code
(``dpfm/model.py``, ``dpfm/utils.py``, ``dpfm/diffusion_net``) is imported from ``--repo`` at
run time, never copied; it needs potpourri3d, robust-laplacian and scikit-learn, which
geofeat's environment already has. Its FAUST_r ground truth uses ``torch.lstsq``, which
torch 2 removed; this script computes the same least squares with ``torch.linalg.lstsq``.

The pair is ``(x, y)`` = (the reference's ``shape1``, ``shape2``): the functional map takes
coefficients on ``x`` to ``y`` and the point map sends every vertex of ``y`` to ``x``. When
the clone holds ``shrec_holes.pth``, the table adds the first ``faust_r_holes`` test pair with
it (functional map from the refined features, real overlap masks): the reference's partial
ground truth sends vertices without a counterpart to the last vertex of ``x``, so its loss is
also given with those rows zeroed, as ours has them.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from benchmarks.common import DEFAULT_DATA, data_folder
from benchmarks.parity.common import (
    Stage,
    as_surface_operators,
    compare,
    evecs_up_to_sign,
    markdown,
    reference_import,
    seconds_per_call,
)
from geofeat.adapters.blocks.operators import surface_operators
from geofeat.adapters.dpfm import DPFMHead
from geofeat.adapters.dpfm.losses import nce_loss, template_fmap, weighted_overlap_bce
from geofeat.adapters.dpfm.sampling import ReferenceCandidates, reference_candidates, reference_sample_interpolation
from geofeat.adapters.heads import load_head
from geofeat.datasets import load_dataset

DEFAULT_PAIR = ("tr_reg_080", "tr_reg_081")  # (x, y) = (shape1, shape2) of the reference
#: Seed of torch's generator before the reference draws its farthest-point start (it uses no seed).
SAMPLING_SEED = 0


class _Setup:
    """Everything both implementations share for one pair.

    A FAUST_r pair ``pair_names = (x, y)``, or the first test pair of a partial benchmark
    (``dataset``), with a release checkpoint and head settings over the ``"reference"`` preset.
    """

    def __init__(
        self,
        checkpoint: Path,
        data_root: Path,
        load,
        pair_names: tuple[str, str] = DEFAULT_PAIR,
        dataset: str = "faust_r",
        settings: dict | None = None,
    ) -> None:
        if dataset == "faust_r":
            x_name, y_name = pair_names
            self.raw_pair = load_dataset("faust_r", root=data_root, split="all", pairs=[(y_name, x_name)])[0]
        else:
            self.raw_pair = load_dataset(dataset, root=data_root, split="test")[0]
        self.head = load_head("dpfm", checkpoint=checkpoint, progress=False, augmentation=False, **(settings or {}))
        self.c = self.head.config
        self.pair = self.head.prepare(self.raw_pair)  # the unit-area float32 meshes both implementations get
        self.raw = torch.load(checkpoint, map_location="cpu", weights_only=True)
        self.model_mod = load("model")
        self.utils = load("utils")
        self.geometry = load("diffusion_net.geometry")
        self.cfg = {
            "fmap": {
                "C_in": 3,
                "n_feat": self.c.width,
                "n_fmap": self.c.n_fmap,
                "k_eig": self.c.n_eig,
                "lambda_": self.c.lambda_,
                "resolvant_gamma": self.c.gamma,
                "robust": self.c.fmap_features == "refined",
            },
            "attention": {
                "num_head": self.c.n_heads,
                "gnn_dim": self.c.attention_dim,
                "ref_n_layers": self.c.n_attention_layers,
                "cross_sampling_ratio": self.c.sampling_ratio,
                "attention_type": "normal",
            },
            "overlap": {"overlap_feat_dim": 32},
        }
        self.meshes = {"x": self.pair.x, "y": self.pair.y}
        self.shape: dict[str, dict] = {}
        torch.manual_seed(SAMPLING_SEED)
        for s, mesh in self.meshes.items():
            verts = torch.from_numpy(mesh.verts.astype(np.float32))
            faces = torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64))
            frames, mass, lap, evals, evecs, grad_x, grad_y = self.geometry.compute_operators(verts, faces, self.c.n_eig)
            order = self.utils.farthest_point_sample(verts.t(), ratio=0.9)
            dists, ranks = self.utils.square_distance(verts.unsqueeze(0), verts[order].unsqueeze(0)).sort(dim=-1)
            self.shape[s] = {
                "xyz": verts,
                "faces": faces,
                "frames": frames,
                "mass": mass,
                "L": lap,
                "evals": evals,
                "evecs": evecs,
                "gradX": grad_x,
                "gradY": grad_y,
                "sample_idx": (order, ranks[:, :, :130].clone(), dists[:, :, :130].clone()),
            }
        self.net = self.model_mod.DPFMNet(self.cfg)
        self.net.load_state_dict(self.raw)
        self.net.eval()
        n_samples = {s: self.head.n_samples(m.n_vertices) for s, m in self.meshes.items()}
        for s, mesh in self.meshes.items():
            r = self.shape[s]
            self.head.use_inputs(mesh, r["xyz"], as_surface_operators(r, mesh))
            order, ranks, dists = r["sample_idx"]
            interp = reference_sample_interpolation(ReferenceCandidates(order, ranks[0], dists[0]), n_samples[s])
            self.head.use_samples(mesh, interp)
        self.head.model.eval()
        self.batch = {"shape1": self.shape["x"], "shape2": self.shape["y"]}
        k = self.c.n_fmap
        ex, ey = self.shape["x"]["evecs"][:, :k], self.shape["y"]["evecs"][:, :k]
        n_x, n_y = self.pair.x.n_vertices, self.pair.y.n_vertices
        if self.pair.corr_x is not None:
            corr_x, corr_y = torch.from_numpy(self.pair.corr_x), torch.from_numpy(self.pair.corr_y)
            # the reference's FAUST_r ground truth (faust_scape_dataset.py), torch.lstsq -> torch.linalg.lstsq
            self.c_gt = torch.linalg.lstsq(ex[corr_x], ey[corr_y]).solution.t()
            self.map21 = -torch.ones(n_y, dtype=torch.long)
            self.map21[corr_y] = corr_x
            self.masks = (torch.ones(n_x, dtype=torch.long), torch.ones(n_y, dtype=torch.long))
            self.c_gt_zeroed = self.c_gt
        else:
            # the reference's partial ground truth (shrec_partial_dataset.py): P[i, map21[i]] = 1, so map21 = -1 hits the last vertex
            self.map21 = torch.from_numpy(self.pair.map_yx)
            perm = torch.zeros(n_y, n_x)
            perm[torch.arange(n_y), self.map21] = 1
            trans_y = ey.t() * self.shape["y"]["mass"][None]
            self.c_gt = trans_y @ perm @ ex
            perm[self.map21 < 0] = 0
            self.c_gt_zeroed = trans_y @ perm @ ex
            # the masks as data: the pair's own (geometric) overlap masks, which our loss reads too
            self.masks = tuple(torch.from_numpy(np.asarray(m)).long() for m in (self.pair.overlap_x, self.pair.overlap_y))
        self.criterion = self.utils.DPFMLoss(
            w_fmap=self.c.w_fmap,
            w_acc=self.c.w_overlap,
            w_nce=self.c.w_nce,
            nce_t=self.c.nce_temperature,
            nce_num_pairs=self.c.nce_pairs,
        )

    def reference_loss(self, net, zeroed: bool = False) -> torch.Tensor:
        """The reference's training loss of the pair (its train script's call); ``zeroed``: C_gt without its -1 rows."""
        c_pred, o12, o21, f1, f2 = net(self.batch)
        c_gt = self.c_gt_zeroed if zeroed else self.c_gt
        return self.criterion(c_gt[None], c_pred, self.map21, f1, f2, o12, o21, *self.masks)

    def reference_pointmap(self, c_pred: torch.Tensor, exact: bool = True) -> np.ndarray:
        """Nearest neighbour of every row of Phi_y among the rows of Phi_x C^T.

        The reference repository has no FAUST_r evaluation; this is the protocol of its
        published number. ``exact``: a float64 kd-tree; else float32 ``torch.cdist``.
        """
        k = self.c.n_fmap
        emb_x = self.shape["x"]["evecs"][:, :k] @ c_pred.T
        emb_y = self.shape["y"]["evecs"][:, :k]
        if exact:
            return cKDTree(emb_x.double().numpy()).query(emb_y.double().numpy())[1]
        return torch.cdist(emb_y, emb_x).argmin(dim=1).numpy()


def _training_step(head, model: torch.nn.Module, net_train: torch.nn.Module, s, seed: int, **reference_options):
    """Backward of one training loss in both implementations from the same torch seed (same dropout masks).

    Returns ``(loss_ours, loss_ref)``; the gradients stay on the parameters, ``model`` ends in evaluation mode.
    """
    torch.manual_seed(seed)
    loss_ref = s.reference_loss(net_train, **reference_options)
    net_train.zero_grad()
    loss_ref.backward()
    model.train()
    model.zero_grad()
    torch.manual_seed(seed)
    with torch.enable_grad():
        loss_ours = head.training_loss(s.pair)
        loss_ours.backward()
    model.eval()
    return loss_ours, loss_ref


def _gradients(model: torch.nn.Module, net: torch.nn.Module) -> Stage:
    """Largest gradient difference over all parameters (reference names mapped to ours)."""
    grads = {name: p.grad for name, p in net.named_parameters()}
    mapped = DPFMHead.release_state(grads, source="reference gradients").state
    ours = dict(model.named_parameters())
    worst, scale, where = 0.0, 0.0, ""
    for name, grad in mapped.items():
        diff = float((ours[name].grad - grad).abs().max())
        scale = max(scale, float(grad.abs().max()))
        if diff >= worst:
            worst, where = diff, name
    return Stage("training step: gradients (all parameters)", worst, scale, f"worst: {where}")


def dpfm_stages(repo: Path, checkpoint: Path, data_root: Path, pair: tuple[str, str] = DEFAULT_PAIR, timing: bool = False):
    """Stage table of DPFM on one FAUST_r pair: a list of `Stage` (stage, max abs diff, reference scale, note).

    With ``timing=True`` returns ``(stages, timings)``, the timings of `dpfm_timings` on the
    same inputs.

    Parameters
    ----------
    repo : Path
        Clone of ``pvnieo/DPFM`` (the folder holding ``dpfm/``).
    checkpoint : Path
        ``faust.pth``.
    data_root : Path
        Folder holding ``FAUST_r``.
    pair : (str, str)
        Shapes ``(x, y)``: the reference's ``shape1`` and ``shape2``.
    """
    rows: list[Stage] = []
    with reference_import(repo, "dpfm") as load:
        s = _Setup(checkpoint, data_root, load, pair)
        head, c, net = s.head, s.c, s.net
        model = head.model

        # -- what each implementation computes by itself
        raw_verts = torch.from_numpy(s.raw_pair.x.verts.astype(np.float32))
        faces = s.shape["x"]["faces"]
        ref_xyz = s.utils.normalize_area_scale(s.geometry.normalize_positions(raw_verts), faces)
        ours_xyz = head.features(head.prepare(s.raw_pair).x)
        rows.append(compare("input xyz (ours: prepared pair; ref: its loader)", ours_xyz, ref_xyz))
        ours_ops = surface_operators(s.pair.x, c.n_eig, laplacian_kind=c.laplacian, construction=c.operators, cache=False)
        r = s.shape["x"]
        rows.append(compare("operators: mass", ours_ops.mass, r["mass"]))
        rows.append(compare("operators: eigenvalues", ours_ops.evals, r["evals"]))
        rows.append(evecs_up_to_sign(ours_ops.evecs, r["evecs"], r["mass"], c.n_fmap))
        rows.append(evecs_up_to_sign(ours_ops.evecs, r["evecs"], r["mass"], c.n_eig))
        rows.append(compare("operators: gradient X", ours_ops.grad_x, r["gradX"]))
        rows.append(compare("operators: gradient Y", ours_ops.grad_y, r["gradY"]))
        rows.append(compare("operators: tangent frames", ours_ops.frames, r["frames"]))
        order, ranks, dists = r["sample_idx"]
        ours_cand = reference_candidates(s.pair.x.verts, order=order)
        rows.append(
            Stage(
                "sampling: 130 candidates per vertex (fraction differing), ref's FPS order",
                float((ours_cand.ranks != ranks[0]).double().mean()),
                1.0,
                "FPS start is random in the reference",
            )
        )
        rows.append(compare("sampling: candidate squared distances", ours_cand.sq_dists, dists[0]))

        # -- from here on both get the reference's operators, coordinates and sample record
        with torch.no_grad():
            ref_feat = {
                k: net.feature_extractor(
                    r["xyz"],
                    r["mass"],
                    L=r["L"],
                    evals=r["evals"],
                    evecs=r["evecs"],
                    gradX=r["gradX"],
                    gradY=r["gradY"],
                    faces=r["faces"],
                ).unsqueeze(0)
                for k, r in s.shape.items()
            }
            ours_in = {k: head.shape_inputs(m) for k, m in s.meshes.items()}
            our_feat = {k: model.extractor(*ours_in[k]) for k in s.meshes}
        for k in ("x", "y"):
            rows.append(compare(f"DiffusionNet output {k}", our_feat[k], ref_feat[k][0]))
        with torch.no_grad():
            ref_x, ref_y, ref_ox, ref_oy = net.feat_refiner(
                s.shape["x"]["xyz"], s.shape["y"]["xyz"], ref_feat["x"], ref_feat["y"], s.batch
            )
            interp = {k: head.samples(m) for k, m in s.meshes.items()}
            our_x, our_y = model.refiner(our_feat["x"], our_feat["y"], interp["x"], interp["y"])
            our_ox, our_oy = torch.sigmoid(model.overlap(our_x)), torch.sigmoid(model.overlap(our_y))
        rows.append(compare("refined features x", our_x, ref_x[0]))
        rows.append(compare("refined features y", our_y, ref_y[0]))
        rows.append(compare("overlap probabilities x", our_ox, ref_ox, "FAUST masks are all ones: never trained"))
        rows.append(compare("overlap probabilities y", our_oy, ref_oy))
        with torch.no_grad():
            c_ref = net(s.batch)[0][0]
            out = head.forward(s.pair)
        rows.append(compare("functional map C (k_y, k_x)", out.fmap, c_ref))
        p2p_ref = s.reference_pointmap(c_ref)
        p2p_ours = head.match(s.raw_pair).map_yx  # match prepares the pair itself (the same meshes)
        rows.append(
            Stage(
                "point map y -> x (fraction of vertices that differ)",
                float((p2p_ours != p2p_ref).mean()),
                1.0,
                "nearest neighbours in float64 on both sides",
            )
        )
        p2p_cdist = s.reference_pointmap(c_ref, exact=False)
        rows.append(
            Stage(
                "point map y -> x, reference NN by float32 torch.cdist (fraction differing)",
                float((p2p_ours != p2p_cdist).mean()),
                1.0,
                "near-ties decided by float32 rounding",
            )
        )

        # -- losses: ground truth, the terms, and one training step from identical weights
        k = c.n_fmap
        our_gt = template_fmap(r["evecs"][:, :k], s.shape["y"]["evecs"][:, :k], s.pair.corr_x, s.pair.corr_y)
        rows.append(compare("loss: ground-truth C (template least squares)", our_gt, s.c_gt))
        prob = torch.rand(s.pair.x.n_vertices, generator=torch.Generator().manual_seed(1)) * 0.98 + 0.01
        mask = torch.rand(s.pair.x.n_vertices, generator=torch.Generator().manual_seed(2)) < 0.3
        rows.append(
            compare(
                "loss: weighted overlap BCE (random mask and probabilities)",
                weighted_overlap_bce(torch.logit(prob.double()).float(), mask, 0.0),
                s.utils.WeightedBCELoss()(prob, mask.float()),
            )
        )
        full_map = torch.from_numpy(p2p_ours)
        nce_ref = s.utils.NCESoftmaxLoss(c.nce_temperature, 10**6)(our_feat["x"], our_feat["y"], full_map)
        nce_ours = nce_loss(our_feat["x"], our_feat["y"], p2p_ours, 10**6, c.nce_temperature, np.random.default_rng(0))
        rows.append(compare("loss: NCE (all vertices, a full map)", nce_ours, nce_ref))

        net_train = copy.deepcopy(net).train()
        loss_ours, loss_ref = _training_step(head, model, net_train, s, seed=123)
        rows.append(compare("training step: loss (dropout on, same seed)", loss_ours, loss_ref))
        rows.append(_gradients(model, net_train))
        holes = Path(repo) / "dpfm" / "data" / "saved_models" / "shrec_holes.pth"
        if holes.is_file():
            rows += _partial_stages(holes, data_root, load)
        else:
            rows.append(Stage("partial pair (shrec_holes.pth)", float("nan"), 1.0, f"not run: {holes} is missing"))
        if timing:
            return rows, _timings(s)
    return rows


def _partial_stages(checkpoint: Path, data_root: Path, load) -> list[Stage]:
    """Stages on the first faust_r_holes test pair with ``shrec_holes.pth`` (functional map from the refined features).

    NCE is off in both (its pairs are drawn at random); the overlap masks are the pair's.
    """
    settings = {k: v for k, v in DPFMHead.PRESETS["reference_shrec16_holes"].items() if DPFMHead.PRESETS["reference"].get(k) != v}
    s = _Setup(checkpoint, data_root, load, dataset="faust_r_holes", settings=settings | {"w_nce": 0.0})
    head, model, net = s.head, s.head.model, s.net
    tag = f"partial {s.pair.y.name} -> {s.pair.x.name} (shrec_holes.pth): "
    rows: list[Stage] = []
    with torch.no_grad():
        ref_x, ref_y, ref_ox, ref_oy = net.feat_refiner(
            s.shape["x"]["xyz"],
            s.shape["y"]["xyz"],
            *(
                net.feature_extractor(
                    r["xyz"],
                    r["mass"],
                    L=r["L"],
                    evals=r["evals"],
                    evecs=r["evecs"],
                    gradX=r["gradX"],
                    gradY=r["gradY"],
                    faces=r["faces"],
                ).unsqueeze(0)
                for r in (s.shape["x"], s.shape["y"])
            ),
            s.batch,
        )
        c_ref = net(s.batch)[0][0]
        out = head.forward(s.pair)
    rows.append(compare(tag + "refined features x", out.feat_x, ref_x[0]))
    rows.append(compare(tag + "refined features y", out.feat_y, ref_y[0]))
    rows.append(compare(tag + "overlap probabilities x", torch.sigmoid(out.overlap_logits_x), ref_ox))
    rows.append(compare(tag + "overlap probabilities y", torch.sigmoid(out.overlap_logits_y), ref_oy))
    rows.append(compare(tag + "functional map C (refined features)", out.fmap, c_ref))
    net_train = copy.deepcopy(net).train()
    with torch.no_grad():
        torch.manual_seed(7)
        loss_bug = s.reference_loss(net_train)
    loss_ours, loss_ref = _training_step(head, model, net_train, s, seed=7, zeroed=True)
    rows.append(
        compare(
            tag + "training loss vs reference's own C_gt",
            loss_ours,
            loss_bug,
            "its C_gt sends vertices without a counterpart to the last vertex of x",
        )
    )
    rows.append(compare(tag + "training loss (C_gt rows of unmatched vertices zero)", loss_ours, loss_ref))
    grads = _gradients(model, net_train)
    rows.append(grads._replace(stage=tag + grads.stage))
    return rows


def dpfm_timings(repo: Path, checkpoint: Path, data_root: Path, pair: tuple[str, str] = DEFAULT_PAIR) -> dict[str, float]:
    """Seconds per pair of both implementations, inputs ready: inference (network, functional map, point map)
    and one training step (forward, loss, backward, Adam step); median of 3 after a warm-up."""
    with reference_import(repo, "dpfm") as load:
        return _timings(_Setup(checkpoint, data_root, load, pair))


def _timings(s: _Setup) -> dict[str, float]:
    head, net = s.head, s.net

    def reference_inference():
        with torch.no_grad():
            return s.reference_pointmap(net(s.batch)[0][0])

    net_train = copy.deepcopy(net).train()
    opt_ref = torch.optim.Adam(net_train.parameters(), lr=1e-3, betas=(0.9, 0.99))

    def reference_step():
        loss = s.reference_loss(net_train)
        loss.backward()
        opt_ref.step()
        opt_ref.zero_grad()

    saved = copy.deepcopy(head.model.state_dict())
    opt_ours = torch.optim.Adam(head.model.parameters(), lr=1e-3)

    def our_step():
        head.model.train()
        with torch.enable_grad():
            loss = head.training_loss(s.pair)
            opt_ours.zero_grad()
            loss.backward()
            opt_ours.step()

    out = {
        "inference_reference_s": seconds_per_call(reference_inference),
        "inference_geofeat_s": seconds_per_call(lambda: head.match(s.raw_pair)),
        "train_step_reference_s": seconds_per_call(reference_step),
        "train_step_geofeat_s": seconds_per_call(our_step),
    }
    head.model.load_state_dict(saved)
    head.model.eval()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", required=True, help="your clone of the DPFM reference repository (pvnieo/DPFM)")
    parser.add_argument("--checkpoint", default=None, help="faust.pth (default: <repo>/dpfm/data/saved_models/faust.pth)")
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)")
    parser.add_argument(
        "--pair", nargs=2, default=list(DEFAULT_PAIR), metavar=("X", "Y"), help="shapes x (shape1) and y (shape2)"
    )
    parser.add_argument("--no-timing", action="store_true")
    args = parser.parse_args(argv)
    checkpoint = Path(args.checkpoint or Path(args.repo) / "dpfm" / "data" / "saved_models" / "faust.pth")
    pair = tuple(args.pair)
    result = dpfm_stages(Path(args.repo), checkpoint, data_folder(args.data_root, "--data-root"), pair, timing=not args.no_timing)
    rows, timings = result if isinstance(result, tuple) else (result, {})
    print(markdown(rows, f"DPFM ({checkpoint.name}, {pair[1]} -> {pair[0]})"))
    for key, value in timings.items():
        print(f"{key}: {value:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
