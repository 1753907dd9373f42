"""Shared fixtures: the real FAUST_r shapes (required, never skipped) and an isolated cache."""

from __future__ import annotations

from pathlib import Path

import pytest
from shapes import CHECKPOINTS_ENV, DATA_ENV, checkpoints_root, data_root

import geofeat


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
def release_checkpoints() -> Path:
    """The folder of the authors' release checkpoints (``ulrssm/faust_scape.pth``, ``dpfm/faust.pth``); fails if absent."""
    root = checkpoints_root()
    wanted = [root / "ulrssm" / "faust_scape.pth", root / "dpfm" / "faust.pth"]
    missing = [str(p) for p in wanted if not p.is_file()]
    if missing:
        pytest.fail(
            f"release checkpoints not found: {missing}. Set {CHECKPOINTS_ENV} to the folder that holds ulrssm/ and dpfm/ "
            "(see the README, section 'Matching heads'). Checkpoint tests fail rather than skip.",
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
