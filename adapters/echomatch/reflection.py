"""The correspondence reflection of EchoMatch: two soft point maps composed into a round trip and read at spatial neighbours."""

from __future__ import annotations

import warnings

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from geofeat.errors import HeadError


def pointmap_matrix(map_yx, n_x: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Dense one-hot matrix of a hard point map y -> x; rows of unmatched vertices (``-1``) are zero.

    Parameters
    ----------
    map_yx : array_like of int, shape (V_y,)
        For each vertex of ``y`` a vertex of ``x``, or ``-1``.
    n_x : int
        Number of vertices of ``x``.
    dtype : torch.dtype

    Returns
    -------
    torch.Tensor, shape (V_y, n_x)
        ``P[v, map_yx[v]] = 1``.
    """
    index = torch.as_tensor(np.asarray(map_yx), dtype=torch.int64)
    if index.ndim != 1:
        raise HeadError(f"map_yx must be a 1-D integer array, shape (V_y,); found shape {tuple(index.shape)}.")
    if index.numel() and (int(index.min()) < -1 or int(index.max()) >= n_x):
        raise HeadError(
            f"map_yx must hold vertex indices in [0, {n_x - 1}] or -1; found range [{int(index.min())}, {int(index.max())}]."
        )
    matrix = torch.zeros(index.shape[0], n_x, dtype=dtype)
    rows = torch.nonzero(index >= 0).squeeze(1)
    matrix[rows, index[rows]] = 1
    return matrix


def correspondence_reflection(p_xy: torch.Tensor, p_yx: torch.Tensor) -> torch.Tensor:
    """The round trip x -> y -> x of two (soft) point maps: ``R_x = P_xy P_yx``.

    Parameters
    ----------
    p_xy : torch.Tensor, shape (V_x, V_y)
        Point map from ``x`` to ``y`` (rows are vertices of ``x``; a soft map's rows sum to one).
    p_yx : torch.Tensor, shape (V_y, V_x)
        Point map back.

    Returns
    -------
    torch.Tensor, shape (V_x, V_x)
        ``R[i, j]``: how much of vertex ``i`` comes back at vertex ``j``; the identity (on the
        overlap) for an exact pair of maps. Swap the arguments for ``R_y``.
    """
    if p_xy.ndim != 2 or p_yx.ndim != 2 or p_xy.shape[1] != p_yx.shape[0] or p_xy.shape[0] != p_yx.shape[1]:
        raise HeadError(
            f"p_xy and p_yx must have shapes (V_x, V_y) and (V_y, V_x); found {tuple(p_xy.shape)} and {tuple(p_yx.shape)}."
        )
    return p_xy @ p_yx


def spatial_neighbours(verts: np.ndarray, k: int) -> np.ndarray:
    """The ``min(k, V)`` nearest vertices of every vertex in Euclidean space, itself first.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
    k : int

    Returns
    -------
    numpy.ndarray, shape (V, min(k, V)), int64
        Sorted by distance; column 0 is the vertex itself (ties in position aside).
    """
    verts = np.asarray(verts, dtype=np.float64)
    k = min(int(k), verts.shape[0])
    _, index = cKDTree(verts).query(verts, k=k)
    index = np.asarray(index, dtype=np.int64).reshape(verts.shape[0], k)
    for row in np.flatnonzero(index[:, 0] != np.arange(verts.shape[0])):  # coincident vertices: itself first
        where = np.flatnonzero(index[row] == row)
        index[row, where[0] if where.size else k - 1] = index[row, 0]
        index[row, 0] = row
    return index


class _SampledProduct(torch.autograd.Function):
    """``out[i, j] = a[i, :] @ b[:, index[i, j]]`` without forming ``a @ b`` (a sampled matrix product)."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(a, b, index)
        n, k = index.shape
        try:  # sampled dense-dense product on a CSR pattern: a few times faster than the dense product
            order = index.argsort(dim=1)
            cols = index.gather(1, order)
            crow = torch.arange(0, n * k + 1, k, device=index.device)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "CSR support is in beta"
                pattern = torch.sparse_csr_tensor(
                    crow, cols.reshape(-1), a.new_zeros(n * k), (n, b.shape[1]), check_invariants=False
                )
                values = torch.sparse.sampled_addmm(pattern, a, b, beta=0.0).values().reshape(n, k)
            return torch.empty_like(values).scatter_(1, order, values)
        except (RuntimeError, NotImplementedError):  # a device without sampled_addmm: gather in chunks
            b_t = b.T.contiguous()
            rows = max(1, _CHUNK_ELEMENTS // max(1, k * a.shape[1]))
            out = [
                torch.einsum("im,ijm->ij", a[start : start + rows], b_t[index[start : start + rows]])
                for start in range(0, n, rows)
            ]
            return torch.cat(out) if out else a.new_zeros(index.shape)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        a, b, index = ctx.saved_tensors
        n, k = index.shape
        rows = torch.arange(n, device=index.device).repeat_interleave(k)
        # G (n, n_b): grad[i, j] at (i, index[i, j]); d/da = G b^T, d/db = (G^T a)^T
        g = torch.sparse_coo_tensor(
            torch.stack([rows, index.reshape(-1)]), grad.reshape(-1), (n, b.shape[1]), check_invariants=False
        ).coalesce()
        grad_a = torch.sparse.mm(g, b.T.contiguous()) if ctx.needs_input_grad[0] else None
        grad_b = torch.sparse.mm(g.t().coalesce(), a).T if ctx.needs_input_grad[1] else None
        return grad_a, grad_b, None


#: Elements of the largest temporary of `_SampledProduct` (16M float32: 64 MB).
_CHUNK_ELEMENTS = 1 << 24


def sampled_reflection(p_xy: torch.Tensor, p_yx: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """The entries of `correspondence_reflection` at each vertex's neighbours, without the dense product.

    ``out[i, j] = (P_xy P_yx)[i, neighbours[i, j]]``: costs ``V_x * k * V_y`` instead of
    ``V_x^2 * V_y`` and never holds a (V_x, V_x) matrix; differentiable with respect to both maps.

    Parameters
    ----------
    p_xy : torch.Tensor, shape (V_x, V_y)
    p_yx : torch.Tensor, shape (V_y, V_x)
    neighbours : torch.Tensor, shape (V_x, k), int64

    Returns
    -------
    torch.Tensor, shape (V_x, k)
    """
    if p_xy.ndim != 2 or p_yx.ndim != 2 or p_xy.shape[1] != p_yx.shape[0] or p_xy.shape[0] != p_yx.shape[1]:
        raise HeadError(
            f"p_xy and p_yx must have shapes (V_x, V_y) and (V_y, V_x); found {tuple(p_xy.shape)} and {tuple(p_yx.shape)}."
        )
    if neighbours.ndim != 2 or neighbours.shape[0] != p_xy.shape[0]:
        raise HeadError(f"neighbours must have shape ({p_xy.shape[0]}, k); found {tuple(neighbours.shape)}.")
    return _SampledProduct.apply(p_xy, p_yx, neighbours.to(torch.int64))


def reflection_features(scores: torch.Tensor, width: int | None = None) -> torch.Tensor:
    """The input of the overlap network: reflection entries at the neighbours, scaled to a maximum of one.

    Parameters
    ----------
    scores : torch.Tensor, shape (V, k)
        `sampled_reflection` (or ``torch.gather(correspondence_reflection(...), 1, neighbours)``).
    width : int, optional
        Columns of the result; zero columns are appended when ``k < width`` (a shape with
        fewer vertices than neighbours requested). Default ``k``.

    Returns
    -------
    torch.Tensor, shape (V, width)
        ``scores`` divided by their largest value over the shape.
    """
    scores = scores / scores.max().clamp_min(torch.finfo(scores.dtype).tiny)
    width = scores.shape[1] if width is None else int(width)
    if scores.shape[1] < width:
        scores = F.pad(scores, (0, width - scores.shape[1]))
    return scores


def round_trip_error(reflection: torch.Tensor, verts, mask=None) -> torch.Tensor:
    """Mean expected Euclidean distance between a vertex and where its round trip lands.

    Parameters
    ----------
    reflection : torch.Tensor, shape (V, V)
        `correspondence_reflection` (rows of a soft round trip sum to one).
    verts : array_like, shape (V, 3)
    mask : array_like of bool, shape (V,), optional
        Vertices to average over (default all).

    Returns
    -------
    torch.Tensor, shape ()
        ``mean_i sum_j R[i, j] |v_i - v_j|``: zero for an exact round trip.
    """
    v = torch.tensor(np.asarray(verts), dtype=reflection.dtype, device=reflection.device)
    dist = torch.cdist(v, v, compute_mode="donot_use_mm_for_euclid_dist")  # exact zeros on the diagonal
    per_vertex = (reflection * dist).sum(dim=1)
    if mask is not None:
        per_vertex = per_vertex[torch.as_tensor(np.asarray(mask, dtype=bool), device=reflection.device)]
    return per_vertex.mean()
