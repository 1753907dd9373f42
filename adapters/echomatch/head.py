"""EchoMatch (Xie, Ehm, Roetzer, El Amrani, Gao, Bernard and Cremers, CVPR 2025): partial-to-partial matching by correspondence reflection.

Both shapes go through one DiffusionNet feature extractor. Cosine similarities of the
L2-normalised features, divided by a learned temperature, give two soft point maps by a
row-wise softmax: ``P_xy`` (V_x, V_y) from ``x`` to ``y`` and ``P_yx`` (V_y, V_x) back. Their
product ``R_x = P_xy P_yx`` (V_x, V_x) is the *correspondence reflection* of ``x``: row ``i``
says where vertex ``i`` lands after a round trip through ``y``. A vertex that has a
counterpart comes back to itself or next to it; one outside the overlap echoes somewhere
else or nowhere. For each vertex the reflection is read at its nearest neighbours in space
(itself first), divided by the largest value over the shape, and a small DiffusionNet turns
these values into an overlap probability (the same network for ``y`` with ``R_y = P_yx P_xy``).

Training is supervised (``training_loss``):

- functional-map loss: ``||C - C_gt||_F^2`` between the regularised functional map of the
  features (`geofeat.adapters.blocks.fmap_layers.regularized_fmap`, first ``n_fmap`` eigenpairs;
  the features of ``y`` outside its ground-truth overlap are zeroed while training) and a
  ground-truth map fitted to the known correspondences with a strong Laplacian-mask
  regulariser (`regularized_gt_fmap`);
- overlap loss: class-balanced binary cross-entropy of both overlap predictions;
- cross-NCE: for every ground-truth pair, InfoNCE over all vertices of the other shape, in
  both directions; self-NCE: every vertex against all vertices of its own shape (spreads the
  features). Both on L2-normalised features with a fixed temperature.

Prediction (``predict``): every vertex of ``y`` goes to the vertex of ``x`` with the most
similar normalised feature (nearest neighbour), and the overlap probabilities are
thresholded.

>>> head = make_head("echomatch", preset="reference", epochs=5)             # doctest: +SKIP
>>> head.fit(train_pairs); match = head.match(pair)                        # doctest: +SKIP
>>> match.map_yx, match.overlap_y, match.overlap_x                         # doctest: +SKIP
>>> head = load_head("echomatch", checkpoint="echo_match_cp2p24_xyz.pth")  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.adapters.blocks.fmap_layers import regularized_fmap
from geofeat.adapters.blocks.operators import SurfaceOperators
from geofeat.adapters.echomatch.config import EchoMatchConfig
from geofeat.adapters.echomatch.losses import balanced_bce_with_logits, cross_nce_loss, regularized_gt_fmap, self_nce_loss
from geofeat.adapters.echomatch.networks import EchoMatchNet, EchoMatchOutput
from geofeat.adapters.echomatch.reflection import spatial_neighbours
from geofeat.adapters.inputs import ground_truth_map, ground_truth_overlaps
from geofeat.adapters.learned import LearnedHead
from geofeat.adapters.release import ReleaseState, diffusionnet_state
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError
from geofeat.mesh import Mesh
from geofeat.storage.lru import LRUCache

__all__ = ["EchoMatchHead"]


class EchoMatchHead(LearnedHead):
    """EchoMatch: learned features, overlap prediction by correspondence reflection, nearest-neighbour map."""

    name = "echomatch"
    config_class = EchoMatchConfig
    #: ``"reference"``: the conventions of the authors' code (DeepShapeMatchingKit,
    #: ``options/echo_match/train/echo_match_*_xyz.yaml``): vertex coordinates in, the
    #: DiffusionNet reference operators on the cotangent Laplacian, 128 eigenpairs for the
    #: networks and 50 for the functional maps, gradient norm clipped at 1.
    PRESETS = {
        "reference": {
            "descriptor": "xyz",
            "laplacian": "cotan",
            "operators": "ulrssm",
            "n_eig": 128,
            "n_fmap": 50,
            "feature_channels": 128,
            "width": 128,
            "n_blocks": 4,
            "dropout": 0.5,
            "temperature_init": 0.1,
            "learn_log_temperature": False,
            "n_neighbours": 64,
            "overlap_width": 16,
            "overlap_blocks": 3,
            "fmap_lambda": 100.0,
            "fmap_gamma": 0.5,
            "gt_fmap_lambda": 1e6,
            "w_fmap": 1.0,
            "w_overlap": 1.0,
            "w_nce_self": 0.1,
            "w_nce_cross": 0.1,
            "nce_temperature": 0.07,
            "prune_strategy": "y",
            "overlap_threshold": 0.5,
            "restrict_to_overlap": False,
            "epochs": 900,
            "lr": 1e-3,
            "grad_clip": 1.0,
        }
    }

    def __init__(self, config: EchoMatchConfig | None = None, **settings):
        super().__init__(config, **settings)
        self._neighbours: LRUCache[str, torch.Tensor] = LRUCache(64)

    @classmethod
    def release_state(cls, raw: dict, source: str = "checkpoint") -> ReleaseState:
        """Translate a checkpoint of the authors' EchoMatch model for this head.

        The layout is DeepShapeMatchingKit's ``{"networks": {"echo_match_net": state}}`` (or
        the bare ``state``): ``feature_extractor.*`` and ``overlap_diffusion_net.*`` are
        DiffusionNets with DPFM's key spelling (`release.diffusionnet_state` with
        ``style="dpfm"``), ``permutation_network.tau`` the learned temperature. A
        ``module.`` prefix (DataParallel) is dropped, as the reference does when it resumes.
        The sizes come from the tensors; only ``xyz`` inputs (3 channels) are supported.

        Returns
        -------
        ReleaseState
            Settings (``feature_channels``, ``width``, ``n_blocks``, ``n_neighbours``,
            ``overlap_width``, ``overlap_blocks``, ``descriptor``), our state dict (the same
            tensor objects) and the input width.

        Raises
        ------
        HeadError
            Another layout, a missing, unexpected or wrongly shaped key (named), or sizes
            our `EchoMatchNet` does not have.
        """
        networks = raw.get("networks", raw)
        state = networks.get("echo_match_net", networks) if isinstance(networks, dict) else None
        if not isinstance(state, dict) or "permutation_network.tau" not in {k.replace("module.", "") for k in state}:
            raise HeadError(
                f"{source}: expected the EchoMatch layout {{'networks': {{'echo_match_net': state_dict}}}} with "
                "'feature_extractor.*', 'permutation_network.tau' and 'overlap_diffusion_net.*'."
            )
        state = {k.replace("module.", ""): v for k, v in state.items()}
        ours: dict[str, torch.Tensor] = {}
        sizes = {}
        for ref_prefix, our_prefix in (("feature_extractor.", "features."), ("overlap_diffusion_net.", "overlap.")):
            sizes[our_prefix], part = diffusionnet_state(state, "dpfm", prefix=ref_prefix, what=source)
            ours.update({our_prefix + k: v for k, v in part.items()})
        ours["temperature"] = state["permutation_network.tau"]
        unexpected = sorted(
            k for k in state if not k.startswith(("feature_extractor.", "overlap_diffusion_net.", "permutation_network.tau"))
        )
        if unexpected:
            raise HeadError(f"{source}: unexpected key(s) {unexpected} in the EchoMatch network.")
        feat, over = sizes["features."], sizes["overlap."]
        for name, s in (("feature", feat), ("overlap", over)):
            if s["mlp_hidden"] != [s["width"]] * 2 or not s["with_gradient_rotations"]:
                raise HeadError(
                    f"{source}: the {name} DiffusionNet's block MLPs {s['mlp_hidden']} / gradient rotations differ from EchoMatch's."
                )
        if over["out_channels"] != 1:
            raise HeadError(f"{source}: the overlap DiffusionNet has {over['out_channels']} outputs instead of 1.")
        if feat["in_channels"] != 3:
            raise HeadError(
                f"{source}: the feature DiffusionNet takes {feat['in_channels']} input channels; only xyz checkpoints "
                "(3 channels) are supported (the DINO ones need the reference's own DINO features)."
            )
        settings = {
            "descriptor": "xyz",
            "descriptor_params": {},
            "feature_channels": feat["out_channels"],
            "width": feat["width"],
            "n_blocks": feat["n_blocks"],
            "n_neighbours": over["in_channels"],
            "overlap_width": over["width"],
            "overlap_blocks": over["n_blocks"],
            "learn_log_temperature": False,  # the checkpoint holds the raw temperature
        }
        return ReleaseState(settings, ours, feat["in_channels"])

    def build_model(self, in_channels: int) -> EchoMatchNet:
        """`EchoMatchNet` for ``in_channels`` input features, sized by the config."""
        return EchoMatchNet(in_channels, self.config)

    def neighbours(self, mesh: Mesh) -> torch.Tensor:
        """`spatial_neighbours` of ``mesh`` on the head's device, (V, min(n_neighbours, V)) int64 (kept for 64 meshes)."""
        return self._neighbours.get_or_compute(
            mesh.hash, lambda: torch.as_tensor(spatial_neighbours(mesh.verts, self.config.n_neighbours), device=self.device)
        )

    def network_outputs(self, pair: ShapePair) -> tuple[EchoMatchOutput, SurfaceOperators, SurfaceOperators]:
        """Run the network on a pair; also returns the operators of ``x`` and ``y``."""
        model = self._ensure_model(pair.x)
        in_x, ops_x = self.shape_inputs(pair.x)
        in_y, ops_y = self.shape_inputs(pair.y)
        for mesh, feats in ((pair.x, in_x), (pair.y, in_y)):
            if feats.shape[1] != self.in_channels:
                raise HeadError(
                    f"head {self.name!r} was built for {self.in_channels} input channels, but {mesh.name!r} has "
                    f"{feats.shape[1]} with descriptor {self.config.descriptor!r}."
                )
        out = model(in_x, ops_x, self.neighbours(pair.x), in_y, ops_y, self.neighbours(pair.y))
        return out, ops_x, ops_y

    def loss_terms(self, pair: ShapePair) -> dict[str, torch.Tensor]:
        """The weighted loss terms of one pair: ``"fmap"``, ``"overlap"``, ``"nce_cross"``, ``"nce_self"``.

        Raises
        ------
        HeadError
            A malformed ground truth, or a pair without any correspondence.
        """
        c = self.config
        map_np = ground_truth_map(pair)
        overlap_x_np, overlap_y_np = ground_truth_overlaps(pair)
        out, ops_x, ops_y = self.network_outputs(pair)
        device = out.feat_x.device
        # copies: a pair's arrays may be read-only, which torch refuses to share
        map_yx = torch.tensor(map_np, device=device)
        overlap_x = torch.tensor(overlap_x_np, device=device)
        overlap_y = torch.tensor(overlap_y_np, device=device)

        k = c.n_fmap
        evecs_x, evecs_y = ops_x.evecs[:, :k], ops_y.evecs[:, :k]
        evals_x, evals_y = ops_x.evals[:k], ops_y.evals[:k]
        use_x, use_y = out.feat_x, out.feat_y
        if c.prune_strategy in ("y", "both"):
            use_y = use_y * overlap_y[:, None].to(use_y.dtype)
        if c.prune_strategy == "both":
            use_x = use_x * overlap_x[:, None].to(use_x.dtype)
        c_pred = regularized_fmap(
            use_x, use_y, evecs_x, evecs_y, ops_x.mass, ops_y.mass, evals_x, evals_y, lambda_=c.fmap_lambda, gamma=c.fmap_gamma
        )
        c_gt = regularized_gt_fmap(map_yx, evecs_x, evecs_y, evals_x, evals_y, c.gt_fmap_lambda, c.fmap_gamma, ops_y.mass)

        corr_y = torch.nonzero(map_yx >= 0).squeeze(1)
        corr_x = map_yx[corr_y]
        bce_x = balanced_bce_with_logits(out.overlap_logits_x, overlap_x)
        bce = bce_x + balanced_bce_with_logits(out.overlap_logits_y, overlap_y)
        nce_self = self_nce_loss(out.feat_x, c.nce_temperature) + self_nce_loss(out.feat_y, c.nce_temperature)
        return {
            "fmap": c.w_fmap * (c_pred - c_gt).square().sum(),
            "overlap": c.w_overlap * bce,
            "nce_cross": c.w_nce_cross * cross_nce_loss(out.feat_x, out.feat_y, corr_x, corr_y, c.nce_temperature),
            "nce_self": c.w_nce_self * nce_self,
        }

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """Sum of `loss_terms`: functional map + overlap BCE + cross-NCE + self-NCE."""
        return sum(self.loss_terms(pair).values())

    def overlap_probabilities(self, pair: ShapePair) -> tuple[np.ndarray, np.ndarray]:
        """Predicted overlap probabilities ``(x (V_x,), y (V_y,))`` float32 (network in eval mode, no gradients)."""
        self._ensure_model(pair.x).eval()
        with torch.no_grad():
            out, _, _ = self.network_outputs(pair)
        return (
            torch.sigmoid(out.overlap_logits_x).cpu().numpy().astype(np.float32),
            torch.sigmoid(out.overlap_logits_y).cpu().numpy().astype(np.float32),
        )

    def predict(self, pair: ShapePair) -> Match:
        """Nearest neighbour of the normalised features and overlaps above ``overlap_threshold``.

        Returns
        -------
        Match
            ``map_yx`` (V_y,) int64, ``overlap_y`` (V_y,) bool, ``overlap_x`` (V_x,) bool.
        """
        out, _, _ = self.network_outputs(pair)
        threshold = self.config.overlap_threshold
        prob_x, prob_y = torch.sigmoid(out.overlap_logits_x), torch.sigmoid(out.overlap_logits_y)
        overlap_x, overlap_y = prob_x > threshold, prob_y > threshold
        fx, fy = F.normalize(out.feat_x, dim=-1), F.normalize(out.feat_y, dim=-1)
        candidates = torch.arange(fx.shape[0], device=fx.device)
        if self.config.restrict_to_overlap and bool(overlap_x.any()):
            candidates = torch.nonzero(overlap_x).squeeze(1)
        map_yx = candidates[_nearest(fx[candidates], fy)]
        return Match(
            map_yx.cpu().numpy().astype(np.int64),
            overlap_y.cpu().numpy(),
            overlap_x.cpu().numpy(),
            prob_y.cpu().numpy().astype(np.float32),
            prob_x.cpu().numpy().astype(np.float32),
        )


def _nearest(fx: torch.Tensor, fy: torch.Tensor, block: int = 4096) -> torch.Tensor:
    """For every row of ``fy`` (unit vectors) the row of ``fx`` with the largest dot product (= nearest)."""
    return torch.cat([(fy[start : start + block] @ fx.T).argmax(dim=1) for start in range(0, fy.shape[0], block)])
