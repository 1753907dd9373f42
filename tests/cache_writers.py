"""Shared test helper: a feature-cache writer for tests that start several writing processes at once.

Test modules import it (``from cache_writers import ...``; the tests folder is on ``sys.path``);
a test module never imports another test module.
"""

from __future__ import annotations

import numpy as np

from geofeat import FeatureCache

#: Keys that every `write_shared_and_own_keys` worker writes, each with the same content.
N_SHARED_KEYS = 4


def shared_key(i: int) -> str:
    """The ``i``-th key written by every worker (64 hex digits)."""
    return f"{i:064x}"


def write_shared_and_own_keys(root: str, worker: int, n: int) -> int:
    """Write into the store at ``root`` what concurrent writers write: shared keys and keys of one's own.

    Round ``i`` puts the shared key ``i % 4`` with identical content in every worker, a
    (200, 4) entry of random values under a key only this worker uses, then reads the shared
    key back. Run it in several processes at once (it is picklable for a ``spawn`` pool).

    Parameters
    ----------
    root : str
        The `FeatureCache` folder.
    worker : int
        This worker's number (>= 0): seeds its random entries and makes its own keys unique.
    n : int
        Rounds.

    Returns
    -------
    int
        ``n``: every round finished.

    Raises
    ------
    AssertionError
        A shared key read back is missing or has the wrong shape.

    Notes
    -----
    The store then holds ``N_SHARED_KEYS`` shared entries (shape (500, 8), every value equal
    to the key's number ``i``) plus ``n`` own entries per worker.
    """
    store = FeatureCache(root)
    rng = np.random.default_rng(worker)
    for i in range(n):
        key = shared_key(i % N_SHARED_KEYS)
        store.put(key, np.full((500, 8), i % N_SHARED_KEYS, dtype=np.float32))
        own = rng.standard_normal((200, 4)).astype(np.float32)
        store.put(f"{worker + 1:032x}{i:032x}", own)  # never equal to a shared key
        got = store.get(key)
        assert got is not None and got.shape == (500, 8)
    return n
