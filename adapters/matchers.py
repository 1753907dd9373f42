"""Training-free matchers and their heads: nearest neighbours in feature space (``nn``) and functional maps (+ ZoomOut, ``fmap``).

`nn_match` and `fmap_match` take per-vertex features of any geofeat descriptor and return a complete point map
``map_yx`` (V_y,) int64 from the source ``y`` to the target ``x``, the convention of
`geofeat.datasets.ShapePair`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from geofeat.adapters.base import FEATURES_KEPT, Head, HeadConfig
from geofeat.adapters.blocks import functional_maps as fm
from geofeat.adapters.blocks.functional_maps import NearestNeighborIndex
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import FunctionalMapError
from geofeat.geometry.spectral import spectral_basis
from geofeat.mesh import Mesh
from geofeat.storage.lru import LRUCache

if TYPE_CHECKING:
    import torch


def _check_features(feat, mesh: Mesh | None, name: str) -> np.ndarray:
    arr = np.asarray(feat)
    if arr.ndim != 2:
        raise FunctionalMapError(f"{name} must be a (n_vertices, n_channels) array; found shape {arr.shape}.")
    if mesh is not None and arr.shape[0] != mesh.n_vertices:
        raise FunctionalMapError(f"{name} has {arr.shape[0]} rows but mesh {mesh.name!r} has {mesh.n_vertices} vertices.")
    return arr


def nn_match(feat_x, feat_y, device: str | torch.device = "cpu") -> np.ndarray:
    """Match every vertex of ``y`` to the vertex of ``x`` with the nearest feature vector.

    Parameters
    ----------
    feat_x : array_like, shape (V_x, C), or NearestNeighborIndex
        Target features, or a `NearestNeighborIndex` of them: built once, it saves the
        reference's set-up (principal axes, float32 copy) when one target is matched to
        several sources.
    feat_y : array_like, shape (V_y, C)
        Source features (same channels).
    device : str or torch.device
        Where the exact Euclidean search runs (``"auto"``: CUDA when available); it is
        blocked, so 5k x 5k x 128 takes well under a second on a CPU.

    Returns
    -------
    numpy.ndarray, shape (V_y,), int64
        ``map_yx``.
    """
    prepared = isinstance(feat_x, NearestNeighborIndex)
    n_x = feat_x.dim if prepared else _check_features(feat_x, None, "feat_x").shape[1]
    fy = _check_features(feat_y, None, "feat_y")
    if n_x != fy.shape[1]:
        raise FunctionalMapError(f"feat_x and feat_y must have the same number of channels; found {n_x} and {fy.shape[1]}.")
    index = feat_x if prepared else NearestNeighborIndex(feat_x)
    return index.query(fy, device=device)


def fmap_match(
    mesh_x: Mesh,
    mesh_y: Mesh,
    feat_x,
    feat_y,
    k: int = 30,
    zoomout: bool = True,
    k_final: int = 100,
    zoomout_step: int = 1,
    descr_weight: float = 1.0,
    lap_weight: float = 0.3,
    laplacian_kind: str = "robust",
    n_eig: int = 128,
    device: str | torch.device = "cpu",
) -> np.ndarray:
    """Match ``y`` to ``x`` through a functional map estimated from features, optionally refined by ZoomOut.

    The pipeline: Laplace-Beltrami bases of both meshes (`spectral_basis`, cached), a
    ``(k, k)`` functional map from `fm.fmap_from_descriptors` (descriptor preservation and
    resolvent Laplacian commutativity, mass-normalised feature columns), then either its
    point map or ZoomOut from ``k`` to ``k_final``.

    Parameters
    ----------
    mesh_x, mesh_y : Mesh
        Target and source shapes.
    feat_x : array_like, shape (V_x, C)
    feat_y : array_like, shape (V_y, C)
    k : int
        Size of the functional map estimated from the features.
    zoomout : bool
        Refine with ZoomOut.
    k_final : int
        Final ZoomOut size (``k_final - k`` must be a multiple of ``zoomout_step``).
    zoomout_step : int
        ZoomOut size increase per iteration (1 in the paper).
    descr_weight, lap_weight : float
        Weights of `fm.fmap_from_descriptors`.
    laplacian_kind : {"robust", "cotan"}
        Laplacian of the bases.
    n_eig : int
        Eigenpairs computed per basis (at least ``k`` and ``k_final``); the default 128 is
        the spectral descriptors' default, so their cached bases are reused.
    device : str or torch.device
        Where the nearest-neighbour searches run.

    Returns
    -------
    numpy.ndarray, shape (V_y,), int64
        ``map_yx``.
    """
    fx = _check_features(feat_x, mesh_x, "feat_x")
    fy = _check_features(feat_y, mesh_y, "feat_y")
    if zoomout and (k_final < k or zoomout_step < 1 or (k_final - k) % zoomout_step):
        raise FunctionalMapError(
            f"need k <= k_final with k_final - k a multiple of zoomout_step >= 1; found k={k}, k_final={k_final}, step={zoomout_step}."
        )
    n_eig = max(n_eig, k, k_final) if zoomout else max(n_eig, k)
    basis_x = spectral_basis(mesh_x, n_eig, laplacian_kind)
    basis_y = spectral_basis(mesh_y, n_eig, laplacian_kind)
    c = fm.fmap_from_descriptors(basis_x, basis_y, fx, fy, k, descr_weight=descr_weight, lap_weight=lap_weight)
    if not zoomout:
        return fm.pointmap_from_fmap(c, basis_x, basis_y, device=device)
    c = fm.zoomout_refine(c, basis_x, basis_y, (k_final - k) // zoomout_step, zoomout_step, device=device)
    return fm.pointmap_from_fmap(c, basis_x, basis_y, device=device)


class NearestNeighbourHead(Head):
    """Nearest neighbour in feature space (training-free)."""

    name = "nn"

    def __init__(self, config: HeadConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        # a target is matched to several sources in a row: its search index is built once
        self._indices: LRUCache[tuple[str, str, str], NearestNeighborIndex] = LRUCache(FEATURES_KEPT)

    def match(self, pair: ShapePair) -> Match:
        pair = self.prepare(pair)
        index = self._indices.get_or_compute(self._features_key(pair.x), lambda: NearestNeighborIndex(self.features(pair.x)))
        map_yx = nn_match(index, self.features(pair.y))
        return Match(map_yx, np.ones(pair.y.n_vertices, dtype=bool))


@dataclass
class FunctionalMapConfig(HeadConfig):
    """`HeadConfig` plus the functional-map size and ZoomOut (see `fmap_match`)."""

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
        map_yx = fmap_match(
            pair.x,
            pair.y,
            self.features(pair.x),
            self.features(pair.y),
            k=c.k,
            zoomout=c.zoomout,
            k_final=c.k_final,
            n_eig=max(c.n_eig, c.k_final if c.zoomout else c.k),
        )
        return Match(map_yx, np.ones(pair.y.n_vertices, dtype=bool))
