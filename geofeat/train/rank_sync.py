"""What the ranks of a GeoLoRA run exchange to train as one: weights, optimizer state, gradients and stops.

Rank 0 alone reads and writes the run folder; at the start it hands the other ranks its LoRA
weights (`broadcast_parameters`) and the optimizer state it resumed (`to_cpu` makes it
picklable). Each step the gradients summed over every rank's samples are averaged over all
ranks (`average_gradients`), and a stop (Ctrl-C, the time budget) is agreed on by all ranks
(`any_rank`). With one process every function here is local.
"""

from __future__ import annotations

import torch

from geofeat.runtime import distributed

__all__ = ["any_rank", "average_gradients", "broadcast_parameters", "to_cpu"]


def to_cpu(obj):
    """``obj`` with every tensor in it (nested dicts, lists, tuples) moved to the CPU (to pickle it for another rank)."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {key: to_cpu(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_cpu(value) for value in obj)
    return obj


def broadcast_parameters(params: list[torch.nn.Parameter]) -> None:
    """Give ``params`` rank 0's values on every rank: one broadcast of them flattened into one tensor.

    Parameters
    ----------
    params : list of torch.nn.Parameter
        The same parameters, in the same order, on every rank.
    """
    with torch.no_grad():
        flat = distributed.broadcast_tensor_from_main(torch.cat([p.detach().reshape(-1) for p in params]))
        for p, value in zip(params, flat.split([p.numel() for p in params]), strict=True):
            p.copy_(value.view_as(p))


def average_gradients(params: list[torch.nn.Parameter], n_shapes: int, world_size: int) -> None:
    """Turn the gradients summed over this rank's shapes into the mean over the ``n_shapes`` of all ranks.

    Several ranks: one all-reduce (sum) of all the gradients flattened into one tensor (zeros
    for a rank without a usable shape), then the division.

    Parameters
    ----------
    params : list of torch.nn.Parameter
        The trained parameters, in the same order on every rank.
    n_shapes : int
        The usable samples of the step on all ranks.
    world_size : int
        The number of ranks.
    """
    if world_size > 1:
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params])
        distributed.all_reduce_sum(flat)
        if n_shapes != 1:
            flat.div_(n_shapes)
        for p, grad in zip(params, flat.split([p.numel() for p in params]), strict=True):
            p.grad = grad.view_as(p)
    elif n_shapes != 1:
        for p in params:
            if p.grad is not None:
                p.grad.div_(n_shapes)


def any_rank(flag: bool, world_size: int, device: torch.device) -> bool:
    """True when ``flag`` is true on any rank (every rank must call this at the same point).

    Parameters
    ----------
    flag : bool
    world_size : int
        The number of ranks; with 1, ``flag`` itself.
    device : torch.device
        The device of the all-reduce (the rank's own: NCCL reduces on the GPU).
    """
    if world_size == 1:
        return bool(flag)
    votes = torch.tensor([float(bool(flag))], dtype=torch.float64, device=device)
    return distributed.all_reduce_sum(votes).item() > 0
