"""Settings: where the feature cache lives."""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: Environment variable that moves the cache.
CACHE_ENV = "GEOFEAT_CACHE_DIR"

_cache_dir_override: Path | None = None


def default_cache_dir() -> Path:
    """The user's cache directory for geofeat (XDG on Linux, Library/Caches on macOS, LOCALAPPDATA on Windows)."""
    if sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    elif os.name == "nt":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local"))
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "geofeat"


def cache_dir() -> Path:
    """The cache directory in force: `set_cache_dir`, else ``$GEOFEAT_CACHE_DIR``, else the default."""
    if _cache_dir_override is not None:
        return _cache_dir_override
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else default_cache_dir()


def set_cache_dir(path: str | os.PathLike | None) -> None:
    """Move the cache for this process (None goes back to the environment or the default)."""
    global _cache_dir_override
    _cache_dir_override = None if path is None else Path(path).expanduser()
