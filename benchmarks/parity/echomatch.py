"""EchoMatch parity: geofeat's head against the authors' code (DeepShapeMatchingKit), stage by stage.

EchoMatch has no released weights, so both implementations start from the SAME random
weights: the reference model (``Echo_Match_Model``, built from the clone's own
``options/echo_match/train/echo_match_cp2p24_xyz.yaml``: network, loss, Adam) is created
with a fixed seed and its tensors are copied into our `EchoMatchHead` (``reference``
preset) through an explicit key mapping (`geofeat.adapters.release.diffusionnet_state`; the
reference's ``DiffusionNet_A`` uses the DPFM key spelling). Both then get:

* the same pair of unit-area meshes (float32 vertices): FAUST_r ``tr_reg_080 -> tr_reg_081``
  (``--pair full``) or the first ``faust_r_p2p`` test pair, two CUTS partial shapes
  (``--pair partial``);
* the same operators: ours (``operators="diffusionnet"``, cotangent Laplacian, 128
  eigenpairs), handed to the reference as its ``operators``, ``evecs``, ``evals`` and
  ``evecs_trans`` (first 50); a first block of rows compares them with the reference's own
  ``compute_operators``;
* the same ground truth (correspondences, overlap masks) and the same spatial
  neighbourhoods (ours, handed over as a rank matrix in ``data["dist"]``, which the
  reference reads when both shapes have one; the row ``neighbours`` counts where the
  reference's own float32 top-k would order them otherwise);
* for the training step, the same dropout masks (the torch generator is reseeded before
  each forward, and both draw in the same order); the reference's random xyz augmentation,
  which our head does not have, is replaced by the identity.

The reference's weights are copied after its first (inference) forward, because that
forward writes ``max(t, 1e-8)`` into every diffusion time (initialised at 0); our
`LearnedDiffusion` clamps at 0 instead, see the head's notes.

Rows: operators, input features; at inference (eval mode): features, overlap probabilities,
point map; one training step: features, soft maps, reflection features (the overlap
network's input), overlap probabilities, functional map, ground-truth functional map, each
loss term, total loss, gradients before and after the reference's gradient clipping, and
the weights after one Adam step. Timings: inference and one training step of both, on the
same pair (operators precomputed for both).

    python -m benchmarks.parity.echomatch --repo PATH/TO/DeepShapeMatchingKit [--pair partial] [--float64]

``--float64`` runs both in double precision: what remains then is a difference of formula,
not of rounding. The reference code is imported from ``--repo`` at run time (never copied
into geofeat); ``wandb``, which its base model imports but never calls here, is stubbed
when it is not installed.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import sys
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

import geofeat.adapters.echomatch.head as echomatch_module
from benchmarks.common import DEFAULT_DATA, data_folder
from benchmarks.parity.common import Stage, compare, markdown, reference_import, seconds_per_call
from geofeat.adapters.echomatch import EchoMatchHead
from geofeat.adapters.heads import make_head
from geofeat.adapters.inputs import ground_truth_map, ground_truth_overlaps, normalized_mesh
from geofeat.datasets import load_dataset
from geofeat.datasets.records import ShapePair

#: The reference's training configuration its model is built from (relative to the clone).
REFERENCE_CONFIG = "options/echo_match/train/echo_match_cp2p24_xyz.yaml"
PAIRS = ("full", "partial")
#: The floor the reference writes into its diffusion times at every forward.
REFERENCE_TIME_FLOOR = 1e-8


# ----------------------------------------------------------------------------- the reference


@contextlib.contextmanager
def _wandb_stub() -> Iterator[None]:
    """A stand-in ``wandb`` module while the reference is imported, if the real one is absent."""
    try:
        import wandb  # noqa: F401

        yield
        return
    except ImportError:
        pass
    sys.modules["wandb"] = types.ModuleType("wandb")
    try:
        yield
    finally:
        sys.modules.pop("wandb", None)


def reference_options(repo: Path) -> dict[str, Any]:
    """The reference's EchoMatch training options, for one CPU process (no data sets, no validation)."""
    import yaml

    opt = yaml.safe_load((Path(repo) / REFERENCE_CONFIG).read_text())
    opt.update(num_gpu=0, is_train=True, val=None, path={}, datasets={})
    return opt


