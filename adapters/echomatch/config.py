"""EchoMatch's settings: `EchoMatchConfig` and the choices of its string settings."""

from __future__ import annotations

from dataclasses import dataclass

from geofeat.adapters.base import HeadConfig, check_integers, check_numbers
from geofeat.checks import check_boolean
from geofeat.errors import HeadError

#: Which features are zeroed outside the ground-truth overlap before the functional map while
#: training: those of ``y`` (the reference's default), of both shapes, or none.
PRUNE_STRATEGIES = ("y", "both", "none")
#: Lower bound of a raw learned temperature (our choice; the reference does not bound it).
MIN_TEMPERATURE = 1e-4


@dataclass
class EchoMatchConfig(HeadConfig):
    """`HeadConfig` plus the EchoMatch network and loss settings (defaults: the authors' values).

    Parameters
    ----------
    feature_channels : int
        Output channels of the feature DiffusionNet (128).
    width : int
        Width of the feature DiffusionNet (128).
    n_blocks : int
        Blocks of the feature DiffusionNet (4).
    dropout : float
        Dropout probability in the MLPs of both DiffusionNets (0.5).
    temperature_init : float
        Initial value of the learned softmax temperature of the soft point maps (0.1).
    learn_log_temperature : bool
        Our choice (default): learn the logarithm of the temperature, positive by
        construction. ``False``: the reference's raw parameter (clamped at
        `MIN_TEMPERATURE` when in use).
    n_neighbours : int
        Spatial neighbours (the vertex itself included) at which the reflection is read: the
        input width of the overlap network (64).
    overlap_width : int
        Width of the overlap DiffusionNet (16).
    overlap_blocks : int
        Blocks of the overlap DiffusionNet (3).
    n_fmap : int
        Eigenpairs of the functional map (50); at most ``n_eig`` (the operators, 128).
    fmap_lambda : float
        Laplacian-mask weight of the feature functional map (100).
    fmap_gamma : float
        Resolvent exponent of the Laplacian mask (0.5).
    gt_fmap_lambda : float
        Laplacian-mask weight of the ground-truth functional map (1e6); 0 gives
        ``Phi_y^T M_y P_yx Phi_x``.
    w_fmap, w_overlap, w_nce_self, w_nce_cross : float
        Loss weights (1, 1, 0.1, 0.1).
    nce_temperature : float
        Temperature of both NCE losses (0.07).
    prune_strategy : {"y", "both", "none"}
        Features zeroed outside the ground-truth overlap before the training functional map
        (``"y"``).
    overlap_threshold : float
        Probability above which a vertex is predicted to overlap (0.5).
    restrict_to_overlap : bool
        Our option: match ``y`` only to vertices of ``x`` predicted to overlap (all of ``x``
        when none is). Off by default, as in the reference.
    epochs, lr, grad_clip
        900, 1e-3 and 1.0 (gradient norm clipped before every step), the authors' training
        settings.
    """

    feature_channels: int = 128
    width: int = 128
    n_blocks: int = 4
    dropout: float = 0.5
    temperature_init: float = 0.1
    learn_log_temperature: bool = True
    n_neighbours: int = 64
    overlap_width: int = 16
    overlap_blocks: int = 3
    n_fmap: int = 50
    fmap_lambda: float = 100.0
    fmap_gamma: float = 0.5
    gt_fmap_lambda: float = 1e6
    w_fmap: float = 1.0
    w_overlap: float = 1.0
    w_nce_self: float = 0.1
    w_nce_cross: float = 0.1
    nce_temperature: float = 0.07
    prune_strategy: str = "y"
    overlap_threshold: float = 0.5
    restrict_to_overlap: bool = False
    epochs: int = 900
    lr: float = 1e-3
    grad_clip: float | None = 1.0

    def __post_init__(self) -> None:
        check_integers(
            "echomatch", self, ("feature_channels", "width", "n_neighbours", "overlap_width", "n_fmap", "n_eig", "epochs"), 1
        )
        check_integers("echomatch", self, ("n_blocks", "overlap_blocks"), 0)
        if self.n_fmap > self.n_eig:
            raise HeadError(
                f"echomatch: n_fmap={self.n_fmap} eigenpairs for the functional map, but the operators have only "
                f"n_eig={self.n_eig}; raise n_eig or lower n_fmap."
            )
        check_numbers(
            "echomatch", self, ("fmap_lambda", "gt_fmap_lambda", "w_fmap", "w_overlap", "w_nce_self", "w_nce_cross"), 0.0
        )
        check_numbers("echomatch", self, ("temperature_init", "nce_temperature", "lr"), 0.0, low_open=True)
        check_numbers("echomatch", self, ("fmap_gamma",), 0.0, 1.0, low_open=True)
        check_numbers("echomatch", self, ("dropout",), 0.0, 1.0, high_open=True)
        check_numbers("echomatch", self, ("overlap_threshold",), 0.0, 1.0, low_open=True, high_open=True)
        for name in ("learn_log_temperature", "restrict_to_overlap"):
            setattr(self, name, check_boolean(getattr(self, name), name, owner="echomatch", error=HeadError))
        if self.prune_strategy not in PRUNE_STRATEGIES:
            raise HeadError(f"echomatch setting prune_strategy must be one of {PRUNE_STRATEGIES}; found {self.prune_strategy!r}.")
