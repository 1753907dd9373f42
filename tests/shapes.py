"""Shared test helpers: the repository root, the data folder and seeded synthetic meshes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

import geofeat

REPO = Path(__file__).resolve().parents[1]
DATA_ENV = "GEOFEAT_DATA"


def data_root() -> Path:
    """``$GEOFEAT_DATA``, else ``../shared/data`` beside the repository."""
    return Path(os.environ.get(DATA_ENV, REPO.parent / "shared" / "data"))


CHECKPOINTS_ENV = "GEOFEAT_CHECKPOINTS"


def checkpoints_root() -> Path:
    """``$GEOFEAT_CHECKPOINTS``, else ``../shared/checkpoints`` beside the repository (the authors' release weights)."""
    return Path(os.environ.get(CHECKPOINTS_ENV, REPO.parent / "shared" / "checkpoints"))


def sphere(subdivisions: int = 3, radius: float = 1.0) -> geofeat.Mesh:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return geofeat.Mesh(np.asarray(s.vertices), np.asarray(s.faces), name=f"sphere{subdivisions}")


def bumpy(seed: int = 0, subdivisions: int = 3) -> geofeat.Mesh:
    """A seeded smooth asymmetric closed surface."""
    from geofeat.demo import blob

    return blob(subdivisions, seed, f"bumpy{seed}")
