"""DPFM (Attaiki, Pai and Ovsjanikov 2021, "DPFM: Deep Partial Functional Maps"), a supervised partial matcher.

The network has four parts:

1. a feature extractor: `DiffusionNet` from the input features (any geofeat descriptor, or
   ``"xyz"`` as in the paper) to ``width`` channels on each shape;
2. a cross-attention refinement: on farthest-point samples of both shapes (a fraction
   ``sampling_ratio`` of the vertices), a linear lift to ``attention_dim`` channels, then
   ``n_attention_layers`` rounds in which the samples of ``x`` attend to those of ``y`` and
   then the samples of ``y`` to the updated ones of ``x`` (multi-head attention, a message
   MLP with instance normalisation, residual updates); after each round every vertex gets
   the inverse-squared-distance weighted mean of its 3 nearest samples (Euclidean, in
   coordinates normalised to unit area), and a linear layer maps back to ``width`` channels;
3. an overlap predictor: a small MLP on the L2-normalised refined features giving, for
   every vertex of both shapes, the probability that it has a counterpart on the other;
4. a regularised functional map (`geofeat.adapters.blocks.fmap_layers.regularized_fmap`, resolvent
   mask, ``lambda_`` and ``gamma``) in the first ``n_fmap`` eigenfunctions, from the refined
   features (or those of the extractor, ``fmap_features="extracted"``).

Training is supervised: the squared Frobenius distance to the ground-truth functional map
``Phi_y^T M_y P_yx Phi_x`` (rows of vertices of ``y`` without a counterpart are zero),
class-weighted binary cross-entropy of the overlap of both shapes, and optionally a
contrastive (InfoNCE) term on corresponding features. A match converts the functional map to
a point map (nearest neighbours of spectral embeddings, or of features with
``pointmap="features"``) and thresholds the overlap probabilities.

The authors' released models (``pvnieo/DPFM``, ``dpfm/data/saved_models``) load with
`DPFMHead.release_state` (``load_head("dpfm", checkpoint=...)``); ``DPFMHead.PRESETS``
holds the settings of their code. Where that code differs from our defaults:

- input: vertex coordinates centred on their mean and scaled to unit total area, as float32
  (FAUST_r / SCAPE_r; its SHREC'16 data are used as stored), no augmentation at test;
  training augments them (``augmentation=True``: random rotation, noise and per-axis scale);
- operators: cotan Laplacian and DiffusionNet's own operator construction, 128 eigenpairs
  (``laplacian="cotan"``, ``operators="diffusionnet"``);
- attention heads: channel ``c`` belongs to head ``c % n_heads`` (``head_layout="interleaved"``;
  ours takes contiguous blocks of channels);
- interpolation of the refined features (``interpolation="reference"``): the reference meant
  the 3 nearest samples, but it reads the ranks of the 130 nearest of a 0.9-fraction
  farthest-point sample as vertex indices, and picks three of those that are samples in the
  order of torch's unstable sort (see `reference_sample_interpolation`). The presets
  reproduce this, so that a release checkpoint computes here what it computes in the
  reference code; it only touches the refined features (the overlap, and the functional map
  where ``fmap_features="refined"``). The released SHREC'16 weights work better with the
  intended interpolation (docs/heads.md gives the numbers): pass ``interpolation="nearest"``
  to use those checkpoints as their authors trained them;
- functional map from the DiffusionNet features on FAUST_r, SCAPE_r and SHREC'16 cuts
  (``fmap_features="extracted"``, the reference's ``robust: False``), refined on holes;
- ground-truth functional map on FAUST_r: least squares on the template points
  (``fmap_ground_truth="template_lstsq"``); the overlap loss of a one-class mask weighs 0
  (``single_class_weight=0``);
- still different (training only): the reference draws NCE pairs among all vertices of ``y``
  (its ``-1`` entries then pick the last vertex of ``x``) and its partial ground truth sends
  vertices without a counterpart to the last vertex of ``x``; ours skips them. Its optimiser
  is Adam with betas (0.9, 0.99) and step decay; the shared training loop uses torch's default
  betas.

>>> head = make_head("dpfm", descriptor="xyz", epochs=100)                 # doctest: +SKIP
>>> head.fit(load_dataset("synthetic_cuts", split="train"))                # doctest: +SKIP
>>> match = head.match(pair)  # map_yx (V_y,), overlap_y (V_y,), overlap_x (V_x,)  # doctest: +SKIP
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.adapters.blocks.functional_maps import nearest_neighbors
from geofeat.adapters.dpfm.config import DPFMConfig, check_config
from geofeat.adapters.dpfm.losses import ground_truth_fmap, nce_loss, template_fmap, weighted_overlap_bce
from geofeat.adapters.dpfm.networks import DPFMNet, DPFMOutput
from geofeat.adapters.dpfm.sampling import (
    SampleInterpolation,
    reference_candidates,
    reference_sample_interpolation,
    sample_interpolation,
)
from geofeat.adapters.inputs import ground_truth_map, ground_truth_overlaps, unit_area_verts
from geofeat.adapters.learned import LearnedHead
from geofeat.adapters.release import ReleaseState, diffusionnet_state, state_problems
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError
from geofeat.mesh import Mesh
from geofeat.storage.lru import LRUCache

__all__ = ["DPFMHead", "augment_xyz"]


#: Reference augmentation (its training script): maximal rotation about x, y, z in degrees,
#: noise standard deviation and clip, per-axis scale range.
AUGMENT_ROTATION_DEGREES = (30.0, 30.0, 60.0)
AUGMENT_NOISE = (0.01, 0.05)
AUGMENT_SCALE = (0.9, 1.1)
_SAMPLE_CACHE_SIZE = 64


def augment_xyz(xyz: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """Randomly rotated, noisy and rescaled coordinates (the reference's training augmentation).

    Rotation ``R_z R_y R_x`` with angles uniform in +-`AUGMENT_ROTATION_DEGREES`, Gaussian
    noise of standard deviation ``AUGMENT_NOISE[0]`` clipped to +-``AUGMENT_NOISE[1]``, then a
    scale per axis uniform in `AUGMENT_SCALE`.

    Parameters
    ----------
    xyz : torch.Tensor, shape (V, 3)
    rng : numpy.random.Generator

    Returns
    -------
    torch.Tensor, shape (V, 3), dtype and device of ``xyz``
    """
    angles = np.radians([rng.uniform(-a, a) for a in AUGMENT_ROTATION_DEGREES])
    cx, cy, cz = np.cos(angles)
    sx, sy, sz = np.sin(angles)
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    rotation = torch.as_tensor(rot_z @ rot_y @ rot_x, dtype=xyz.dtype, device=xyz.device)
    std, clip = AUGMENT_NOISE
    noise = torch.as_tensor(np.clip(std * rng.standard_normal(tuple(xyz.shape)), -clip, clip), dtype=xyz.dtype, device=xyz.device)
    scale = torch.as_tensor(rng.uniform(*AUGMENT_SCALE, size=3), dtype=xyz.dtype, device=xyz.device)
    return (xyz @ rotation.T + noise) * scale


def _dpfm_extractor_key(ours: str) -> str:
    """The reference (original DiffusionNet) name of a key of our `DiffusionNet` state dict."""
    parts = ours.split(".")
    if parts[0] in ("first", "last"):
        return f"{parts[0]}_lin.{parts[1]}"
    block = f"block_{parts[1]}"
    if parts[2] == "diffusion":
        return f"{block}.diffusion.diffusion_time"
    if parts[2] == "gradient_features":
        return f"{block}.gradient_features.{'A_re' if parts[3] == 'a_re' else 'A_im'}.weight"
    return f"{block}.mlp.miniMLP_mlp_layer_{int(parts[3]) // 3:03d}.{parts[4]}"


# ----------------------------------------------------------------------------- head


class DPFMHead(LearnedHead):
    """DPFM as a geofeat head: supervised training on pairs with ground truth, overlap-aware matches.

    Settings are those of `DPFMConfig`; bad ones raise `geofeat.errors.HeadError`.
    """

    name = "dpfm"
    config_class = DPFMConfig
    #: Settings of the authors' code. ``"reference"``: FAUST_r / SCAPE_r (``config/faust.yaml``,
    #: ``config/scape.yaml``, shapes at unit area, template least-squares ground truth);
    #: ``"reference_shrec16_cuts"`` / ``"reference_shrec16_holes"``: its SHREC'16 configurations
    #: (its data: full shapes at unit area, each partial shape in the frame and scale of its
    #: full shape, i.e. `normalized_pair`). Inputs are the coordinates of the prepared pair.
    #: The sizes of a release checkpoint come from its tensors.
    PRESETS = {
        "reference": {
            "descriptor": "xyz",
            "descriptor_params": {"normalize": False},
            "mesh_normalization": "unit_area",
            "laplacian": "cotan",
            "operators": "diffusionnet",
            "n_eig": 128,
            "n_fmap": 50,
            "width": 128,
            "n_blocks": 4,
            "dropout": True,
            "attention_dim": 128,
            "n_heads": 4,
            "n_attention_layers": 1,
            "sampling_ratio": 0.7,
            "max_samples": None,
            "n_interpolation": 3,
            "head_layout": "interleaved",
            "interpolation": "reference",
            "lambda_": 100.0,
            "gamma": 0.5,
            "fmap_features": "extracted",
            "overlap_weighted_fmap": False,
            "w_fmap": 1.0,
            "w_overlap": 1.0,
            "w_nce": 0.0,
            "nce_temperature": 0.07,
            "nce_pairs": 4096,
            "single_class_weight": 0.0,
            "fmap_ground_truth": "template_lstsq",
            "augmentation": True,
            "pointmap": "fmap",
            "lr": 1e-3,
        },
    }
    PRESETS["reference_shrec16_cuts"] = PRESETS["reference"] | {
        "sampling_ratio": 0.4,
        "fmap_ground_truth": "projection",
    }
    PRESETS["reference_shrec16_holes"] = PRESETS["reference_shrec16_cuts"] | {
        "n_fmap": 30,
        "sampling_ratio": 0.3,
        "fmap_features": "refined",
        "w_nce": 1.0,
        "nce_pairs": 512,
    }

    def __init__(self, config: DPFMConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        check_config(self.config)
        self._samples: LRUCache[str, SampleInterpolation] = LRUCache(_SAMPLE_CACHE_SIZE)
        self._rng = np.random.default_rng(self.config.seed)

    def build_model(self, in_channels: int) -> DPFMNet:
        """`DPFMNet` for ``in_channels`` input features."""
        return DPFMNet(in_channels, self.config)

    @classmethod
    def release_state(cls, raw: Mapping[str, torch.Tensor], source: str = "checkpoint") -> ReleaseState:
        """Translate a state dict of the authors' ``DPFMNet`` (``dpfm/data/saved_models/*.pth``) for this head.

        Key mapping (``L`` a layer, ``P`` weight or bias; Conv1d kernel-1 weights (out, in, 1)
        become Linear weights (out, in)):

        ===========================================================  ==========================================
        reference                                                     ours
        ===========================================================  ==========================================
        ``feature_extractor.*``                                       ``extractor.*`` (`release.diffusionnet_state`, style "dpfm")
        ``feat_refiner.first_lin.P`` / ``last_lin.P``                  ``refiner.first.P`` / ``refiner.last.P``
        ``feat_refiner.layers.L.attn.proj.{0,1,2}.P``                  ``refiner.layers.L.attention.{query,key,value}.P``
        ``feat_refiner.layers.L.attn.merge.P``                         ``refiner.layers.L.attention.merge.P``
        ``feat_refiner.layers.L.mlp.0.P`` / ``mlp.3.P``                ``refiner.layers.L.hidden.P`` / ``out.P``
        ``feat_refiner.overlap_predictor.overlap_score_net.{0,2}.P``   ``overlap.net.{0,2}.P``
        ===========================================================  ==========================================

        The widths, number of blocks, attention width and layers are read from the tensors;
        the number of attention heads is not stored in them (the reference uses 4, the
        preset's ``n_heads``), and its head layout is ``"interleaved"``.

        Parameters
        ----------
        raw : mapping of str to torch.Tensor
            The loaded state dict.
        source : str
            Name of the checkpoint in error messages.

        Returns
        -------
        ReleaseState
            Settings (sizes, ``descriptor="xyz"``), our state dict, input channels (3).

        Raises
        ------
        HeadError
            A missing, unexpected or wrongly shaped key (the checkpoint's name for it).
        """
        if not isinstance(raw, Mapping) or not all(isinstance(v, torch.Tensor) for v in raw.values()):
            raise HeadError(f"{source}: expected a DPFM state dict (str -> tensor).")
        extractor_prefix, refiner_prefix = "feature_extractor.", "feat_refiner."
        outside = sorted(k for k in raw if not k.startswith((extractor_prefix, refiner_prefix)))
        if outside:
            raise HeadError(f"{source}: unexpected key(s) {outside} in a DPFM checkpoint.")
        sizes, extractor = diffusionnet_state(raw, "dpfm", prefix=extractor_prefix, what=source)
        width = sizes["width"]
        first = f"{refiner_prefix}first_lin.weight"
        if first not in raw:
            raise HeadError(f"{source}: missing key {first}.")
        attention_dim = int(raw[first].shape[0])
        layer_re = re.compile(re.escape(refiner_prefix) + r"layers\.(\d+)\.")
        layers = sorted({int(m.group(1)) for k in raw if (m := layer_re.match(k))})
        if layers != list(range(len(layers))):
            raise HeadError(f"{source}: refiner layers must be numbered 0..n-1; found {layers}.")
        mapping = {"first_lin": "first", "last_lin": "last"}
        mapping |= {f"overlap_predictor.overlap_score_net.{i}": f"overlap.net.{i}" for i in (0, 2)}
        for i in layers:
            ours_l, theirs_l = f"refiner.layers.{i}", f"layers.{i}"
            for j, name in enumerate(("query", "key", "value")):
                mapping[f"{theirs_l}.attn.proj.{j}"] = f"{ours_l}.attention.{name}"
            mapping[f"{theirs_l}.attn.merge"] = f"{ours_l}.attention.merge"
            mapping[f"{theirs_l}.mlp.0"] = f"{ours_l}.hidden"
            mapping[f"{theirs_l}.mlp.3"] = f"{ours_l}.out"
        mapping = {
            f"{refiner_prefix}{k}.{p}": (v if v.startswith(("refiner.", "overlap.")) else f"refiner.{v}") + f".{p}"
            for k, v in mapping.items()
            for p in ("weight", "bias")
        }
        settings = {
            "descriptor": "xyz",
            "descriptor_params": {"normalize": False},
            "width": width,
            "n_blocks": sizes["n_blocks"],
            "attention_dim": attention_dim,
            "n_attention_layers": len(layers),
        }
        expected = DPFMNet(3, DPFMConfig(**(cls.PRESETS["reference"] | settings))).state_dict()
        names = {f"extractor.{k}": extractor_prefix + _dpfm_extractor_key(k) for k in extractor}
        names |= {ours: theirs for theirs, ours in mapping.items()}
        state = {f"extractor.{k}": v for k, v in extractor.items()}
        unexpected = sorted(k for k in raw if k.startswith(refiner_prefix) and k not in mapping)
        for theirs, ours in mapping.items():
            if theirs in raw:
                tensor = raw[theirs]
                if tensor.ndim == 3 and tensor.shape[-1] == 1 and expected[ours].ndim == 2:
                    tensor = tensor[..., 0]  # Conv1d kernel 1 -> Linear
                state[ours] = tensor
        problems = ([f"unexpected {unexpected}"] if unexpected else []) + state_problems(expected, state, names, raw)
        if problems:
            raise HeadError(f"{source} does not fit DPFM: " + "; ".join(problems) + ".")
        return ReleaseState(settings, {k: v.detach().clone().float().contiguous() for k, v in state.items()}, 3)

    # -- per-shape data

    def n_samples(self, n_vertices: int) -> int:
        """Farthest-point samples used on a shape of ``n_vertices`` vertices."""
        n = max(1, int(self.config.sampling_ratio * n_vertices))
        if self.config.max_samples is not None:
            n = min(n, int(self.config.max_samples))
        return min(n, n_vertices)

    def samples(self, mesh: Mesh) -> SampleInterpolation:
        """Farthest-point samples of a mesh of a prepared pair and their interpolation, on the head's device (kept for 64 meshes).

        Computed on the coordinates as they are where the head normalises its pairs
        (``mesh_normalization``) or with ``interpolation="reference"`` (the reference samples
        the coordinates its network sees); else on the vertices centred and scaled to unit area.
        """
        return self._samples.get_or_compute(mesh.hash, lambda: self._sample_interpolation(mesh))

    def _sample_interpolation(self, mesh: Mesh) -> SampleInterpolation:
        c = self.config
        if c.mesh_normalization is not None or c.interpolation == "reference":
            points = mesh.verts
        else:
            points = unit_area_verts(mesh, required=False)
        n_samples = self.n_samples(mesh.n_vertices)
        if c.interpolation == "reference" and n_samples < mesh.n_vertices:
            entry = reference_sample_interpolation(reference_candidates(points, c.seed), n_samples)
        else:
            entry = sample_interpolation(points, n_samples, c.n_interpolation, c.seed)
        return entry.to(self.device)

    def use_samples(self, mesh: Mesh, interpolation: SampleInterpolation) -> None:
        """Pin the samples and interpolation of ``mesh`` (e.g. the reference code's own record of it)."""
        if interpolation.neighbours.shape[0] != mesh.n_vertices or interpolation.weights.shape != interpolation.neighbours.shape:
            raise HeadError(
                f"dpfm: the interpolation has {interpolation.neighbours.shape[0]} rows; mesh {mesh.name!r} has {mesh.n_vertices} vertices."
            )
        self._samples.put(mesh.hash, interpolation.to(self.device))

    def forward(self, pair: ShapePair, augment: bool = False) -> DPFMOutput:
        """Run the model on a prepared pair (`Head.prepare`; gradients as the caller sets them).

        ``augment`` applies `augment_xyz` to both inputs.
        """
        model = self._ensure_model(pair.x)
        input_x, ops_x = self.shape_inputs(pair.x)
        input_y, ops_y = self.shape_inputs(pair.y)
        if input_x.shape[1] != self.in_channels or input_y.shape[1] != self.in_channels:
            raise HeadError(
                f"dpfm: the model takes {self.in_channels} input channels; pair {pair.name} has "
                f"{input_x.shape[1]} (x) and {input_y.shape[1]} (y)."
            )
        if augment:
            input_x, input_y = augment_xyz(input_x, self._rng), augment_xyz(input_y, self._rng)
        return model(input_x, input_y, ops_x, ops_y, self.samples(pair.x), self.samples(pair.y))

    # -- the interface

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """``w_fmap * ||C - C_gt||^2 + w_overlap * (BCE_x + BCE_y) + w_nce * NCE`` for one prepared pair."""
        c = self.config
        map_yx = ground_truth_map(pair)
        overlap_x, overlap_y = ground_truth_overlaps(pair)
        out = self.forward(pair, augment=c.augmentation)
        _, ops_x = self.shape_inputs(pair.x)
        _, ops_y = self.shape_inputs(pair.y)
        k = c.n_fmap
        if c.fmap_ground_truth == "template_lstsq":
            if pair.corr_x is None or pair.corr_y is None:
                raise HeadError(
                    f"dpfm: fmap_ground_truth='template_lstsq' needs template correspondences; pair {pair.name} has none."
                )
            c_gt = template_fmap(ops_x.evecs[:, :k], ops_y.evecs[:, :k], pair.corr_x, pair.corr_y)
        else:
            c_gt = ground_truth_fmap(map_yx, ops_x.evecs[:, :k], ops_y.evecs[:, :k], ops_y.mass)
        loss = c.w_fmap * (out.fmap - c_gt).square().sum()
        device = out.fmap.device
        target_x = torch.as_tensor(overlap_x, device=device)
        target_y = torch.as_tensor(overlap_y, device=device)
        loss = loss + c.w_overlap * (
            weighted_overlap_bce(out.overlap_logits_x, target_x, c.single_class_weight)
            + weighted_overlap_bce(out.overlap_logits_y, target_y, c.single_class_weight)
        )
        if c.w_nce > 0:
            loss = loss + c.w_nce * nce_loss(out.feat_x, out.feat_y, map_yx, c.nce_pairs, c.nce_temperature, self._rng)
        return loss

    def predict(self, pair: ShapePair) -> Match:
        """Point map y -> x and thresholded overlaps of both shapes of a prepared pair."""
        c = self.config
        out = self.forward(pair)
        if c.pointmap == "fmap":
            _, ops_x = self.shape_inputs(pair.x)
            _, ops_y = self.shape_inputs(pair.y)
            k = c.n_fmap
            emb_x = (ops_x.evecs[:, :k] @ out.fmap.T).cpu().numpy()
            emb_y = ops_y.evecs[:, :k].cpu().numpy()
            map_yx = nearest_neighbors(emb_x, emb_y, device=self.device)
        else:
            fx = F.normalize(out.feat_x, p=2, dim=-1).cpu().numpy()
            fy = F.normalize(out.feat_y, p=2, dim=-1).cpu().numpy()
            map_yx = nearest_neighbors(fx, fy, device=self.device)
        prob_x = torch.sigmoid(out.overlap_logits_x).cpu().numpy().astype(np.float32)
        prob_y = torch.sigmoid(out.overlap_logits_y).cpu().numpy().astype(np.float32)
        threshold = c.overlap_threshold
        return Match(np.asarray(map_yx, dtype=np.int64), prob_y > threshold, prob_x > threshold, prob_y, prob_x)
