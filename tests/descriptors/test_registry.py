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
    monkeypatch.setitem(registry._REGISTRY, "fake", entry)
    info = {i.name: i for i in geofeat.descriptors()}["fake"]
    assert not info.available and "geofeat[dino]" in info.reason
    with pytest.raises(MissingDependencyError, match=r"no_such_module_xyz.*pip install 'geofeat\[dino\]'"):
        geofeat.compute(bumpy(), "fake")


def test_params_are_stored_as_given_and_json():
    d = registry.make_descriptor("hks", n_descr=8)
    assert d.get_params() == {"n_eig": 128, "n_descr": 8, "laplacian": "robust", "normalize": True}
    assert d.params_json() == '{"laplacian":"robust","n_descr":8,"n_eig":128,"normalize":true}'
