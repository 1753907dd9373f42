import numpy as np
import pytest
from shapes import bumpy

import geofeat
from geofeat.descriptors import registry
from geofeat.errors import DescriptorError, MissingDependencyError


def test_compute_contract_on_faust_path(faust_dir):
    feats = geofeat.compute(faust_dir / "off" / "tr_reg_000.off", "wks", cache=False)
    assert feats.shape == (4999, 128) and feats.dtype == np.float32 and feats.flags["C_CONTIGUOUS"]


def test_unknown_name_lists_valid_names():
    with pytest.raises(DescriptorError, match=r"unknown descriptor 'wsk'; valid names: .*hks.*wks"):
        geofeat.compute(bumpy(), "wsk")


def test_unknown_parameter_lists_valid_parameters():
    with pytest.raises(DescriptorError, match=r"unknown parameter\(s\) \['k'\].*n_eig=128, n_descr=128"):
        geofeat.compute(bumpy(), "wks", k=50)


def test_descriptors_listing():
    infos = {info.name: info for info in geofeat.descriptors()}
    assert {"hks", "wks"} <= set(infos)
    assert infos["wks"].available and infos["wks"].params["n_descr"] == 128


def test_missing_dependency_names_the_extra(monkeypatch):
    entry = registry.RegistryEntry("fake", "geofeat.descriptors.spectral:WKS", requires=("no_such_module_xyz",), extra="dino")
    monkeypatch.setattr(registry, "_REGISTRY", registry._REGISTRY.copy())
    registry.register(entry)
    info = {i.name: i for i in geofeat.descriptors()}["fake"]
    assert not info.available and "geofeat[dino]" in info.reason
    with pytest.raises(MissingDependencyError, match=r"no_such_module_xyz.*pip install 'geofeat\[dino\]'"):
        geofeat.compute(bumpy(), "fake")


def test_params_are_stored_as_given_and_json():
    d = registry.make_descriptor("hks", n_descr=8)
    assert d.get_params() == {"n_eig": 128, "n_descr": 8, "laplacian": "robust", "normalize": True}
    assert d.params_json() == '{"laplacian":"robust","n_descr":8,"n_eig":128,"normalize":true}'


def test_register_refuses_a_taken_name_unless_overwrite(monkeypatch):
    monkeypatch.setattr(registry, "_REGISTRY", registry._REGISTRY.copy())
    with pytest.raises(DescriptorError, match=r"a descriptor named 'wks' is already registered; pass overwrite=True"):
        registry.register(registry.RegistryEntry("WKS", "geofeat.descriptors.spectral:HKS"))
    assert registry.descriptor_class("wks").__name__ == "WKS"
    registry.register(registry.RegistryEntry("WKS", "geofeat.descriptors.spectral:HKS"), overwrite=True)
    assert registry.descriptor_class("wks").__name__ == "HKS"


def test_names_are_case_and_dash_insensitive():
    assert registry.descriptor_class(" WKS ").__name__ == "WKS"
    assert registry.descriptor_entry("DinoV3").name == "dinov3"
    with pytest.raises(DescriptorError, match="Did you mean 'dinov3'"):
        registry.descriptor_entry("dino-v3")
