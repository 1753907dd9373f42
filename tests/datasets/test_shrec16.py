"""SHREC'16 Partial loader on tiny files in the contest, ULRSSM and DPFM layouts, and on the real DPFM sample."""

import numpy as np
import pytest

from geofeat.datasets.registry import load_dataset
from geofeat.datasets.shrec16 import Shrec16Partial
from geofeat.errors import DatasetError

# null shape "cat": a 6-vertex strip with faces (0,1,2) (1,2,3) (2,3,4) (3,4,5)
BARYC = [  # 1-based triangle, three weights -> corner with the largest weight
    "1 0.2 0.7 0.1",  # corner 1 of (0,1,2) -> 1
    "3 0.5 0.2 0.3",  # corner 0 of (2,3,4) -> 2
    "99 0.3 0.3 0.4",  # no such triangle -> -1
    "4 0.4 0.2 0.4",  # tie: first corner of (3,4,5) -> 3
]
BARYC_SYM = ["2 0.1 0.1 0.8", "1 0.9 0.05 0.05", "4 0 1 0", "0 1 0 0"]  # -> 3, 0, 4, -1


@pytest.fixture
def contest_root(tmp_path, off_writer, lines_writer):
    root = tmp_path / "shrec16_train"
    off_writer(root / "null" / "cat.off", 6)
    off_writer(root / "null" / "dog.off", 5)
    off_writer(root / "cuts" / "cuts_cat_shape_1.off", 4)
    lines_writer(root / "cuts" / "cuts_cat_shape_1.baryc_gt", BARYC)
    lines_writer(root / "cuts" / "cuts_cat_shape_1.baryc_gt_sym", BARYC_SYM)
    off_writer(root / "cuts" / "cuts_dog_shape_10.off", 3)
    lines_writer(root / "cuts" / "cuts_dog_shape_10.baryc_gt", ["1 0 0 1", "2 0 1 0", "3 1 0 0"])
    off_writer(root / "cuts" / "cuts_dog_shape_2.off", 3)
    lines_writer(root / "cuts" / "cuts_dog_shape_2.baryc_gt", ["3 0 0 1", "3 0 1 0", "3 1 0 0"])
    return root


def test_contest_layout_converts_barycentric_ground_truth(contest_root):
    dataset = load_dataset("shrec16_cuts", contest_root)
    assert dataset.pair_names == ["cuts_cat_shape_1->cat", "cuts_dog_shape_2->dog", "cuts_dog_shape_10->dog"]
    pair = dataset[0]
    assert pair.protocol == "p2f" and pair.x.name == "cat" and pair.y.name == "cuts_cat_shape_1"
    np.testing.assert_array_equal(pair.map_yx, [1, 2, -1, 3])
    np.testing.assert_array_equal(pair.map_yx_sym, [3, 0, 4, -1])
    np.testing.assert_array_equal(pair.overlap_y, [True, True, False, True])
    assert pair.overlap_x is None and pair.map_yx.dtype == np.int64
    np.testing.assert_array_equal(dataset[2].map_yx, [2, 2, 2])  # dog faces: (0,1,2) (1,2,3) (2,3,4)
    assert dataset[2].map_yx_sym is None  # no .baryc_gt_sym file
    assert dataset[1].x is dataset[2].x  # the null shape is read once


def test_ulrssm_layout_reads_one_based_vts(tmp_path, off_writer, lines_writer):
    root = tmp_path / "SHREC16_test"
    off_writer(root / "null" / "off" / "wolf.off", 6)
    off_writer(root / "holes" / "off" / "holes_wolf_shape_3.off", 4)
    lines_writer(root / "holes" / "corres" / "holes_wolf_shape_3.vts", [3, 1, 0, 6])
    dataset = load_dataset("shrec16_holes", tmp_path, split="test")  # parent folder + split picks SHREC16_test/
    assert dataset.layout == "ulrssm" and dataset.pair_names == ["holes_wolf_shape_3->wolf"]
    pair = dataset[0]
    np.testing.assert_array_equal(pair.map_yx, [2, 0, -1, 5])
    np.testing.assert_array_equal(pair.overlap_y, [True, True, False, True])
    assert pair.map_yx_sym is None
    lines_writer(root / "holes" / "corres" / "holes_wolf_shape_3.vts", [3, 1, 7, 6])
    with pytest.raises(DatasetError, match=r"must lie in \[1, 6\]"):
        load_dataset("shrec16_holes", root)[0]
    lines_writer(root / "holes" / "corres" / "holes_wolf_shape_3.vts", [3, 1, 2])
    with pytest.raises(DatasetError, match="expected 4 entries"):
        load_dataset("shrec16_holes", root)[0]
    with pytest.raises(DatasetError, match="SHREC16"):  # split="train" looks for SHREC16/, which is absent
        load_dataset("shrec16_holes", tmp_path, split="train")


