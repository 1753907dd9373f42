"""Point sampling on shapes: greedy farthest-point sampling.

>>> samples = farthest_point_sampling(mesh.verts, 500, seed=0)   # (500,) int64 vertex indices  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np

from geofeat.checks import check_integer
from geofeat.errors import MeshError

__all__ = ["farthest_point_sampling"]


def farthest_point_sampling(points, n_samples: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """Indices of ``n_samples`` points spread by greedy farthest-point sampling (Euclidean).

    Starts from a point drawn with ``seed``; each next sample is the point farthest from all
    samples so far (the first on ties). Any prefix of the result is itself a farthest-point
    sample.

    Parameters
    ----------
    points : array_like, shape (N, D)
        Finite coordinates (computed in float64).
    n_samples : int
        ``1 <= n_samples <= N``.
    seed : int or numpy.random.Generator
        Chooses the first sample.

    Returns
    -------
    numpy.ndarray, shape (n_samples,), int64
        Distinct indices into ``points``, in the order they were chosen.

    Raises
    ------
    MeshError
        ``points`` is not a non-empty finite (N, D) array, or ``n_samples`` is outside ``[1, N]``.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] == 0 or not np.isfinite(pts).all():
        raise MeshError(f"farthest_point_sampling: points must be a finite (N, D) array with N >= 1; found shape {pts.shape}.")
    n = pts.shape[0]
    check_integer(n_samples, "n_samples", owner="farthest_point_sampling", low=1, high=n, error=MeshError)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    chosen = np.empty(int(n_samples), dtype=np.int64)
    chosen[0] = rng.integers(n)
    nearest = np.full(n, np.inf)
    for i in range(1, int(n_samples)):
        diff = pts - pts[chosen[i - 1]]
        np.minimum(nearest, np.einsum("nd,nd->n", diff, diff), out=nearest)
        chosen[i] = int(np.argmax(nearest))
    return chosen
