"""Writers of tiny files in the on-disk benchmark formats (shared by the loader tests), and the shared real samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from shapes import DATA_ENV, data_root


def strip_mesh(n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A triangle strip: vertex i at (i // 2, i % 2, 0.01 i); faces (i, i+1, i+2)."""
    i = np.arange(n_vertices)
    verts = np.stack([i // 2, i % 2, 0.01 * i], axis=1).astype(float)
    faces = np.stack([i[:-2], i[1:-1], i[2:]], axis=1)
    return verts, faces


def write_off(path: Path, n_vertices: int) -> np.ndarray:
    """Write a strip mesh with ``n_vertices`` vertices as OFF; returns its faces (F, 3)."""
    verts, faces = strip_mesh(n_vertices)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["OFF", f"{len(verts)} {len(faces)} 0"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in verts]
    lines += ["3 " + " ".join(str(int(v)) for v in row) for row in faces]
    path.write_text("\n".join(lines) + "\n")
    return faces


def write_lines(path: Path, values) -> None:
    """One value (or one row of values) per line."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [" ".join(str(v) for v in np.atleast_1d(row)) for row in values]
    path.write_text("\n".join(rows) + "\n")


@pytest.fixture
def off_writer():
    return write_off


@pytest.fixture
def lines_writer():
    return write_lines


def shared_sample(folder: str, probe: str) -> Path:
    """``<shared data>/<folder>``, failing (never skipping) when its file ``probe`` is absent."""
    root = data_root() / folder
    if not (root / probe).is_file():
        pytest.fail(
            f"shared sample {folder} not found at {root} (no {probe}). Set {DATA_ENV} to the folder that holds "
            f"{folder}/ (see the README, section 'Test'). Data-dependent tests fail rather than skip.",
            pytrace=False,
        )
    return root


@pytest.fixture(scope="session")
def psmal_sample() -> Path:
    """The PARTIALSMAL folder of the shared PSMAL sample (three real train pairs, one map direction each)."""
    return shared_sample("PSMAL_sample", "PARTIALSMAL/train/maps/cuts_0_cow_02_cuts_22_dog_05.vts") / "PARTIALSMAL"


@pytest.fixture(scope="session")
def shrec16_dpfm_sample() -> Path:
    """The shared SHREC'16 sample in DPFM's layout (one real CUTS pair, test split)."""
    return shared_sample("SHREC16_dpfm_sample", "shrec_partial_test/maps/cuts-cat1_cuts-cat.map")
