"""ULRSSM parity: geofeat's head against the authors' code, stage by stage, on one FAUST_r pair.

Both implementations get the same unit-area mesh (float32 vertices, as the reference reads
its preprocessed files) and the weights of the release checkpoint. The first stages
compare what each computes by itself (operators, WKS input); from the network on, both get
the *reference's* operators and input features, so that each later row isolates one stage.

    python -m benchmarks.parity.ulrssm --repo PATH/TO/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching

(``python -m benchmarks.parity`` runs this and the DPFM and EchoMatch checks together.)
The reference code is imported from ``--repo`` at run time; it needs potpourri3d,
robust-laplacian, scikit-learn and networkx, which geofeat's environment already has.
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

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
from geofeat.adapters.heads import load_head
from geofeat.adapters.ulrssm import ULRSSMHead
from geofeat.datasets import load_dataset

DEFAULT_PAIR = ("tr_reg_081", "tr_reg_080")  # (y, x)


def _reference_operators(load, mesh, k: int) -> dict[str, torch.Tensor]:
    """The reference's operators of ``mesh`` (float32 vertices, k eigenpairs), as its dataset builds them."""
    geometry = load("utils.geometry_util")
    verts = torch.from_numpy(mesh.verts.astype(np.float32))
    faces = torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64))
    frames, mass, lap, evals, evecs, grad_x, grad_y = geometry.compute_operators(verts, faces, k=k)
    return {
        "verts": verts,
        "faces": faces,
        "frames": frames,
        "mass": mass,
        "L": lap,
        "evals": evals,
        "evecs": evecs,
        "gradX": grad_x,
        "gradY": grad_y,
    }


