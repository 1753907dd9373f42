"""Descriptors: the `Descriptor` contract, the registry and `compute`."""

from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.collection import compute_many
from geofeat.descriptors.compute import compute
from geofeat.descriptors.registry import (
    DescriptorInfo,
    RegistryEntry,
    as_descriptor,
    descriptor_class,
    descriptors,
    make_descriptor,
    register,
)

__all__ = [
    "Descriptor",
    "DescriptorInfo",
    "RegistryEntry",
    "as_descriptor",
    "compute",
    "compute_many",
    "descriptor_class",
    "descriptors",
    "make_descriptor",
    "register",
]
