"""One way to save and load a folder of settings and weights: heads, LoRA, trainer checkpoints.

>>> folder = save_pretrained("runs/nn", "head", {"descriptor": "wks"}, {"linear.weight": torch.ones(4, 3)})  # doctest: +SKIP
>>> saved = from_pretrained("runs/nn", "head", HeadError)                                                   # doctest: +SKIP
>>> saved.config, saved.tensors()["linear.weight"].shape                                                    # doctest: +SKIP
({'descriptor': 'wks'}, torch.Size([4, 3]))

A saved folder holds

``config.json``
    ``{"kind", "format_version", "geofeat_version", "config", "info"}``: what the folder is
    (``"head"``, ``"lora"``, ...), the version of this layout, the geofeat that wrote
    it, the settings that rebuild the object, and free-form information (step, loss, ...).
``weights.safetensors``
    The tensors (on the CPU, contiguous), when there are any.
any extra files
    Written by the caller's writers (the trainer's ``trainer_state.pt``).

The folder is written whole into a temporary sibling folder, ``fsync``-ed and renamed into
place (`geofeat.storage.files.atomic_folder`): a reader sees the old folder or the whole new one,
and an interrupted save leaves the old one as it was. A folder written by `save_pretrained`
is replaced by the next save; any other folder that holds something is never overwritten.
"""

from __future__ import annotations

import glob
import json
import os
import secrets
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from geofeat._version import __version__
from geofeat.errors import GeofeatError, MissingDependencyError, StoreError
from geofeat.storage.files import atomic_folder, remove_dead_temporary_folders

if TYPE_CHECKING:
    import torch

__all__ = ["CONFIG_FILE", "FORMAT_VERSION", "WEIGHTS_FILE", "Pretrained", "from_pretrained", "save_pretrained", "unread_layout"]

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "weights.safetensors"
#: Version of the layout written by `save_pretrained`; a folder of a later version is refused.
FORMAT_VERSION = 1
_ENVELOPE_KEYS = ("kind", "format_version", "geofeat_version", "config", "info")
#: Files that mark a folder of a layout this geofeat does not read, and what such a folder holds.
_UNREAD_LAYOUTS = {
    "adapter_config.json": "a LoRA or trainer checkpoint as adapter_config.json + adapter.safetensors",
    "head_config.json": "a head as head_config.json + weights.safetensors",
}
#: Kinds of a ``config.json`` that this geofeat does not read, and what such a folder holds.
_UNREAD_KINDS = {"lora_adapter": "a LoRA or trainer checkpoint of kind 'lora_adapter'"}


def _require_safetensors() -> Any:
    try:
        import safetensors.torch
    except ImportError as exc:
        raise MissingDependencyError(
            "saved weights need the optional dependency 'safetensors', which is not installed; install it with: "
            "pip install 'geofeat[dino]' (or pip install safetensors)"
        ) from exc
    return safetensors.torch


def _json_text(value: Any, what: str, error: type[GeofeatError]) -> str:
    try:
        return json.dumps(value, indent=2, sort_keys=True, allow_nan=False) + "\n"
    except (TypeError, ValueError) as exc:
        raise error(
            f"{what} must hold only JSON values (strings, numbers, booleans, None, lists, dicts with string keys; "
            f"no NaN or infinity): {exc}. Convert the value (a tuple to a list, a path to a string, an array to a list)."
        ) from exc


def unread_layout(folder: str | os.PathLike) -> str | None:
    """What ``folder`` holds when it is of a layout this geofeat does not read.

    That is a folder with the files of another layout instead of ``config.json``, or with a
    ``config.json`` of a kind this geofeat does not read.

    Parameters
    ----------
    folder : str or os.PathLike

    Returns
    -------
    str or None
        A description of the folder's content (e.g. ``"a head as head_config.json +
        weights.safetensors"``); None for any other folder.
    """
    folder = Path(folder)
    if (folder / CONFIG_FILE).exists():
        kind = (_read_envelope(folder) or {}).get("kind")
        return _UNREAD_KINDS.get(kind) if isinstance(kind, str) else None
    return next((what for name, what in _UNREAD_LAYOUTS.items() if (folder / name).is_file()), None)


def _read_envelope(folder: Path) -> dict[str, Any] | None:
    """The parsed ``config.json`` of a folder written by `save_pretrained`, or None when it is no such folder."""
    try:
        data = json.loads((folder / CONFIG_FILE).read_text())
    except (OSError, ValueError):
        return None
    if isinstance(data, dict) and {"kind", "format_version", "config"} <= set(data):
        return data
    return None