def test_shape_subset_and_its_errors(contest_root, tmp_path):
    listing = tmp_path / "subset.txt"
    listing.write_text("cuts_dog_shape_10.off\n")
    assert Shrec16Partial(contest_root, shapes=listing).pair_names == ["cuts_dog_shape_10->dog"]
    with pytest.raises(DatasetError, match="cuts_cow_shape_1"):
        Shrec16Partial(contest_root, shapes=["cuts_cow_shape_1"])


def test_missing_null_shape_or_ground_truth_is_an_error(contest_root, off_writer):
    (contest_root / "cuts" / "cuts_dog_shape_2.baryc_gt").unlink()
    with pytest.raises(DatasetError, match="no ground-truth file"):
        Shrec16Partial(contest_root)
    off_writer(contest_root / "cuts" / "cuts_horse_shape_1.off", 3)
    with pytest.raises(DatasetError, match=r"null shape .*horse\.off is missing"):
        Shrec16Partial(contest_root, shapes=["cuts_horse_shape_1"])


def test_row_count_must_match_the_partial_shape(contest_root, lines_writer):
    lines_writer(contest_root / "cuts" / "cuts_cat_shape_1.baryc_gt", BARYC[:3])
    with pytest.raises(DatasetError, match="one row per partial vertex"):
        load_dataset("shrec16_cuts", contest_root)[0]


def test_wrong_layout_shows_both_layouts_and_source(tmp_path):
    with pytest.raises(DatasetError) as err:
        load_dataset("shrec16_cuts", tmp_path)
    message = str(err.value)
    assert "Expected layout" in message and "baryc_gt" in message and "null/off/" in message
    assert "dais.unive.it/~shrec2016" in message


