"""`geofeat.registry`: the one lazy-registry mechanism of descriptors, datasets and heads."""

import sys

import pytest

from geofeat.errors import DatasetError, DescriptorError, GeofeatError, HeadError, MissingDependencyError
from geofeat.registry import LazyEntry, Registry, canonical_name


def test_lazy_entry_imports_on_load_and_names_the_extra():
    entry = LazyEntry("toy", "json:dumps")
    assert entry.missing() == [] and entry.load() is sys.modules["json"].dumps
    assert LazyEntry("x", "json:loads").load() is sys.modules["json"].loads
    assert LazyEntry("x", len).load() is len  # an object is its own target
    needy = LazyEntry("toy", "json:dumps", requires=("no_such_module_xyz",), extra="dino")
    assert needy.missing() == ["no_such_module_xyz"]
    with pytest.raises(MissingDependencyError, match=r"widget 'toy' needs no_such_module_xyz.*pip install 'geofeat\[dino\]'"):
        needy.load("widget")
    assert LazyEntry("t", "m:a", requires=("zz_mod",)).install_hint() == "pip install zz_mod"


def _things() -> Registry:
    things = Registry("thing", GeofeatError)
    things.register(LazyEntry("alpha_one", "json:dumps"))
    things.register(LazyEntry("beta", "json:loads"))
    return things


def test_lookup_suggests_close_names():
    registry = _things()
    assert registry.entry("beta").target == "json:loads"
    with pytest.raises(
        GeofeatError, match=r"unknown thing 'alpha_on'; valid names: alpha_one, beta\. Did you mean 'alpha_one'\?"
    ):
        registry.entry("alpha_on")
    with pytest.raises(GeofeatError, match=r"unknown thing 3"):
        registry.entry(3)
    assert registry.entry("ALPHA-ONE").name == "alpha_one"


def test_names_are_case_dash_and_space_insensitive():
    registry = _things()
    assert canonical_name(" Alpha-One ") == "alpha_one"
    assert registry.load(" Alpha-One ") is sys.modules["json"].dumps
    assert "ALPHA-ONE" in registry and "alpha" not in registry and 3 not in registry
    assert registry.names() == list(registry) == ["alpha_one", "beta"] and len(registry) == 2
    stored = registry.register(LazyEntry("Gamma-Ray", "json:dumps", summary="s"))
    assert stored.name == "gamma_ray" and stored.summary == "s" and registry.entry("gamma_ray") is stored


def test_duplicates_are_refused_unless_overwrite():
    registry = _things()
    with pytest.raises(GeofeatError, match=r"a thing named 'beta' is already registered; pass overwrite=True"):
        registry.register(LazyEntry("BETA", "json:dumps"))  # the same name under the case rule
    assert registry.entry("beta").target == "json:loads"
    registry.register(LazyEntry("BETA", "json:dumps"), overwrite=True)
    assert registry.entry("beta").target == "json:dumps"


def test_register_checks_the_entry_and_unregister_copy():
    registry = _things()
    with pytest.raises(GeofeatError, match=r"registered as a geofeat.registry.LazyEntry.*found str"):
        registry.register("json:dumps")
    with pytest.raises(GeofeatError, match="must not be empty"):
        registry.register(LazyEntry(" ", "json:dumps"))
    copy = registry.copy()
    assert copy.unregister("Beta").target == "json:loads"
    assert copy.names() == ["alpha_one"] and registry.names() == ["alpha_one", "beta"]
    with pytest.raises(GeofeatError, match="unknown thing 'beta'"):
        copy.unregister("beta")


def test_missing_dependency_through_the_registry():
    registry = Registry("widget", HeadError)
    registry.register(LazyEntry("toy", "json:dumps", requires=("no_such_module_xyz",), extra="dino"))
    with pytest.raises(MissingDependencyError, match=r"widget 'toy' needs no_such_module_xyz.*pip install 'geofeat\[dino\]'"):
        registry.load("TOY")


def test_the_three_registries_share_it():
    from geofeat.adapters.head_registry import head_class
    from geofeat.datasets.registry import load_dataset
    from geofeat.descriptors.registry import descriptor_class

    for call, error, text in (
        (lambda: descriptor_class("wsk"), DescriptorError, "Did you mean 'wks'"),
        (lambda: load_dataset("faust_rr", "/nowhere"), DatasetError, "Did you mean 'faust_r'"),
        (lambda: head_class("dpfn"), HeadError, "Did you mean 'dpfm'"),
    ):
        with pytest.raises(error, match=text):
            call()