def ulrssm_stages(repo: Path, checkpoint: Path, data_root: Path, pair_names=DEFAULT_PAIR, timing: bool = True):
    """Stage table of ULRSSM (list of `Stage`) and timings (dict) on one FAUST_r pair.

    Parameters
    ----------
    repo : Path
        Clone of ``dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching``.
    checkpoint : Path
        ``faust_scape.pth``.
    data_root : Path
        Folder holding ``FAUST_r``.
    pair_names : (str, str)
        Shapes (y, x) of the pair.
    """
    torch.manual_seed(0)
    dataset = load_dataset("faust_r", root=data_root, split="all", pairs=[pair_names])
    pair = dataset[0]
    head = load_head("ulrssm", checkpoint=checkpoint, progress=False)
    c = head.config
    raw_pair, pair = pair, head.prepare(pair)  # the unit-area meshes both implementations get
    mesh_x, mesh_y = pair.x, pair.y
    raw = torch.load(checkpoint, map_location="cpu", weights_only=True)
    rows: list[Stage] = []
    timings: dict[str, float] = {}
    with reference_import(repo) as load:
        diffusion = load("networks.diffusion_network")
        fmap_network = load("networks.fmap_network")
        permutation = load("networks.permutation_network")
        fmap_loss = load("losses.fmap_loss")
        fmap_util = load("utils.fmap_util")
        geometry = load("utils.geometry_util")

        # -- stages each implementation computes by itself
        ref = {name: _reference_operators(load, m, c.n_eig) for name, m in (("x", mesh_x), ("y", mesh_y))}
        ours_ops = head.operators(pair.x)
        r = ref["x"]
        rows.append(compare("operators: mass", ours_ops.mass, r["mass"]))
        rows.append(compare("operators: eigenvalues", ours_ops.evals, r["evals"]))
        rows.append(evecs_up_to_sign(ours_ops.evecs, r["evecs"], r["mass"], c.diffusion_eig))
        rows.append(compare("operators: gradient X", ours_ops.grad_x, r["gradX"]))
        rows.append(compare("operators: gradient Y", ours_ops.grad_y, r["gradY"]))
        rows.append(compare("operators: tangent frames", ours_ops.frames, r["frames"]))
        wks_ref = {
            s: geometry.compute_wks_autoscale(
                ref[s]["evals"][None, : c.diffusion_eig], ref[s]["evecs"][None, :, : c.diffusion_eig], ref[s]["mass"][None]
            )[0]
            for s in ("x", "y")
        }
        rows.append(compare("input WKS (each on its own operators)", head.features(pair.x), wks_ref["x"]))

        # -- from here on both get the reference's operators and input features
        for s, mesh in (("x", pair.x), ("y", pair.y)):
            head.use_inputs(mesh, wks_ref[s], as_surface_operators(ref[s], mesh))
        # the reference reads its DiffusionNet operators from a disk cache at test time; give it one
        cache_dir = tempfile.mkdtemp(prefix="ulrssm_ops_")
        net = diffusion.DiffusionNet(in_channels=128, out_channels=256, input_type="wks", cache_dir=cache_dir)
        net.load_state_dict(raw["networks"]["feature_extractor"])
        net.eval()
        head.model.eval()
        with torch.no_grad():
            feat_ref = {s: net(ref[s]["verts"][None], ref[s]["faces"][None], feats=wks_ref[s][None])[0] for s in ("x", "y")}
            feat_ours = {s: head._embed(m)[0] for s, m in (("x", pair.x), ("y", pair.y))}
        why = "reference net solves its own k=128 eigenpairs inside forward; ours gets the first 128 of k=200"
        rows.append(compare("DiffusionNet output x", feat_ours["x"], feat_ref["x"], why))
        rows.append(compare("DiffusionNet output y", feat_ours["y"], feat_ref["y"], why))

        k = c.n_fmap
        evecs = {s: ref[s]["evecs"][:, :k] for s in ("x", "y")}
        evecs_trans = {s: (evecs[s] * ref[s]["mass"][:, None]).T for s in ("x", "y")}
        evals = {s: ref[s]["evals"][:k] for s in ("x", "y")}
        modules = (fmap_network, permutation, fmap_loss)

        def reference_loss(fx, fy):
            return _reference_loss(modules, c, ref, fx, fy, partial=False)

        with torch.no_grad():
            cxy_ref, cyx_ref, pyx_ref, terms_ref = reference_loss(feat_ref["x"], feat_ref["y"])
            terms_ours = head.loss_terms(pair, partial=False)
        from geofeat.adapters.blocks.fmap_layers import regularized_fmap, soft_pointmap

        with torch.no_grad():
            cxy_ours, cyx_ours = regularized_fmap(
                feat_ours["x"],
                feat_ours["y"],
                evecs["x"],
                evecs["y"],
                ref["x"]["mass"],
                ref["y"]["mass"],
                evals["x"],
                evals["y"],
                lambda_=c.fmap_lambda,
                gamma=c.resolvent_gamma,
                bidirectional=True,
            )
            pyx_ours = soft_pointmap(feat_ours["x"], feat_ours["y"], temperature=c.temperature)
        rows.append(compare("functional map C_xy", cxy_ours, cxy_ref))
        rows.append(compare("functional map C_yx", cyx_ours, cyx_ref))
        rows.append(compare("soft point map P_yx", pyx_ours, pyx_ref))
        for ours_name, ref_name in (("bij", "l_bij"), ("orth", "l_orth"), ("couple", "l_align"), ("total", "l_total")):
            rows.append(compare(f"loss: {ours_name}", terms_ours[ours_name], terms_ref[ref_name]))

        # -- point map at test time (the reference's validate_single, non-isometric: false)
        with torch.no_grad():
            hard = permutation.Similarity(tau=c.temperature, hard=True)
            nx, ny = (torch.nn.functional.normalize(feat_ref[s], dim=-1) for s in ("x", "y"))
            pyx_hard = hard((ny @ nx.T)[None])[0]
            cxy_test = evecs_trans["y"] @ (pyx_hard @ evecs["x"])
            p2p_ref = fmap_util.fmap2pointmap(cxy_test, evecs["x"], evecs["y"]).numpy()
        p2p_ours = head.match(raw_pair).map_yx  # match prepares the pair itself
        same = float((p2p_ours == p2p_ref).mean())
        rows.append(Stage("point map y -> x (fraction of vertices that differ)", 1.0 - same, 1.0))

        # -- one training step from identical weights (dropout off in both: its masks are random)
        net_train = copy.deepcopy(net)
        head.model.eval()
        net_train.eval()
        loss_ref = reference_loss(
            *(net_train(ref[s]["verts"][None], ref[s]["faces"][None], feats=wks_ref[s][None])[0] for s in ("x", "y"))
        )[3]["l_total"]
        net_train.zero_grad()
        loss_ref.backward()
        head.model.zero_grad()
        with torch.enable_grad():
            loss_ours = head.loss_terms(pair, partial=False)["total"]
            loss_ours.backward()
        rows.append(compare("training step: loss", loss_ours, loss_ref))
        rows.append(_gradients(head, net_train))
        rows += _partial_training_step(head, net, modules, load, data_root)
        if timing:
            timings = _timings(
                head, pair, raw_pair, net, ref, wks_ref, reference_loss, fmap_util, permutation, evecs, evecs_trans, c
            )
    return rows, timings


