"""Shared fixtures: the real FAUST_r shapes (required, never skipped) and seeded synthetic meshes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

import geofeat

REPO = Path(__file__).resolve().parents[1]
DATA_ENV = "GEOFEAT_DATA"


def data_root() -> Path:
    """``$GEOFEAT_DATA``, else ``../shared/data`` beside the repository."""
    return Path(os.environ.get(DATA_ENV, REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def faust_dir() -> Path:
    root = data_root() / "FAUST_r"
    if not (root / "off" / "tr_reg_000.off").is_file():
        pytest.fail(
            f"FAUST_r test data not found at {root}. Set {DATA_ENV} to the folder that holds FAUST_r/ "
            "(see the README, section 'Data'). Data-dependent tests fail rather than skip.",
            pytrace=False,
        )
    return root


@pytest.fixture(scope="session")
def faust_mesh(faust_dir) -> geofeat.Mesh:
    return geofeat.load_mesh(faust_dir / "off" / "tr_reg_000.off")


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path, monkeypatch):
    """Every test gets its own cache directory; the user's cache is never touched."""
    monkeypatch.setenv("GEOFEAT_CACHE_DIR", str(tmp_path / "cache"))
    geofeat.set_cache_dir(None)
    yield tmp_path / "cache"
    geofeat.set_cache_dir(None)


def sphere(subdivisions: int = 3, radius: float = 1.0) -> geofeat.Mesh:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return geofeat.Mesh(np.asarray(s.vertices), np.asarray(s.faces), name=f"sphere{subdivisions}")


def bumpy(seed: int = 0, subdivisions: int = 3) -> geofeat.Mesh:
    """A seeded smooth asymmetric closed surface."""
    from geofeat.demo import blob

    return blob(subdivisions, seed, f"bumpy{seed}")
