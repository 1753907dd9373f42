"""The names of the heads: `HEADS`, `head_class`.

Every head is registered under a name with its ``"module:Class"`` target, imported on first
use, so that listing the heads loads neither torch nor a head's module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from geofeat.errors import HeadError
from geofeat.registry import LazyEntry, lookup

if TYPE_CHECKING:
    from .heads import Head

__all__ = ["HEADS", "head_class"]

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