def save_pretrained(
    folder: str | os.PathLike,
    kind: str,
    config: Mapping[str, Any],
    tensors: Mapping[str, torch.Tensor] | None = None,
    *,
    info: Mapping[str, Any] | None = None,
    extra_files: Mapping[str, Callable[[Path], None]] | None = None,
    error: type[GeofeatError] = StoreError,
    durable: bool = True,
) -> Path:
    """Write a folder of settings and weights in one piece (see the module notes for the layout).

    Parameters
    ----------
    folder : str or os.PathLike
        Created with its parents; a folder written by `save_pretrained` there is replaced.
    kind : str
        What the folder is (``"head"``, ``"lora"``); `from_pretrained` checks it.
    config : Mapping
        JSON-serialisable settings that rebuild the object.
    tensors : Mapping of str to torch.Tensor, optional
        The weights, written as ``weights.safetensors`` (moved to the CPU, made contiguous);
        None: no weights file.
    info : Mapping, optional
        JSON-serialisable free-form information (step, loss, source), stored beside ``config``.
    extra_files : Mapping of str to callable, optional
        ``{file name: writer}``; ``writer(path)`` writes that file into the folder.
    error : type
        The `GeofeatError` subclass raised for bad input or a folder that cannot be replaced.
    durable : bool
        ``fsync`` everything before the folder is renamed into place (see `geofeat.storage.files.atomic_folder`).

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    GeofeatError
        Of type ``error``: ``config`` or ``info`` is not JSON-serialisable, a tensor or file name
        is not valid, or ``folder`` is a file or a folder holding something not written by
        `save_pretrained`; nothing is written then.
    MissingDependencyError
        ``tensors`` given but safetensors is not installed.
    """
    folder = Path(folder)
    if not isinstance(kind, str) or not kind:
        raise error(f"kind must be a non-empty string naming what the folder holds, got {kind!r}.")
    if not isinstance(config, Mapping):
        raise error(f"config must be a mapping of settings, got {type(config).__name__}.")
    save_id = secrets.token_hex(16)
    envelope = {
        "kind": kind,
        "format_version": FORMAT_VERSION,
        "geofeat_version": __version__,
        "save_id": save_id,
        "has_weights": tensors is not None,
        "config": dict(config),
        "info": dict(info or {}),
    }
    text = _json_text(envelope, f"the config and info of {folder}", error)
    extra_files = dict(extra_files or {})
    for name in extra_files:
        if not name or Path(name).name != name or name in (".", "..") or name in (CONFIG_FILE, WEIGHTS_FILE):
            raise error(f"extra file name {name!r} must be a plain file name other than {CONFIG_FILE} and {WEIGHTS_FILE}.")
    weights = None
    if tensors is not None:
        st = _require_safetensors()
        import torch

        bad = sorted(str(k) for k, v in tensors.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor))
        if bad:
            raise error(f"tensors must map names (str) to torch.Tensor; these entries do not: {bad[:5]}.")
        weights = {name: value.detach().to("cpu").contiguous() for name, value in tensors.items()}
    if folder.is_symlink() or folder.is_file():
        raise error(f"{folder} is a file or a link; expected a folder to save into. Choose another path or remove it.")
    if folder.is_dir() and any(folder.iterdir()) and _read_envelope(folder) is None:
        raise error(
            f"{folder} already holds files not written by save_pretrained (no {CONFIG_FILE} with kind and "
            "format_version); they are never overwritten. Choose an empty or new folder, or remove that one."
        )

    def write(tmp: Path) -> None:
        (tmp / CONFIG_FILE).write_text(text)
        if weights is not None:
            st.save_file(weights, str(tmp / WEIGHTS_FILE), metadata={"kind": kind, "save_id": save_id})
        for name, writer in extra_files.items():
            writer(tmp / name)

    return atomic_folder(folder, write, durable=durable)


