"""`geofeat.storage.jsonconfig.JsonConfig`: one dict/JSON/unknown-key rule for every configuration."""

import json
import logging
from dataclasses import dataclass, field

import pytest

from geofeat.errors import BackboneError, HeadError, TrainingError
from geofeat.storage.jsonconfig import JsonConfig


@dataclass
class Toy(JsonConfig):
    size: int = 3
    names: tuple[str, ...] = ("a", "b")
    extra_params: dict = field(default_factory=dict)


def test_round_trip_and_json_form(tmp_path):
    toy = Toy(size=5, names=("x",), extra_params={"k": (1, 2)})
    assert toy.to_dict() == {"size": 5, "names": ["x"], "extra_params": {"k": [1, 2]}}
    path = toy.save(tmp_path / "toy.json")
    assert json.loads(path.read_text()) == toy.to_dict()
    again = Toy.load(path)
    assert again.to_dict() == toy.to_dict() and again.unknown == {} and again.unknown_keys == []
    assert Toy.load(path, size=7, names=None).size == 7  # overrides that are None are skipped


def test_unknown_keys_warned_kept_aside_and_saved_back(tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        toy = Toy.from_dict({"size": 4, "from_the_future": {"x": 1}, "note": "hi"})
    assert "from_the_future" in caplog.text and "note" in caplog.text
    assert toy == Toy(size=4)  # settings only
    assert toy.unknown == {"from_the_future": {"x": 1}, "note": "hi"}
    assert toy.unknown_keys == ["from_the_future", "note"]
    assert "note" not in toy.to_dict(unknown=False)
    toy.save(tmp_path / "t.json")
    saved = json.loads((tmp_path / "t.json").read_text())
    assert saved["from_the_future"] == {"x": 1} and saved["size"] == 4
    assert Toy.load(tmp_path / "t.json").unknown == toy.unknown


def test_every_configuration_uses_it(tmp_path):
    from geofeat.adapters.base import HeadConfig
    from geofeat.adapters.head_registry import head_class
    from geofeat.backbones.lora import LoraSettings
    from geofeat.train.config import TrainConfig

    for cls in (HeadConfig, head_class("ulrssm").config_class, TrainConfig, LoraSettings):
        assert issubclass(cls, JsonConfig)
    (tmp_path / "list.json").write_text("[1]")
    for cls, error in ((HeadConfig, HeadError), (TrainConfig, TrainingError), (LoraSettings, BackboneError)):
        with pytest.raises(error, match="mapping"):
            cls.load(tmp_path / "list.json")
        with pytest.raises(error, match="does not exist"):
            cls.load(tmp_path / "missing.json")
    config = TrainConfig.from_dict({"data": "shapes", "wandb_project": "x"})
    config.save(tmp_path / "c.json")
    assert json.loads((tmp_path / "c.json").read_text())["wandb_project"] == "x"
    assert TrainConfig.from_file(tmp_path / "c.json") == config


def test_unknown_values_are_kept_in_json_form(tmp_path):
    import datetime

    toy = Toy.from_dict({"size": 1, "when": datetime.date(2026, 1, 2), "pair": (1, 2)})
    assert toy.unknown == {"when": "2026-01-02", "pair": [1, 2]}
    toy.save(tmp_path / "t.json")
    assert Toy.load(tmp_path / "t.json").unknown == toy.unknown
