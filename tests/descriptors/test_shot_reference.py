"""geofeat's SHOT against pyshot's recorded rows (tests/data/shot_reference.npz, see tests/data/README.md)."""

import json
from pathlib import Path

import numpy as np
import pytest

import geofeat
from geofeat.descriptors.shot import SHOT, shot_descriptors

RECORDED = Path(__file__).resolve().parents[1] / "data" / "shot_reference.npz"
#: pyshot sums in float32: normalised rows agree to about 3e-7, unnormalised entries (up to ~50) to a few 1e-6
ATOL = {"faust_dsmk": 1e-6, "faust_r0.1_b7_16vol": 1e-6, "cloud_r0.5_b5_nonorm": 2e-5}


@pytest.fixture(scope="module")
def recorded():
    with np.load(RECORDED) as data:
        return {key: data[key] for key in data.files}


@pytest.mark.parametrize("name", sorted(ATOL))
def test_equals_recorded_pyshot_rows(name, recorded, faust_dir):
    if name.startswith("faust"):
        mesh = geofeat.load_mesh(faust_dir / "off" / "tr_reg_080.off")
        np.testing.assert_allclose(np.asarray(mesh.verts).sum(0), recorded["faust_verts_sum"], rtol=1e-12)
    else:
        mesh = geofeat.Mesh(recorded["cloud_verts"])
    params = json.loads(str(recorded[f"{name}_params"]))
    rows = recorded[f"{name}_rows"]
    theirs = recorded[f"{name}_descriptors"].astype(np.float64)
    normals = SHOT(cloud_normals="zero").normals(mesh)  # pyshot: zero normals on a point cloud
    ours, report = shot_descriptors(mesh.verts, normals, queries=rows, **params)
    tie = report["sign_tie"]  # pyshot keeps Eigen's arbitrary sign there
    assert tie.mean() < 0.05
    np.testing.assert_allclose(ours[~tie], theirs[~tie], rtol=0, atol=ATOL[name])
