"""The official release's training sets: which files, in which order, in which frame."""

import numpy as np
import pytest
from shapes import bumpy, data_root, write_off

from geofeat.errors import TrainingError
from geofeat.train.shapes import load_training_shapes, official_training_files


def test_faust_is_the_first_80_shapes_of_faust_r():
    files = official_training_files("faust", data_root())
    assert [p.name for p in files] == [f"tr_reg_{i:03d}.off" for i in range(80)]


def test_becos_takes_each_shape_of_the_pair_folders_once_and_leaves_out_the_red_list(tmp_path):
    train = tmp_path / "BeCoS" / "full_full" / "train"
    for folder, names in {"0": ("0_cat3", "1_horse7"), "2": ("0_horse7", "1_gorilla1"), "10": ("0_cat3", "1_centaur0")}.items():
        for name in names:
            write_off(train / folder / f"{name}.off", bumpy(0, 1))
    (train / "notes").mkdir()  # not a pair folder
    becos = official_training_files("becos", tmp_path)
    assert [f"{p.parent.name}/{p.name}" for p in becos] == [
        "0/0_cat3.off",
        "0/1_horse7.off",
        "2/1_gorilla1.off",
        "10/1_centaur0.off",
    ]
    without = official_training_files("becos_without_shrec16", tmp_path)
    assert [p.name for p in without] == ["1_gorilla1.off"]


def test_smal_keeps_the_five_animals_and_turns_them_upside_down(tmp_path):
    folder = tmp_path / "SMAL_r" / "off"
    for name in ("cow_01", "dog_2", "hippo_03", "lion_x", "horse_1"):
        write_off(folder / f"{name}.off", bumpy(1, 1))
    assert [p.stem for p in official_training_files("smal", tmp_path)] == ["cow_01", "dog_2", "lion_x"]
    meshes = load_training_shapes("smal", root=str(tmp_path), progress=False)
    np.testing.assert_allclose(meshes[0].verts, bumpy(1, 1).verts * [1.0, -1.0, -1.0])


def test_a_missing_training_folder_says_what_it_looks_for(tmp_path):
    with pytest.raises(TrainingError, match="BeCoS/full_full/train"):
        official_training_files("becos", tmp_path)
