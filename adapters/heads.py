"""Heads by name: `make_head`, `load_head` (a saved folder or the authors' release checkpoint).

>>> head = make_head("ulrssm", descriptor="wks", epochs=5)                 # doctest: +SKIP
>>> head.fit(load_dataset("faust_r_cuts", split="train"))                  # doctest: +SKIP
>>> match = head.match(pair)              # map_yx (V_y,), overlap_y (V_y,), overlap_x (V_x,) or None
>>> head.save("runs/ulrssm"); same = load_head("runs/ulrssm")             # doctest: +SKIP

The interface is `geofeat.adapters.base` (`Head`, `HeadConfig`); the training-free heads
(``nn``, ``fmap``) are in `geofeat.adapters.matchers`; what a head reads from a pair in
`geofeat.adapters.inputs`; the shared part of the learned heads in
`geofeat.adapters.learned`; the names of the heads in `geofeat.adapters.head_registry`; the
mapping of the authors' release checkpoints in `geofeat.adapters.release`.
"""

from __future__ import annotations

import copy
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from geofeat.adapters.base import HEAD_KIND, Head
from geofeat.adapters.head_registry import head_class
from geofeat.errors import HeadError
from geofeat.storage.pretrained import CONFIG_FILE, WEIGHTS_FILE, from_pretrained
from geofeat.storage.safe_load import load_torch_file

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)

__all__ = ["load_head", "make_head", "preset_settings"]


def make_head(name: str, preset: str | None = None, **settings: Any) -> Head:
    """Build the head ``name`` from keyword settings of its configuration.

    Parameters
    ----------
    name : str
        A name of `head_registry.HEADS`.
    preset : str, optional
        The name of a set of defaults in the head's ``PRESETS`` (e.g. ``"reference"``: the
        authors' conventions): its values fill in every setting that ``settings`` do not
        give. None: the defaults of the head's configuration.
    **settings
        Fields of the head's configuration.
    """
    cls = head_class(name)
    return cls(**(preset_settings(cls, preset) | settings))


def preset_settings(cls: type[Head], preset: str | None) -> dict[str, Any]:
    """The settings of ``cls.PRESETS[preset]`` (empty for None); `HeadError` for an unknown preset."""
    if preset is None:
        return {}
    if preset not in cls.PRESETS:
        raise HeadError(f"head {cls.name!r} has no preset {preset!r}; presets: {sorted(cls.PRESETS) or 'none'}.")
    return copy.deepcopy(cls.PRESETS[preset])


def load_head(
    source: str | os.PathLike, checkpoint: str | os.PathLike | None = None, preset: str | None = None, **settings: Any
) -> Head:
    """A head saved by `Head.save`, or a head built from the authors' release checkpoint.

    Parameters
    ----------
    source : str or path-like
        A folder written by `Head.save`; or, with ``checkpoint``, a head name
        (``"ulrssm"``, ``"dpfm"``).
    checkpoint : str or path-like, optional
        A release checkpoint of the authors' code (a ``torch.save`` file). The head gets its
        ``"reference"`` preset, its sizes read from the tensors, and the weights through an
        exact key mapping (see the head's ``release_state``).
    preset : str, optional
        With ``checkpoint``: the head's preset, whose values fill in every setting that the
        checkpoint's tensors and ``settings`` do not give. None (the default) means
        ``"reference"`` (`make_head`'s None means no preset) because the released weights were
        trained with the authors' settings (input descriptor, mesh normalisation, operators).
        DPFM also has ``"reference_shrec16_cuts"`` and ``"reference_shrec16_holes"``. A saved
        folder carries its own settings: a preset without ``checkpoint`` is refused.
    **settings
        With ``checkpoint``: settings that override the preset (e.g. ``tta_steps=5``).

    Raises
    ------
    HeadError
        An unreadable file, or a checkpoint with missing, unexpected or wrongly shaped keys
        (each named).
    """
    if checkpoint is not None:
        return _from_release(str(source), Path(checkpoint), "reference" if preset is None else preset, settings)
    if preset is not None:
        raise HeadError(f"preset {preset!r} only applies with a release checkpoint; a saved head folder keeps its own settings.")
    if settings:
        raise HeadError(f"settings {sorted(settings)} only apply with a release checkpoint; change head.config instead.")
    saved = from_pretrained(source, HEAD_KIND, HeadError)
    name = saved.info.get("head")
    if not isinstance(name, str):
        raise HeadError(
            f"{saved.folder / CONFIG_FILE} names no head: expected the head's name under info.head, as Head.save "
            f"writes; found {name!r}. Save the head again."
        )
    cls = head_class(name)
    head = cls(cls.config_class.from_dict(saved.config))
    head.restore(saved)
    return head


def _from_release(name: str, checkpoint: Path, preset: str, settings: dict[str, Any]) -> Head:
    """`load_head` with a release checkpoint (heads with a ``release_state`` class method and ``load_state``)."""
    cls = head_class(name)
    release_state = getattr(cls, "release_state", None)
    if release_state is None or not hasattr(cls, "load_state"):
        raise HeadError(f"head {name!r} cannot load release checkpoints; heads that can: ulrssm, dpfm, echomatch.")
    if checkpoint.is_dir():
        raise HeadError(
            f"release checkpoint {checkpoint} is a folder; expected the authors' .pth file. "
            f"A folder saved by geofeat ({CONFIG_FILE} + {WEIGHTS_FILE}) loads with load_head(folder)."
        )
    if not checkpoint.is_file():
        raise HeadError(f"release checkpoint {checkpoint} does not exist.")
    raw = load_torch_file(checkpoint, HeadError, what="a release checkpoint of the authors' code")
    if not isinstance(raw, dict):
        raise HeadError(f"{checkpoint}: expected a dict of tensors; found {type(raw).__name__}.")
    release = release_state(raw, source=str(checkpoint))
    head = cls(**(preset_settings(cls, preset) | release.settings | settings))
    head.load_state(release.state, release.in_channels, source=str(checkpoint))
    return head
