"""`compute` with a name or an instance, and the one loop over a collection (`compute_each`, `compute_many`)."""

import numpy as np
import pytest
from shapes import bumpy, sphere

import geofeat
from geofeat.descriptors import as_descriptor, make_descriptor
from geofeat.descriptors.compute import compute_each
from geofeat.descriptors.spectral import HKS, WKS
from geofeat.errors import DescriptorError, MeshError


def test_an_instance_gives_what_the_name_and_parameters_give_from_one_entry():
    mesh = bumpy(0, 2)
    store = geofeat.FeatureCache()
    by_name = geofeat.compute(mesh, "wks", cache=store, n_descr=16)
    by_instance = geofeat.compute(mesh, WKS(n_descr=16), cache=store)  # read from the entry the name wrote
    np.testing.assert_array_equal(by_name, by_instance)
    assert by_instance.shape == (mesh.n_vertices, 16) and len(store.entries()) == 1
    assert geofeat.make_descriptor is make_descriptor
    assert geofeat.compute(mesh, make_descriptor("WKS", n_descr=16), cache=store).shape == (mesh.n_vertices, 16)
    assert len(store.entries()) == 1


def test_an_instance_with_parameters_or_a_class_is_refused():
    mesh = bumpy(0, 2)
    with pytest.raises(
        DescriptorError, match=r"parameters \['n_descr'\] were given with the descriptor instance WKS\(.*not both"
    ):
        geofeat.compute(mesh, WKS(), n_descr=8)
    with pytest.raises(DescriptorError, match=r"found the class HKS\. Pass an instance: HKS\(\)"):
        geofeat.compute(mesh, HKS)
    with pytest.raises(DescriptorError, match=r"expected a registered descriptor name .* found 3 \(int\)"):
        as_descriptor(3)
    hks = HKS(n_descr=4)
    assert as_descriptor(hks) is hks and as_descriptor("hks", n_descr=4).get_params() == hks.get_params()


def test_compute_each_reports_each_shape_and_goes_on_after_a_failure(tmp_path):
    store = geofeat.FeatureCache(tmp_path / "store")
    meshes = [bumpy(0, 2), tmp_path / "missing.off", sphere(2)]
    wks = WKS(n_descr=8)
    geofeat.compute(meshes[0], wks, cache=store)  # present before the loop
    outcomes = list(compute_each(meshes, wks, store, progress=False))
    assert [o.index for o in outcomes] == [0, 1, 2]
    assert [o.status for o in outcomes] == ["present", "failed", "computed"]
    assert isinstance(outcomes[1].error, MeshError) and outcomes[1].features is None and outcomes[1].key is None
    assert outcomes[2].mesh_hash == meshes[2].hash and outcomes[2].features.shape == (meshes[2].n_vertices, 8)
    assert store.get(outcomes[2].key) is not None and len(store.entries()) == 2
    uncached = list(compute_each(meshes[:1], wks, None, progress=False))
    assert uncached[0].status == "computed" and uncached[0].key is None


def test_compute_many_equals_compute_in_input_order(tmp_path):
    meshes = [bumpy(seed, 2) for seed in range(3)]
    many = geofeat.compute_many(meshes, "hks", cache=tmp_path / "store", progress=False, n_descr=4)
    for mesh, features in zip(meshes, many, strict=True):
        np.testing.assert_array_equal(features, geofeat.compute(mesh, "hks", cache=tmp_path / "store", n_descr=4))
    assert len(geofeat.FeatureCache(tmp_path / "store").entries()) == 3
    again = geofeat.compute_many(iter(meshes), HKS(n_descr=4), cache=False, progress=False)  # any iterable, an instance
    for a, b in zip(many, again, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_compute_many_raises_the_first_failure_and_checks_before_work(tmp_path):
    with pytest.raises(DescriptorError, match="unknown parameter"):
        geofeat.compute_many([tmp_path / "never_read.off"], "hks", k=3)
    with pytest.raises(MeshError):
        geofeat.compute_many([bumpy(0, 2), tmp_path / "missing.off"], "hks", cache=False, progress=False)
    with pytest.raises(geofeat.GeofeatError, match="n_jobs"):
        geofeat.compute_many([bumpy(0, 2)], "hks", n_jobs=0)


def test_compute_many_in_two_worker_processes(tmp_path):
    meshes = [bumpy(seed, 2) for seed in range(3)]
    store = tmp_path / "store"
    parallel = geofeat.compute_many(meshes, WKS(n_descr=8), cache=store, n_jobs=2, progress=False)
    assert [f.shape for f in parallel] == [(m.n_vertices, 8) for m in meshes]
    assert len(geofeat.FeatureCache(store).entries()) == 3
    for mesh, features in zip(meshes, parallel, strict=True):  # read back from the entries the workers wrote
        np.testing.assert_array_equal(features, geofeat.compute(mesh, WKS(n_descr=8), cache=store))