def _reference_loss(modules, c, ref, fx, fy, partial: bool):
    """The reference's training loss of one pair (its ``FMNetModel.feed_data``), from features (V, C).

    Returns ``C_xy``, ``C_yx``, ``P_yx`` and the loss terms (``l_bij``, ``l_orth``, ``l_align``, ``l_total``).
    """
    fmap_network, permutation, fmap_loss = modules
    k = c.n_fmap
    evecs = {s: ref[s]["evecs"][:, :k] for s in ("x", "y")}
    evecs_trans = {s: (evecs[s] * ref[s]["mass"][:, None]).T for s in ("x", "y")}
    evals = {s: ref[s]["evals"][:k] for s in ("x", "y")}
    fmap_net = fmap_network.RegularizedFMNet(lmbda=c.fmap_lambda, resolvant_gamma=c.resolvent_gamma, bidirectional=True)
    cxy, cyx = fmap_net(fx[None], fy[None], evals["x"][None], evals["y"][None], evecs_trans["x"][None], evecs_trans["y"][None])
    if partial:
        terms = fmap_loss.PartialFmapsLoss(w_bij=c.w_bij, w_orth=c.w_orth)(cxy, cyx, evals["x"][None], evals["y"][None])
    else:
        terms = fmap_loss.SURFMNetLoss(w_bij=c.w_bij, w_orth=c.w_orth, w_lap=0.0)(cxy, cyx, evals["x"][None], evals["y"][None])
    sim = permutation.Similarity(tau=c.temperature, hard=False)
    nx, ny = torch.nn.functional.normalize(fx, dim=-1), torch.nn.functional.normalize(fy, dim=-1)
    similarity = (nx @ ny.T)[None]
    pxy, pyx = sim(similarity), sim(similarity.transpose(1, 2))
    align = fmap_loss.SquaredFrobeniusLoss(loss_weight=c.w_couple)
    terms["l_align"] = align(cxy, evecs_trans["y"][None] @ (pyx @ evecs["x"][None]))
    if not partial:
        terms["l_align"] = terms["l_align"] + align(cyx, evecs_trans["x"][None] @ (pxy @ evecs["y"][None]))
    terms["l_total"] = terms["l_bij"] + terms["l_orth"] + terms["l_align"]
    return cxy[0], cyx[0], pyx[0], terms


def _partial_training_step(head: ULRSSMHead, net, modules, load, data_root: Path) -> list[Stage]:
    """Loss terms and gradients of one training step on a partial pair (the reference's ``partial: true``).

    The pair is the first of ``faust_r_cuts`` (a CUTS partial of one FAUST_r test shape
    against another full shape), the weights those of the checkpoint, dropout off.
    """
    pair = head.prepare(load_dataset("faust_r_cuts", root=data_root, split="test")[0])
    c = head.config
    ref = {s: _reference_operators(load, m, c.n_eig) for s, m in (("x", pair.x), ("y", pair.y))}
    geometry = load("utils.geometry_util")
    wks = {
        s: geometry.compute_wks_autoscale(
            ref[s]["evals"][None, : c.diffusion_eig], ref[s]["evecs"][None, :, : c.diffusion_eig], ref[s]["mass"][None]
        )[0]
        for s in ("x", "y")
    }
    for s, mesh in (("x", pair.x), ("y", pair.y)):
        head.use_inputs(mesh, wks[s], as_surface_operators(ref[s], mesh))
    net_train = copy.deepcopy(net).eval()
    head.model.eval()
    feats = [net_train(ref[s]["verts"][None], ref[s]["faces"][None], feats=wks[s][None])[0] for s in ("x", "y")]
    terms_ref = _reference_loss(modules, c, ref, *feats, partial=True)[3]
    net_train.zero_grad()
    terms_ref["l_total"].backward()
    head.model.zero_grad()
    with torch.enable_grad():
        terms_ours = head.loss_terms(pair)  # protocol p2f: the partial losses
        terms_ours["total"].backward()
    rows = [
        compare(f"partial pair: loss {ours}", terms_ours[ours].detach(), terms_ref[theirs].detach())
        for ours, theirs in (("bij", "l_bij"), ("orth", "l_orth"), ("couple", "l_align"), ("total", "l_total"))
    ]
    gradients = _gradients(head, net_train)
    rows.append(gradients._replace(stage="partial pair: gradients (all parameters)"))
    return rows


