"""DPFM's settings: `DPFMConfig`, the choices of its string settings and their checks."""

from __future__ import annotations

from dataclasses import dataclass

from geofeat.adapters.base import HeadConfig, check_integers, check_numbers
from geofeat.adapters.dpfm.sampling import REFERENCE_CANDIDATE_RATIO
from geofeat.checks import check_boolean
from geofeat.errors import HeadError

__all__ = ["FMAP_FEATURES", "FMAP_GROUND_TRUTHS", "HEAD_LAYOUTS", "INTERPOLATIONS", "POINTMAPS", "DPFMConfig", "check_config"]

#: Which features the functional map is computed from.
FMAP_FEATURES = ("refined", "extracted")
#: How a match turns the prediction into a point map.
POINTMAPS = ("fmap", "features")
#: Which channels form an attention head: contiguous blocks (ours) or every ``n_heads``-th channel (the reference).
HEAD_LAYOUTS = ("contiguous", "interleaved")
#: How refined features reach every vertex: its nearest samples (ours) or the reference code's choice.
INTERPOLATIONS = ("nearest", "reference")
#: Ground-truth functional map of the loss: projection of the point map, or least squares on template points.
FMAP_GROUND_TRUTHS = ("projection", "template_lstsq")


@dataclass
class DPFMConfig(HeadConfig):
    """`HeadConfig` plus the DPFM sizes, functional map, losses and matching.

    Defaults are the reference configuration for SHREC'16 cuts where it sets a value.

    Parameters
    ----------
    width : int
        Channels of the DiffusionNet blocks and of its output features (128).
    n_blocks : int
        DiffusionNet blocks (4).
    dropout : bool
        Dropout (p = 0.5) in the DiffusionNet block MLPs (True).
    attention_dim : int
        Channels inside the cross-attention refinement (128).
    n_heads : int
        Attention heads (4); must divide ``attention_dim``.
    n_attention_layers : int
        Cross-attention rounds (1); 0 skips the refinement (then only the two linear layers
        act per vertex).
    sampling_ratio : float
        Fraction of the vertices of each shape sampled by farthest-point sampling for the
        attention, in (0, 1] (0.4; 1 attends over all vertices, no interpolation).
    max_samples : int or None
        Upper bound on the samples per shape (None: no bound), for small machines.
    n_interpolation : int
        Nearest samples averaged to bring refined features back to every vertex (3).
    n_fmap : int
        Eigenfunctions of the functional map on each shape (50), ``<= n_eig``.
    lambda_ : float
        Weight of the resolvent Laplacian term of the functional map (100).
    gamma : float
        Resolvent exponent in (0, 1] (0.5).
    fmap_features : {"refined", "extracted"}
        Compute the functional map (and the NCE term) from the refined features (the
        reference's ``robust: True``, its HOLES setting) or from the DiffusionNet output
        (``robust: False``, its CUTS setting). With ``"extracted"`` only the overlap loss
        trains the cross-attention refiner.
    overlap_weighted_fmap : bool
        Multiply the features by the predicted overlap probability before the functional map
        (not in the reference code, which uses the overlap only in the loss; off by default).
    w_fmap : float
        Weight of the functional-map loss (1).
    w_overlap : float
        Weight of the overlap loss of each shape (1).
    w_nce : float
        Weight of the contrastive loss (0.1, the default of the reference's loss class; its
        configurations use 0 for cuts and 1 for holes).
    nce_temperature : float
        Temperature of the contrastive loss (0.07).
    nce_pairs : int
        Corresponding vertex pairs drawn for the contrastive loss per step (4096).
    single_class_weight : float
        Weight of every vertex in the overlap loss of a shape whose ground-truth mask holds
        a single class (the partial shape of a P2F pair is all overlap). The reference's
        class weights (the fraction of the other class) are 0 there, so it never trains
        that side; 0 reproduces it, the default 0.5 teaches the all-overlap answer.
    pointmap : {"fmap", "features"}
        Point map of a match: nearest neighbours of spectral embeddings under the predicted
        functional map, or of the (L2-normalised) functional-map features.
    overlap_threshold : float
        Probability above which a vertex is predicted to overlap, in (0, 1) (0.5).
    head_layout : {"contiguous", "interleaved"}
        Channels of attention head ``h``: the ``h``-th block of ``attention_dim / n_heads``
        channels, or the channels ``c`` with ``c % n_heads == h`` (the reference's layout,
        needed by its released weights).
    interpolation : {"nearest", "reference"}
        How the refined sample features reach every vertex: its ``n_interpolation`` nearest
        samples, inverse-squared-distance weighted; or the reference code's choice
        (`reference_sample_interpolation`, ``n_interpolation`` must be 3), which the
        presets reproduce (see the module notes: the released weights work better with
        ``"nearest"``).
    fmap_ground_truth : {"projection", "template_lstsq"}
        Ground truth of the functional-map loss: `ground_truth_fmap` of ``map_yx``, or
        `template_fmap`, the least-squares map between the eigenvectors at the template
        points of the pair (``pair.corr_x``, ``pair.corr_y``), as the reference's FAUST_r /
        SCAPE_r training.
    augmentation : bool
        Train on randomly rotated, noisy and rescaled coordinates (`augment_xyz`, the
        reference's training augmentation); needs ``descriptor="xyz"``.
    """

    width: int = 128
    n_blocks: int = 4
    dropout: bool = True
    attention_dim: int = 128
    n_heads: int = 4
    n_attention_layers: int = 1
    sampling_ratio: float = 0.4
    max_samples: int | None = None
    n_interpolation: int = 3
    n_fmap: int = 50
    lambda_: float = 100.0
    gamma: float = 0.5
    fmap_features: str = "refined"
    overlap_weighted_fmap: bool = False
    w_fmap: float = 1.0
    w_overlap: float = 1.0
    w_nce: float = 0.1
    nce_temperature: float = 0.07
    nce_pairs: int = 4096
    single_class_weight: float = 0.5
    pointmap: str = "fmap"
    overlap_threshold: float = 0.5
    head_layout: str = "contiguous"
    interpolation: str = "nearest"
    fmap_ground_truth: str = "projection"
    augmentation: bool = False


