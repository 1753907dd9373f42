"""Benchmark datasets by name: `load_dataset`, `dataset_names`, `register_dataset`.

>>> from geofeat.datasets import load_dataset
>>> pairs = load_dataset("faust_r", "../shared/data", split="test")   # folder holding FAUST_r/
>>> len(pairs), pairs.pair_names[0]
(380, 'tr_reg_080->tr_reg_081')
>>> pair = pairs[0]                                # ShapePair, meshes read now

Names follow the rule of every geofeat registry (`geofeat.registry.Registry`): case-insensitive,
``-`` equals ``_``, and registering a name that exists raises `DatasetError` unless ``overwrite=True``. Each name is a loader plus the options it fixes
(``shrec16_cuts`` is the SHREC'16 loader with ``partiality="cuts"``): a `geofeat.registry.LazyEntry`
whose loader module is imported when the dataset is first opened.
"""

from __future__ import annotations

import inspect
import logging
import os
from collections.abc import Callable

from geofeat.datasets.base import PairDataset
from geofeat.datasets.faust import FaustRemeshed, ScapeRemeshed
from geofeat.errors import DatasetError
from geofeat.registry import LazyEntry, Registry, canonical_name

log = logging.getLogger(__name__)

_REGISTRY = Registry("dataset", DatasetError)


def register_dataset(
    name: str, factory: Callable[..., PairDataset] | str, *, description: str = "", overwrite: bool = False, **fixed
) -> None:
    """Make ``factory`` available as ``load_dataset(name, ...)``.

    Parameters
    ----------
    name : str
        Dataset name (case-insensitive; ``-`` and ``_`` are equivalent).
    factory : callable or str
        Called as ``factory(root, split, **fixed, **options)``; returns a `PairDataset` (or
        any sequence of `ShapePair` with ``pair_names``). A ``"module:attr"`` string is
        imported when the dataset is first opened.
    description : str
        One line for listings.
    overwrite : bool
        Replace an existing entry instead of raising.
    **fixed
        Options fixed by this name; a caller passing a different value gets an error.

    Raises
    ------
    DatasetError
        The name is already registered and ``overwrite`` is false.
    """
    _REGISTRY.register(LazyEntry(name, factory, summary=description, options=dict(fixed)), overwrite=overwrite)


def dataset_names() -> list[str]:
    """Names accepted by `load_dataset`, sorted."""
    return _REGISTRY.names()


def dataset_description(name: str) -> str:
    """The one-line description of a registered dataset."""
    return _REGISTRY.entry(name).summary


def dataset_options(name: str) -> set[str] | None:
    """The options ``load_dataset(name, ...)`` takes besides ``root`` and ``split``.

    Returns
    -------
    set of str or None
        The loader's keyword options without those the name fixes; None when the loader
        takes any keyword (``**kwargs``). Opening the name imports its loader module.
    """
    entry = _REGISTRY.entry(name)
    accepted = _accepted_options(entry.load("dataset"))
    return None if accepted is None else accepted - set(entry.options)


def load_dataset(name: str, root: str | os.PathLike | None = None, split: str = "test", **options) -> PairDataset:
    """Open a benchmark dataset by name.

    Parameters
    ----------
    name : str
        One of `dataset_names` (for example ``"faust_r"``, ``"shrec16_cuts"``, ``"becos_p2p"``).
    root : path-like or None
        The dataset's folder, or a folder that contains it under its usual name (so one data
        folder can serve every dataset). None: ``$GEOFEAT_DATA``.
    split : str
        ``"test"`` by default; the loaders document their splits.
    **options
        Loader options (see each loader). ``seed`` is accepted by every name and ignored by
        the file-based datasets, whose pairs are fixed.

    Returns
    -------
    PairDataset
        A lazy sequence of `ShapePair`; files are read when a pair is requested.

    Raises
    ------
    DatasetError
        Unknown name, an option the loader does not take or that contradicts the name, or a
        missing or malformed dataset.
    """
    entry = _REGISTRY.entry(name)
    factory = entry.load("dataset")
    for key, value in entry.options.items():
        if key in options and options[key] != value:
            raise DatasetError(f"dataset {canonical_name(name)!r} fixes {key}={value!r}; found {key}={options[key]!r}.")
    options = {**options, **entry.options}
    accepted = _accepted_options(factory)
    if accepted is not None:
        if "seed" in options and "seed" not in accepted:
            log.debug("dataset %r has fixed pairs; seed=%r ignored", name, options.pop("seed"))
        unknown = sorted(set(options) - accepted)
        if unknown:
            raise DatasetError(
                f"dataset {canonical_name(name)!r} does not take option(s) {', '.join(unknown)}; "
                f"it takes: {', '.join(sorted(accepted - set(entry.options))) or 'none'}."
            )
    return factory(root, split, **options)