def reference_data(mesh, xyz: torch.Tensor, ops, n_fmap: int, corr: torch.Tensor, mask: torch.Tensor) -> dict:
    """The reference's batch (size 1) of one shape, from our mesh, operators and ground truth."""
    evecs_trans = ops.evecs.T * ops.mass[None]
    return {
        "name": [mesh.name],
        "verts": xyz[None],
        "faces": torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64)[None],
        "xyz": xyz[None],
        "operators": {
            "mass": ops.mass[None],
            "L": None,  # only the implicit diffusion reads it; the reference runs the spectral one
            "evals": ops.evals[None],
            "evecs": ops.evecs[None],
            "gradX": torch.stack([ops.grad_x]),
            "gradY": torch.stack([ops.grad_y]),
        },
        "evecs": ops.evecs[:, :n_fmap][None],
        "evals": ops.evals[:n_fmap][None],
        "evecs_trans": evecs_trans[:n_fmap][None],
        "mass": ops.mass[None],
        "corr": corr[None],
        "partiality_mask": mask.to(ops.mass.dtype)[None],
    }


def rank_distances(neighbours: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """A (V, V) matrix whose ``topk(k, largest=False, sorted=True)`` gives back exactly ``neighbours`` (V, k)."""
    n, k = neighbours.shape
    dist = torch.full((n, n), float(k + 1), dtype=dtype)
    dist.scatter_(1, neighbours, torch.arange(k, dtype=dtype).expand(n, k).contiguous())
    return dist


class _Timer:
    def start(self) -> None:
        pass

    def record(self) -> None:
        pass


@contextlib.contextmanager
def no_augmentation(diffusion_module: types.ModuleType) -> Iterator[None]:
    """The reference's xyz augmentation replaced by the identity (ours has none)."""
    original = diffusion_module.data_augmentation
    diffusion_module.data_augmentation = lambda verts, **_: verts
    try:
        yield
    finally:
        diffusion_module.data_augmentation = original


# ----------------------------------------------------------------------------- recording


class Recorder:
    """Forward hooks and function spies that keep (detached copies of) what an implementation computed."""

    def __init__(self) -> None:
        self.values: dict[str, list] = {}
        self._handles: list = []
        self._restore: list[Callable[[], None]] = []

    def add(self, key: str, value) -> None:
        self.values.setdefault(key, []).append(_detach(value))

    def output(self, module: torch.nn.Module, key: str) -> None:
        self._handles.append(module.register_forward_hook(lambda _m, _a, out: self.add(key, out)))

    def inputs(self, module: torch.nn.Module, key: str) -> None:
        self._handles.append(module.register_forward_pre_hook(lambda _m, a, kw: self.add(key, (a, kw)), with_kwargs=True))

    def spy(self, owner, name: str, key: str) -> None:
        """Replace ``owner.name`` by a wrapper that records its result, until `close`."""
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            out = original(*args, **kwargs)
            self.add(key, out)
            return out

        setattr(owner, name, wrapper)
        self._restore.append(lambda: setattr(owner, name, original))

    def close(self) -> None:
        for handle in self._handles:
            handle.remove()
        for restore in reversed(self._restore):
            restore()
        self._handles, self._restore = [], []


def _detach(value):
    if isinstance(value, torch.Tensor):
        return value.detach().clone()
    if isinstance(value, tuple) and hasattr(value, "_fields"):
        return type(value)(*(_detach(v) for v in value))
    if isinstance(value, (list, tuple)):
        return type(value)(_detach(v) for v in value)
    if isinstance(value, dict):
        return {k: _detach(v) for k, v in value.items()}
    return value


@contextlib.contextmanager
def grad_clip_spy(store: list) -> Iterator[None]:
    """Keep every parameter's gradient (by ``id``) just before ``torch.nn.utils.clip_grad_norm_`` clips it."""
    original = torch.nn.utils.clip_grad_norm_

    def spy(parameters, *args, **kwargs):
        parameters = list(parameters)
        store.append({id(p): p.grad.detach().clone() for p in parameters if p.grad is not None})
        return original(parameters, *args, **kwargs)

    torch.nn.utils.clip_grad_norm_ = spy
    try:
        yield
    finally:
        torch.nn.utils.clip_grad_norm_ = original


# ----------------------------------------------------------------------------- rows


def _count(stage: str, n: int, total: int, note: str) -> Stage:
    return Stage(stage, float(n), float(total), note)


def _pointmap_row(ours: np.ndarray, ref: np.ndarray, feat_x: torch.Tensor, feat_y: torch.Tensor) -> Stage:
    """Vertices of ``y`` mapped elsewhere, and how close to a tie the reference's own features put them."""
    differ = np.flatnonzero(ours != ref)
    note = "count of vertices of y; scale = V_y"
    if differ.size:
        fx = torch.nn.functional.normalize(feat_x.double(), dim=-1)
        fy = torch.nn.functional.normalize(feat_y.double(), dim=-1)[torch.as_tensor(differ)]
        gap = (fy * fx[torch.as_tensor(ref[differ])]).sum(-1) - (fy * fx[torch.as_tensor(ours[differ])]).sum(-1)
        note += f"; cosine gap of the two choices in the reference's features <= {float(gap.abs().max()):.1e} (ties)"
    return _count("eval point map y->x (nearest feature)", int(differ.size), ref.size, note)


def _evecs_row(ours: torch.Tensor, theirs: torch.Tensor, mass: torch.Tensor, label: str) -> Stage:
    inner = (ours.double() * mass[:, None].double() * theirs.double()).sum(0).abs()
    gap = (1 - inner).abs()
    return Stage(
        f"operators {label}: eigenvectors (1 - |<ours, ref>_M|)", float(gap.max()), 1.0, f"worst index {int(gap.argmax())}"
    )


def operator_rows(geometry: types.ModuleType, mesh, ops, label: str) -> list[Stage]:
    """Our ``diffusionnet`` operators against the reference's ``compute_operators`` on the same float32 vertices."""
    verts = torch.as_tensor(mesh.verts, dtype=torch.float32)
    faces = torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64)
    _, mass, _, evals, evecs, grad_x, grad_y = geometry.compute_operators(verts, faces, k=ops.k)
    return [
        compare(f"operators {label}: mass", ops.mass, mass),
        compare(f"operators {label}: eigenvalues", ops.evals, evals),
        _evecs_row(ops.evecs, evecs, mass, label),
        compare(f"operators {label}: gradient X", ops.grad_x, grad_x),
        compare(f"operators {label}: gradient Y", ops.grad_y, grad_y),
    ]


