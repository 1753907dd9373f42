"""DPFM's farthest-point samples and how every vertex reads the features of the samples.

DPFM's cross-attention refiner works on a farthest-point sample of each shape
(`geofeat.geometry.sampling.farthest_point_sampling`) and brings the refined sample features
back to every vertex. `sample_interpolation` does what the paper means (each vertex averages
its nearest samples, inverse-squared-distance weighted); `reference_candidates` and
`reference_sample_interpolation` reproduce what the authors' code does instead (see
`geofeat.adapters.dpfm`, ``interpolation="reference"``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial import cKDTree

from geofeat.checks import check_integer
from geofeat.errors import HeadError
from geofeat.geometry.sampling import farthest_point_sampling

__all__ = [
    "INTERPOLATION_EPS",
    "REFERENCE_CANDIDATES",
    "REFERENCE_CANDIDATE_RATIO",
    "ReferenceCandidates",
    "SampleInterpolation",
    "reference_candidates",
    "reference_sample_interpolation",
    "sample_interpolation",
]

#: Reference interpolation: fraction of the vertices in its farthest-point candidate list.
REFERENCE_CANDIDATE_RATIO = 0.9
#: Reference interpolation: nearest candidates kept for every vertex.
REFERENCE_CANDIDATES = 130
#: Added to squared distances before inverting them into interpolation weights (as the reference).
INTERPOLATION_EPS = 1e-8


class SampleInterpolation(NamedTuple):
    """Farthest-point samples of a shape and how every vertex averages them.

    Attributes
    ----------
    samples : torch.Tensor, shape (S,), int64
        Sampled vertex indices.
    neighbours : torch.Tensor, shape (V, n), int64
        For every vertex its ``n`` nearest samples, as positions in ``samples``.
    weights : torch.Tensor, shape (V, n), float32
        Inverse squared distances, normalised to sum to one per vertex (a sample's own
        weight is 1 up to ``INTERPOLATION_EPS``).
    """

    samples: torch.Tensor
    neighbours: torch.Tensor
    weights: torch.Tensor

    def to(self, device: torch.device) -> SampleInterpolation:
        return SampleInterpolation(*(t.to(device) for t in self))

    def interpolate(self, sampled: torch.Tensor) -> torch.Tensor:
        """Per-vertex features (V, C) from per-sample features (S, C)."""
        return (sampled[self.neighbours] * self.weights.unsqueeze(-1)).sum(dim=1)


def sample_interpolation(points, n_samples: int, n_neighbours: int = 3, seed: int = 0) -> SampleInterpolation:
    """Farthest-point samples of ``points`` and inverse-squared-distance interpolation weights.

    Parameters
    ----------
    points : array_like, shape (V, 3)
        Vertex positions (the head passes them centred and scaled to unit area).
    n_samples : int
        ``1 <= n_samples <= V`` (else `HeadError`).
    n_neighbours : int
        Samples averaged per vertex (clipped to ``n_samples``).
    seed : int
        Seed of `farthest_point_sampling`.

    Returns
    -------
    SampleInterpolation
        CPU tensors.
    """
    pts = np.asarray(points, dtype=np.float64)
    check_integer(n_samples, "n_samples", owner="sample_interpolation", low=1, high=len(pts), error=HeadError)
    samples = farthest_point_sampling(pts, n_samples, seed)
    k = max(1, min(int(n_neighbours), len(samples)))
    dist, nbr = cKDTree(pts[samples]).query(pts, k=k)
    dist, nbr = dist.reshape(len(pts), k), nbr.reshape(len(pts), k)
    inv = 1.0 / (np.square(dist) + INTERPOLATION_EPS)
    weights = inv / inv.sum(axis=1, keepdims=True)
    return SampleInterpolation(
        torch.from_numpy(samples),
        torch.from_numpy(nbr.astype(np.int64)),
        torch.from_numpy(weights.astype(np.float32)),
    )


class ReferenceCandidates(NamedTuple):
    """The per-shape sampling record of the DPFM reference code (what its data loader stores).

    Attributes
    ----------
    order : torch.Tensor, shape (S,), int64
        Vertices of a farthest-point sample of ``int(0.9 V)`` points, in the order chosen.
    ranks : torch.Tensor, shape (V, n), int64
        For every vertex, the positions in ``order`` of its ``n = min(130, S)`` nearest
        samples, nearest first.
    sq_dists : torch.Tensor, shape (V, n), float32
        Their squared distances, computed in float32 as ``|p|^2 - 2 p.q + |q|^2``.
    """

    order: torch.Tensor
    ranks: torch.Tensor
    sq_dists: torch.Tensor


def reference_candidates(points, seed: int = 0, block: int = 1024, order=None) -> ReferenceCandidates:
    """Candidate samples of a shape as the DPFM reference code prepares them.

    A farthest-point sample of ``int(0.9 V)`` vertices (`farthest_point_sampling`; the
    reference starts at a random vertex of torch's global generator) and, for every vertex,
    its 130 nearest samples by float32 squared distance (the reference's expansion, sorted).

    Parameters
    ----------
    points : array_like, shape (V, 3)
        Vertex positions as the reference sees them (FAUST_r: centred, unit area, float32).
    seed : int
        Seed of the first sample.
    block : int
        Rows of the distance matrix handled at a time (memory bound).
    order : array_like of int, shape (S,), optional
        Use this sample order instead of drawing one (e.g. the reference's own).

    Returns
    -------
    ReferenceCandidates
        CPU tensors.
    """
    pts = torch.as_tensor(np.asarray(points, dtype=np.float32))
    n_vertices = pts.shape[0]
    n_order = int(REFERENCE_CANDIDATE_RATIO * n_vertices)
    if n_order < 1:
        raise HeadError(f"reference_candidates: a shape of {n_vertices} vertices has no {REFERENCE_CANDIDATE_RATIO} sample.")
    if order is None:
        order = torch.from_numpy(farthest_point_sampling(pts.double().numpy(), n_order, seed))
    else:
        order = torch.as_tensor(np.asarray(order, dtype=np.int64))
    cand = pts[order]
    cand_sq = cand.square().sum(-1).view(1, -1)
    n_keep = min(REFERENCE_CANDIDATES, len(order))
    ranks, dists = [], []
    for start in range(0, n_vertices, block):
        rows = pts[start : start + block]
        d = -2 * rows @ cand.T
        d += rows.square().sum(-1).view(-1, 1)
        d += cand_sq
        d, index = d.sort(dim=-1)
        ranks.append(index[:, :n_keep].clone())
        dists.append(d[:, :n_keep].clone())
    return ReferenceCandidates(order, torch.cat(ranks), torch.cat(dists))


def reference_sample_interpolation(candidates: ReferenceCandidates, n_samples: int) -> SampleInterpolation:
    """The samples and per-vertex interpolation of the DPFM reference code, quirks included.

    The samples are the first ``n_samples`` of ``candidates.order``. The reference meant
    every vertex to average its 3 nearest samples, but it reads the candidate ranks (positions
    in ``order``) as vertex indices: a candidate counts when the vertex with the index of its
    rank is a sample, and that vertex's features are used, weighted by the candidate's
    inverse squared distance (``1 / (d^2 + 1e-8)``, normalised, float32). Of the counting
    candidates it takes the first three of ``torch.argsort(counts, descending=True)``, whose
    order among equal keys is torch's (unstable sort). Each shape gets its own scrambling,
    drawn with the random start of the farthest-point sample.

    Parameters
    ----------
    candidates : ReferenceCandidates
        From `reference_candidates` (or the reference's own ``sample_idx`` record).
    n_samples : int
        ``1 <= n_samples <= len(candidates.order)``.

    Returns
    -------
    SampleInterpolation
        CPU tensors; ``neighbours`` index the samples.

    Raises
    ------
    HeadError
        A vertex with fewer than 3 counting candidates, or a weight that is not finite
        (where the reference itself would index out of range or give NaN).
    """
    order, ranks, sq_dists = candidates
    n_vertices = ranks.shape[0]
    if not 1 <= n_samples <= len(order):
        raise HeadError(f"reference_sample_interpolation: n_samples must lie in [1, {len(order)}]; found {n_samples}.")
    samples = order[:n_samples]
    counts = torch.from_numpy(np.isin(ranks.numpy(), samples.numpy())).int()
    pick = torch.argsort(counts.unsqueeze(0), dim=-1, descending=True)[0, :, :3]
    chosen = torch.gather(ranks, 1, pick)
    if not bool(torch.gather(counts, 1, pick).all()):
        raise HeadError("reference_sample_interpolation: a vertex has fewer than 3 counting candidates; sample more vertices.")
    lookup = torch.arange(max(n_vertices, int(chosen.max()) + 1))
    lookup[samples] = torch.arange(n_samples)
    recip = 1.0 / (torch.gather(sq_dists, 1, pick) + INTERPOLATION_EPS)
    weights = recip / recip.sum(dim=1, keepdim=True)
    if not bool(torch.isfinite(weights).all()):
        raise HeadError("reference_sample_interpolation: a squared distance of -1e-8 gives an infinite weight.")
    return SampleInterpolation(samples.clone(), lookup[chosen], weights.float())