def _accepted_options(factory: Callable) -> set[str] | None:
    """Keyword options ``factory`` takes besides root and split; None when it takes ``**kwargs``."""
    try:
        parameters = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return None
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        return None
    return {p.name for p in parameters if p.kind is not inspect.Parameter.VAR_POSITIONAL} - {"root", "split", "self"}


def _register_builtins() -> None:
    shrec16, pfaust = "geofeat.datasets.shrec16:Shrec16Partial", "geofeat.datasets.pfaust:PFaust"
    synthetic, remeshed = (
        "geofeat.datasets.derived:synthetic_partial_benchmark",
        "geofeat.datasets.derived:remeshed_partial_benchmark",
    )
    register_dataset("faust_r", "geofeat.datasets.faust:FaustRemeshed", description="FAUST_r full-to-full (ULRSSM split 80/20)")
    register_dataset("scape_r", "geofeat.datasets.faust:ScapeRemeshed", description="SCAPE_r full-to-full (ULRSSM split 51/20)")
    for kind in ("cuts", "holes"):
        register_dataset(f"shrec16_{kind}", shrec16, partiality=kind, description=f"SHREC'16 Partial {kind.upper()}, P2F")
    for short, difficulty in (("m", "medium"), ("h", "hard")):
        register_dataset(
            f"pfaust_{short}", pfaust, difficulty=difficulty, description=f"PFAUST-{short.upper()} ({difficulty}), P2F"
        )
    for protocol, setting in (("f2f", "full_full"), ("p2f", "partial_full"), ("p2p", "partial_partial")):
        register_dataset(
            f"becos_{protocol}",
            "geofeat.datasets.becos:BeCoS",
            setting=setting,
            description=f"BeCoS {setting}, {protocol.upper()}",
        )
    register_dataset("psmal", "geofeat.datasets.psmal:PartialSmal", description="PARTIALSMAL, P2P")
    register_dataset("cp2p24", "geofeat.datasets.cp2p24:CP2P24", description="CP2P24, P2P")
    for kind in ("cuts", "holes", "ray"):
        register_dataset(
            f"synthetic_{kind}",
            synthetic,
            kind=kind,
            protocol="p2f",
            description=f"built-in synthetic humans, {kind.upper()} partial to full (no data needed)",
        )
        for prefix, loader in (("faust_r", FaustRemeshed), ("scape_r", ScapeRemeshed)):
            register_dataset(
                f"{prefix}_{kind}",
                remeshed,
                loader=loader,
                kind=kind,
                protocol="p2f",
                description=f"{loader.title} {kind.upper()} partial shapes matched to full shapes (seeded)",
            )
    scans = "geofeat.datasets.scans:"
    register_dataset(
        "synthetic_scans",
        scans + "synthetic_scan_benchmark",
        description="built-in synthetic humans, depth scans (point clouds) matched to full shapes (no data needed)",
    )
    for prefix, loader in (("faust_r", FaustRemeshed), ("scape_r", ScapeRemeshed)):
        register_dataset(
            f"{prefix}_scans",
            scans + "remeshed_scan_benchmark",
            loader=loader,
            description=f"{loader.title} depth scans (point clouds) matched to full shapes (seeded)",
        )
    register_dataset(
        "synthetic_p2p",
        synthetic,
        kind="cuts",
        protocol="p2p",
        description="built-in synthetic humans, two CUTS partial shapes (no data needed)",
    )
    for prefix, loader in (("faust_r", FaustRemeshed), ("scape_r", ScapeRemeshed)):
        register_dataset(
            f"{prefix}_p2p",
            remeshed,
            loader=loader,
            kind="cuts",
            protocol="p2p",
            description=f"{loader.title} two CUTS partial shapes of different shapes (seeded)",
        )


_register_builtins()
