"""Dataset registry: names, fixed options, options, errors."""

import pytest

from geofeat.datasets import registry
from geofeat.datasets.faust import FaustRemeshed
from geofeat.datasets.registry import dataset_names, load_dataset, register_dataset
from geofeat.errors import DatasetError, GeofeatError


def test_builtin_names():
    expected = {"faust_r", "scape_r", "shrec16_cuts", "shrec16_holes", "pfaust_m", "pfaust_h"}
    expected |= {"becos_f2f", "becos_p2f", "becos_p2p", "psmal", "cp2p24"}
    assert expected <= set(dataset_names())
    assert dataset_names() == sorted(dataset_names())


def test_names_are_case_and_dash_insensitive_and_root_defaults_to_env(faust_dir, monkeypatch):
    monkeypatch.setenv("GEOFEAT_DATA", str(faust_dir.parent))
    dataset = load_dataset("FAUST-R", split="test", seed=3)  # seed: accepted, ignored (fixed pairs)
    assert isinstance(dataset, FaustRemeshed) and len(dataset) == 380


def test_unknown_name_suggests_close_ones():
    with pytest.raises(DatasetError, match="Did you mean 'faust_r'") as err:
        load_dataset("faust", "/nowhere")
    assert isinstance(err.value, GeofeatError) and isinstance(err.value, ValueError)


def test_options_are_checked(tmp_path):
    with pytest.raises(DatasetError, match="fixes partiality='cuts'"):
        load_dataset("shrec16_cuts", tmp_path, partiality="holes")
    with pytest.raises(DatasetError, match=r"does not take option\(s\) colour; it takes: .*pairs"):
        load_dataset("faust_r", tmp_path, colour="red")


def test_missing_root_without_env(monkeypatch):
    monkeypatch.delenv("GEOFEAT_DATA", raising=False)
    with pytest.raises(DatasetError, match="GEOFEAT_DATA"):
        load_dataset("cp2p24")


def test_register_dataset(monkeypatch):
    monkeypatch.setattr(registry, "_REGISTRY", registry._REGISTRY.copy())
    seen = {}

    def factory(root, split, **options):
        seen.update(root=root, split=split, **options)
        return []

    register_dataset("My-Set", factory, description="test", kind="cuts")
    assert "my_set" in dataset_names()
    load_dataset("my_set", "somewhere", split="val", seed=1)
    assert seen == {"root": "somewhere", "split": "val", "kind": "cuts", "seed": 1}
    with pytest.raises(DatasetError, match="already registered"):
        register_dataset("my_set", factory)
    register_dataset(" MY-SET", factory, description="replaced", overwrite=True)
    assert registry.dataset_description("my_set") == "replaced" and dataset_names().count("my_set") == 1
