"""The interface of every matcher: `HeadConfig` (and its checks) and `Head`.

A head reads its input features from any registered geofeat descriptor
(``descriptor="wks"``, ``"geolora"`` with ``descriptor_params={"checkpoint": ...}``) or the
raw vertex coordinates (``descriptor="xyz"``, as the original papers do). A saved head is a
folder written by `geofeat.storage.pretrained.save_pretrained` (kind ``"head"``): ``config.json``
with the settings and, under ``info``, the head's name (and a learned head's input width),
plus ``weights.safetensors`` for learned heads.

torch is imported inside the methods that need it, not at the top: the training-free heads
(``nn``, ``fmap``) and the evaluation workers never load it (1 to 2 s of start-up).
"""

from __future__ import annotations

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

from geofeat.adapters.inputs import MESH_NORMALIZATIONS, descriptor_params_for, input_features, normalized_pair
from geofeat.checks import canonical, check_integer, check_number
from geofeat.datasets.records import Match, ShapePair
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.registry import make_descriptor
from geofeat.errors import GeofeatError, HeadError
from geofeat.mesh import Mesh
from geofeat.runtime.devices import resolve_device
from geofeat.storage.jsonconfig import JsonConfig
from geofeat.storage.lru import LRUCache
from geofeat.storage.pretrained import Pretrained, save_pretrained

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

__all__ = ["HEAD_KIND", "Head", "HeadConfig", "check_integers", "check_numbers"]

#: The ``kind`` of a saved head folder (`geofeat.storage.pretrained`).
HEAD_KIND = "head"
#: Input feature arrays a head keeps in memory (a target shape is matched to several sources in a row).
FEATURES_KEPT = 4
#: Normalised meshes a head keeps (`Head.prepare`: training sees the same shapes at every epoch).
_NORMALIZED_KEPT = 64


@dataclass
class HeadConfig(JsonConfig):
    """Settings shared by every head (subclasses add their own fields).

    `Head.save` writes them under ``config`` of the folder's ``config.json``; reading goes through
    `geofeat.storage.jsonconfig.JsonConfig.from_dict` (a key that is no setting: a warning, kept aside).

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
        `geofeat.adapters.blocks.operators.surface_operators`); ``"diffusionnet"`` (DPFM) and
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
    #: Presets: named sets of defaults (`make_head`), e.g. ``"reference"``: the conventions of the authors' code.
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
        self._features: LRUCache[tuple[str, str, str], np.ndarray] = LRUCache(FEATURES_KEPT)
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
        """Input features (V, C) float32 of a mesh of a prepared pair (read-only; the last few are kept in memory).

        On a point cloud a spectral descriptor uses the point-cloud Laplacian
        (`geofeat.adapters.inputs.descriptor_params_for`).
        """
        params = descriptor_params_for(mesh, self.config.descriptor_params)

        def build() -> np.ndarray:
            features = input_features(mesh, self.input_descriptor(params), params)
            features.flags.writeable = False  # shared by every later call for this mesh
            return features

        return self._features.get_or_compute(self._features_key(mesh), build)

    def input_descriptor(self, params: dict | None = None) -> Descriptor | str:
        """The descriptor of the input features, built once per descriptor setting (``"xyz"`` stays a name).

        A model-backed descriptor (DINOv2, DINOv3, GeoLoRA) loads its backbone on first use
        and keeps it: building it once here means once per head, not once per mesh.

        Parameters
        ----------
        params : dict, optional
            The descriptor's parameters (default: the head's ``descriptor_params``; a
            point cloud's are `geofeat.adapters.inputs.descriptor_params_for`).
        """
        c = self.config
        params = c.descriptor_params if params is None else params
        key = (c.descriptor, json.dumps(params, sort_keys=True, default=repr))
        if self._descriptor is None or self._descriptor[0] != key:
            built = c.descriptor if c.descriptor == "xyz" else make_descriptor(c.descriptor, **(params or {}))
            self._descriptor = (key, built)
        return self._descriptor[1]

    def _features_key(self, mesh: Mesh) -> tuple[str, str, str]:
        """What the input features of ``mesh`` depend on: its content and the descriptor settings."""
        c = self.config
        params = descriptor_params_for(mesh, c.descriptor_params)
        return mesh.hash, c.descriptor, json.dumps(params, sort_keys=True, default=repr)

    # -- the interface

    def fit(self, pairs: Sequence[ShapePair]) -> list[float]:
        """Train on pairs; returns the loss per step (empty for training-free heads)."""
        return []

    def match(self, pair: ShapePair) -> Match:
        """Predict the correspondence of ``pair.y`` to ``pair.x``."""
        raise NotImplementedError

    def save(self, folder: str | os.PathLike) -> Path:
        """Write the head into ``folder`` in one piece (`geofeat.storage.pretrained.save_pretrained`, kind ``"head"``).

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


def _check_inputs(config: HeadConfig) -> None:
    """Raise `HeadError` for an unknown Laplacian, operator construction or mesh normalisation."""
    from geofeat.adapters.blocks.operators import CONSTRUCTIONS
    from geofeat.geometry.laplacian import LAPLACIANS

    if config.laplacian not in LAPLACIANS:
        raise HeadError(f"laplacian must be one of {LAPLACIANS}; found {config.laplacian!r}.")
    if config.operators not in CONSTRUCTIONS:
        raise HeadError(f"operators must be one of {CONSTRUCTIONS}; found {config.operators!r}.")
    if config.mesh_normalization not in MESH_NORMALIZATIONS:
        raise HeadError(f"mesh_normalization must be one of {MESH_NORMALIZATIONS}; found {config.mesh_normalization!r}.")


def _unknown(config_class: type[HeadConfig], settings: dict) -> list[str]:
    return sorted(set(settings) - {f.name for f in dataclasses.fields(config_class)})