def check_config(c: DPFMConfig) -> None:
    """Raise `HeadError` for any setting outside its range."""

    check_integers("dpfm", c, ("width", "n_heads", "n_interpolation", "n_fmap", "nce_pairs", "attention_dim", "n_eig"), 1)
    check_integers("dpfm", c, ("n_blocks", "n_attention_layers"), 0)
    if c.attention_dim % c.n_heads:
        raise HeadError(f"dpfm: n_heads ({c.n_heads}) must divide attention_dim ({c.attention_dim}).")
    if c.n_fmap > c.n_eig:
        raise HeadError(f"dpfm: n_fmap ({c.n_fmap}) cannot exceed n_eig ({c.n_eig}); raise n_eig or lower n_fmap.")
    if c.max_samples is not None:
        check_integers("dpfm", c, ("max_samples",), 1)
    check_numbers("dpfm", c, ("sampling_ratio", "gamma"), 0.0, 1.0, low_open=True)
    check_numbers("dpfm", c, ("overlap_threshold",), 0.0, 1.0, low_open=True, high_open=True)
    check_numbers("dpfm", c, ("nce_temperature",), 0.0, low_open=True)
    check_numbers("dpfm", c, ("lambda_", "w_fmap", "w_overlap", "w_nce", "single_class_weight"), 0.0)
    if c.fmap_features not in FMAP_FEATURES:
        raise HeadError(f"dpfm: fmap_features must be one of {FMAP_FEATURES}; found {c.fmap_features!r}.")
    if c.pointmap not in POINTMAPS:
        raise HeadError(f"dpfm: pointmap must be one of {POINTMAPS}; found {c.pointmap!r}.")
    for name in ("dropout", "overlap_weighted_fmap", "augmentation"):
        setattr(c, name, check_boolean(getattr(c, name), name, owner="dpfm", error=HeadError))
    for name, valid in (
        ("head_layout", HEAD_LAYOUTS),
        ("interpolation", INTERPOLATIONS),
        ("fmap_ground_truth", FMAP_GROUND_TRUTHS),
    ):
        if getattr(c, name) not in valid:
            raise HeadError(f"dpfm: {name} must be one of {valid}; found {getattr(c, name)!r}.")
    if c.interpolation == "reference":
        if c.n_interpolation != 3:
            raise HeadError(f"dpfm: interpolation='reference' averages 3 samples; found n_interpolation={c.n_interpolation}.")
        if REFERENCE_CANDIDATE_RATIO < c.sampling_ratio < 1 or c.max_samples is not None:
            raise HeadError(
                f"dpfm: interpolation='reference' samples a fraction sampling_ratio <= {REFERENCE_CANDIDATE_RATIO} (or 1) "
                f"of the vertices without max_samples; found sampling_ratio={c.sampling_ratio}, max_samples={c.max_samples}."
            )
    if c.augmentation and c.descriptor != "xyz":
        raise HeadError(f"dpfm: augmentation transforms coordinates; it needs descriptor='xyz', found {c.descriptor!r}.")
