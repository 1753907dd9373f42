"""ULRSSM (Cao, Roetzer and Bernard 2023, "Unsupervised Learning of Robust Spectral Shape Matching").

A DiffusionNet turns the input features of both shapes into per-vertex features. Two
couplings of the shapes are derived from them and trained to agree, without ground truth:

* functional maps ``C_xy`` (k_y, k_x) and ``C_yx`` (k_x, k_y), solved from the features by
  the resolvent-regularised least squares of `fmap_layers.regularized_fmap`, pushed towards
  bijectivity and orthogonality;
* soft point maps ``P_yx`` and ``P_xy``, row-wise softmaxes of the cosine similarities of
  the features divided by a temperature, whose functional maps
  ``Phi_y^T M_y P_yx Phi_x`` must equal ``C_xy`` (and ``C_yx``): the coupling loss.

For partial pairs (protocols ``"p2f"`` and ``"p2p"``, the reference's ``partial: true``)
bijectivity and orthogonality compare with a truncated identity whose rank is estimated
from the spectra, and only the ``y -> x`` coupling is used.

At test time the features are matched by nearest neighbours (cosine), the hard map is
turned into a functional map in the first ``n_fmap`` eigenfunctions and back into a point
map (``refine_fmap=True``, the reference's default, ``non-isometric: false``), after
``tta_steps`` Adam steps of the same unsupervised loss on the pair alone, whose weights are
then restored.

>>> head = ULRSSMHead(descriptor="wks", epochs=15)                          # doctest: +SKIP
>>> head.fit(train_pairs)                                                   # doctest: +SKIP
>>> head.match(pair).map_yx                                                 # doctest: +SKIP

The defaults are the sizes of the paper and of its reference configurations; on a CPU use
smaller ones (``width``, ``width_out``, ``n_eig``, ``n_fmap``, ``diffusion_eig``,
``tta_steps``).

Facts from the authors' code (github.com/dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching,
``preprocess.py``, ``datasets/shape_dataset.py``, ``networks/diffusion_network.py``,
``networks/fmap_network.py``, ``losses/fmap_loss.py``, ``models/fmnet_model.py``,
``utils/geometry_util.py``, ``options/{train,test}/faust*.yaml``), all in the ``"reference"``
preset (``make_head("ulrssm", preset="reference")``, also what ``load_head("ulrssm",
checkpoint=...)`` uses):

- data: every full shape centred at its mean vertex and scaled to unit total area, a
  partial shape in the frame of its full shape, read as float32
  (``mesh_normalization="unit_area"``, see `normalized_pair`);
- operators (``operators="ulrssm"``, ``laplacian="cotan"``): cotangent Laplacian and lumped
  mass (+1e-8 of the mean), 200 eigenpairs for the functional maps, the first 128 for
  DiffusionNet; normals = sum of normalised face normals; tangent-plane gradients fitted by
  least squares with an absolute Tikhonov term 1e-5;
- input: WKS on the 128 DiffusionNet eigenpairs, 128 energies on the log-eigenvalue range
  (first non-zero to largest, sigma = 7 x range / 128, ends pulled in by 2 sigma), each
  channel normalised to unit mass-weighted norm (``geofeat.compute(mesh, "wks", n_eig=128,
  n_descr=128, laplacian="cotan")``);
- network: DiffusionNet 128 -> 128 x 4 blocks -> 256, dropout 0.5 in the block MLPs, and
  gradient features in ULRSSM's variant (``gradient_mixing="ulrssm"``, see
  `SpatialGradientFeatures`);
- losses: bijectivity + orthogonality (weights 1, 1) of the regularised functional maps
  (lambda 100, resolvent gamma 0.5), coupling with the soft maps at temperature 0.07
  (weight 1), no Laplacian term; partial pairs: identity truncated at the rank
  ``#{lambda_partial < max lambda_full}``, one direction of coupling;
- test: hard nearest neighbours of the normalised features -> functional map in 200
  eigenfunctions -> point map by nearest neighbours of ``Phi_x C^T`` among ``Phi_y``; no
  test-time adaptation for FAUST_r / SCAPE_r, 15 steps for SHREC'16.

How each stage compares with the authors' code, and what the release checkpoints give, is
in docs/heads.md ("Stage by stage against the authors' code"). Our defaults differ from the
preset in: no mesh normalisation, the robust Laplacian and our scale-free operator
construction, 128 eigenpairs, the complex product in the gradient features, and 15
test-time adaptation steps. Not reproduced: the reference's test-time adaptation keeps one
Adam state across all test pairs (ours starts a fresh Adam per pair); training data
augmentation (only for xyz input in the reference).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.adapters.base import HeadConfig, check_integers, check_numbers
from geofeat.adapters.blocks.diffusion_net import GRADIENT_MIXINGS, DiffusionNet
from geofeat.adapters.blocks.fmap_layers import pointmap_to_fmap, regularized_fmap, soft_pointmap, soft_pointmaps
from geofeat.adapters.blocks.fmap_losses import (
    coupling_loss,
    fmap_bijectivity_loss,
    fmap_orthogonality_loss,
    laplacian_commutativity_loss,
    partial_bijectivity_loss,
    partial_orthogonality_loss,
)
from geofeat.adapters.blocks.functional_maps import nearest_neighbors
from geofeat.adapters.blocks.operators import SurfaceOperators
from geofeat.adapters.learned import LearnedHead
from geofeat.adapters.release import ReleaseState, diffusionnet_state
from geofeat.checks import canonical, check_boolean, check_number, is_boolean, is_integer
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError
from geofeat.mesh import Mesh
from geofeat.storage.lru import LRUCache

log = logging.getLogger(__name__)

__all__ = ["LOSS_TERMS", "PARTIAL_PROTOCOLS", "ULRSSMConfig", "ULRSSMHead"]

#: Pair protocols trained with the partial losses.
PARTIAL_PROTOCOLS = ("p2f", "p2p")
#: Keys of `ULRSSMHead.loss_terms` (unweighted terms, and the weighted total).
LOSS_TERMS = ("bij", "orth", "couple", "lap", "total")
#: Meshes whose DiffusionNet operators (the first ``diffusion_eig`` eigenpairs) the head keeps.
_DIFFUSION_OPS_KEPT = 64


@dataclass
class ULRSSMConfig(HeadConfig):
    """`HeadConfig` plus the ULRSSM settings; the defaults are those of the paper's code.

    Parameters
    ----------
    n_eig : int
        Eigenpairs computed per shape (default 200 = ``n_fmap``); at least ``n_fmap`` and
        ``diffusion_eig``.
    cosine_annealing : bool
        Default True (the reference anneals Adam's 1e-3 with a cosine, to 1e-4 per epoch;
        the shared loop anneals to 0 per step).
    width : int
        DiffusionNet channels inside the blocks (reference 128).
    width_out : int
        Output feature channels (reference 256).
    n_blocks : int
        DiffusionNet blocks (reference 4).
    dropout : bool or float
        Dropout in the block MLPs: True is p = 0.5, the reference's default.
    diffusion_eig : int
        Eigenpairs DiffusionNet diffuses with (reference 128).
    n_fmap : int
        Eigenfunctions of the functional maps (reference 200); at most ``n_eig``.
    temperature : float
        Softmax temperature of the soft point maps on cosine similarities (reference 0.07).
    fmap_lambda : float
        Weight of the resolvent Laplacian term of the functional-map solve (reference 100).
    resolvent_gamma : float
        Resolvent exponent (reference 0.5).
    w_bij, w_orth, w_couple, w_lap : float
        Loss weights of bijectivity, orthogonality, the point-map / functional-map coupling
        and Laplacian commutativity (reference 1, 1, 1, 0; full pairs only for ``w_lap``).
    grad_clip : float or None
        Clip the gradient norm to this before every optimiser step, in training and in
        test-time adaptation (reference 1.0); None: no clipping.
    refine_fmap : bool
        At test time convert the nearest-neighbour map of the features into a functional
        map of ``n_fmap`` eigenfunctions and back (the reference's default); False: the plain
        nearest-neighbour map (the reference's ``non-isometric`` test path).
    tta_steps : int
        Test-time adaptation: Adam steps of the unsupervised loss on each matched pair,
        whose weights are restored afterwards (reference ``refine: 15``; its FAUST and
        SCAPE test settings use none, 0 here).
    tta_lr : float
        Adam learning rate of the test-time adaptation (reference 1e-3).
    gradient_mixing : {"complex", "ulrssm"}
        How DiffusionNet's gradient features mix the two gradient components (see
        `geofeat.adapters.blocks.diffusion_net.SpatialGradientFeatures`): ``"ulrssm"`` is the
        variant of the reference code, which its released weights need.
    """

    n_eig: int = 200
    cosine_annealing: bool = True
    width: int = 128
    width_out: int = 256
    n_blocks: int = 4
    dropout: bool | float = True
    diffusion_eig: int = 128
    n_fmap: int = 200
    temperature: float = 0.07
    fmap_lambda: float = 100.0
    resolvent_gamma: float = 0.5
    w_bij: float = 1.0
    w_orth: float = 1.0
    w_couple: float = 1.0
    w_lap: float = 0.0
    grad_clip: float | None = 1.0
    refine_fmap: bool = True
    tta_steps: int = 15
    tta_lr: float = 1e-3
    gradient_mixing: str = "complex"


class ULRSSMHead(LearnedHead):
    """The ULRSSM matcher: an unsupervised DiffusionNet feature extractor with functional-map losses.

    Parameters
    ----------
    config : ULRSSMConfig, optional
        All settings; or give them as keywords (``ULRSSMHead(width=32, n_fmap=30)``).

    Raises
    ------
    HeadError
        A setting out of range (for example ``n_fmap > n_eig``).
    """

    name = "ulrssm"
    config_class = ULRSSMConfig
    #: ``"reference"``: the conventions of the authors' code for FAUST_r / SCAPE_r
    #: (``options/train/faust_scape.yaml``, ``options/test/faust.yaml``), listed in the module notes.
    PRESETS = {
        "reference": {
            "descriptor": "wks",
            "descriptor_params": {"n_eig": 128, "n_descr": 128, "laplacian": "cotan", "normalize": True},
            "mesh_normalization": "unit_area",
            "laplacian": "cotan",
            "operators": "ulrssm",
            "n_eig": 200,
            "diffusion_eig": 128,
            "n_fmap": 200,
            "width": 128,
            "width_out": 256,
            "n_blocks": 4,
            "dropout": True,
            "temperature": 0.07,
            "fmap_lambda": 100.0,
            "resolvent_gamma": 0.5,
            "w_bij": 1.0,
            "w_orth": 1.0,
            "w_couple": 1.0,
            "w_lap": 0.0,
            "refine_fmap": True,
            "tta_steps": 0,
            "gradient_mixing": "ulrssm",
        }
    }

    def __init__(self, config: ULRSSMConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        _validate(self.config)
        # mesh hash -> (its operators from shape_inputs, their first diffusion_eig eigenpairs)
        self._diffusion_ops: LRUCache[str, tuple[SurfaceOperators, SurfaceOperators]] = LRUCache(_DIFFUSION_OPS_KEPT)

    @classmethod
    def release_state(cls, raw: dict, source: str = "checkpoint") -> ReleaseState:
        """Translate the authors' checkpoint (``{"networks": {"feature_extractor": state}}``) for this head.

        The sizes (input channels, width, output channels, blocks) come from the tensors;
        128 input channels mean the reference WKS input (``n_descr`` = the input width), 3
        mean ``"xyz"`` (the SHREC'16, TOSCA and SMAL checkpoints).

        Raises
        ------
        HeadError
            No ``feature_extractor``, or a missing, unexpected or wrongly shaped key.
        """
        networks = raw.get("networks", raw)
        state = networks.get("feature_extractor") if isinstance(networks, dict) else None
        if not isinstance(state, dict):
            raise HeadError(f"{source}: expected the ULRSSM layout {{'networks': {{'feature_extractor': state_dict}}}}.")
        sizes, ours = diffusionnet_state(state, "ulrssm", what=source)
        if sizes["mlp_hidden"] != [sizes["width"]] * 2 or not sizes["with_gradient_rotations"]:
            raise HeadError(f"{source}: block MLPs {sizes['mlp_hidden']} / gradient rotations differ from ULRSSM's DiffusionNet.")
        settings: dict[str, Any] = {"width": sizes["width"], "width_out": sizes["out_channels"], "n_blocks": sizes["n_blocks"]}
        if sizes["in_channels"] == 3:  # coordinates of the prepared pair, as the reference feeds them
            settings |= {"descriptor": "xyz", "descriptor_params": {"normalize": False}}
        else:
            params = dict(cls.PRESETS["reference"]["descriptor_params"], n_descr=sizes["in_channels"])
            settings |= {"descriptor": "wks", "descriptor_params": params}
        return ReleaseState(settings, ours, sizes["in_channels"])

    # -- the LearnedHead interface

    def build_model(self, in_channels: int) -> torch.nn.Module:
        """A DiffusionNet from ``in_channels`` to ``width_out`` channels."""
        c = self.config
        return DiffusionNet(
            in_channels, c.width_out, width=c.width, n_blocks=c.n_blocks, dropout=c.dropout, gradient_mixing=c.gradient_mixing
        )

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """The unsupervised loss of one pair (partial variant for ``"p2f"`` and ``"p2p"``), a scalar."""
        return self.loss_terms(pair)["total"]

    def predict(self, pair: ShapePair) -> Match:
        """Nearest neighbours of the L2-normalised features, refined through the functional map.

        Returns
        -------
        Match
            ``map_yx`` (V_y,) int64 and ``overlap_y`` all True (ULRSSM predicts no overlap).
        """
        feat_x, ops_x = self._embed(pair.x)
        feat_y, ops_y = self._embed(pair.y)
        feat_x, feat_y = F.normalize(feat_x, p=2, dim=-1), F.normalize(feat_y, p=2, dim=-1)
        map_yx = nearest_neighbors(_numpy(feat_x), _numpy(feat_y), device=self.device)
        if self.config.refine_fmap:
            k = self._n_fmap(ops_x, ops_y)
            evecs_x, evecs_y = ops_x.evecs[:, :k], ops_y.evecs[:, :k]
            hard = torch.from_numpy(map_yx).to(evecs_x.device)
            c_xy = pointmap_to_fmap(hard, evecs_x, evecs_y, ops_y.mass)  # (k, k)
            map_yx = nearest_neighbors(_numpy(evecs_x @ c_xy.T), _numpy(evecs_y), device=self.device)
        return Match(np.asarray(map_yx, dtype=np.int64), np.ones(pair.y.n_vertices, dtype=bool))

    # -- test-time adaptation

    def match(self, pair: ShapePair) -> Match:
        """Predict ``pair``; with ``tta_steps > 0`` after adapting the weights to it, then restore them exactly."""
        if self.config.tta_steps == 0:
            return super().match(pair)
        pair = self.prepare(pair)
        model = self._ensure_model(pair.x)
        saved = {name: value.detach().clone() for name, value in model.state_dict().items()}
        try:
            self._adapt(pair, self.config.tta_steps)
            model.eval()
            with torch.no_grad():
                return self.predict(pair)
        finally:
            with torch.no_grad():
                model.load_state_dict(saved)
            model.zero_grad(set_to_none=True)

    def adapt(self, pair: ShapePair, steps: int | None = None) -> list[float]:
        """Test-time adaptation: Adam steps of the unsupervised loss on ``pair`` alone (weights NOT restored).

        The model is in evaluation mode (no dropout), as in the reference, with a fresh Adam
        (``tta_lr``, no schedule) and the gradient clipped to ``grad_clip``. `match` does
        this and restores the weights afterwards.

        Parameters
        ----------
        pair : ShapePair
            As given to `match` (it is prepared here).
        steps : int, optional
            Default ``tta_steps``.

        Returns
        -------
        list of float
            The loss before each step.
        """
        steps = self.config.tta_steps if steps is None else steps
        if not is_integer(steps) or steps < 0:
            raise HeadError(f"steps must be a non-negative integer; found {steps!r}.")
        return self._adapt(self.prepare(pair), steps)

    def _adapt(self, pair: ShapePair, steps: int) -> list[float]:
        """`adapt` on a prepared pair."""
        c = self.config
        model = self._ensure_model(pair.x)
        model.eval()
        params = [p for p in model.parameters() if p.requires_grad]
        optimizer = torch.optim.Adam(params, lr=c.tta_lr)
        losses: list[torch.Tensor] = []  # read back at the end: reading one waits for the device
        with torch.enable_grad():
            for _ in range(steps):
                loss = self.training_loss(pair)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                if c.grad_clip is not None:
                    torch.nn.utils.clip_grad_norm_(params, c.grad_clip)
                optimizer.step()
                losses.append(loss.detach())
        model.zero_grad(set_to_none=True)
        return torch.stack(losses).tolist() if losses else []

    # -- the loss

    @staticmethod
    def is_partial(pair: ShapePair) -> bool:
        """Whether ``pair`` gets the partial losses (its protocol is one of `PARTIAL_PROTOCOLS`)."""
        return pair.protocol in PARTIAL_PROTOCOLS

    def loss_terms(self, pair: ShapePair, partial: bool | None = None) -> dict[str, torch.Tensor]:
        """The unweighted loss terms of one pair and their weighted sum.

        Parameters
        ----------
        pair : ShapePair
            ``x`` the target (the full shape of a P2F pair), ``y`` the source; ground truth unused.
        partial : bool, optional
            Use the partial variants; default `is_partial` of the pair.

        Returns
        -------
        dict of str to torch.Tensor
            Scalars under `LOSS_TERMS`: ``"bij"``, ``"orth"`` (both directions for full
            pairs, ``C_xy`` only for partial ones), ``"couple"`` (``C_xy`` against ``P_yx``,
            plus ``C_yx`` against ``P_xy`` for full pairs), ``"lap"`` (zero for partial pairs
            or ``w_lap = 0``) and ``"total"`` = the weighted sum.
        """
        c = self.config
        partial = self.is_partial(pair) if partial is None else bool(partial)
        self._ensure_model(pair.x)
        feat_x, ops_x = self._embed(pair.x)
        feat_y, ops_y = self._embed(pair.y)
        k = self._n_fmap(ops_x, ops_y)
        evecs_x, evecs_y = ops_x.evecs[:, :k], ops_y.evecs[:, :k]
        # the eigenvalues are only read on the host (mask, partial rank): their CPU copies
        evals_x, evals_y = self.host_eigenvalues(pair.x)[:k], self.host_eigenvalues(pair.y)[:k]
        c_xy, c_yx = regularized_fmap(
            feat_x,
            feat_y,
            evecs_x,
            evecs_y,
            ops_x.mass,
            ops_y.mass,
            evals_x,
            evals_y,
            lambda_=c.fmap_lambda,
            gamma=c.resolvent_gamma,
            bidirectional=True,
        )
        zero = feat_x.new_zeros(())
        terms = dict.fromkeys(LOSS_TERMS, zero)
        if partial:
            terms["bij"] = partial_bijectivity_loss(c_xy, c_yx, evals_x, evals_y)
            terms["orth"] = partial_orthogonality_loss(c_xy, evals_x, evals_y)
        else:
            terms["bij"] = fmap_bijectivity_loss(c_xy, c_yx)
            terms["orth"] = fmap_orthogonality_loss(c_xy) + fmap_orthogonality_loss(c_yx)
            if c.w_lap > 0:
                terms["lap"] = laplacian_commutativity_loss(c_xy, evals_x, evals_y) + laplacian_commutativity_loss(
                    c_yx, evals_y, evals_x
                )
        if c.w_couple > 0 and partial:
            p_yx = soft_pointmap(feat_x, feat_y, temperature=c.temperature)  # (V_y, V_x)
            terms["couple"] = coupling_loss(c_xy, p_yx, evecs_x, evecs_y, ops_y.mass)
        elif c.w_couple > 0:
            p_yx, p_xy = soft_pointmaps(feat_x, feat_y, temperature=c.temperature)  # (V_y, V_x), (V_x, V_y)
            terms["couple"] = coupling_loss(c_xy, p_yx, evecs_x, evecs_y, ops_y.mass)
            terms["couple"] = terms["couple"] + coupling_loss(c_yx, p_xy, evecs_y, evecs_x, ops_x.mass)
        terms["total"] = c.w_bij * terms["bij"] + c.w_orth * terms["orth"] + c.w_couple * terms["couple"] + c.w_lap * terms["lap"]
        return terms

    # -- helpers

    def _embed(self, mesh: Mesh) -> tuple[torch.Tensor, SurfaceOperators]:
        """Network features (V, width_out) of ``mesh`` and its operators (all ``n_eig`` eigenpairs)."""
        model = self._ensure_model(mesh)
        feats, ops = self.shape_inputs(mesh)
        return model(feats, self._diffusion_operators(mesh, ops)), ops

    def _diffusion_operators(self, mesh: Mesh, ops: SurfaceOperators) -> SurfaceOperators:
        """The operators ``ops`` of ``mesh`` with their first ``diffusion_eig`` eigenpairs, for DiffusionNet.

        One record per operators, kept: what a record makes once for the backward pass
        (`SurfaceOperators.gradient_transposes`) is not made again at every step.
        """
        k = min(self.config.diffusion_eig, ops.k)
        if k == ops.k:
            return ops
        kept = self._diffusion_ops.get(mesh.hash)
        if kept is None or kept[0] is not ops or kept[1].k != k:
            sliced = dataclasses.replace(ops, evals=ops.evals[:k], evecs=ops.evecs[:, :k])
            kept = self._diffusion_ops.put(mesh.hash, (ops, sliced))
        return kept[1]

    def _n_fmap(self, ops_x: SurfaceOperators, ops_y: SurfaceOperators) -> int:
        """``n_fmap`` clipped to the eigenpairs both shapes have."""
        k = min(self.config.n_fmap, ops_x.k, ops_y.k)
        if k < self.config.n_fmap:
            log.debug("%s: using %d eigenfunctions for the functional maps instead of %d", self.name, k, self.config.n_fmap)
        return k


# ----------------------------------------------------------------------------- validation


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu").numpy()


def _validate(c: ULRSSMConfig) -> None:
    """Raise `HeadError` for a setting out of range."""
    check_integers("ulrssm", c, ("n_eig", "width", "width_out", "n_blocks", "diffusion_eig", "n_fmap"), 1)
    if c.n_fmap > c.n_eig:
        raise HeadError(f"ulrssm: n_fmap ({c.n_fmap}) must be at most n_eig ({c.n_eig}); raise n_eig or lower n_fmap.")
    if c.diffusion_eig > c.n_eig:
        raise HeadError(
            f"ulrssm: diffusion_eig ({c.diffusion_eig}) must be at most n_eig ({c.n_eig}); raise n_eig or lower diffusion_eig."
        )
    check_numbers("ulrssm", c, ("temperature", "tta_lr", "lr"), 0.0, low_open=True)
    check_numbers("ulrssm", c, ("fmap_lambda", "w_bij", "w_orth", "w_couple", "w_lap"), 0.0)
    check_numbers("ulrssm", c, ("resolvent_gamma",), 0.0, 1.0, low_open=True)
    if c.grad_clip is not None:
        check_numbers("ulrssm", c, ("grad_clip",), 0.0, low_open=True)
    check_integers("ulrssm", c, ("tta_steps",), 0)
    if not is_boolean(c.dropout):
        expected = "True, False or a probability in [0, 1)"
        check_number(c.dropout, "dropout", owner="ulrssm", low=0, high=1, high_open=True, error=HeadError, expected=expected)
    c.dropout = canonical(c.dropout)
    if c.gradient_mixing not in GRADIENT_MIXINGS:
        raise HeadError(f"ulrssm: gradient_mixing must be one of {GRADIENT_MIXINGS}; found {c.gradient_mixing!r}.")
    c.refine_fmap = check_boolean(c.refine_fmap, "refine_fmap", owner="ulrssm", error=HeadError)
