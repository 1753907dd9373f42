"""The one bounded in-memory cache, `geofeat.storage.lru.LRUCache`."""

import threading

import numpy as np
import pytest

from geofeat.storage.lru import LRUCache


def test_least_recently_used_entry_goes_first():
    cache = LRUCache(2)
    cache.put("a", 1)
    cache["b"] = 2
    assert cache.get("a") == 1  # "a" is now the most recent
    cache.put("c", 3)
    assert list(cache) == ["a", "c"]
    assert "b" not in cache and len(cache) == 2
    assert cache.get("b") is None and cache.get("b", 0) == 0
    with pytest.raises(KeyError):
        cache["b"]
    assert cache.pop("a") == 1 and list(cache) == ["c"]
    cache.clear()
    assert len(cache) == 0


def test_unbounded_and_limits_read_at_insertion():
    assert len(LRUCache(None)) == 0
    cache = LRUCache()
    for i in range(100):
        cache.put(i, i)
    assert len(cache) == 100
    size = {"n": 3}
    cache = LRUCache(lambda: size["n"])
    for i in range(5):
        cache.put(i, i)
    assert list(cache) == [2, 3, 4]
    size["n"] = 1
    cache.put(5, 5)
    assert list(cache) == [5]


def test_weight_limit_keeps_the_newest_entry():
    cache = LRUCache(10, max_weight=100, weigh=lambda a: a.nbytes)
    cache.put("small", np.zeros(5))  # 40 bytes
    cache.put("other", np.zeros(5))  # 80 in all
    cache.put("big", np.zeros(50))  # 400 bytes alone: kept, the others go
    assert list(cache) == ["big"]
    with pytest.raises(TypeError, match="weigh"):
        LRUCache(2, max_weight=10)


def test_get_or_compute_computes_once():
    calls = []
    cache = LRUCache(4)

    def compute():
        calls.append(1)
        return "value"

    assert cache.get_or_compute("k", compute) == "value"
    assert cache.get_or_compute("k", compute) == "value"
    assert len(calls) == 1
    # None is a value like any other
    assert cache.get_or_compute("none", lambda: None) is None
    assert cache.get_or_compute("none", lambda: 1 / 0) is None


def test_threads_share_it_safely():
    cache = LRUCache(8)

    def work(offset):
        for i in range(2000):
            cache.get_or_compute((offset + i) % 32, lambda i=i: i)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(cache) == 8
