"""One interface for every matcher: a configuration, training on pairs, matching a pair, checkpoints.

>>> head = make_head("ulrssm", descriptor="wks", epochs=5)                 # doctest: +SKIP
>>> head.fit(load_dataset("faust_r_cuts", split="train"))                  # doctest: +SKIP
>>> match = head.match(pair)              # map_yx (V_y,), overlap_y (V_y,), overlap_x (V_x,) or None
>>> head.save("runs/ulrssm"); same = load_head("runs/ulrssm")             # doctest: +SKIP

This module holds the interface (`Head`, `HeadConfig` and its checks), the two
training-free heads (``nn``, ``fmap``), and building and loading heads by name
(`make_head`, `load_head`). Around it: what a head reads from a pair (`inputs`: ground
truth, mesh normalisation, input features), the shared part of the learned heads
(`learned.LearnedHead`: training loop, per-shape inputs, weights), the names of the heads
(`head_registry`) and the mapping of the authors' release checkpoints (`release`).

Every head reads its input features from any registered geofeat descriptor
(``descriptor="wks"``, ``"geolora"`` with ``descriptor_params={"checkpoint": ...}``) or the
raw vertex coordinates (``descriptor="xyz"``, as the original papers do). A saved head is a
folder written by `geofeat.pretrained.save_pretrained` (kind ``"head"``): ``config.json``
with the settings and, under ``info``, the head's name (and a learned head's input width),
plus ``weights.safetensors`` for learned heads.

torch is imported inside the methods that need it, not at the top: the training-free heads
(``nn``, ``fmap``) and the evaluation workers never load it (1 to 2 s of start-up).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from geofeat.checks import canonical, check_integer, check_number
from geofeat.datasets.records import Match, ShapePair
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.registry import make_descriptor
from geofeat.devices import resolve_device
from geofeat.errors import GeofeatError, HeadError
from geofeat.jsonconfig import JsonConfig
from geofeat.lru import LRUCache
from geofeat.mesh import Mesh
from geofeat.pretrained import CONFIG_FILE, WEIGHTS_FILE, Pretrained, from_pretrained, save_pretrained
from geofeat.safe_load import load_torch_file

from . import matchers
from .functional_maps import NearestNeighborIndex
from .head_registry import head_class
from .inputs import MESH_NORMALIZATIONS, input_features, normalized_pair

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

__all__ = [
    "FunctionalMapConfig",
    "FunctionalMapHead",
    "Head",
    "HeadConfig",
    "NearestNeighbourHead",
    "check_integers",
    "check_numbers",
    "load_head",
    "make_head",
    "preset_settings",
    "upgrade_head",
]

#: The ``kind`` of a saved head folder (`geofeat.pretrained`).
HEAD_KIND = "head"
#: Files of the layout Head.save wrote before `geofeat.pretrained` (see `upgrade_head`).
_OLD_CONFIG_FILE = "head_config.json"
_OLD_LAYOUT_HINT = "Rewrite it in place with geofeat.adapters.heads.upgrade_head(folder) (the weights are kept)."
#: Input feature arrays a head keeps in memory (a target shape is matched to several sources in a row).
_FEATURES_KEPT = 4
#: Normalised meshes a head keeps (`Head.prepare`: training sees the same shapes at every epoch).
_NORMALIZED_KEPT = 64


@dataclass
class HeadConfig(JsonConfig):
    """Settings shared by every head (subclasses add their own fields).

    `Head.save` writes them under ``config`` of the folder's ``config.json``; reading goes through
    `geofeat.jsonconfig.JsonConfig.from_dict` (a key that is no setting: a warning, kept aside).

    Parameters
    ----------
    descriptor : str
        Input features: a registered descriptor name, or ``"xyz"`` (vertex coordinates).
    descriptor_params : dict
        Keyword parameters of the descriptor.
    n_eig : int
        Eigenpairs of the surface operators (DiffusionNet, functional maps).
    epochs : int
        Passes over the training pairs.
    lr : float
        Adam learning rate.
    cosine_annealing : bool
        Anneal the learning rate to 0 over the training with a cosine.
    grad_clip : float or None
        Clip the gradient norm to this before every step.
    max_minutes : float or None
        Stop training after this much wall time.
    seed : int
        Seeds the initialisation and the pair order.
    device : str
        ``"auto"``: CUDA when present, else CPU.
    progress : bool
        Progress bars.
    laplacian : {"robust", "cotan"}
        Laplacian of the surface operators (eigenpairs, mass).
    operators : {"geofeat", "diffusionnet", "ulrssm"}
        Construction of the DiffusionNet operators (see
        `geofeat.adapters.operators.surface_operators`); ``"diffusionnet"`` (DPFM) and
        ``"ulrssm"`` (ULRSSM, EchoMatch) are those of the reference code the released
        models were trained with.
    mesh_normalization : {None, "unit_area"}
        What the head does to every pair before computing inputs and operators (see
        `normalized_pair`). ``"unit_area"``: the references' preprocessing: full shapes
        centred at their mean vertex and scaled to unit total face area, a P2F partial
        shape moved and scaled with its full shape, coordinates rounded to float32 (the
        references read their meshes as float32). Point maps and overlaps do not depend on
        it (the vertex order is kept); geodesic errors are computed on the original meshes.
    """

    descriptor: str = "wks"
    descriptor_params: dict = field(default_factory=dict)
    n_eig: int = 128
    epochs: int = 1
    lr: float = 1e-3
    cosine_annealing: bool = False
    grad_clip: float | None = None
    max_minutes: float | None = None
    seed: int = 0
    device: str = "cpu"
    progress: bool = True
    laplacian: str = "robust"
    operators: str = "geofeat"
    mesh_normalization: str | None = None

    error: ClassVar[type[GeofeatError]] = HeadError


def check_integers(head: str, config: HeadConfig, names: Sequence[str], low: int) -> None:
    """Raise `HeadError` unless every named setting of ``config`` is an integer ``>= low`` (NumPy integers stored back as int)."""
    for name in names:
        setattr(config, name, check_integer(getattr(config, name), name, owner=head, low=low, error=HeadError))


def check_numbers(
    head: str,
    config: HeadConfig,
    names: Sequence[str],
    low: float,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
) -> None:
    """Raise `HeadError` unless every named setting is a finite number in the interval ``low .. high``.

    ``low_open`` / ``high_open`` exclude the bound itself. NumPy scalars are stored back as
    Python numbers.
    """
    for name in names:
        value = getattr(config, name)
        check_number(value, name, owner=head, low=low, high=high, low_open=low_open, high_open=high_open, error=HeadError)
        setattr(config, name, canonical(value))


class Head:
    """A matcher: ``fit`` on training pairs (a no-op when training-free), ``match`` a pair, save and load.

    Subclasses set ``name`` and ``config_class``.
    """

    name: ClassVar[str] = ""
    config_class: ClassVar[type[HeadConfig]] = HeadConfig
    #: Named sets of settings, e.g. ``"reference"``: the conventions of the authors' code.
    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {}

    def __init__(self, config: HeadConfig | None = None, **settings: Any):
        if config is not None and settings:
            raise HeadError("give either a config or keyword settings, not both.")
        if config is None:
            unknown = _unknown(self.config_class, settings)
            if unknown:
                valid = [f.name for f in dataclasses.fields(self.config_class)]
                raise HeadError(f"unknown setting(s) {unknown} for head {self.name!r}; valid: {valid}.")
            config = self.config_class(**settings)
        if not isinstance(config, self.config_class):
            raise HeadError(f"head {self.name!r} takes a {self.config_class.__name__}; found {type(config).__name__}.")
        self.config = config
        _check_inputs(config)
        self._features: LRUCache[tuple[str, str, str], np.ndarray] = LRUCache(_FEATURES_KEPT)
        self._normalized: LRUCache[tuple, Mesh] = LRUCache(_NORMALIZED_KEPT)
        self._descriptor: tuple[tuple[str, str], Descriptor | str] | None = None

    # -- inputs

    @property
    def device(self) -> torch.device:
        """Where the head computes."""
        return resolve_device(self.config.device)

    def prepare(self, pair: ShapePair) -> ShapePair:
        """The pair after `HeadConfig.mesh_normalization` (`normalized_pair`); heads compute on prepared pairs.

        `match` and `fit` prepare every pair once; the other methods that take a pair
        (``training_loss``, ``predict``, ``loss_terms``...) expect a prepared one. The
        normalised meshes of the last 64 shapes are kept.
        """
        return normalized_pair(pair, self.config.mesh_normalization, self._normalized)

    def features(self, mesh: Mesh) -> np.ndarray:
        """Input features (V, C) float32 of a mesh of a prepared pair (read-only; the last few are kept in memory)."""
        c = self.config

        def build() -> np.ndarray:
            features = input_features(mesh, self.input_descriptor(), c.descriptor_params)
            features.flags.writeable = False  # shared by every later call for this mesh
            return features

        return self._features.get_or_compute(self._features_key(mesh), build)

    def input_descriptor(self) -> Descriptor | str:
        """The descriptor of the input features, built once per descriptor setting (``"xyz"`` stays a name).

        A model-backed descriptor (DINOv2, DINOv3, GeoLoRA) loads its backbone on first use
        and keeps it: building it once here means once per head, not once per mesh.
        """
        c = self.config
        key = (c.descriptor, json.dumps(c.descriptor_params, sort_keys=True, default=repr))
        if self._descriptor is None or self._descriptor[0] != key:
            built = c.descriptor if c.descriptor == "xyz" else make_descriptor(c.descriptor, **(c.descriptor_params or {}))
            self._descriptor = (key, built)
        return self._descriptor[1]

    def _features_key(self, mesh: Mesh) -> tuple[str, str, str]:
        """What the input features of ``mesh`` depend on: its content and the descriptor settings."""
        c = self.config
        return mesh.hash, c.descriptor, json.dumps(c.descriptor_params, sort_keys=True, default=repr)

    # -- the interface

    def fit(self, pairs: Sequence[ShapePair]) -> list[float]:
        """Train on pairs; returns the loss per step (empty for training-free heads)."""
        return []

    def match(self, pair: ShapePair) -> Match:
        """Predict the correspondence of ``pair.y`` to ``pair.x``."""
        raise NotImplementedError

    def save(self, folder: str | os.PathLike) -> Path:
        """Write the head into ``folder`` in one piece (`geofeat.pretrained.save_pretrained`, kind ``"head"``).

        ``config.json`` holds the settings and, under ``info``, the head's name (and what
        `saved_state` adds); ``weights.safetensors`` the tensors of a learned head. A folder
        saved before is replaced; a folder holding other files is refused.

        Returns
        -------
        pathlib.Path
            The folder.

        Raises
        ------
        HeadError
            A setting that is no JSON value, a folder that cannot be replaced, or a learned
            head without a module.
        """
        info, tensors = self.saved_state()
        return save_pretrained(
            folder, HEAD_KIND, self.config.to_dict(), tensors, info={"head": self.name} | info, error=HeadError
        )

    def saved_state(self) -> tuple[dict[str, Any], dict[str, torch.Tensor] | None]:
        """What `save` writes beside the settings: entries of ``info`` and the tensors (none for training-free heads)."""
        return {}, None

    def restore(self, saved: Pretrained) -> None:
        """Take back what `saved_state` gave from a folder read by `load_head`; training-free heads have nothing."""


class NearestNeighbourHead(Head):
    """Nearest neighbour in feature space (training-free)."""

    name = "nn"

    def __init__(self, config: HeadConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        # a target is matched to several sources in a row: its search index is built once
        self._indices: LRUCache[tuple[str, str, str], NearestNeighborIndex] = LRUCache(_FEATURES_KEPT)

    def match(self, pair: ShapePair) -> Match:
        pair = self.prepare(pair)
        index = self._indices.get_or_compute(self._features_key(pair.x), lambda: NearestNeighborIndex(self.features(pair.x)))
        map_yx = matchers.nn_match(index, self.features(pair.y))
        return Match(map_yx, np.ones(pair.y.n_vertices, dtype=bool))


@dataclass
class FunctionalMapConfig(HeadConfig):
    """`HeadConfig` plus the functional-map size and ZoomOut (see `matchers.fmap_match`)."""

    k: int = 30
    zoomout: bool = False
    k_final: int = 100


class FunctionalMapHead(Head):
    """A functional map from the input features, converted to a point map (training-free)."""

    name = "fmap"
    config_class = FunctionalMapConfig

    def match(self, pair: ShapePair) -> Match:
        c = self.config
        pair = self.prepare(pair)
        map_yx = matchers.fmap_match(
            pair.x, pair.y, self.features(pair.x), self.features(pair.y), k=c.k, zoomout=c.zoomout, k_final=c.k_final,
            n_eig=max(c.n_eig, c.k_final if c.zoomout else c.k),
        )  # fmt: skip
        return Match(map_yx, np.ones(pair.y.n_vertices, dtype=bool))


def make_head(name: str, preset: str | None = None, **settings: Any) -> Head:
    """Build the head ``name`` from keyword settings of its configuration.

    Parameters
    ----------
    name : str
        A name of `head_registry.HEADS`.
    preset : str, optional
        A key of the head's ``PRESETS`` (e.g. ``"reference"``: the authors' conventions);
        ``settings`` override the preset's values.
    **settings
        Fields of the head's configuration.
    """
    cls = head_class(name)
    return cls(**(preset_settings(cls, preset) | settings))


def preset_settings(cls: type[Head], preset: str | None) -> dict[str, Any]:
    """The settings of ``cls.PRESETS[preset]`` (empty for None); `HeadError` for an unknown preset."""
    if preset is None:
        return {}
    if preset not in cls.PRESETS:
        raise HeadError(f"head {cls.name!r} has no preset {preset!r}; presets: {sorted(cls.PRESETS) or 'none'}.")
    return copy.deepcopy(cls.PRESETS[preset])


def load_head(
    source: str | os.PathLike, checkpoint: str | os.PathLike | None = None, preset: str = "reference", **settings: Any
) -> Head:
    """A head saved by `Head.save`, or a head built from the authors' release checkpoint.

    Parameters
    ----------
    source : str or path-like
        A folder written by `Head.save`; or, with ``checkpoint``, a head name
        (``"ulrssm"``, ``"dpfm"``).
    checkpoint : str or path-like, optional
        A release checkpoint of the authors' code (a ``torch.save`` file). The head gets its
        ``"reference"`` preset, its sizes read from the tensors, and the weights through an
        exact key mapping (see the head's ``release_state``).
    preset : str
        With ``checkpoint``: the head's preset to start from (default ``"reference"``; DPFM
        also has ``"reference_shrec16_cuts"`` and ``"reference_shrec16_holes"``).
    **settings
        With ``checkpoint``: settings that override the preset (e.g. ``tta_steps=5``).

    Raises
    ------
    HeadError
        An unreadable file, or a checkpoint with missing, unexpected or wrongly shaped keys
        (each named).
    """
    if checkpoint is not None:
        return _from_release(str(source), Path(checkpoint), preset, settings)
    if settings:
        raise HeadError(f"settings {sorted(settings)} only apply with a release checkpoint; change head.config instead.")
    saved = from_pretrained(source, HEAD_KIND, HeadError, older_layout_hint=_OLD_LAYOUT_HINT)
    name = saved.info.get("head")
    if not isinstance(name, str):
        raise HeadError(
            f"{saved.folder / CONFIG_FILE} names no head: expected the head's name under info.head, as Head.save "
            f"writes; found {name!r}. Save the head again."
        )
    cls = head_class(name)
    head = cls(cls.config_class.from_dict(saved.config))
    head.restore(saved)
    return head


def upgrade_head(folder: str | os.PathLike) -> Path:
    """Rewrite a head folder of the older layout (``head_config.json`` + ``weights.safetensors``) in place.

    The older `Head.save` wrote ``head_config.json`` (``{"head", "geofeat_version",
    "config"}``) and, for a learned head, ``weights.safetensors`` with the input width in its
    metadata. The folder is rewritten whole by `geofeat.pretrained.save_pretrained` with the
    same settings and tensors, so that `load_head` reads it.

    Parameters
    ----------
    folder : str or os.PathLike

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    HeadError
        The folder holds no ``head_config.json``, or its files cannot be read.
    """
    folder = Path(folder)
    old_config, weights = folder / _OLD_CONFIG_FILE, folder / WEIGHTS_FILE
    if not old_config.is_file():
        raise HeadError(f"{folder} holds no {_OLD_CONFIG_FILE}; there is nothing to upgrade.")
    try:
        payload = json.loads(old_config.read_text())
    except (OSError, ValueError) as exc:
        raise HeadError(f"could not read {old_config} as JSON ({exc}); the file is damaged.") from exc
    if not isinstance(payload, dict) or not isinstance(payload.get("head"), str) or not isinstance(payload.get("config"), dict):
        raise HeadError(f"{old_config} is not a head configuration: expected an object with 'head' (a name) and 'config'.")
    info: dict[str, Any] = {"head": payload["head"]}
    tensors = None
    if weights.is_file():
        from safetensors import safe_open
        from safetensors.torch import load_file

        try:
            with safe_open(str(weights), framework="pt") as handle:
                info["in_channels"] = int((handle.metadata() or {})["in_channels"])
            tensors = load_file(str(weights))
        except Exception as exc:  # SafetensorError, OSError, a missing or bad in_channels entry
            raise HeadError(
                f"could not read {weights} with its 'in_channels' metadata ({type(exc).__name__}: {exc}); the file is "
                "truncated or damaged, or was not written by Head.save."
            ) from exc
    save_pretrained(folder, HEAD_KIND, payload["config"], tensors, info=info, error=HeadError, overwrite=True)
    log.info("upgraded the head in %s to config.json + weights.safetensors", folder)
    return folder


def _from_release(name: str, checkpoint: Path, preset: str, settings: dict[str, Any]) -> Head:
    """`load_head` with a release checkpoint (heads with a ``release_state`` class method and ``load_state``)."""
    cls = head_class(name)
    release_state = getattr(cls, "release_state", None)
    if release_state is None or not hasattr(cls, "load_state"):
        raise HeadError(f"head {name!r} cannot load release checkpoints; heads that can: ulrssm, dpfm, echomatch.")
    if checkpoint.is_dir():
        raise HeadError(
            f"release checkpoint {checkpoint} is a folder; expected the authors' .pth file. "
            f"A folder saved by geofeat ({CONFIG_FILE} + {WEIGHTS_FILE}) loads with load_head(folder)."
        )
    if not checkpoint.is_file():
        raise HeadError(f"release checkpoint {checkpoint} does not exist.")
    raw = load_torch_file(checkpoint, HeadError, what="a release checkpoint of the authors' code")
    if not isinstance(raw, dict):
        raise HeadError(f"{checkpoint}: expected a dict of tensors; found {type(raw).__name__}.")
    release = release_state(raw, source=str(checkpoint))
    head = cls(**(preset_settings(cls, preset) | release.settings | settings))
    head.load_state(release.state, release.in_channels, source=str(checkpoint))
    return head


def _check_inputs(config: HeadConfig) -> None:
    """Raise `HeadError` for an unknown Laplacian, operator construction or mesh normalisation."""
    from geofeat.geometry.laplacian import LAPLACIANS

    from .operators import CONSTRUCTIONS

    if config.laplacian not in LAPLACIANS:
        raise HeadError(f"laplacian must be one of {LAPLACIANS}; found {config.laplacian!r}.")
    if config.operators not in CONSTRUCTIONS:
        raise HeadError(f"operators must be one of {CONSTRUCTIONS}; found {config.operators!r}.")
    if config.mesh_normalization not in MESH_NORMALIZATIONS:
        raise HeadError(f"mesh_normalization must be one of {MESH_NORMALIZATIONS}; found {config.mesh_normalization!r}.")


def _unknown(config_class: type[HeadConfig], settings: dict) -> list[str]:
    return sorted(set(settings) - {f.name for f in dataclasses.fields(config_class)})
