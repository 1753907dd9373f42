"""`geofeat.registry`: the one lazy-registry mechanism of descriptors, datasets and heads."""

import sys

import pytest

from geofeat.errors import DatasetError, DescriptorError, GeofeatError, HeadError, MissingDependencyError
from geofeat.registry import LazyEntry, as_entry, lookup


def test_lazy_entry_imports_on_load_and_names_the_extra():
    entry = LazyEntry("toy", "json:dumps")
    assert entry.missing() == [] and entry.load() is sys.modules["json"].dumps
    assert as_entry("x", "json:loads").load() is sys.modules["json"].loads
    assert as_entry("x", len).load() is len
    needy = LazyEntry("toy", "json:dumps", requires=("no_such_module_xyz",), extra="dino")
    assert needy.missing() == ["no_such_module_xyz"]
    with pytest.raises(MissingDependencyError, match=r"widget 'toy' needs no_such_module_xyz.*pip install 'geofeat\[dino\]'"):
        needy.load("widget")
    assert LazyEntry("t", "m:a", requires=("zz_mod",)).install_hint() == "pip install zz_mod"


def test_lookup_suggests_close_names():
    registry = {"alpha_one": LazyEntry("alpha_one", "json:dumps"), "beta": "json:loads"}
    assert lookup(registry, "beta", "thing", GeofeatError).target == "json:loads"
    with pytest.raises(
        GeofeatError, match=r"unknown thing 'alpha_on'; valid names: alpha_one, beta\. Did you mean 'alpha_one'\?"
    ):
        lookup(registry, "alpha_on", "thing", GeofeatError)
    with pytest.raises(GeofeatError, match=r"unknown thing 3"):
        lookup(registry, 3, "thing", GeofeatError)
    assert (
        lookup(registry, "ALPHA-ONE", "thing", GeofeatError, canonical=lambda n: n.lower().replace("-", "_")).name == "alpha_one"
    )


def test_the_three_registries_share_it():
    from geofeat.adapters.heads import head_class
    from geofeat.datasets.registry import load_dataset
    from geofeat.descriptors.registry import descriptor_class

    for call, error, text in (
        (lambda: descriptor_class("wsk"), DescriptorError, "Did you mean 'wks'"),
        (lambda: load_dataset("faust_rr", "/nowhere"), DatasetError, "Did you mean 'faust_r'"),
        (lambda: head_class("dpfn"), HeadError, "Did you mean 'dpfm'"),
    ):
        with pytest.raises(error, match=text):
            call()
