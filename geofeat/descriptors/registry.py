"""The registry of descriptor names: lazy imports and clear errors for missing extras (`geofeat.registry`).

Names follow the rule of every geofeat registry: case-insensitive, ``-`` equals ``_``, and
registering a name that exists raises `DescriptorError` unless ``overwrite=True``.
"""

from __future__ import annotations

from dataclasses import dataclass

from geofeat.descriptors.base import Descriptor
from geofeat.errors import DescriptorError
from geofeat.registry import LazyEntry, Registry

#: How to build one descriptor: ``LazyEntry(name, "module:ClassName", requires, extra, summary)``.
RegistryEntry = LazyEntry


@dataclass(frozen=True)
class DescriptorInfo:
    """What `geofeat.descriptors()` reports for one name."""

    name: str
    available: bool
    reason: str
    summary: str
    params: dict


_REGISTRY = Registry("descriptor", DescriptorError)


def register(entry: RegistryEntry, overwrite: bool = False) -> None:
    """Make a descriptor available by name (``geofeat.compute(mesh, name)``).

    Parameters
    ----------
    entry : RegistryEntry
        ``RegistryEntry(name, "module:ClassName", requires=..., extra=..., summary=...)``; the
        target may also be the `Descriptor` subclass itself. The name is stored in canonical
        form (lower case, ``_`` for ``-``).
    overwrite : bool
        Replace an entry of the same name instead of raising.

    Raises
    ------
    DescriptorError
        The name is already registered and ``overwrite`` is false.
    """
    _REGISTRY.register(entry, overwrite=overwrite)


register(RegistryEntry("hks", "geofeat.descriptors.spectral:HKS", summary="Heat Kernel Signature, log-spaced times"))
register(RegistryEntry("wks", "geofeat.descriptors.spectral:WKS", summary="Wave Kernel Signature (ULRSSM/pyFM definition)"))
register(
    RegistryEntry("shot", "geofeat.descriptors.shot:SHOT", summary="SHOT histograms of normal orientations (pyshot definition)")
)
register(
    RegistryEntry(
        "dinov2",
        "geofeat.descriptors.dino:DINOv2",
        requires=("transformers",),
        extra="dino",
        summary="DINOv2 features from multi-view renders, back-projected to vertices",
    )
)
register(
    RegistryEntry(
        "dinov3",
        "geofeat.descriptors.dino:DINOv3",
        requires=("transformers",),
        extra="dino",
        summary="DINOv3 features from multi-view renders, back-projected to vertices",
    )
)


register(
    RegistryEntry(
        "geolora",
        "geofeat.descriptors.dino:GeoLoRA",
        requires=("transformers", "peft", "safetensors"),
        extra="dino",
        summary="GeoLoRA: DINOv3 + a LoRA trained on partial shapes, back-projected from multi-view renders",
    )
)


def descriptor_entry(name: str) -> RegistryEntry:
    """The registry entry of ``name``, not imported: its optional modules (``requires``), ``extra`` and ``summary``.

    Raises
    ------
    DescriptorError
        Unknown name (the message lists the valid ones).
    """
    return _REGISTRY.entry(name)


def descriptor_class(name: str) -> type[Descriptor]:
    """The `Descriptor` subclass registered under ``name``, imported now.

    Raises
    ------
    DescriptorError
        Unknown name (the message lists the valid ones).
    MissingDependencyError
        An optional dependency is missing (the message names the extra to install).
    """
    return _REGISTRY.load(name)


def make_descriptor(name: str, **params) -> Descriptor:
    """Build the descriptor ``name`` from keyword parameters, rejecting unknown ones.

    Build a model-backed descriptor (DINOv2, DINOv3, GeoLoRA) once and pass the instance to
    `geofeat.compute` for every mesh: it loads its weights on first use and keeps them.

    Parameters
    ----------
    name : str
        A registered name (see `descriptors`; case-insensitive, ``-`` equals ``_``).
    **params
        The descriptor's parameters; the defaults of the others.

    Returns
    -------
    Descriptor
        Not run yet; no weights are loaded here.

    Raises
    ------
    DescriptorError
        Unknown name or parameter (the message lists the valid ones), or a bad value.
    MissingDependencyError
        An optional dependency is missing (the message names the extra to install).

    Examples
    --------
    >>> from geofeat.descriptors import make_descriptor
    >>> make_descriptor("wks", n_descr=64)
    WKS(n_eig=128, n_descr=64, laplacian='robust', normalize=True)
    """
    cls = descriptor_class(name)
    valid = cls.param_names()
    unknown = sorted(set(params) - set(valid))
    if unknown:
        defaults = ", ".join(f"{k}={v!r}" for k, v in cls.param_defaults().items())
        raise DescriptorError(f"unknown parameter(s) {unknown} for descriptor {name!r}; valid parameters: {defaults}.")
    return cls(**params)


def as_descriptor(descriptor: str | Descriptor, **params) -> Descriptor:
    """A `Descriptor` from a registered name and parameters, or an instance as it is.

    Parameters
    ----------
    descriptor : str or Descriptor
        A registered name (built with `make_descriptor`) or an instance (used as it is).
    **params
        Parameters for a name; none may be given with an instance.

    Raises
    ------
    DescriptorError
        An instance together with parameters, a class instead of an instance, anything else
        that is neither, or what `make_descriptor` raises.
    """
    if isinstance(descriptor, Descriptor):
        if params:
            raise DescriptorError(
                f"parameters {sorted(params)} were given with the descriptor instance {descriptor!r}; "
                f"set them on the instance ({type(descriptor).__name__}(...)) or pass the name "
                f"({descriptor.name!r}) with the parameters, not both."
            )
        return descriptor
    if isinstance(descriptor, type) and issubclass(descriptor, Descriptor):
        raise DescriptorError(
            f"expected a descriptor name or instance; found the class {descriptor.__name__}. "
            f"Pass an instance: {descriptor.__name__}() (parameters as keywords)."
        )
    if not isinstance(descriptor, str):
        raise DescriptorError(
            f"expected a registered descriptor name (e.g. 'wks') or a Descriptor instance; "
            f"found {descriptor!r} ({type(descriptor).__name__})."
        )
    return make_descriptor(descriptor, **params)


def descriptors() -> list[DescriptorInfo]:
    """Every registered descriptor, whether it can run here and why not.

    Returns
    -------
    list of DescriptorInfo
        Sorted by name.
    """
    infos = []
    for name in _REGISTRY.names():
        entry = _REGISTRY.entry(name)
        missing = entry.missing()
        if missing:
            reason = f"missing {', '.join(missing)}: {entry.install_hint(missing)}"
            infos.append(DescriptorInfo(name, False, reason, entry.summary, {}))
            continue
        cls = descriptor_class(name)
        infos.append(DescriptorInfo(name, True, "ok", entry.summary, cls.param_defaults()))
    return infos
