"""The one base of geofeat's configuration dataclasses: dicts, JSON files, unknown keys.

`HeadConfig` (heads), `TrainConfig` (GeoLoRA training) and `LoraSettings` (LoRA)
are dataclasses deriving from `JsonConfig`. They share:

* `JsonConfig.to_dict` / `JsonConfig.from_dict`: JSON-ready values (tuples as lists);
* `JsonConfig.save` / `JsonConfig.load`: a JSON file written atomically
  (`geofeat.storage.files.atomic_write`), read back as JSON (or YAML for ``.yaml`` / ``.yml``);
* one rule for keys that are no setting of this version (a file written by a newer
  geofeat, or a note a user added): a warning names them, they are kept aside in
  `JsonConfig.unknown` and written back by `to_dict` and `save`, so nothing is lost by
  loading and saving a file again. They never change a setting.

`JsonConfig.save` is the one way to write a settings file on its own (the trainer's
``config.json`` of a run). Settings saved together with weights (heads, LoRA folders,
trainer checkpoints) go through `geofeat.storage.pretrained.save_pretrained`, which stores
`to_dict` under the ``"config"`` key of its ``config.json``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from geofeat.errors import GeofeatError
from geofeat.storage.files import atomic_write

__all__ = ["JsonConfig"]

C = TypeVar("C", bound="JsonConfig")

_UNKNOWN = "_unknown_keys"


def _plain(value: Any) -> Any:
    """``value`` with tuples as lists and containers copied (the JSON form)."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


class JsonConfig:
    """Mixin for configuration dataclasses (derive from it and decorate with ``@dataclass``).

    Class attributes
    ----------------
    error : type
        The `GeofeatError` subclass raised for unreadable files (set by each subclass).
    """

    error: ClassVar[type[GeofeatError]] = GeofeatError
    # set on each subclass by ``@dataclass``
    __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    # -- unknown keys

    @property
    def unknown(self) -> dict[str, Any]:
        """Keys of the mapping this was built from that are no setting, with their values (kept aside, saved back)."""
        return dict(self.__dict__.get(_UNKNOWN, {}))

    @property
    def unknown_keys(self) -> list[str]:
        """Sorted names of `unknown`."""
        return sorted(self.__dict__.get(_UNKNOWN, {}))

    # -- dicts

    @classmethod
    def field_names(cls) -> list[str]:
        """Names of the settings, in declaration order."""
        return [f.name for f in dataclasses.fields(cls) if not f.name.startswith("_")]

    def to_dict(self, unknown: bool = True) -> dict[str, Any]:
        """The settings as a JSON-ready dict (tuples as lists).

        Parameters
        ----------
        unknown : bool
            Include the keys kept aside by `from_dict` (settings win on a clash).

        Returns
        -------
        dict
        """
        data = {name: _plain(getattr(self, name)) for name in self.field_names()}
        return {**_plain(self.__dict__.get(_UNKNOWN, {})), **data} if unknown else data

    @classmethod
    def from_dict(cls: type[C], data: Mapping[str, Any], **overrides: Any) -> C:
        """Build from a mapping; unknown keys are warned about and kept aside (`unknown`).

        Parameters
        ----------
        data : Mapping
            Settings by name.
        **overrides
            Settings that win over ``data``; those that are None are skipped.

        Returns
        -------
        JsonConfig
        """
        known = set(cls.field_names())
        unknown = {k: v for k, v in data.items() if k not in known}
        if unknown:
            logging.getLogger(cls.__module__).warning(
                "%s: keys %s are no settings of this version of geofeat: ignored, kept aside and saved back unchanged.",
                cls.__name__,
                sorted(unknown),
            )
        values = {k: v for k, v in data.items() if k in known}
        values.update({k: v for k, v in overrides.items() if v is not None})
        config = cls(**values)
        # kept in JSON form (a YAML date becomes its text), so that saving never fails on them
        config.__dict__[_UNKNOWN] = json.loads(json.dumps(unknown, default=str))
        return config

    # -- files

    def save(self, path: str | os.PathLike) -> Path:
        """Write `to_dict` (unknown keys included) as JSON, atomically; return the path."""
        text = json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n"
        path = Path(path)
        atomic_write(path, lambda tmp: tmp.write_text(text))
        return path

    @classmethod
    def read_mapping(cls, path: str | os.PathLike) -> dict[str, Any]:
        """The mapping in a ``.json`` file (``.yaml`` / ``.yml``: YAML).

        Raises
        ------
        GeofeatError
            Of the class's `error` type: a missing or unparsable file, or one that holds no mapping.
        """
        path = Path(path)
        if not path.is_file():
            raise cls.error(f"configuration file {path} does not exist.")
        try:
            text = path.read_text()
            if path.suffix.lower() in (".yaml", ".yml"):
                import yaml

                data = yaml.safe_load(text)
            else:
                data = json.loads(text)
        except Exception as exc:  # OSError, json and yaml raise unrelated error types
            raise cls.error(f"could not parse {path}: {exc}") from exc
        if not isinstance(data, dict):
            raise cls.error(f"{path} must hold a mapping of settings, found {type(data).__name__}.")
        return data

    @classmethod
    def load(cls: type[C], path: str | os.PathLike, **overrides: Any) -> C:
        """`read_mapping` then `from_dict` (``overrides`` that are not None win)."""
        return cls.from_dict(cls.read_mapping(path), **overrides)