@dataclass(frozen=True)
class Pretrained:
    """A folder written by `save_pretrained`, as read by `from_pretrained`: its config and weights of one save.

    Attributes
    ----------
    folder : pathlib.Path
    kind : str
    config : dict
        The settings saved.
    info : dict
        The free-form information saved.
    geofeat_version : str
        The geofeat that wrote the folder.
    error : type
        The `GeofeatError` subclass raised when the weights cannot be read.
    weights : bytes or None
        ``weights.safetensors`` as read with ``config.json`` (None: the folder has none);
        `tensors` parses them.
    """

    folder: Path
    kind: str
    config: dict
    info: dict
    geofeat_version: str
    error: type[GeofeatError] = StoreError
    weights: bytes | None = field(default=None, repr=False)

    @property
    def weights_path(self) -> Path:
        """``<folder>/weights.safetensors``."""
        return self.folder / WEIGHTS_FILE

    def has_weights(self) -> bool:
        """Whether the folder held a weights file when it was read."""
        return self.weights is not None

    def tensors(self, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """The tensors of ``weights.safetensors`` (read with the config), on ``device``.

        Raises
        ------
        GeofeatError
            Of the type given to `from_pretrained`: no weights file, or one that cannot be
            read (truncated, damaged, not safetensors).
        """
        if self.weights is None:
            raise self.error(
                f"{self.folder} holds no {WEIGHTS_FILE}; this {self.kind} was saved without weights, "
                "or the file was removed. Save it again."
            )
        st = _require_safetensors()
        try:
            tensors = st.load(self.weights)
        except Exception as exc:  # safetensors raises its own SafetensorError and others
            raise self.error(
                f"could not read {self.weights_path} as safetensors ({type(exc).__name__}: {exc}); the file is truncated "
                "or damaged (an interrupted copy?). Copy or save the folder again."
            ) from exc
        return {name: value.to(device) for name, value in tensors.items()}


#: Times `from_pretrained` reads a folder again that another process replaced while it read it.
READ_ATTEMPTS = 5


def _being_replaced(folder: Path) -> bool:
    """Whether a save of ``folder`` has set its content aside or is writing its new content (`geofeat.storage.files.atomic_folder`)."""
    parent = folder.parent
    return parent.is_dir() and any(parent.glob(f".{glob.escape(folder.name)}.old-*"))


def _saved_or_being_replaced(folder: Path) -> bool:
    """Whether ``folder`` holds a config now or a save of it is under way.

    Looked at config, set-aside, config: a save that moves from one state to the next between two looks is still
    seen, unless a whole further save starts and stops between them.
    """
    return (folder / CONFIG_FILE).is_file() or _being_replaced(folder) or (folder / CONFIG_FILE).is_file()


def _weights_save_id(weights: bytes) -> str | None:
    """The ``save_id`` in a safetensors file's metadata (its JSON header), or None."""
    try:
        size = int.from_bytes(weights[:8], "little")
        header = json.loads(weights[8 : 8 + size])
        return header.get("__metadata__", {}).get("save_id")
    except (ValueError, UnicodeDecodeError, AttributeError):
        return None


def from_pretrained(
    folder: str | os.PathLike,
    kind: str | tuple[str, ...],
    error: type[GeofeatError],
) -> Pretrained:
    """Read a folder written by `save_pretrained`: its ``config.json`` and weights, of one save, checking its kind.

    Both files carry the save's ``save_id``; a reader that got them from two saves (another
    process replaced the folder between the two reads) reads the folder again, up to
    `READ_ATTEMPTS` times; so does one whose config says it has weights when the weights file
    is gone. A folder whose ``config.json`` carries no ``save_id`` is read as it is.

    Parameters
    ----------
    folder : str or os.PathLike
    kind : str or tuple of str
        The kind (or kinds) accepted.
    error : type
        The `GeofeatError` subclass raised for every problem here and in `Pretrained.tensors`.

    Returns
    -------
    Pretrained

    Raises
    ------
    GeofeatError
        Of type ``error``: a missing folder, a missing or unparsable ``config.json``, another
        kind, a folder of a layout this geofeat does not read (`unread_layout`) or of a later
        layout version.
    """
    folder = Path(folder)
    kinds = (kind,) if isinstance(kind, str) else tuple(kind)
    expected = " or ".join(repr(k) for k in kinds)
    for attempt in range(READ_ATTEMPTS):
        try:
            saved, save_id = _read_folder(folder, kinds, expected, error)
        except GeofeatError:
            # a save between its two renames (or one killed there: restored when its writer is dead), or one that
            # finished since the failed read: read again; anything else is the folder's own problem
            if attempt + 1 < READ_ATTEMPTS and _saved_or_being_replaced(folder):
                remove_dead_temporary_folders(folder.parent, folder.name)
                time.sleep(0.02 * (attempt + 1))
                continue
            if _being_replaced(folder):
                raise error(
                    f"{folder} is being replaced by another process's save (its previous content is set aside beside "
                    "it); load it again once the saving stops."
                ) from None
            raise
        weights_id = None if saved.weights is None else _weights_save_id(saved.weights)
        if save_id is None or weights_id is None or weights_id == save_id:  # no id to compare: damage is tensors()'s to report
            return saved
    raise error(
        f"{folder} was replaced while it was being read, {READ_ATTEMPTS} times in a row (another process keeps saving "
        "it); its config and weights came from different saves. Load it again once the saving stops."
    )


def _refuse_run_folder(folder: Path, expected: str, error: type[GeofeatError]) -> None:
    """A training run folder (config.json of its settings, ``checkpoints/step_N``) given where one save is expected."""
    checkpoints = folder / "checkpoints"
    if not checkpoints.is_dir():
        return
    saved = sorted(p for p in checkpoints.iterdir() if p.is_dir() and not p.name.startswith("."))
    newest = f"the newest is {saved[-1]}" if saved else "it holds none yet"
    raise error(f"{folder} is a training run folder, not a {expected}: pass one of its checkpoints/step_N folders ({newest}).")


def _read_folder(folder: Path, kinds: tuple[str, ...], expected: str, error: type[GeofeatError]) -> tuple[Pretrained, str | None]:
    """One read of ``config.json`` and ``weights.safetensors``, checked; the config's ``save_id`` (None when it has none)."""
    if not folder.exists():
        raise error(f"{folder} does not exist; expected a folder written by save_pretrained holding a {expected}.")
    if not folder.is_dir():
        raise error(f"{folder} is a file; expected a folder written by save_pretrained holding a {expected}.")
    found = unread_layout(folder)
    if found is not None:
        raise error(
            f"{folder} holds {found}, a layout this geofeat does not read; expected a {expected} as {CONFIG_FILE} + "
            f"{WEIGHTS_FILE} written by save_pretrained. Save it again with this version of geofeat, into a new folder."
        )
    path = folder / CONFIG_FILE
    if not path.is_file():
        raise error(f"{folder} has no {CONFIG_FILE}; expected a folder written by save_pretrained holding a {expected}.")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise error(f"could not read {path} as JSON ({exc}); the file is damaged: copy or save the folder again.") from exc
    if not isinstance(data, dict) or not {"kind", "format_version", "config"} <= set(data):
        _refuse_run_folder(folder, expected, error)
        keys = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise error(
            f"{path} is not the config of a folder written by save_pretrained: expected the keys "
            f"{list(_ENVELOPE_KEYS)}, found {keys}."
        )
    found = data["kind"]
    if found not in kinds:
        raise error(f"{folder} holds a {found!r}, not a {expected}; load it with the function for a {found!r}.")
    version = data["format_version"]
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:  # bool: True is an int in Python
        raise error(
            f"{path}: format_version must be a whole number from 1 (this geofeat writes {FORMAT_VERSION}); found "
            f"{version!r}. The file was edited or damaged: save the folder again."
        )
    if version > FORMAT_VERSION:
        raise error(
            f"{folder} was written in layout version {version!r} by geofeat {data.get('geofeat_version', '?')}; this "
            f"geofeat ({__version__}) reads layout version {FORMAT_VERSION} and earlier: upgrade geofeat."
        )
    config, info = data["config"], data.get("info", {})
    if not isinstance(config, dict) or not isinstance(info, dict):
        raise error(f"{path}: 'config' and 'info' must be JSON objects; the file is damaged: save the folder again.")
    try:
        weights = (folder / WEIGHTS_FILE).read_bytes()
    except FileNotFoundError:
        if data.get("has_weights") is True:  # removed, or the folder was swapped between the two reads
            raise error(
                f"{folder} holds no {WEIGHTS_FILE}, though its {CONFIG_FILE} says it was saved with weights: the file "
                "was removed (save the folder again), or another process replaced the folder while it was read."
            ) from None
        weights = None
    except OSError as exc:
        raise error(f"could not read {folder / WEIGHTS_FILE}: {exc}.") from exc
    saved = Pretrained(folder, found, config, info, str(data.get("geofeat_version", "")), error, weights)
    return saved, data.get("save_id")