# ----------------------------------------------------------------------------- the pair and the weights


def parity_pair(data_root: Path, which: str) -> ShapePair:
    """FAUST_r ``tr_reg_080 -> tr_reg_081`` or the first ``faust_r_p2p`` test pair, on unit-area float32 meshes.

    The meshes are centred and scaled to unit area so that the reference's raw-coordinate
    input and our centred unit-area ``xyz`` are the same numbers.
    """
    if which not in PAIRS:
        raise SystemExit(f"pair must be one of {PAIRS}; found {which!r}.")
    pair = load_dataset("faust_r" if which == "full" else "faust_r_p2p", data_root, split="test")[0]
    x, y = normalized_mesh(pair.x, "unit_area"), normalized_mesh(pair.y, "unit_area")
    return ShapePair(x, y, pair.map_yx, pair.overlap_x, pair.overlap_y, protocol=pair.protocol)


def weight_mapping(ref_state: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Our state dict from the reference's (`EchoMatchHead.release_state`), and our key -> reference key."""
    release = EchoMatchHead.release_state({"networks": {"echo_match_net": ref_state}}, source="reference EchoMatch")
    by_id = {id(v): k for k, v in ref_state.items()}
    names = {k: by_id[id(v)] for k, v in release.state.items()}
    unused = sorted(set(ref_state) - set(names.values()))
    if unused:
        raise SystemExit(f"reference tensors without a counterpart in our head: {unused}")
    return release.state, names


def _double(ops):
    """The operators with every floating tensor in float64."""
    return dataclasses.replace(
        ops,
        **{
            f.name: getattr(ops, f.name).double()
            for f in dataclasses.fields(ops)
            if isinstance(getattr(ops, f.name), torch.Tensor) and getattr(ops, f.name).is_floating_point()
        },
    )


def _ground_truth(pair: ShapePair) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``corr_x``, ``corr_y`` (the reference's correspondence lists) and the overlap masks of x and y."""
    map_yx = torch.as_tensor(ground_truth_map(pair))
    overlap_x, overlap_y = (torch.as_tensor(m) for m in ground_truth_overlaps(pair))
    corr_y = torch.nonzero(map_yx >= 0).squeeze(1)
    return map_yx[corr_y], corr_y, overlap_x, overlap_y


# ----------------------------------------------------------------------------- the comparison


def echomatch_stages(
    repo: Path,
    data_root: Path,
    pair: str = "full",
    seed: int = 0,
    operators: bool = True,
    timing: bool = True,
    float64: bool = False,
    keep: dict | None = None,
) -> tuple[list[Stage], dict[str, float]]:
    """Stage table of EchoMatch (list of `Stage`) and timings (dict) on one pair.

    Parameters
    ----------
    repo : Path
        Clone of ``xieyizheng/DeepShapeMatchingKit``.
    data_root : Path
        Folder holding ``FAUST_r``.
    pair : {"full", "partial"}
        FAUST_r ``tr_reg_080 -> tr_reg_081``, or the first ``faust_r_p2p`` test pair.
    seed : int
        Seeds the reference's random initialisation and the dropout masks.
    operators : bool
        Also compare our operators with the reference's ``compute_operators``.
    timing : bool
        Time inference and one training step of both (median of 3 after a warm-up).
    float64 : bool
        Both implementations in double precision (weights, operators, inputs).
    keep : dict, optional
        Filled with the objects behind the numbers: ``model`` (reference), ``head``,
        ``names`` (our parameter -> reference parameter), ``ref_grads`` / ``our_grads``
        (before clipping, by ``id`` of the parameter), ``data``, ``pair``, ``initial`` (our
        state dict before the training step).

    Returns
    -------
    rows : list of Stage
        Counting rows (neighbours, point map) give a count as ``max_abs`` and the total as ``scale``.
    timings : dict of str to float
        Seconds: ``inference_reference_s``, ``inference_geofeat_s``, ``train_step_reference_s``,
        ``train_step_geofeat_s`` (empty without ``timing``).
    """
    previous = torch.get_default_dtype()
    if float64:
        torch.set_default_dtype(torch.float64)
    try:
        with reference_import(repo) as load, _wandb_stub():
            return _run(load, Path(repo), Path(data_root), pair, seed, operators, timing, float64, keep)
    finally:
        torch.set_default_dtype(previous)


def _run(load, repo, data_root, which, seed, operators, timing, float64, keep):
    model_module = load("models.echo_match_model")
    diffusion_module = load("networks.diffusion_a_network")
    opt = reference_options(repo)
    pair = parity_pair(data_root, which)
    rows: list[Stage] = []

    # -- settings: our reference preset against the reference's yaml
    head = make_head("echomatch", preset="reference", progress=False, seed=seed, epochs=1)
    c, preset = head.config, head.PRESETS["reference"]
    net_cfg, loss_opt = opt["networks"]["echo_match_net"]["cfg"], opt["train"]["losses"]["echo_match_loss"]
    pairs = {
        "feature_channels": net_cfg["feature_extractor"]["out_channels"],
        "n_neighbours": net_cfg["overlap"]["neighbor_size"],
        "overlap_width": net_cfg["overlap"]["hidden_channels"],
        "overlap_blocks": net_cfg["overlap"]["blocks"],
        "n_fmap": net_cfg["fmap"]["n_fmap"],
        "fmap_lambda": net_cfg["fmap"]["lambda_"],
        "fmap_gamma": net_cfg["fmap"]["resolvant_gamma"],
        "gt_fmap_lambda": opt.get("lambda", 0),
        "w_fmap": loss_opt.get("w_fmap", 1),
        "w_overlap": loss_opt.get("w_acc", 1),
        "w_nce_self": loss_opt.get("w_nce_self", 1),
        "w_nce_cross": loss_opt.get("w_nce_cross", 0.1),
        "lr": opt["train"]["optims"]["echo_match_net"]["lr"],
        "epochs": opt["train"]["total_epochs"],
    }
    wrong = {k: (preset[k], v) for k, v in pairs.items() if float(preset[k]) != float(v)}
    rows.append(
        _count("settings: preset vs reference yaml", len(wrong), len(pairs), f"mismatches {wrong}" if wrong else "all equal")
    )

    # -- the reference model (network, loss, Adam from its own yaml), fixed seed
    torch.manual_seed(seed)
    model = model_module.Echo_Match_Model(copy.deepcopy(opt))
    net = model.networks["echo_match_net"]
    loss_module = model.losses["echo_match_loss"]
    if float64:  # the reference casts the overlap masks with .float(); give them the predictions' dtype
        loss_module.binary_loss.register_forward_pre_hook(lambda _m, args: (args[0], args[1].to(args[0].dtype)))

    # -- inputs: ours, handed to the reference unchanged
    if float64:  # the head computes in the dtype of its weights; keep its inputs in double too
        for mesh in (pair.x, pair.y):
            feats, ops = head.shape_inputs(mesh)
            head._inputs[mesh.hash] = (feats.double(), _double(ops))
    (in_x, ops_x), (in_y, ops_y) = head.shape_inputs(pair.x), head.shape_inputs(pair.y)
    if operators:
        geometry = load("utils.geometry_util")
        rows += operator_rows(geometry, pair.x, ops_x, "x") + operator_rows(geometry, pair.y, ops_y, "y")
    corr_x, corr_y, overlap_x, overlap_y = _ground_truth(pair)
    raw_x = torch.as_tensor(pair.x.verts, dtype=torch.float32).to(in_x.dtype)
    raw_y = torch.as_tensor(pair.y.verts, dtype=torch.float32).to(in_y.dtype)
    rows.append(compare("input xyz x", in_x, raw_x, "ours: centred, unit area; reference: coordinates as stored"))
    rows.append(compare("input xyz y", in_y, raw_y))
    data = {
        "first": reference_data(pair.x, raw_x, ops_x, c.n_fmap, corr_x, overlap_x),
        "second": reference_data(pair.y, raw_y, ops_y, c.n_fmap, corr_y, overlap_y),
    }
    for label, mesh, raw, side in (("x", pair.x, raw_x, "first"), ("y", pair.y, raw_y, "second")):
        mine = head.neighbours(mesh)
        theirs = torch.topk(torch.cdist(raw.float(), raw.float()), mine.shape[1], largest=False, sorted=True)[1]
        n_rows = int((mine != theirs).any(dim=1).sum())
        n_sets = sum(set(a.tolist()) != set(b.tolist()) for a, b in zip(mine, theirs, strict=True))
        note = f"rows the reference's float32 top-k orders otherwise ({n_sets} with other vertices); both get ours below"
        rows.append(_count(f"neighbours {label}", n_rows, mine.shape[0], note))
        data[side]["dist"] = rank_distances(mine, raw.dtype)[None]

    # -- inference, eval mode (the reference first: its forward floors the diffusion times)
    rec_ref, rec_ours = Recorder(), Recorder()
    rec_ref.output(net.feature_extractor, "feat")
    model.eval()
    # its test-time augmentation is the identity; its rotation matrix is float32, so skipped in float64
    with torch.no_grad(), no_augmentation(diffusion_module) if float64 else contextlib.nullcontext():
        ref_out = model.validate_single(copy.copy(data), _Timer())
    state, names = weight_mapping(net.state_dict(keep_vars=True))
    head.load_state({k: v.detach().clone() for k, v in state.items()}, in_x.shape[1], "reference EchoMatch")
    ours = head.model
    rec_ours.output(ours.features, "feat")
    match = head.match(pair)
    rec_ref.close()
    rec_ours.close()
    for i, label in enumerate(("x", "y")):
        rows.append(compare(f"eval features {label}", rec_ours.values["feat"][i], rec_ref.values["feat"][i][0]))
    rows.append(compare("eval overlap probability x", match.overlap_prob_x, ref_out["overlap_score12"]))
    rows.append(compare("eval overlap probability y", match.overlap_prob_y, ref_out["overlap_score21"]))
    feats = [v[0] for v in rec_ref.values["feat"][:2]]
    rows.append(_pointmap_row(match.map_yx, ref_out["p2p"].reshape(-1).numpy(), *feats))

    # -- one training step, train mode, same dropout masks
    rec_ref, rec_ours = Recorder(), Recorder()
    rec_ref.output(net.feature_extractor, "feat")
    rec_ref.output(net.permutation_network, "soft")
    rec_ref.inputs(net.overlap_diffusion_net, "overlap_in")
    rec_ref.output(net.overlap_diffusion_net, "overlap_out")
    rec_ref.output(net.fmreg_net, "fmap")
    rec_ref.inputs(loss_module, "loss_in")
    rec_ref.output(loss_module, "loss_out")
    rec_ref.output(loss_module.nce_softmax_loss, "nce_cross")
    rec_ours.output(ours.features, "feat")
    rec_ours.output(ours, "out")
    rec_ours.inputs(ours.overlap, "overlap_in")
    rec_ours.spy(echomatch_module, "regularized_fmap", "fmap")
    rec_ours.spy(echomatch_module, "regularized_gt_fmap", "gt_fmap")
    rec_ours.spy(head, "loss_terms", "terms")
    ref_grads: list = []
    our_grads: list = []
    before = {k: v.detach().clone() for k, v in ours.state_dict().items()}
    try:
        model.train()
        with no_augmentation(diffusion_module), grad_clip_spy(ref_grads):
            torch.manual_seed(seed + 1)
            model.feed_data(copy.copy(data))
            model.optimize_parameters()
        with grad_clip_spy(our_grads):
            torch.manual_seed(seed + 1)
            losses = head.fit([pair])  # our own training loop: one epoch of one pair = one Adam step
    finally:
        rec_ref.close()
        rec_ours.close()
    if len(losses) != 1:
        raise SystemExit(f"our training loop made {len(losses)} steps instead of 1")
    r, o = rec_ref.values, rec_ours.values
    for i, label in enumerate(("x", "y")):
        rows.append(compare(f"train features {label} (dropout on)", o["feat"][i], r["feat"][i][0]))
    out = o["out"][0]
    rows.append(compare("soft map P_xy", out.p_xy, r["soft"][0][0]))
    rows.append(compare("soft map P_yx", out.p_yx, r["soft"][1][0]))
    for i, label in enumerate(("x", "y")):
        rows.append(
            compare(
                f"reflection features {label}",
                o["overlap_in"][i][0][0],
                r["overlap_in"][i][1]["x_in"][0],
                "overlap-network input: P_xy P_yx at the neighbours / max",
            )
        )
    logits = (out.overlap_logits_x, out.overlap_logits_y)
    for i, label in enumerate(("x", "y")):
        rows.append(compare(f"overlap probability {label}", torch.sigmoid(logits[i]), r["overlap_out"][i].reshape(-1)))
    c_gt_ref = r["loss_in"][0][0][0]  # the model passes (C_gt, Cxy, ...) positionally
    rows.append(compare("functional map C_xy (y pruned)", o["fmap"][0], r["fmap"][0][0]))
    rows.append(compare("ground-truth functional map", o["gt_fmap"][0], c_gt_ref[0], "ours solved in float64"))
    terms = o["terms"][0]
    fmap_ref, acc_ref, nce_ref = r["loss_out"][0]
    cross_ref = r["nce_cross"][0] * c.w_nce_cross
    rows.append(compare("loss fmap", terms["fmap"], fmap_ref))
    rows.append(compare("loss overlap (BCE x + BCE y)", terms["overlap"], acc_ref))
    rows.append(compare("loss cross-NCE (weighted)", terms["nce_cross"], cross_ref))
    rows.append(compare("loss self-NCE (weighted)", terms["nce_self"], nce_ref - cross_ref))
    rows.append(compare("loss total", losses[0], model.loss_metrics["l_total"], "ours: from our training loop"))
    ours_params, ref_params = dict(ours.named_parameters()), dict(net.named_parameters())
    for label, clipped in (("gradients before clipping", False), ("gradients after clipping to norm 1", True)):
        worst, worst_key, scale = 0.0, "", 0.0
        for key, p in ours_params.items():
            rp = ref_params[names[key]]
            g_ours, g_ref = (p.grad, rp.grad) if clipped else (our_grads[0][id(p)], ref_grads[0][id(rp)])
            diff = float((g_ours.double() - g_ref.double()).abs().max())
            scale = max(scale, float(g_ref.abs().max()))
            if diff >= worst:
                worst, worst_key = diff, key
        rows.append(Stage(label, worst, scale, f"all parameters; worst {worst_key}"))
    rows.append(_step_row(ours_params, ref_params, names, before, ref_grads[0], c.lr))
    if not float64:
        rows += _yardstick_rows(
            model_module,
            opt,
            data,
            before,
            names,
            ref_params,
            ref_grads[0],
            our_grads[0],
            ours_params,
            diffusion_module,
            seed + 1,
            float(model.loss_metrics["l_total"]),
            losses[0],
        )

    if keep is not None:
        keep.update(
            model=model,
            head=head,
            names=names,
            ref_grads=ref_grads[0],
            our_grads=our_grads[0],
            data=data,
            pair=pair,
            initial=before,
        )
    times = _timings(model, head, data, pair, diffusion_module) if timing else {}
    return rows, times


def _step_row(ours_params, ref_params, names, before, ref_grads, lr: float) -> Stage:
    """Weights after one Adam step; entries off by more than a thousandth of a step, and their gradients."""
    worst, worst_key, moved, n_far, n_all, g_far, g_max = 0.0, "", 0.0, 0, 0, 0.0, 0.0
    for key, p in ours_params.items():
        rp = ref_params[names[key]]
        delta = (p.detach().double() - rp.detach().double()).abs()
        moved = max(moved, float((p.detach() - before[key]).abs().max()))
        far = delta > 1e-3 * lr
        n_far, n_all = n_far + int(far.sum()), n_all + delta.numel()
        g_max = max(g_max, float(ref_grads[id(rp)].abs().max()))
        if far.any():
            g_far = max(g_far, float(ref_grads[id(rp)][far].abs().max()))
        if float(delta.max()) >= worst:
            worst, worst_key = float(delta.max()), key
    note = (
        f"worst {worst_key}; {n_far} of {n_all} entries differ by more than 1e-3 of a step (lr {lr:g}); "
        f"their |reference gradient| <= {g_far:.1e} of max {g_max:.1e} (Adam's first step is lr * g / (|g| + eps))"
    )
    return Stage("weights after one Adam step", worst, moved, note)


def _as_dtype(value, dtype: torch.dtype):
    if isinstance(value, dict):
        return {k: _as_dtype(v, dtype) for k, v in value.items()}
    if isinstance(value, list):
        return [_as_dtype(v, dtype) for v in value]
    if isinstance(value, torch.Tensor) and value.is_floating_point():
        return value.to(dtype)
    return value


def _yardstick_rows(
    model_module,
    opt,
    data,
    initial,
    names,
    ref_params,
    ref_grads,
    our_grads,
    ours_params,
    diffusion_module,
    dropout_seed: int,
    ref_loss: float,
    our_loss: float,
) -> list[Stage]:
    """How far float32 is from exact: the reference's loss and gradients in float64 from the same weights, data and masks.

    The gradients of the functional-map loss pass through the solve of the regularised
    normal equations ``A A^T + lambda diag(W_i)``, which is ill-conditioned for random
    features; so float32 gradients of either implementation are only good to about 1e-2 of
    their largest entry. These rows put the float32 differences between the two
    implementations next to the reference's own float32 error.
    """
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)  # the reference creates some tensors without a dtype
    try:
        model64 = model_module.Echo_Match_Model(copy.deepcopy(opt))
        net64 = model64.networks["echo_match_net"]
        net64.load_state_dict({names[k]: v.double() for k, v in initial.items()})
        binary = model64.losses["echo_match_loss"].binary_loss
        binary.register_forward_pre_hook(lambda _m, args: (args[0], args[1].to(args[0].dtype)))
        model64.train()
        with no_augmentation(diffusion_module):
            torch.manual_seed(dropout_seed)
            model64.feed_data(_as_dtype(copy.copy(data), torch.float64))
        loss64 = sum(v for k, v in model64.loss_metrics.items() if k != "l_total")
        loss64.backward()
    finally:
        torch.set_default_dtype(previous)
    exact = dict(net64.named_parameters())
    scale = max(float(p.grad.abs().max()) for p in exact.values())
    rows = [
        Stage("yardstick: loss, reference float32 vs float64", abs(ref_loss - float(loss64)), float(loss64)),
        Stage("yardstick: loss, ours float32 vs reference float64", abs(our_loss - float(loss64)), float(loss64)),
    ]
    for label, grads, params in (("reference", ref_grads, ref_params), ("ours", our_grads, ours_params)):
        worst, flips = 0.0, 0
        for key, p in ours_params.items():
            g32 = grads[id(params[names[key]] if label == "reference" else p)].double()
            g64 = exact[names[key]].grad
            worst = max(worst, float((g32 - g64).abs().max()))
            flips += int((torch.sign(g32) != torch.sign(g64)).sum())
        note = f"{flips} entries with the other sign (each moves the other way in Adam's first step)"
        rows.append(Stage(f"yardstick: gradients, {label} float32 vs reference float64", worst, scale, note))
    return rows


def _timings(model, head, data: dict, pair: ShapePair, diffusion_module) -> dict[str, float]:
    """Median seconds of inference and of one training step, reference and ours (operators precomputed for both)."""

    def reference_inference():
        model.eval()
        with torch.no_grad():
            model.validate_single(copy.copy(data), _Timer())

    def reference_step():
        model.train()
        with no_augmentation(diffusion_module):
            model.feed_data(copy.copy(data))
            model.optimize_parameters()

    saved = copy.deepcopy(head.model.state_dict())
    out = {
        "inference_reference_s": seconds_per_call(reference_inference),
        "inference_geofeat_s": seconds_per_call(lambda: head.match(pair)),
        "train_step_reference_s": seconds_per_call(reference_step),
        "train_step_geofeat_s": seconds_per_call(lambda: head.fit([pair])),
    }
    head.model.load_state_dict(saved)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", type=Path, required=True, help="your clone of DeepShapeMatchingKit")
    parser.add_argument(
        "--data-root", type=Path, default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)"
    )
    parser.add_argument("--pair", choices=(*PAIRS, "both"), default="both")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-operators", action="store_true", help="skip the operator comparison")
    parser.add_argument("--no-timing", action="store_true")
    parser.add_argument("--float64", action="store_true", help="both implementations in double precision")
    args = parser.parse_args(argv)
    data_root = data_folder(args.data_root, "--data-root")
    for which in PAIRS if args.pair == "both" else (args.pair,):
        rows, times = echomatch_stages(
            args.repo, data_root, which, args.seed, not args.no_operators, not args.no_timing, args.float64
        )
        precision = "float64" if args.float64 else "float32"
        print(markdown(rows, f"EchoMatch, {which} pair, identical random weights (seed {args.seed}), {precision}"))
        for key, value in times.items():
            print(f"- {key}: {value:.3f} ({torch.get_num_threads()} torch threads)")
        print(flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