def _gradients(head: ULRSSMHead, net: torch.nn.Module) -> Stage:
    """Largest gradient difference over all parameters (reference names mapped to ours)."""
    grads = {name: p.grad for name, p in net.named_parameters()}
    mapped = ULRSSMHead.release_state({"networks": {"feature_extractor": grads}}).state
    ours = dict(head.model.named_parameters())
    worst, scale, where = 0.0, 0.0, ""
    for name, grad in mapped.items():
        diff = float((ours[name].grad - grad).abs().max())
        scale = max(scale, float(grad.abs().max()))
        if diff >= worst:
            worst, where = diff, name
    return Stage("training step: gradients (all parameters)", worst, scale, f"worst: {where}")


def _timings(
    head, pair, raw_pair, net, ref, wks_ref, reference_loss, fmap_util, permutation, evecs, evecs_trans, c
) -> dict[str, float]:
    """Seconds per pair: inference (network + point map, inputs ready) and one training step, both implementations."""
    hard = permutation.Similarity(tau=c.temperature, hard=True)

    def reference_inference():
        with torch.no_grad():
            fx, fy = (net(ref[s]["verts"][None], ref[s]["faces"][None], feats=wks_ref[s][None])[0] for s in ("x", "y"))
            nx, ny = torch.nn.functional.normalize(fx, dim=-1), torch.nn.functional.normalize(fy, dim=-1)
            cxy = evecs_trans["y"] @ (hard((ny @ nx.T)[None])[0] @ evecs["x"])
            return fmap_util.fmap2pointmap(cxy, evecs["x"], evecs["y"])

    net_train = copy.deepcopy(net).train()
    opt_ref = torch.optim.Adam(net_train.parameters(), lr=1e-3)

    def reference_step():
        loss = reference_loss(
            *(net_train(ref[s]["verts"][None], ref[s]["faces"][None], feats=wks_ref[s][None])[0] for s in ("x", "y"))
        )[3]["l_total"]
        opt_ref.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net_train.parameters(), 1.0)
        opt_ref.step()

    saved = copy.deepcopy(head.model.state_dict())
    opt_ours = torch.optim.Adam(head.model.parameters(), lr=1e-3)

    def our_step():
        head.model.train()
        with torch.enable_grad():
            loss = head.training_loss(pair)
            opt_ours.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(head.model.parameters(), 1.0)
            opt_ours.step()

    out = {
        "inference_reference_s": seconds_per_call(reference_inference),
        "inference_geofeat_s": seconds_per_call(lambda: head.match(raw_pair)),
        "train_step_reference_s": seconds_per_call(reference_step),
        "train_step_geofeat_s": seconds_per_call(our_step),
    }
    head.model.load_state_dict(saved)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", required=True, help="your clone of the ULRSSM reference repository")
    parser.add_argument("--checkpoint", default=None, help="faust_scape.pth (default: <repo>/checkpoints/faust_scape.pth)")
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)")
    parser.add_argument("--no-timing", action="store_true")
    args = parser.parse_args(argv)
    checkpoint = Path(args.checkpoint or Path(args.repo) / "checkpoints" / "faust_scape.pth")
    data_root = data_folder(args.data_root, "--data-root")
    rows, timings = ulrssm_stages(Path(args.repo), checkpoint, data_root, timing=not args.no_timing)
    print(markdown(rows, f"ULRSSM ({checkpoint.name}, {DEFAULT_PAIR[0]} -> {DEFAULT_PAIR[1]})"))
    for key, value in timings.items():
        print(f"{key}: {value:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
