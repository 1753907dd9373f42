"""One interface for every matcher: a configuration, training on pairs, matching a pair, checkpoints.

>>> head = make_head("ulrssm", descriptor="wks", epochs=5)                 # doctest: +SKIP
>>> head.fit(load_dataset("faust_r_cuts", split="train"))                  # doctest: +SKIP
>>> match = head.match(pair)              # map_yx (V_y,), overlap_y (V_y,), overlap_x (V_x,) or None
>>> head.save("runs/ulrssm"); same = load_head("runs/ulrssm")             # doctest: +SKIP

Every head reads its input features from any registered geofeat descriptor
(``descriptor="wks"``, ``"geolora"`` with ``descriptor_params={"checkpoint": ...}``) or the
raw vertex coordinates (``descriptor="xyz"``, as the original papers do). Learned heads
subclass `LearnedHead`: they build a torch module from the input width, give a training loss
for a pair and a prediction for a pair; the loop (Adam, optional cosine annealing, time
budget, progress bar) and the checkpoint format (``head_config.json`` + ``weights.safetensors``)
are shared.

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
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from geofeat._version import __version__
from geofeat.checks import canonical, check_integer, check_number, is_boolean
from geofeat.datasets.records import Match, ShapePair  # Match is re-exported: heads return it
from geofeat.descriptors.compute import compute
from geofeat.devices import resolve_device
from geofeat.errors import GeofeatError, HeadError, UnusablePair
from geofeat.files import atomic_write
from geofeat.jsonconfig import JsonConfig
from geofeat.lru import LRUCache
from geofeat.mesh import Mesh
from geofeat.progress import progress_bar
from geofeat.registry import LazyEntry, lookup
from geofeat.safe_load import load_torch_file

from . import matchers
from .functional_maps import NearestNeighborIndex

if TYPE_CHECKING:
    import torch

    from .operators import SurfaceOperators

log = logging.getLogger(__name__)

__all__ = [
    "HEADS",
    "FunctionalMapHead",
    "Head",
    "HeadConfig",
    "HeadError",
    "LearnedHead",
    "Match",
    "UnusablePair",
    "NearestNeighbourHead",
    "ground_truth_map",
    "ground_truth_overlaps",
    "input_features",
    "load_head",
    "make_head",
    "normalized_mesh",
    "normalized_pair",
]

CONFIG_FILE = "head_config.json"
#: Meshes whose input features and operators a learned head keeps (`LearnedHead.shape_inputs`).
_INPUTS_KEPT = 64
#: Input feature arrays a head keeps in memory (a target shape is matched to several sources in a row).
_FEATURES_KEPT = 4
WEIGHTS_FILE = "weights.safetensors"


@dataclass
class HeadConfig(JsonConfig):
    """Settings shared by every head (subclasses add their own fields).

    `Head.save` writes them into ``head_config.json``; reading goes through
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


def ground_truth_map(pair: ShapePair) -> np.ndarray:
    """The ground-truth ``map_yx`` of a training pair, checked.

    Returns
    -------
    numpy.ndarray, shape (V_y,), int64
        A vertex of ``x`` for every vertex of ``y``, or -1.

    Raises
    ------
    HeadError
        A map of the wrong shape, type or range.
    UnusablePair
        No vertex of ``y`` has a counterpart (supervised heads skip such pairs).
    """
    map_yx = np.asarray(pair.map_yx)
    n_x, n_y = pair.x.n_vertices, pair.y.n_vertices
    if map_yx.shape != (n_y,) or not np.issubdtype(map_yx.dtype, np.integer):
        raise HeadError(
            f"pair {pair.name}: map_yx must be an integer array of shape ({n_y},); found {map_yx.dtype} {map_yx.shape}."
        )
    if map_yx.size and (map_yx.min() < -1 or map_yx.max() >= n_x):
        raise HeadError(
            f"pair {pair.name}: map_yx must hold vertices of x in [0, {n_x - 1}] or -1; "
            f"found range [{map_yx.min()}, {map_yx.max()}]."
        )
    if not (map_yx >= 0).any():
        raise UnusablePair(f"pair {pair.name}: no correspondence in the ground truth (map_yx is all -1).")
    return map_yx.astype(np.int64, copy=False)


