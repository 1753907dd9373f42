"""`geofeat.train.resume`: a run folder is resumed only on the shapes its checkpoint recorded."""

from pathlib import Path

import pytest

from geofeat.errors import TrainingError
from geofeat.train.resume import check_same_shapes

MINE = [["a", "1" * 64], ["b", "2" * 64]]


def test_the_same_shapes_resume():
    check_same_shapes([list(r) for r in MINE], MINE, Path("run/checkpoints/step_0000002"), Path("run"), "data")


def test_a_checkpoint_without_recorded_shapes_is_refused():
    with pytest.raises(TrainingError, match="records no training shapes.*Train again into a new out folder"):
        check_same_shapes(None, MINE, Path("run/checkpoints/step_0000002"), Path("run"), "data")


def test_changed_shapes_are_named():
    changed = [MINE[0], ["b", "3" * 64]]
    with pytest.raises(TrainingError, match="trained on other shapes"):
        check_same_shapes(changed, MINE, Path("run/checkpoints/step_0000002"), Path("run"), "data")
