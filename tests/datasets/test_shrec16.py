"""SHREC'16 Partial loader on tiny files in the contest layout and in the ULRSSM layout."""

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
