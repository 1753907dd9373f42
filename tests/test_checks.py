"""`geofeat.checks`: the one set of parameter checks, and the places that use it."""

import numpy as np
import pytest

from geofeat.checks import check_integer, check_number
from geofeat.errors import DescriptorError, SpectralError


def test_expected_replaces_the_default_wording():
    with pytest.raises(DescriptorError, match=r"n_jobs must be a positive integer number of processes; found 0 \(int\)"):
        check_integer(0, "n_jobs", low=1, expected="a positive integer number of processes")
    with pytest.raises(DescriptorError, match=r"x must be an integer >= 1; found True \(bool\)"):
        check_integer(True, "x", low=1)
    with pytest.raises(SpectralError, match=r"owner: p must be a probability; found 1.5"):
        check_number(1.5, "p", owner="owner", high=1, error=SpectralError, expected="a probability")


def test_boundary_checks_accept_numpy_scalars_and_refuse_bools():
    from geofeat.adapters.blocks.diffusion_net import DiffusionNet
    from geofeat.backbones.lora import LoraSettings
    from geofeat.errors import BackboneError, DiffusionNetError

    settings = LoraSettings(rank=np.int64(4), alpha=np.float32(8.0), dropout=np.float64(0.1))
    assert type(settings.rank) is int and settings.rank == 4
    assert type(settings.alpha) is float and type(settings.dropout) is float
    with pytest.raises(BackboneError, match="rank"):
        LoraSettings(rank=True)
    with pytest.raises(DiffusionNetError, match="n_blocks must be a non-negative integer"):
        DiffusionNet(4, 2, width=8, n_blocks=False)
    with pytest.raises(DiffusionNetError, match=r"dropout must be True, False or a probability in \[0, 1\)"):
        DiffusionNet(4, 2, width=8, dropout="yes")


def test_training_settings_refuse_bools_and_keep_numpy_scalars_as_python_values():
    from geofeat.errors import TrainingError
    from geofeat.train.config import TrainConfig

    with pytest.raises(TrainingError, match="rank must be a positive integer, found True"):
        TrainConfig(data="x", rank=True)
    with pytest.raises(TrainingError, match="lr must be a number > 0"):
        TrainConfig(data="x", lr=float("inf"))
    config = TrainConfig(data="x", steps=np.int64(5), lr=np.float32(0.5))
    assert type(config.steps) is int and type(config.lr) is float and config.to_dict()["steps"] == 5


def test_key_values_are_json_when_they_parse_and_given_once():
    from geofeat.checks import parse_key_values
    from geofeat.errors import ExtractError

    assert parse_key_values(["n_eig=12", " scale =0.5", "normalize=false", "laplacian=cotan", "x=[1, 2]", "s="]) == {
        "n_eig": 12,
        "scale": 0.5,
        "normalize": False,
        "laplacian": "cotan",
        "x": [1, 2],
        "s": "",
    }
    with pytest.raises(DescriptorError, match=r"--param expects KEY=VALUE \(for example --param n_descr=128\); found 'n_eig'"):
        parse_key_values(["n_eig"])
    with pytest.raises(ExtractError, match=r"--head-param expects KEY=VALUE.*found '=3'"):
        parse_key_values(["=3"], "--head-param", error=ExtractError)
    with pytest.raises(DescriptorError, match=r"--param n_eig is given twice \(3 and '4'\); give it once"):
        parse_key_values(["n_eig=3", "n_eig=4"])
