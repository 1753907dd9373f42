"""`compute`: the features of one mesh, through the feature cache.

`lookup_or_compute` reads an entry or computes and stores it; `FeatureStorage` carries the
store and whether writing it is required. Over a collection, `geofeat.descriptors.collection`
runs the same steps (`geofeat.descriptors.collection.compute_each`, `compute_many`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from geofeat._version import __version__
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.cache import FeatureCache, cache_key
from geofeat.descriptors.registry import as_descriptor
from geofeat.errors import CacheError
from geofeat.mesh import Mesh, as_mesh

log = logging.getLogger(__name__)

CacheArg = bool | str | os.PathLike | FeatureCache | None
MeshLike = Mesh | str | os.PathLike | tuple | object
DescriptorArg = str | Descriptor

#: Roots of default stores already reported as not writable (warned once per process).
_UNWRITABLE_WARNED: set[str] = set()


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


def entry_key(descriptor: Descriptor, mesh: Mesh) -> str:
    """The feature-store key of ``descriptor`` on ``mesh`` (see `geofeat.descriptors.cache.cache_key`): what `compute` looks up."""
    return cache_key(mesh.hash, descriptor.name, descriptor.params_json(), descriptor.version, descriptor.weights_digest())


def compute(mesh_or_path: MeshLike, descriptor: DescriptorArg, cache: CacheArg = True, **params) -> np.ndarray:
    """Per-vertex features of a mesh.

    Parameters
    ----------
    mesh_or_path : Mesh, path, (verts, faces) or trimesh object
        A `Mesh`; a ``.off``/``.obj``/``.ply`` file read with `load_mesh`; a pair
        ``(verts, faces)`` of arrays (``faces`` None for a point cloud); a
        ``trimesh.Trimesh`` or ``trimesh.PointCloud`` (see `geofeat.mesh.as_mesh`).
    descriptor : str or Descriptor
        A registered descriptor name (see `geofeat.descriptors()`), built with ``**params``
        on every call, or a descriptor instance (``WKS(n_descr=64)``,
        `geofeat.descriptors.make_descriptor`), used as it is. A model-backed descriptor
        (DINOv2, DINOv3, GeoLoRA) loads its weights once per instance: build it once and
        pass the instance for every mesh.
    cache : bool, path or FeatureCache
        Where to look up and store the result; ``False`` computes without caching. When the
        default store (``True``) cannot be written (a read-only file system), the features
        are computed without caching and a warning is logged once. A store named here (a
        path or a `FeatureCache`) that cannot be written raises `CacheError` instead.
    **params
        Descriptor parameters with a name (an unknown one raises an error listing the valid
        ones); none with an instance. NumPy scalars are accepted; booleans must be booleans.

    Returns
    -------
    numpy.ndarray, shape (V, dim), float32, C-contiguous
        Finite values; non-finite output raises `DescriptorError` and is never cached.

    Raises
    ------
    MeshError
        An input that is not a mesh (the message lists what is accepted) or a malformed one.
    DescriptorError
        Unknown descriptor or parameter, bad parameter value, parameters given with an
        instance, non-finite features.
    CacheError
        A store named by ``cache`` cannot be written.
    """
    mesh = as_mesh(mesh_or_path)
    descriptor = as_descriptor(descriptor, **params)
    features, _, _ = lookup_or_compute(descriptor, mesh, resolve_cache(cache), explicit=cache is not True)
    return features


def lookup_or_compute(
    descriptor: Descriptor, mesh: Mesh, store: FeatureCache | None, explicit: bool = True
) -> tuple[np.ndarray, str | None, bool]:
    """The features of ``descriptor`` on ``mesh``: read from ``store``, else computed and stored.

    Parameters
    ----------
    descriptor : Descriptor
    mesh : Mesh
    store : FeatureCache or None
        None: compute without caching.
    explicit : bool
        True: the caller named the store, which must be writable (`CacheError` before the
        work, or when the write fails). False (the default store): a failed write logs a
        warning once and the features are returned uncached.

    Returns
    -------
    features : numpy.ndarray, shape (V, dim), float32, C-contiguous
    key : str or None
        The store key (`entry_key`); None without a store.
    present : bool
        True when the features were read from the store.

    Raises
    ------
    DescriptorError
        Features of the wrong shape or not finite (nothing is written).
    CacheError
        ``explicit`` and the store cannot be written.
    """
    return FeatureStorage(store, required=explicit).lookup_or_compute(descriptor, mesh)


@dataclass(frozen=True, eq=False)
class StoreLookup:
    """What `FeatureStorage.look_up` found in a store.

    Attributes
    ----------
    key : str or None
        The store key (`entry_key`); None without a store.
    features : numpy.ndarray or None
        The entry's features, shape (V, dim), float32, C-contiguous; None when the entry is
        missing (or there is no store).
    """

    key: str | None
    features: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class FeatureStorage:
    """Where features are looked up and written, and whether writing them is required.

    Attributes
    ----------
    store : FeatureCache or None
        None: nothing is looked up or written.
    required : bool
        True: the caller named the store, which must be writable (`CacheError` before the
        work, or when the write fails). False (the default store): a failed write logs a
        warning once and the features are returned uncached.
    """

    store: FeatureCache | None
    required: bool = True

    def look_up(self, descriptor: Descriptor, mesh: Mesh) -> StoreLookup:
        """The store entry of ``descriptor`` on ``mesh``, if there is one: the first half of `lookup_or_compute`.

        Raises
        ------
        CacheError
            The entry is missing, writing is required and the store cannot be written
            (checked here, before any work).
        """
        if self.store is None:
            return StoreLookup(None)
        key = entry_key(descriptor, mesh)
        hit = self.store.get(key, n_rows=mesh.n_vertices)
        if hit is not None:
            log.debug("cache hit %s for %s on %r", key[:12], descriptor.name, mesh.name)
            return StoreLookup(key, np.ascontiguousarray(hit, dtype=np.float32))
        if self.required:
            self.store.check_writable()  # fail before the work, not after it
        return StoreLookup(key)

    def lookup_or_compute(self, descriptor: Descriptor, mesh: Mesh) -> tuple[np.ndarray, str | None, bool]:
        """`lookup_or_compute` with this store and policy: ``(features, key, present)``."""
        found = self.look_up(descriptor, mesh)
        if found.features is not None:
            return found.features, found.key, True
        features = descriptor(mesh)
        self.write(descriptor, mesh, found.key, features)
        return features, found.key, False

    def write(self, descriptor: Descriptor, mesh: Mesh, key: str | None, features: np.ndarray) -> None:
        """Write the checked ``features`` of ``mesh`` as the entry ``key`` (nothing without a store).

        Parameters
        ----------
        descriptor : Descriptor
        mesh : Mesh
            V vertices.
        key : str or None
            The entry (`look_up`'s ``key``).
        features : numpy.ndarray, shape (V, dim), float32

        Raises
        ------
        CacheError
            Writing is required and the write failed (else a warning, once per store).
        """
        if self.store is None or key is None:  # no store: nothing to write (with one, look_up always gives a key)
            return
        meta = {
            "mesh_hash": mesh.hash,
            "mesh_name": mesh.name,
            "descriptor": descriptor.name,
            "params": descriptor.params_json(),
            "descriptor_version": descriptor.version,
            "weights_digest": descriptor.weights_digest(),
            "geofeat_version": __version__,
        }
        try:
            self.store.put(key, features, meta)
        except CacheError as err:
            if self.required:
                raise
            root = str(self.store.root)
            if root not in _UNWRITABLE_WARNED:
                _UNWRITABLE_WARNED.add(root)
                log.warning("features are computed without caching (this warning is shown once): %s", err)
