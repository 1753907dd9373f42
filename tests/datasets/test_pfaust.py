"""PFAUST loader on tiny files in GeoLoRA's layout (neutral_pose/, off_<d>/, corres_<d>/, masks_<d>/)."""

import numpy as np
import pytest

from geofeat.datasets.pfaust import PFaust
from geofeat.datasets.registry import load_dataset
from geofeat.errors import DatasetError

# 8 template points; the partial shape keeps points 0, 2, 3, 5, 6
FULL_VTS = [1, 2, 3, 4, 5, 6, 1, 2]  # 1-based vertex of the full shape (6 vertices) per template point
FULL_SYM = [6, 5, 4, 3, 2, 1, 6, 5]
MASK = [1, 0, 1, 1, 0, 1, 1, 0]
PARTIAL_VTS = [2, 1, 2, 5, 3]  # 1-based partial vertex (5 vertices) per kept point; vertex 2 twice
# kept point -> (partial, full): 0 -> (1, 0), 2 -> (0, 2), 3 -> (1, 3) [dropped: vertex 1 taken], 5 -> (4, 5), 6 -> (2, 0)
EXPECTED = [2, 0, 0, -1, 5]
EXPECTED_SYM = [3, 5, 5, -1, 0]


@pytest.fixture
def faust_r(tmp_path, off_writer, lines_writer):
    root = tmp_path / "FAUST_r"
    for full in ("tr_reg_000", "tr_reg_080", "tr_reg_090"):
        off_writer(root / "neutral_pose" / f"{full}.off", 6)
        lines_writer(root / "corres" / f"{full}.vts", FULL_VTS)
    lines_writer(root / "corres" / "tr_reg_080.sym.vts", FULL_SYM)
    for partial in ("tr_reg_001", "tr_reg_081"):
        off_writer(root / "off_medium" / f"{partial}.off", 5)
        lines_writer(root / "corres_medium" / f"{partial}.vts", PARTIAL_VTS)
        lines_writer(root / "masks_medium" / f"{partial}.vts", MASK)
    return root


def test_test_pairs_are_every_full_shape_against_every_partial_shape(faust_r):
    dataset = load_dataset("pfaust_m", faust_r.parent)  # the folder holding FAUST_r/ is enough
    assert dataset.protocol == "p2f"
    assert dataset.pair_names == ["tr_reg_081->tr_reg_080", "tr_reg_081->tr_reg_090"]
    assert PFaust(faust_r, "train").pair_names == ["tr_reg_001->tr_reg_000"]


def test_template_masks_give_the_vertex_map(faust_r):
    dataset = load_dataset("pfaust_m", faust_r)
    pair = dataset[0]
    assert pair.y.n_vertices == 5 and pair.x.n_vertices == 6 and pair.x.name == "tr_reg_080"
    np.testing.assert_array_equal(pair.map_yx, EXPECTED)
    np.testing.assert_array_equal(pair.map_yx_sym, EXPECTED_SYM)
    np.testing.assert_array_equal(pair.overlap_y, [True, True, True, False, True])
    assert pair.overlap_x is None and pair.map_yx.dtype == np.int64
    assert dataset[1].map_yx_sym is None  # tr_reg_090 has no .sym.vts
    assert dataset[1].y is pair.y


def test_kept_template_points_are_the_pairs_template_correspondences(faust_r):
    """GeoLoRA's evaluation scores every kept template point: the full and partial vertex of each."""
    pair = load_dataset("pfaust_m", faust_r)[0]
    kept = np.flatnonzero(MASK)
    np.testing.assert_array_equal(pair.corr_x, np.asarray(FULL_VTS)[kept] - 1)
    np.testing.assert_array_equal(pair.corr_y, np.asarray(PARTIAL_VTS) - 1)
    np.testing.assert_array_equal(pair.corr_x_sym, np.asarray(FULL_SYM)[kept] - 1)


def test_float_written_indices_are_accepted(faust_r, lines_writer):
    """The public PFAUST release writes indices as floats (2.812000000000000000e+03)."""
    lines_writer(faust_r / "corres_medium" / "tr_reg_081.vts", [f"{v:.18e}" for v in PARTIAL_VTS])
    np.testing.assert_array_equal(PFaust(faust_r)[0].map_yx, EXPECTED)


def test_inconsistent_files_are_errors(faust_r, lines_writer):
    lines_writer(faust_r / "corres_medium" / "tr_reg_081.vts", PARTIAL_VTS[:4])
    with pytest.raises(DatasetError, match="one partial vertex per kept template point, 5 entries"):
        PFaust(faust_r)[0]
    lines_writer(faust_r / "corres_medium" / "tr_reg_081.vts", PARTIAL_VTS)
    lines_writer(faust_r / "masks_medium" / "tr_reg_081.vts", [1, 0, 2, 1, 0, 1, 1, 0])
    with pytest.raises(DatasetError, match="0/1 flags"):
        PFaust(faust_r)[0]
    lines_writer(faust_r / "masks_medium" / "tr_reg_081.vts", MASK + [0])
    with pytest.raises(DatasetError, match="the masks have 9"):
        PFaust(faust_r)[0]


def test_missing_difficulty_folders_show_the_layout(faust_r):
    with pytest.raises(DatasetError) as err:
        load_dataset("pfaust_h", faust_r)
    message = str(err.value)
    assert "missing folder corres_hard/" in message and "masks_hard/" in message
    assert "Expected layout" in message and "github.com/ABracha/PFAUST" in message
    with pytest.raises(DatasetError, match="difficulty"):
        PFaust(faust_r, difficulty="extreme")