def test_baryc_triangles_count_the_file_rows_even_when_the_mesh_drops_repeats(tmp_path, off_writer, lines_writer):
    """A repeated triangle in the null shape's file (DPFM's cat has 12) must not shift later .baryc_gt indices."""
    root = tmp_path / "shrec16"
    rows = [(0, 1, 2), (0, 1, 2), (1, 2, 3), (2, 3, 4), (3, 4, 5), (3, 3, 4)]  # a repeat and a collapsed face
    verts = [(i // 2, i % 2, 0.01 * i) for i in range(6)]
    (root / "null").mkdir(parents=True)
    text = ["OFF", f"6 {len(rows)} 0", *(f"{x} {y} {z}" for x, y, z in verts), *(f"3 {a} {b} {c}" for a, b, c in rows)]
    (root / "null" / "cat.off").write_text("\n".join(text) + "\n")
    off_writer(root / "cuts" / "cuts_cat_shape_1.off", 4)
    lines_writer(root / "cuts" / "cuts_cat_shape_1.baryc_gt", ["3 0.1 0.8 0.1", "5 0 0 1", "6 1 0 0", "7 1 0 0"])
    pair = load_dataset("shrec16_cuts", root)[0]
    assert len(pair.x.faces) == 4  # the Mesh dropped the repeat and the collapsed face
    # file rows 3, 5, 6 (1-based) are (1,2,3), (3,4,5), (3,3,4); row 7 does not exist
    np.testing.assert_array_equal(pair.map_yx, [2, 5, 3, -1])


# ----------------------------------------------------------------------------- DPFM's layout


def write_dpfm(root, off_writer, lines_writer, maps):
    """shapes/ (cuts-cat 8 vertices, cuts-cat1 4, holes-cat 8, holes-cat2 3) and the given maps/ files."""
    for name, n in (("cuts-cat", 8), ("cuts-cat1", 4), ("holes-cat", 8), ("holes-cat2", 3)):
        off_writer(root / "shapes" / f"{name}.off", n)
    for name, values in maps.items():
        lines_writer(root / "maps" / f"{name}.map", values)


def test_dpfm_layout_reads_zero_based_maps_partial_first(tmp_path, off_writer, lines_writer):
    root = tmp_path / "shrec_partial_test"
    write_dpfm(root, off_writer, lines_writer, {"cuts-cat1_cuts-cat": [7, 0, -1, 3], "holes-cat2_holes-cat": [1, 2, 5]})
    dataset = load_dataset("shrec16_cuts", tmp_path, split="test")  # parent folder + split picks shrec_partial_test/
    assert dataset.layout == "dpfm" and dataset.root == root
    assert dataset.pair_names == ["cuts-cat1->cuts-cat"]  # only the CUTS maps
    pair = dataset[0]
    assert (pair.y.n_vertices, pair.x.n_vertices) == (4, 8) and pair.protocol == "p2f"
    np.testing.assert_array_equal(pair.map_yx, [7, 0, -1, 3])
    np.testing.assert_array_equal(pair.overlap_y, [True, True, False, True])
    assert pair.overlap_x is None and pair.map_yx_sym is None
    holes = load_dataset("shrec16_holes", root)
    assert holes.pair_names == ["holes-cat2->holes-cat"]
    np.testing.assert_array_equal(holes[0].map_yx, [1, 2, 5])
    assert Shrec16Partial(root, layout="dpfm", shapes=["cuts-cat1.off"]).pair_names == ["cuts-cat1->cuts-cat"]
    with pytest.raises(DatasetError, match="no map file"):
        Shrec16Partial(root, shapes=["cuts-cat7"])


def test_dpfm_layout_errors(tmp_path, off_writer, lines_writer):
    root = tmp_path / "shrec_partial_train"
    write_dpfm(root, off_writer, lines_writer, {"cuts-cat1_cuts-cat": [8, 1, 2, 8]})  # 1-based by mistake: reaches 8, never 0
    with pytest.raises(DatasetError, match="looks 1-based"):
        load_dataset("shrec16_cuts", tmp_path, split="train")[0]
    lines_writer(root / "maps" / "cuts-cat1_cuts-cat.map", [7, 0, 1])
    with pytest.raises(DatasetError, match="expected 4 entries"):
        load_dataset("shrec16_cuts", root)[0]
    lines_writer(root / "maps" / "cuts-cat3_cuts-cat.map", [0, 1])  # cuts-cat3.off is missing
    with pytest.raises(DatasetError, match="cannot tell which two shapes"):
        load_dataset("shrec16_cuts", root)
    with pytest.raises(DatasetError, match=r"looks like DPFM's layout, but no file matches maps/holes\*\.map"):
        load_dataset("shrec16_holes", root)  # write_dpfm wrote no HOLES map here


def test_dpfm_real_sample_is_zero_based_and_partial_vertices_lie_on_their_counterparts(shrec16_dpfm_sample):
    """The real pair of DPFM's repository: the partial cat is cut from the full one, so 0-based indices land on it."""
    dataset = load_dataset("shrec16_cuts", root=shrec16_dpfm_sample)  # split "test" picks shrec_partial_test/
    assert dataset.layout == "dpfm" and dataset.pair_names == ["cuts-cat1->cuts-cat"]
    pair = dataset[0]
    assert (pair.y.n_vertices, pair.x.n_vertices) == (5110, 10_000)
    stored = np.loadtxt(shrec16_dpfm_sample / "shrec_partial_test" / "maps" / "cuts-cat1_cuts-cat.map", dtype=np.int64)
    np.testing.assert_array_equal(pair.map_yx, stored)
    assert pair.map_yx.min() >= 0 and pair.map_yx.max() < 10_000 and pair.overlap_y.all()
    assert len(pair.x.faces) == 19_940 - 12  # the 12 repeated triangles are dropped; vertex indices are unaffected
    diagonal = pair.x.bbox_diagonal()
    as_stored = np.linalg.norm(pair.y.verts - pair.x.verts[pair.map_yx], axis=1) / diagonal
    shifted = np.linalg.norm(pair.y.verts - pair.x.verts[pair.map_yx - 1], axis=1) / diagonal  # read as 1-based
    assert np.median(as_stored) < 1e-3 and as_stored.max() < 1e-2
    assert np.median(shifted) > 5 * np.median(as_stored) and shifted.max() > 0.1
