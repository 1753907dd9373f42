"""The names of the heads: `HEADS`, `register_head`, `head_class`.

Every head is registered under a name with its ``"module:Class"`` target, imported on first
use, so that listing the heads loads neither torch nor a head's module. The rules are those
of every geofeat registry (`geofeat.registry.Registry`): names are case-insensitive and
``-`` equals ``_``; a taken name is refused unless ``overwrite=True``.
"""

from __future__ import annotations

from geofeat.adapters.base import Head
from geofeat.errors import HeadError
from geofeat.registry import LazyEntry, Registry

__all__ = ["HEADS", "head_class", "register_head"]

#: The registered heads (`geofeat.registry.Registry` of `geofeat.registry.LazyEntry`).
HEADS = Registry("head", HeadError)


def register_head(name: str, target: str | type[Head], *, summary: str = "", overwrite: bool = False) -> None:
    """Make a head available by name (`geofeat.adapters.heads.make_head`, `load_head`).

    Parameters
    ----------
    name : str
        Head name (case-insensitive; ``-`` and ``_`` are equivalent); the head class's
        ``name`` should be the same, since `Head.save` records that one.
    target : str or type
        ``"module:Class"``, imported on first use, or the `Head` subclass itself.
    summary : str
        One line for listings.
    overwrite : bool
        Replace an entry of the same name instead of raising.

    Raises
    ------
    HeadError
        The name is already registered and ``overwrite`` is false.
    """
    HEADS.register(LazyEntry(name, target, summary=summary), overwrite=overwrite)


def head_class(name: str) -> type[Head]:
    """The `Head` subclass registered under ``name`` (`HeadError` for an unknown name, with suggestions)."""
    return HEADS.load(name)


register_head("nn", "geofeat.adapters.matchers:NearestNeighbourHead", summary="nearest neighbour in feature space")
register_head("fmap", "geofeat.adapters.matchers:FunctionalMapHead", summary="functional map from the input features")
register_head(
    "ulrssm", "geofeat.adapters.ulrssm:ULRSSMHead", summary="ULRSSM: unsupervised DiffusionNet features, functional-map losses"
)
register_head("dpfm", "geofeat.adapters.dpfm.head:DPFMHead", summary="DPFM: supervised, overlap-aware functional maps")
register_head(
    "echomatch", "geofeat.adapters.echomatch.head:EchoMatchHead", summary="EchoMatch: overlap by correspondence reflection"
)
