"""Descriptors: the `Descriptor` contract, the registry and `compute`."""

from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.compute import compute
from geofeat.descriptors.registry import DescriptorInfo, RegistryEntry, descriptor_class, descriptors, make_descriptor, register

__all__ = ["Descriptor", "DescriptorInfo", "RegistryEntry", "compute", "descriptor_class", "descriptors", "make_descriptor", "register"]
