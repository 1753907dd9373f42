"""FAUST_r loader on the real shared data; the SCAPE_r variant on tiny files of the same format."""

import numpy as np
import pytest

from geofeat.datasets import base
from geofeat.datasets.faust import FaustRemeshed
from geofeat.datasets.registry import load_dataset
from geofeat.errors import DatasetError


def reference_map(src_vts, tgt_vts, n_src):
    """Plain-Python reading of the .vts convention: 1-based, first template point wins, -1 elsewhere."""
    out = np.full(n_src, -1)
    for src, tgt in zip(src_vts, tgt_vts, strict=True):
        if out[src - 1] == -1:
            out[src - 1] = tgt - 1
    return out


@pytest.fixture(scope="module")
def faust_test(faust_dir):
    return load_dataset("faust_r", faust_dir, split="test")


def test_test_split_holds_all_ordered_pairs_of_the_last_20_shapes(faust_test):
    assert len(faust_test) == 20 * 19
    assert faust_test.shape_names == [f"tr_reg_{i:03d}" for i in range(80, 100)]
    assert faust_test.pair_names[:2] == ["tr_reg_080->tr_reg_081", "tr_reg_080->tr_reg_082"]
    assert all(y != x for y, x in (name.split("->") for name in faust_test.pair_names))
    assert faust_test.protocol == "f2f"


def test_pair_maps_follow_the_vts_files(faust_test, faust_dir):
    index = faust_test.pair_names.index("tr_reg_085->tr_reg_092")
    pair = faust_test[index]
    assert pair.name == "tr_reg_085->tr_reg_092" and pair.protocol == "f2f"
    assert pair.overlap_x is None and pair.overlap_y is None
    vts_y = np.loadtxt(faust_dir / "corres" / "tr_reg_085.vts", dtype=int)
    vts_x = np.loadtxt(faust_dir / "corres" / "tr_reg_092.vts", dtype=int)
    sym_x = np.loadtxt(faust_dir / "corres" / "tr_reg_092.sym.vts", dtype=int)
    assert pair.map_yx.dtype == np.int64 and pair.map_yx.shape == (pair.y.n_vertices,)
    np.testing.assert_array_equal(pair.map_yx, reference_map(vts_y, vts_x, pair.y.n_vertices))
    np.testing.assert_array_equal(pair.map_yx_sym, reference_map(vts_y, sym_x, pair.y.n_vertices))
    # vertices no template point lands on have no counterpart
    unhit = np.setdiff1d(np.arange(pair.y.n_vertices), vts_y - 1)
    assert unhit.size > 0 and np.all(pair.map_yx[unhit] == -1)
    assert pair.map_yx.max() < pair.x.n_vertices
    assert np.mean(pair.map_yx_sym != pair.map_yx) > 0.5  # the mirrored ground truth is a different map


def test_ground_truth_is_geometrically_plausible(faust_test):
    """Same person, two poses: matched vertices have similar distance to the body's centroid."""
    pair = faust_test[faust_test.pair_names.index("tr_reg_080->tr_reg_081")]
    has = pair.map_yx >= 0
    radius_y = np.linalg.norm(pair.y.verts - pair.y.verts.mean(0), axis=1)[has]
    radius_x = np.linalg.norm(pair.x.verts - pair.x.verts.mean(0), axis=1)[pair.map_yx[has]]
    assert np.corrcoef(radius_y, radius_x)[0, 1] > 0.8


def test_each_mesh_file_is_read_once(faust_dir, monkeypatch):
    calls = []
    real = base.load_mesh
    monkeypatch.setattr(base, "load_mesh", lambda path: calls.append(path) or real(path))
    dataset = FaustRemeshed(faust_dir, "test")
    first, second, again = dataset[0], dataset[1], dataset[0]
    assert first.y is second.y is again.y  # tr_reg_080 read once
    assert len(calls) == len(set(calls)) == 3


def test_pairs_from_test_pairs_file(faust_dir):
    listed = [line.split() for line in (faust_dir / "test_pairs.txt").read_text().splitlines() if line.strip()]
    every = FaustRemeshed(faust_dir, "all", pairs="file")
    assert every.pair_names == [f"{y}->{x}" for y, x in listed]
    in_test = FaustRemeshed(faust_dir, "test", pairs="file")
    expected = [f"{y}->{x}" for y, x in listed if int(y[-3:]) >= 80 and int(x[-3:]) >= 80]
    assert in_test.pair_names == expected and 0 < len(expected) < len(listed)


def test_train_split_and_explicit_pairs(faust_dir):
    train = FaustRemeshed(faust_dir, "train")
    assert len(train) == 80 * 79 and train.shape_names[-1] == "tr_reg_079"
    chosen = FaustRemeshed(faust_dir, "test", pairs=[("tr_reg_099", "tr_reg_080")])
    assert chosen.pair_names == ["tr_reg_099->tr_reg_080"]
    with pytest.raises(DatasetError, match="not in the 'test' split"):
        FaustRemeshed(faust_dir, "test", pairs=[("tr_reg_000", "tr_reg_080")])


def test_wrong_layout_shows_expected_tree_and_source(tmp_path):
    (tmp_path / "off").mkdir()
    with pytest.raises(DatasetError) as err:
        load_dataset("faust_r", tmp_path)
    message = str(err.value)
    assert "no file matches off/*.off" in message and "missing folder corres/" in message
    assert "Expected layout" in message and "github.com/llorz/SGA18_orientation_BCICP_dataset" in message


def test_mesh_without_correspondence_file_is_an_error(tmp_path, off_writer):
    off_writer(tmp_path / "off" / "tr_reg_080.off", 4)
    (tmp_path / "corres").mkdir()
    with pytest.raises(DatasetError, match=r"tr_reg_080"):
        load_dataset("faust_r", tmp_path)


def test_scape_format_on_tiny_files(tmp_path, off_writer, lines_writer):
    root = tmp_path / "SCAPE_r"
    for name, n in (("mesh000", 5), ("mesh051", 5), ("mesh052", 6)):
        off_writer(root / "off" / f"{name}.off", n)
    # 6 template points, 1-based; template points 0 and 3 both land on vertex 2 of mesh051
    lines_writer(root / "corres" / "mesh000.vts", [1, 2, 3, 4, 5, 1])
    lines_writer(root / "corres" / "mesh051.vts", [2, 1, 4, 2, 5, 5])
    lines_writer(root / "corres" / "mesh052.vts", [6, 3, 1, 4, 2, 5])
    lines_writer(root / "corres" / "mesh052.sym.vts", [1, 2, 3, 4, 5, 6])
    dataset = load_dataset("scape_r", tmp_path, split="test")  # the parent folder is enough
    assert dataset.pair_names == ["mesh051->mesh052", "mesh052->mesh051"]
    pair = dataset[0]
    np.testing.assert_array_equal(pair.map_yx, [2, 5, -1, 0, 1])
    np.testing.assert_array_equal(pair.map_yx_sym, [1, 0, -1, 2, 4])
    assert dataset[1].map_yx_sym is None  # mesh051 has no .sym.vts
    np.testing.assert_array_equal(dataset[1].map_yx, [3, 4, 0, 1, 4, 1])
    lines_writer(root / "corres" / "mesh052.vts", [7, 3, 1, 4, 2, 5])  # 7 > 6 vertices
    with pytest.raises(DatasetError, match=r"1-based vertex indices must lie in \[1, 6\]"):
        load_dataset("scape_r", root, split="test")[0]