def ground_truth_overlaps(pair: ShapePair) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth overlap masks of a training pair: its own, else derived from ``map_yx``.

    Returns
    -------
    overlap_x : numpy.ndarray, shape (V_x,), bool
        ``pair.overlap_x``, else the vertices of ``x`` that some vertex of ``y`` maps to;
        all True for a full-to-full pair without masks (every vertex of a full shape has a
        counterpart, even where a sparse ground truth such as FAUST_r's template gives
        none; the DPFM reference does the same).
    overlap_y : numpy.ndarray, shape (V_y,), bool
        ``pair.overlap_y``, else ``map_yx >= 0``; all True for a full-to-full pair.
    """
    map_yx = ground_truth_map(pair)
    overlap_x, overlap_y = pair.overlap_x, pair.overlap_y
    if pair.protocol == "f2f" and overlap_x is None and overlap_y is None:
        return np.ones(pair.x.n_vertices, dtype=bool), np.ones(pair.y.n_vertices, dtype=bool)
    if overlap_x is None:
        overlap_x = np.zeros(pair.x.n_vertices, dtype=bool)
        overlap_x[map_yx[map_yx >= 0]] = True
    if overlap_y is None:
        overlap_y = map_yx >= 0
    for name, mask, n in (("overlap_x", overlap_x, pair.x.n_vertices), ("overlap_y", overlap_y, pair.y.n_vertices)):
        if np.shape(mask) != (n,):
            raise HeadError(f"pair {pair.name}: {name} must have shape ({n},); found {np.shape(mask)}.")
    return np.asarray(overlap_x, dtype=bool), np.asarray(overlap_y, dtype=bool)


#: Values of `HeadConfig.mesh_normalization`.
MESH_NORMALIZATIONS = (None, "unit_area")


def normalized_mesh(mesh: Mesh, how: str | None, frame: Mesh | None = None) -> Mesh:
    """A mesh moved and scaled as the references' preprocessing does (see `normalized_pair`).

    Parameters
    ----------
    mesh : Mesh
    how : {None, "unit_area"}
        None returns ``mesh`` itself. ``"unit_area"``: subtract the mean vertex of
        ``frame`` and divide by the square root of its total face area, then round to
        float32 (the references read their preprocessed meshes as float32).
    frame : Mesh, optional
        The triangle mesh whose mean and area define the transform (default ``mesh``).

    Returns
    -------
    Mesh
        Same faces, vertex order and name.
    """
    if how is None:
        return mesh
    if how != "unit_area":
        raise HeadError(f"mesh_normalization must be one of {MESH_NORMALIZATIONS}; found {how!r}.")
    frame = mesh if frame is None else frame
    area = frame.area() if frame.faces is not None else 0.0
    if not area > 0:
        raise HeadError(f"mesh {frame.name!r} has no surface area: mesh_normalization='unit_area' needs a triangle mesh.")
    verts = (mesh.verts - frame.verts.mean(axis=0)) / math.sqrt(area)
    return Mesh(verts.astype(np.float32).astype(np.float64), mesh.faces, name=mesh.name)


def normalized_pair(pair: ShapePair, how: str | None) -> ShapePair:
    """The pair a head computes on: `HeadConfig.mesh_normalization` applied the way the references' data has it.

    With ``"unit_area"`` every full shape is centred at its mean vertex and scaled to unit
    area; the partial shape ``y`` of a P2F pair stays in the frame of the full shape ``x``
    (moved and scaled like it), as in the SHREC'16 data of DPFM and ULRSSM, where a partial
    shape keeps the coordinates and scale of the full shape it was cut from. The two
    shapes of a P2P pair are normalised each by itself (the references define no rule).

    Parameters
    ----------
    pair : ShapePair
    how : {None, "unit_area"}

    Returns
    -------
    ShapePair
        ``pair`` itself for None; else the same record with new ``x`` and ``y`` (vertex
        order, faces, names and ground truth unchanged).
    """
    if how is None:
        return pair
    x = normalized_mesh(pair.x, how)
    y = normalized_mesh(pair.y, how, frame=pair.x if pair.protocol == "p2f" else None)
    return dataclasses.replace(pair, x=x, y=y)


def input_features(mesh: Mesh, descriptor: str, params: dict | None = None) -> np.ndarray:
    """Per-vertex input features of a head: a geofeat descriptor, or ``"xyz"`` coordinates.

    Parameters
    ----------
    mesh : Mesh
    descriptor : str
        A registered descriptor name, or ``"xyz"``.
    params : dict, optional
        The descriptor's parameters. ``"xyz"`` takes one, ``normalize`` (default True):
        centre the vertices on their mean and scale them to unit surface area, shape by
        shape; False: the coordinates as they are (the reference presets, whose pairs are
        already normalised with a partial shape in the frame of its full shape, see
        `normalized_pair`).

    Returns
    -------
    numpy.ndarray, shape (V, C), float32
    """
    if descriptor == "xyz":
        params = dict(params or {})
        normalize = params.pop("normalize", True)
        if params or not is_boolean(normalize):
            raise HeadError(f"descriptor 'xyz' takes only normalize=True/False; found {sorted(params) or normalize!r}.")
        if not normalize:
            return np.ascontiguousarray(mesh.verts, dtype=np.float32)
        verts = mesh.verts - mesh.verts.mean(axis=0)
        area = mesh.area() if mesh.faces is not None else 0.0
        scale = math.sqrt(area) if area > 0 else 1.0
        return np.ascontiguousarray(verts / scale, dtype=np.float32)
    return compute(mesh, descriptor, **(params or {}))


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
        self._inputs: LRUCache[str, tuple[torch.Tensor, SurfaceOperators]] = LRUCache(_INPUTS_KEPT)
        self._features: LRUCache[tuple[str, str, str], np.ndarray] = LRUCache(_FEATURES_KEPT)

    # -- inputs

    @property
    def device(self) -> torch.device:
        """Where the head computes."""
        return resolve_device(self.config.device)

    def prepare(self, pair: ShapePair) -> ShapePair:
        """The pair after `HeadConfig.mesh_normalization` (`normalized_pair`); heads compute on prepared pairs.

        `match` and `fit` prepare every pair once; the other methods that take a pair
        (``training_loss``, ``predict``, ``loss_terms``...) expect a prepared one.
        """
        return normalized_pair(pair, self.config.mesh_normalization)

    def features(self, mesh: Mesh) -> np.ndarray:
        """Input features (V, C) float32 of a mesh of a prepared pair (read-only; the last few are kept in memory)."""
        c = self.config

        def build() -> np.ndarray:
            features = input_features(mesh, c.descriptor, c.descriptor_params)
            features.flags.writeable = False  # shared by every later call for this mesh
            return features

        return self._features.get_or_compute(self._features_key(mesh), build)

    def _features_key(self, mesh: Mesh) -> tuple[str, str, str]:
        """What the input features of ``mesh`` depend on: its content and the descriptor settings."""
        c = self.config
        return mesh.hash, c.descriptor, json.dumps(c.descriptor_params, sort_keys=True, default=repr)

    def operators(self, mesh: Mesh) -> SurfaceOperators:
        """Surface operators of a mesh of a prepared pair, on the CPU."""
        from .operators import surface_operators

        c = self.config
        return surface_operators(mesh, c.n_eig, laplacian_kind=c.laplacian, construction=c.operators)

    def shape_inputs(self, mesh: Mesh) -> tuple[torch.Tensor, SurfaceOperators]:
        """Input features as a tensor (V, C) and the surface operators, on the head's device (kept for 64 meshes)."""
        import torch

        def build() -> tuple[torch.Tensor, SurfaceOperators]:
            feats = torch.tensor(self.features(mesh), device=self.device)  # a copy: the array is shared and read-only
            return feats, self.operators(mesh).to(self.device)

        return self._inputs.get_or_compute(mesh.hash, build)

    def use_inputs(self, mesh: Mesh, features: torch.Tensor, operators: SurfaceOperators) -> None:
        """Use these input features and operators for ``mesh`` instead of computing them.

        For feeding a head exactly the inputs of another implementation (``benchmarks/parity.py``)
        or inputs computed elsewhere. They are kept like computed ones (64 meshes).

        Parameters
        ----------
        mesh : Mesh
        features : torch.Tensor, shape (V, C)
        operators : SurfaceOperators
            With at least ``n_eig`` eigenpairs where the head needs them.
        """
        if features.ndim != 2 or features.shape[0] != mesh.n_vertices or operators.n_vertices != mesh.n_vertices:
            raise HeadError(
                f"use_inputs: features (V, C) and operators must be of mesh {mesh.name!r} with {mesh.n_vertices} vertices; "
                f"found features {tuple(features.shape)} and operators of {operators.n_vertices} vertices."
            )
        import torch

        self._inputs.put(mesh.hash, (features.to(self.device, torch.float32), operators.to(self.device)))

    # -- the interface

    def fit(self, pairs: Sequence[ShapePair]) -> list[float]:
        """Train on pairs; returns the loss per step (empty for training-free heads)."""
        return []

    def match(self, pair: ShapePair) -> Match:
        """Predict the correspondence of ``pair.y`` to ``pair.x``."""
        raise NotImplementedError

    def save(self, folder: str | os.PathLike) -> Path:
        """Write ``head_config.json`` (and the weights of learned heads) into ``folder``."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        payload = {"head": self.name, "geofeat_version": __version__, "config": self.config.to_dict()}
        text = json.dumps(payload, indent=2, sort_keys=True) + "\n"
        atomic_write(folder / CONFIG_FILE, lambda tmp: tmp.write_text(text))
        return folder


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


class LearnedHead(Head):
    """A head with a torch module: the shared training loop and checkpoint format.

    Subclasses implement `build_model` (the module, from the input width), `training_loss`
    (a scalar tensor for one pair) and `predict` (a `Match` for one pair, under ``no_grad``).
    """

    def __init__(self, config: HeadConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        self.model: torch.nn.Module | None = None
        self.in_channels: int | None = None

    def build_model(self, in_channels: int) -> torch.nn.Module:
        """The trainable module for ``in_channels`` input features."""
        raise NotImplementedError

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """Scalar training loss of one pair."""
        raise NotImplementedError

    def predict(self, pair: ShapePair) -> Match:
        """The prediction for one pair (gradients off)."""
        raise NotImplementedError

    def _ensure_model(self, mesh: Mesh) -> torch.nn.Module:
        import torch

        if self.model is None:
            torch.manual_seed(self.config.seed)
            self.in_channels = int(self.shape_inputs(mesh)[0].shape[1])
            self.model = self.build_model(self.in_channels).to(self.device)
        return self.model

    def fit(self, pairs: Sequence[ShapePair]) -> list[float]:
        """Adam over ``epochs`` passes of the pairs in a seeded order; returns the loss of every step."""
        if len(pairs) == 0:
            raise HeadError(f"head {self.name!r}: no training pairs.")
        import torch

        config = self.config
        model = self._ensure_model(pairs[0].x)
        optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr)
        total = config.epochs * len(pairs)
        scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total) if config.cosine_annealing else None
        rng = np.random.default_rng(config.seed)
        losses: list[float] = []
        start = time.perf_counter()
        bar = progress_bar(total=total, desc=f"training {self.name}", unit="pair", show=config.progress)
        try:
            for _ in range(config.epochs):
                for index in rng.permutation(len(pairs)):
                    model.train()
                    try:
                        loss = self.training_loss(self.prepare(pairs[int(index)]))
                    except UnusablePair as skipped:
                        log.info("%s: skipped a training pair: %s", self.name, skipped)
                        bar.update(1)
                        continue
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if config.grad_clip is not None:
                        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
                    optimizer.step()
                    if scheduler is not None:
                        scheduler.step()
                    losses.append(float(loss.detach()))
                    bar.update(1)
                    bar.set_postfix(loss=f"{losses[-1]:.4f}")
                    if config.max_minutes is not None and time.perf_counter() - start > 60.0 * config.max_minutes:
                        log.info("%s: time budget spent after %d steps", self.name, len(losses))
                        return losses
        finally:
            bar.close()
        return losses

    def match(self, pair: ShapePair) -> Match:
        """`predict` the prepared pair with gradients off and the module in evaluation mode."""
        import torch

        pair = self.prepare(pair)
        self._ensure_model(pair.x).eval()
        with torch.no_grad():
            return self.predict(pair)

    def save(self, folder: str | os.PathLike) -> Path:
        """``head_config.json`` and ``weights.safetensors`` (the module's state dict)."""
        if self.model is None:
            raise HeadError(f"head {self.name!r} has no model yet: fit it (or load one) before saving.")
        from safetensors.torch import save_file

        folder = super().save(folder)
        state = {k: v.detach().to("cpu").contiguous() for k, v in self.model.state_dict().items()}
        atomic_write(
            folder / WEIGHTS_FILE, lambda tmp: save_file(state, str(tmp), metadata={"in_channels": str(self.in_channels)})
        )
        return folder

    def load_state(self, state: dict[str, torch.Tensor], in_channels: int, source: str) -> None:
        """Build the module for ``in_channels`` and load ``state`` exactly (see `release.check_state`)."""
        from .release import check_state

        self.in_channels = int(in_channels)
        model = self.build_model(self.in_channels)
        check_state(model, state, source)
        model.load_state_dict(state, strict=True)
        self.model = model.to(self.device)

    def load_weights(self, folder: Path, in_channels: int) -> None:
        """Build the module for ``in_channels`` and load ``weights.safetensors``."""
        from safetensors.torch import load_file

        self.in_channels = in_channels
        self.model = self.build_model(in_channels).to(self.device)
        try:
            self.model.load_state_dict(load_file(str(folder / WEIGHTS_FILE), device=str(self.device)))
        except (RuntimeError, OSError) as exc:
            raise HeadError(f"{folder / WEIGHTS_FILE} does not fit head {self.name!r}: {exc}") from exc
        except Exception as exc:  # safetensors' SafetensorError on a damaged file
            raise HeadError(f"{folder / WEIGHTS_FILE} is not a readable safetensors file (truncated or damaged?): {exc}") from exc


#: name -> "module:Class" (imported on first use)
#: Head names: `geofeat.registry.LazyEntry` values (or bare ``"module:Class"`` strings), imported on first use.
HEADS: dict[str, LazyEntry | str] = {
    "nn": LazyEntry("nn", "geofeat.adapters.heads:NearestNeighbourHead", summary="nearest neighbour in feature space"),
    "fmap": LazyEntry("fmap", "geofeat.adapters.heads:FunctionalMapHead", summary="functional map from the input features"),
    "ulrssm": LazyEntry(
        "ulrssm",
        "geofeat.adapters.ulrssm:ULRSSMHead",
        summary="ULRSSM: unsupervised DiffusionNet features, functional-map losses",
    ),
    "dpfm": LazyEntry("dpfm", "geofeat.adapters.dpfm:DPFMHead", summary="DPFM: supervised, overlap-aware functional maps"),
    "echomatch": LazyEntry(
        "echomatch", "geofeat.adapters.echomatch:EchoMatchHead", summary="EchoMatch: overlap by correspondence reflection"
    ),
}


def head_class(name: str) -> type[Head]:
    """The `Head` subclass registered under ``name`` (`HeadError` for an unknown name, with suggestions)."""
    return lookup(HEADS, name, "head", HeadError).load("head")


def make_head(name: str, preset: str | None = None, **settings: Any) -> Head:
    """Build the head ``name`` from keyword settings of its configuration.

    Parameters
    ----------
    name : str
        A key of `HEADS`.
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
    folder = Path(source)
    if not folder.is_dir():
        raise HeadError(f"{folder} is not a folder; expected one written by Head.save ({CONFIG_FILE} and {WEIGHTS_FILE}).")
    try:
        payload = json.loads((folder / CONFIG_FILE).read_text())
    except (OSError, ValueError) as exc:
        raise HeadError(f"{folder} holds no readable {CONFIG_FILE}: {exc}") from exc
    if not isinstance(payload, dict) or not isinstance(payload.get("config", {}), dict):
        raise HeadError(
            f"{folder / CONFIG_FILE} is not a head configuration: expected an object with 'head' (a name) and "
            "'config' (an object of settings), as Head.save writes."
        )
    cls = head_class(payload.get("head", ""))
    head = cls(cls.config_class.from_dict(payload.get("config", {})))
    if isinstance(head, LearnedHead):
        head.load_weights(folder, _saved_in_channels(folder / WEIGHTS_FILE))
    return head


def _saved_in_channels(path: Path) -> int:
    """The input width recorded in the metadata of a head's ``weights.safetensors``.

    Raises
    ------
    HeadError
        If the file is missing, unreadable or damaged, or has no ``in_channels`` entry.
    """
    from safetensors import safe_open

    if not path.is_file():
        raise HeadError(f"{path} is missing: a learned head's folder holds its weights there (Head.save writes it).")
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
    except Exception as exc:  # safetensors raises its own SafetensorError, and OSError
        raise HeadError(
            f"{path} is not a readable safetensors file (truncated or damaged?): {exc}. Save the head again."
        ) from exc
    try:
        return int(metadata["in_channels"])
    except (KeyError, ValueError) as exc:
        raise HeadError(f"{path} has no valid 'in_channels' entry in its metadata; it was not written by Head.save.") from exc


def _from_release(name: str, checkpoint: Path, preset: str, settings: dict[str, Any]) -> LearnedHead:
    """`load_head` with a release checkpoint."""
    cls = head_class(name)
    release_state = getattr(cls, "release_state", None)
    if not issubclass(cls, LearnedHead) or release_state is None:
        raise HeadError(f"head {name!r} cannot load release checkpoints; heads that can: ulrssm, dpfm, echomatch.")
    if checkpoint.is_dir():
        raise HeadError(
            f"release checkpoint {checkpoint} is a folder; expected the authors' .pth file. "
            "A folder saved by geofeat (head_config.json + weights.safetensors) loads with load_head(folder)."
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
