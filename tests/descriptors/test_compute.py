"""`compute` with a name or an instance, and the one loop over a collection (`compute_each`, `compute_many`)."""

import threading

import numpy as np
import pytest
import torch
from shapes import bumpy, sphere

import geofeat
from geofeat.descriptors import Descriptor, as_descriptor, make_descriptor
from geofeat.descriptors.collection import compute_each, default_prefetch
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


# ---- read-ahead: shapes read, looked up and prepared on a background thread (compute_each's prefetch)


class PreparedForTests(Descriptor):
    """A descriptor whose `prepare` does part of the work (sorted squared distances to a few vertices).

    It records which thread prepared which mesh, and how many meshes were prepared when each
    one was computed; ``wait_for`` holds the first computation until that many are prepared.
    """

    name = "prepared_for_tests"

    def __init__(self, *, n_descr: int = 4, fail_on: int = -1, nan_on: int = -1):
        self.n_descr = n_descr
        self.fail_on = fail_on  # prepare raises a RuntimeError (not a GeofeatError) on a mesh of this many vertices
        self.nan_on = nan_on  # compute_prepared returns NaN on a mesh of this many vertices
        self.prepared_on: list[tuple[str, int]] = []  # (mesh name, thread ident)
        self.computed_after: list[tuple[str, int]] = []  # (mesh name, meshes prepared by then)
        self.wait_for = 0
        self._enough = threading.Event()

    def prepare(self, mesh):
        if mesh.n_vertices == self.fail_on:
            raise RuntimeError("a bug in prepare")
        anchors = mesh.verts[:: max(1, mesh.n_vertices // self.n_descr)][: self.n_descr]
        distances = ((mesh.verts[:, None, :] - anchors[None]) ** 2).sum(-1)
        self.prepared_on.append((mesh.name, threading.get_ident()))
        if len(self.prepared_on) >= self.wait_for:
            self._enough.set()
        return distances

    def compute_prepared(self, mesh, prepared):
        if self.wait_for and not self.computed_after:
            assert self._enough.wait(60), "the read-ahead thread did not prepare the next shapes"
        self.computed_after.append((mesh.name, len(self.prepared_on)))
        if mesh.n_vertices == self.nan_on:
            return np.full_like(prepared, np.nan)
        return np.sqrt(prepared) / (1.0 + prepared.mean(axis=0))

    def compute(self, mesh):
        return self.compute_prepared(mesh, self.prepare(mesh))


def named(mesh, name):
    return geofeat.Mesh(mesh.verts, mesh.faces, name=name)


def collection_with_trouble(tmp_path):
    """Seven inputs: a mesh given twice (present the second time, looked up before the first is stored when read
    ahead), a missing file in the middle, a small mesh last."""
    meshes = [named(bumpy(seed, 2), f"m{seed}") for seed in range(4)]
    return [meshes[0], meshes[1], meshes[0], tmp_path / "missing.off", meshes[2], meshes[3], bumpy(0, 1)]


def summary(outcomes):
    return [(o.index, o.status, o.key, o.mesh_hash, None if o.error is None else (type(o.error), str(o.error))) for o in outcomes]


@pytest.mark.parametrize(
    "make",
    [lambda: PreparedForTests(n_descr=4, nan_on=bumpy(0, 1).n_vertices), lambda: HKS(n_descr=4, n_eig=12)],
    ids=["prepared", "hks"],
)
def test_prefetch_gives_the_outcomes_and_features_of_no_prefetch(tmp_path, make):
    items = collection_with_trouble(tmp_path)
    runs, entries = {}, {}
    for prefetch in (0, 1, 2):
        descriptor = make()
        store = geofeat.FeatureCache(tmp_path / f"store{prefetch}")
        geofeat.compute(items[1], descriptor, cache=store)  # present before the loop
        runs[prefetch] = list(compute_each(items, descriptor, store, prefetch=prefetch, progress=False))
        entries[prefetch] = sorted(path.name for path in store.entries())
    expected = runs[0]
    last = "failed" if make().name == "prepared_for_tests" else "computed"  # non-finite features: refused, not stored
    assert [o.status for o in expected] == ["computed", "present", "present", "failed", "computed", "computed", last]
    assert isinstance(expected[3].error, MeshError)
    if last == "failed":
        assert isinstance(expected[6].error, DescriptorError) and "non-finite" in str(expected[6].error)
    for prefetch in (1, 2):
        assert summary(runs[prefetch]) == summary(expected) and entries[prefetch] == entries[0]
        for a, b in zip(runs[prefetch], expected, strict=True):
            assert (a.features is None) == (b.features is None)
            if a.features is not None:
                np.testing.assert_array_equal(a.features, b.features)
    uncached = list(compute_each(items, make(), None, prefetch=2, progress=False))  # no store: nothing is present
    assert [o.status for o in uncached] == ["computed", "computed", "computed", "failed", "computed", "computed", last]
    np.testing.assert_array_equal(uncached[4].features, expected[4].features)


def test_prepare_runs_on_one_background_thread_at_most_prefetch_shapes_ahead(tmp_path):
    meshes = [named(bumpy(seed, 2), f"m{seed}") for seed in range(6)]
    for prefetch in (1, 2, 3):
        descriptor = PreparedForTests()
        descriptor.wait_for = prefetch + 1  # the first shape is computed once the next `prefetch` ones are prepared
        outcomes = list(compute_each(meshes, descriptor, None, prefetch=prefetch, progress=False))
        assert [o.status for o in outcomes] == ["computed"] * 6
        assert [name for name, _ in descriptor.prepared_on] == [m.name for m in meshes]  # each once, in order
        threads = {ident for _, ident in descriptor.prepared_on}
        assert len(threads) == 1 and threading.get_ident() not in threads
        assert [name for name, _ in descriptor.computed_after] == [m.name for m in meshes]
        for index, (_, prepared) in enumerate(descriptor.computed_after):
            assert prepared <= min(index + 1 + prefetch, len(meshes)), (prefetch, index, prepared)
        assert descriptor.computed_after[0][1] == prefetch + 1
    present = PreparedForTests()
    store = geofeat.FeatureCache(tmp_path / "store")
    list(compute_each(meshes, present, store, prefetch=2, progress=False))
    again = PreparedForTests()
    assert {o.status for o in compute_each(meshes, again, store, prefetch=2, progress=False)} == {"present"}
    assert again.prepared_on == []  # nothing is prepared for a shape whose entry is there
    default = PreparedForTests()
    list(compute_each(meshes[:3], default, None, progress=False))  # prefetch None: on, since prepare is overridden
    assert threading.get_ident() not in {ident for _, ident in default.prepared_on}
    hks = HKS(n_descr=4, n_eig=12)
    with pytest.raises(DescriptorError, match="prefetch"):
        list(compute_each(meshes, hks, None, prefetch=-1, progress=False))


class RecordingCache(geofeat.FeatureCache):
    """A store that records which thread wrote each entry and what had been computed by then."""

    def __init__(self, root, descriptor):
        super().__init__(root)
        self.descriptor = descriptor
        self.writes: list[tuple[str, int]] = []  # (thread name, meshes computed when the write began)

    def put(self, key, features, meta=None):
        self.writes.append((threading.current_thread().name, len(self.descriptor.computed_after)))
        return super().put(key, features, meta)


def test_entries_are_written_on_a_thread_of_their_own_and_each_outcome_comes_once_saved(tmp_path):
    meshes = [named(bumpy(seed, 2), f"m{seed}") for seed in range(5)]
    descriptor = PreparedForTests()
    store = RecordingCache(tmp_path / "store", descriptor)
    for outcome in compute_each(meshes, descriptor, store, prefetch=2, progress=False):
        assert outcome.status == "computed"
        np.testing.assert_array_equal(store.get(outcome.key), outcome.features)  # on disk before it is given
    assert {name.split("_")[0] for name, _ in store.writes} == {"geofeat-write"}
    assert [computed for _, computed in store.writes] == [1, 2, 3, 4, 5]  # each written after its own computation

    stopped = PreparedForTests()
    store = geofeat.FeatureCache(tmp_path / "stopped")
    outcomes = compute_each(meshes, stopped, store, prefetch=2, progress=False)
    assert next(outcomes).index == 0
    outcomes.close()  # shape 1 was computed while shape 0 was written: its entry is finished, not lost
    assert len(stopped.computed_after) == 2 and len(list(store.entries())) == 2


def read_ahead_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("geofeat-read-ahead")]


def working_threads() -> set[threading.Thread]:
    """The threads a Python program waits for at exit (tqdm's monitor, a daemon started by any bar, is left out)."""
    return {t for t in threading.enumerate() if not t.daemon}


def test_an_early_stop_or_an_error_ends_the_read_ahead_thread(tmp_path):
    before = working_threads()
    meshes = [named(bumpy(seed, 2), f"m{seed}") for seed in range(8)]
    descriptor = PreparedForTests()
    outcomes = compute_each(meshes, descriptor, None, prefetch=2, progress=False)
    assert next(outcomes).status == "computed"
    assert read_ahead_threads()  # running while the loop is
    outcomes.close()
    assert read_ahead_threads() == [] and not working_threads() - before
    assert len(descriptor.prepared_on) <= 3  # the shape computed and the 2 ahead of it, no more

    stopped = PreparedForTests()  # compute_many stops at the first failure
    with pytest.raises(MeshError):
        geofeat.compute_many([meshes[0], tmp_path / "missing.off", *meshes[1:]], stopped, cache=False, progress=False)
    assert not working_threads() - before
    assert len(stopped.prepared_on) <= 3  # shapes 0, 2 and 3 at most (the missing file is shape 1)

    buggy = PreparedForTests(fail_on=bumpy(0, 1).n_vertices)  # not a GeofeatError: raised, in its turn
    items = [meshes[0], meshes[1], bumpy(0, 1), meshes[2]]
    seen = []
    with pytest.raises(RuntimeError, match="a bug in prepare"):
        for outcome in compute_each(items, buggy, None, prefetch=2, progress=False):
            seen.append(outcome.index)
    assert seen == [0, 1] and not working_threads() - before


def test_dinov3_renders_ahead_by_default_and_gives_the_same_features(tmp_path):
    from tiny_models import tiny_dinov3

    tiny_dinov3().save_pretrained(tmp_path / "v3")
    params = {"weights": str(tmp_path / "v3"), "views": 4, "image_size": 64, "batch_size": 2, "device": "cpu"}
    meshes = [named(bumpy(seed, 2), f"m{seed}") for seed in range(3)]
    runs = {}
    for prefetch in (0, None):
        descriptor = make_descriptor("dinov3", **params)
        store = geofeat.FeatureCache(tmp_path / f"store{prefetch}")
        runs[prefetch] = list(compute_each(meshes, descriptor, store, prefetch=prefetch, progress=False))
    assert default_prefetch(descriptor) == 2 and default_prefetch(HKS()) == 0
    assert summary(runs[None]) == summary(runs[0]) and {o.status for o in runs[0]} == {"computed"}
    for a, b in zip(runs[None], runs[0], strict=True):
        np.testing.assert_array_equal(a.features, b.features)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_dinov3_on_cuda_renders_ahead_on_its_own_stream_with_bfloat16_and_gives_the_same_features(tmp_path):
    from tiny_models import tiny_dinov3

    from geofeat.descriptors.dino import render_stream

    tiny_dinov3().save_pretrained(tmp_path / "v3")
    params = {"weights": str(tmp_path / "v3"), "views": 9, "image_size": 128, "device": "cuda", "amp": "on"}
    meshes = [named(bumpy(seed, 2), f"m{seed}") for seed in range(4)]
    runs = {}
    for prefetch in (0, 2):
        descriptor = make_descriptor("dinov3", **params)
        runs[prefetch] = list(compute_each(meshes, descriptor, None, prefetch=prefetch, progress=False))
    assert render_stream(torch.device("cuda")) is not torch.cuda.current_stream()
    assert {o.status for o in runs[0]} == {o.status for o in runs[2]} == {"computed"}
    for a, b in zip(runs[2], runs[0], strict=True):
        np.testing.assert_allclose(a.features, b.features, rtol=0, atol=1e-6)
