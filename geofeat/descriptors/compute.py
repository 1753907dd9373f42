"""`compute`: one call from a mesh (or file) and a descriptor name to cached features."""

from __future__ import annotations

import logging
import os

import numpy as np

import geofeat
from geofeat.cache import FeatureCache, cache_key
from geofeat.descriptors.registry import make_descriptor
from geofeat.errors import CacheError
from geofeat.mesh import Mesh, load_mesh

log = logging.getLogger(__name__)

CacheArg = bool | str | os.PathLike | FeatureCache | None


def resolve_cache(cache: CacheArg) -> FeatureCache | None:
    """Turn the ``cache`` argument into a store (or None for no caching).

    ``True``: the default store; ``False``/``None``: no cache; a path: a store there; a
    `FeatureCache`: itself.
    """
    if cache is True:
        return FeatureCache()
    if cache is False or cache is None:
        return None
    if isinstance(cache, FeatureCache):
        return cache
    if isinstance(cache, (str, os.PathLike)):
        return FeatureCache(cache)
    raise CacheError(f"cache must be True, False, a directory path or a FeatureCache; found {type(cache).__name__}.")


def compute(mesh_or_path: Mesh | str | os.PathLike, name: str, cache: CacheArg = True, **params) -> np.ndarray:
    """Per-vertex features of a mesh.

    Parameters
    ----------
    mesh_or_path : Mesh or path
        A `Mesh`, or a ``.off``/``.obj``/``.ply`` file read with `load_mesh`.
    name : str
        Registered descriptor name (see `geofeat.descriptors()`).
    cache : bool, path or FeatureCache
        Where to look up and store the result; ``False`` computes without caching.
    **params
        Descriptor parameters (an unknown one raises an error listing the valid ones).

    Returns
    -------
    numpy.ndarray, shape (V, dim), float32, C-contiguous
    """
    mesh = mesh_or_path if isinstance(mesh_or_path, Mesh) else load_mesh(mesh_or_path)
    descriptor = make_descriptor(name, **params)
    store = resolve_cache(cache)
    if store is None:
        return descriptor(mesh)
    params_json = descriptor.params_json()
    weights = descriptor.weights_digest()
    key = cache_key(mesh.hash, descriptor.name, params_json, descriptor.version, weights)
    hit = store.get(key)
    if hit is not None:
        log.debug("cache hit %s for %s on %r", key[:12], descriptor.name, mesh.name)
        return np.ascontiguousarray(hit, dtype=np.float32)
    features = descriptor(mesh)
    meta = {
        "mesh_hash": mesh.hash,
        "mesh_name": mesh.name,
        "descriptor": descriptor.name,
        "params": params_json,
        "descriptor_version": descriptor.version,
        "weights_digest": weights,
        "geofeat_version": geofeat.__version__,
    }
    store.put(key, features, meta)
    return features
