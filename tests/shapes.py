"""Shared test helpers: the repository root, the data folder and seeded synthetic meshes."""

from __future__ import annotations

import os
import socket
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


def free_port() -> int:
    """A TCP port free on this machine now, for the rendezvous of test ranks (torchrun's MASTER_PORT)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def sphere(subdivisions: int = 3, radius: float = 1.0) -> geofeat.Mesh:
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return geofeat.Mesh(np.asarray(s.vertices), np.asarray(s.faces), name=f"sphere{subdivisions}")


def bumpy(seed: int = 0, subdivisions: int = 3) -> geofeat.Mesh:
    """A seeded smooth asymmetric closed surface."""
    from geofeat.apps.demo import blob

    return blob(subdivisions, seed, f"bumpy{seed}")


def write_off(path: Path, mesh: geofeat.Mesh) -> Path:
    """Write ``mesh`` as an OFF file at ``path`` (folders made), with every coordinate exact."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["OFF", f"{mesh.n_vertices} {len(mesh.faces)} 0"]
    lines += [" ".join(repr(float(c)) for c in v) for v in mesh.verts]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in mesh.faces]
    path.write_text("\n".join(lines) + "\n")
    return path
