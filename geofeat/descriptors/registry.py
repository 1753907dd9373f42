"""The registry of descriptor names: lazy imports and clear errors for missing extras."""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass, field

from geofeat.descriptors.base import Descriptor
from geofeat.errors import DescriptorError, MissingDependencyError


@dataclass(frozen=True)
class RegistryEntry:
    """How to build one descriptor.

    Attributes
    ----------
    name : str
        Registry name.
    target : str
        ``"module:ClassName"`` of the `Descriptor` subclass, imported on first use.
    requires : tuple of str
        Modules that must be importable.
    extra : str or None
        The ``pip install geofeat[extra]`` that provides them.
    summary : str
        One line for listings.
    """

    name: str
    target: str
    requires: tuple[str, ...] = field(default_factory=tuple)
    extra: str | None = None
    summary: str = ""


@dataclass(frozen=True)
class DescriptorInfo:
    """What `geofeat.descriptors()` reports for one name."""

    name: str
    available: bool
    reason: str
    summary: str
    params: dict


_REGISTRY: dict[str, RegistryEntry] = {}


def register(entry: RegistryEntry) -> None:
    """Add (or replace) a registry entry."""
    _REGISTRY[entry.name] = entry


register(RegistryEntry("hks", "geofeat.descriptors.spectral:HKS", summary="Heat Kernel Signature, log-spaced times"))
register(RegistryEntry("wks", "geofeat.descriptors.spectral:WKS", summary="Wave Kernel Signature (ULRSSM/pyFM definition)"))
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
        summary="GeoLoRA: DINOv3 + a LoRA adapter trained on partial shapes, back-projected from multi-view renders",
    )
)


def _missing_modules(entry: RegistryEntry) -> list[str]:
    return [module for module in entry.requires if importlib.util.find_spec(module) is None]


def _unknown_name_error(name: str) -> DescriptorError:
    return DescriptorError(f"unknown descriptor {name!r}; valid names: {', '.join(sorted(_REGISTRY))}.")


def descriptor_class(name: str) -> type[Descriptor]:
    """The `Descriptor` subclass registered under ``name``, imported now.

    Raises
    ------
    DescriptorError
        Unknown name (the message lists the valid ones).
    MissingDependencyError
        An optional dependency is missing (the message names the extra to install).
    """
    entry = _REGISTRY.get(name)
    if entry is None:
        raise _unknown_name_error(name)
    missing = _missing_modules(entry)
    if missing:
        hint = f"pip install 'geofeat[{entry.extra}]'" if entry.extra else f"pip install {' '.join(missing)}"
        raise MissingDependencyError(f"descriptor {name!r} needs {', '.join(missing)}, which is not installed: {hint}")
    module_name, class_name = entry.target.split(":")
    return getattr(importlib.import_module(module_name), class_name)


def make_descriptor(name: str, **params) -> Descriptor:
    """Build the descriptor ``name`` from keyword parameters, rejecting unknown ones."""
    cls = descriptor_class(name)
    valid = cls.param_names()
    unknown = sorted(set(params) - set(valid))
    if unknown:
        defaults = ", ".join(f"{k}={v!r}" for k, v in cls.param_defaults().items())
        raise DescriptorError(f"unknown parameter(s) {unknown} for descriptor {name!r}; valid parameters: {defaults}.")
    return cls(**params)


def descriptors() -> list[DescriptorInfo]:
    """Every registered descriptor, whether it can run here and why not.

    Returns
    -------
    list of DescriptorInfo
        Sorted by name.
    """
    infos = []
    for name in sorted(_REGISTRY):
        entry = _REGISTRY[name]
        missing = _missing_modules(entry)
        if missing:
            reason = f"missing {', '.join(missing)}: pip install 'geofeat[{entry.extra}]'"
            infos.append(DescriptorInfo(name, False, reason, entry.summary, {}))
            continue
        cls = descriptor_class(name)
        infos.append(DescriptorInfo(name, True, "ok", entry.summary, cls.param_defaults()))
    return infos
