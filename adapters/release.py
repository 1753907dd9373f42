"""Release checkpoints of the reference implementations: exact key mappings onto our modules.

The authors of ULRSSM, DPFM and EchoMatch publish ``torch.save`` state dicts of their own
modules. This module maps their DiffusionNet keys onto `geofeat.adapters.blocks.diffusion_net.DiffusionNet`
and checks a mapped state dict against a module before loading it, so that a checkpoint
with a renamed, missing, extra or wrongly shaped tensor is refused with the key named,
never loaded partially.

Facts from the authors' files (key names, read from the released checkpoints):

* ULRSSM and DeepShapeMatchingKit's ``diffusion_b`` network (``style="ulrssm"``): ``first_linear``, ``last_linear``,
  ``blocks.<i>.diffusion.diffusion_time``, ``blocks.<i>.gradient_features.A_re`` / ``A_im``
  (bias-free linear maps), ``blocks.<i>.mlp.miniMLP_linear_<j:03d>``.
* DPFM and DeepShapeMatchingKit's ``DiffusionNet_A`` (EchoMatch), i.e. the original
  DiffusionNet code (``style="dpfm"``): ``first_lin``, ``last_lin``,
  ``block_<i>.diffusion.diffusion_time``, ``block_<i>.gradient_features.A_re`` / ``A_im``,
  ``block_<i>.mlp.miniMLP_mlp_layer_<j:03d>``.

Both networks compute what ours computes: a linear lift, blocks of spectral diffusion
(times clamped at a tiny positive value), gradient features ``tanh(Re(conj(g) (A g)))``,
a per-vertex MLP on ``[x, diffused, gradient features]`` with a residual, and a linear
output layer. The sizes (input, width, output, number of blocks, MLP hidden sizes, whether
gradient rotations are learned) are read from the tensors.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any, NamedTuple

import torch

from geofeat.errors import HeadError

__all__ = ["DIFFUSIONNET_STYLES", "ReleaseState", "check_state", "diffusionnet_state", "state_problems"]

#: Key spellings of the reference DiffusionNets: style -> (first, last, block prefix, mlp linear prefix).
DIFFUSIONNET_STYLES = {
    "ulrssm": ("first_linear", "last_linear", "blocks.{i}", "miniMLP_linear_{j:03d}"),
    "dpfm": ("first_lin", "last_lin", "block_{i}", "miniMLP_mlp_layer_{j:03d}"),
}


class ReleaseState(NamedTuple):
    """A release checkpoint translated for one of our heads.

    Attributes
    ----------
    settings : dict
        Head settings read from the tensors (sizes, input descriptor).
    state : dict of str to torch.Tensor
        The state dict of the head's module, in our key names.
    in_channels : int
        Input feature width of the module.
    """

    settings: dict[str, Any]
    state: dict[str, torch.Tensor]
    in_channels: int


def diffusionnet_state(
    source: Mapping[str, torch.Tensor], style: str, prefix: str = "", what: str = "checkpoint"
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Translate a reference DiffusionNet's tensors into the state dict of our `DiffusionNet`.

    Parameters
    ----------
    source : mapping of str to torch.Tensor
        The reference state dict (other modules' keys, outside ``prefix``, are ignored).
    style : {"ulrssm", "dpfm"}
        Key spelling, see `DIFFUSIONNET_STYLES`.
    prefix : str
        Prefix of the DiffusionNet's keys in ``source`` (e.g. ``"feature_extractor."``).
    what : str
        Name of the source in error messages.

    Returns
    -------
    sizes : dict
        ``in_channels``, ``out_channels``, ``width``, ``n_blocks``, ``mlp_hidden`` (list) and
        ``with_gradient_rotations``: the constructor arguments of our `DiffusionNet`.
    state : dict of str to torch.Tensor
        Our keys (``first.*``, ``blocks.<i>.diffusion.time``,
        ``blocks.<i>.gradient_features.a_re.weight``, ``blocks.<i>.mlp.<3 j>.*`` for the
        j-th linear layer of the block MLP, ``last.*``).

    Raises
    ------
    HeadError
        Unknown style, a missing first/last layer, blocks numbered with gaps, or keys
        under ``prefix`` missing from or unknown to a DiffusionNet of these sizes (all named).
    """
    if style not in DIFFUSIONNET_STYLES:
        raise HeadError(f"unknown DiffusionNet key style {style!r}; expected one of {sorted(DIFFUSIONNET_STYLES)}.")
    first, last, block, linear = DIFFUSIONNET_STYLES[style]
    own = {k[len(prefix) :]: v for k, v in source.items() if k.startswith(prefix)}
    for layer in (first, last):
        if f"{layer}.weight" not in own:
            raise HeadError(f"{what}: missing key {prefix}{layer}.weight (the {style} DiffusionNet's {layer} layer).")
    block_re = re.compile("^" + re.escape(block).replace(r"\{i\}", r"(\d+)") + r"\.")
    indices = sorted({int(m.group(1)) for k in own if (m := block_re.match(k))})
    if indices != list(range(len(indices))):
        raise HeadError(f"{what}: DiffusionNet blocks must be numbered 0..n-1; found {indices}.")
    linear_re = re.compile(re.escape(linear).replace(r"\{j:03d\}", r"(\d+)") + r"\.weight$")
    n_linear = 1 + max((int(m.group(1)) for k in own if (m := linear_re.search(k))), default=-1)
    state: dict[str, torch.Tensor] = {}
    missing: list[str] = []

    def take(ref_key: str, our_key: str) -> None:
        if ref_key in own:
            state[our_key] = own[ref_key]
        else:
            missing.append(prefix + ref_key)

    for param in ("weight", "bias"):
        take(f"{first}.{param}", f"first.{param}")
        take(f"{last}.{param}", f"last.{param}")
    rotations = any(f"{block.format(i=i)}.gradient_features.A_im.weight" in own for i in indices)
    for i in indices:
        b = block.format(i=i)
        take(f"{b}.diffusion.diffusion_time", f"blocks.{i}.diffusion.time")
        take(f"{b}.gradient_features.A_re.weight", f"blocks.{i}.gradient_features.a_re.weight")
        if rotations:
            take(f"{b}.gradient_features.A_im.weight", f"blocks.{i}.gradient_features.a_im.weight")
        for j in range(n_linear):
            for param in ("weight", "bias"):
                take(f"{b}.mlp.{linear.format(j=j)}.{param}", f"blocks.{i}.mlp.{3 * j}.{param}")
    unused = sorted(prefix + k for k in set(own) - _reference_keys(first, last, block, linear, indices, n_linear, rotations))
    if missing or unused or n_linear == 0:
        problems = [f"{label} {items}" for label, items in (("missing key(s)", missing), ("unexpected key(s)", unused)) if items]
        if n_linear == 0:
            problems.append("no block MLP layers")
        raise HeadError(f"{what}: the {style} DiffusionNet does not map onto ours: " + "; ".join(problems) + ".")
    hidden = [int(state[f"blocks.0.mlp.{3 * j}.weight"].shape[0]) for j in range(n_linear - 1)] if indices else []
    sizes = {
        "in_channels": int(own[f"{first}.weight"].shape[1]),
        "width": int(own[f"{first}.weight"].shape[0]),
        "out_channels": int(own[f"{last}.weight"].shape[0]),
        "n_blocks": len(indices),
        "mlp_hidden": hidden,
        "with_gradient_rotations": rotations,
    }
    return sizes, state


def _reference_keys(first, last, block, linear, indices, n_linear, rotations) -> set[str]:
    """Every key a reference DiffusionNet of these sizes has."""
    keys = {f"{layer}.{p}" for layer in (first, last) for p in ("weight", "bias")}
    for i in indices:
        b = block.format(i=i)
        keys |= {f"{b}.diffusion.diffusion_time", f"{b}.gradient_features.A_re.weight"}
        if rotations:
            keys.add(f"{b}.gradient_features.A_im.weight")
        keys |= {f"{b}.mlp.{linear.format(j=j)}.{p}" for j in range(n_linear) for p in ("weight", "bias")}
    return keys


def check_state(module: torch.nn.Module, state: Mapping[str, torch.Tensor], what: str) -> None:
    """Raise `HeadError` unless ``state`` has exactly the keys and shapes of ``module``'s state dict.

    Parameters
    ----------
    module : torch.nn.Module
    state : mapping of str to torch.Tensor
    what : str
        Name of the source (a checkpoint path) in the message.

    Raises
    ------
    HeadError
        Naming every missing, unexpected and wrongly shaped key (with both shapes), every
        key of another kind of number (integers or booleans for floating-point weights)
        and every floating-point key holding NaN or infinite values.
    """
    problems = state_problems(module.state_dict(), state)
    if problems:
        raise HeadError(f"{what} does not fit {type(module).__name__}: " + "; ".join(problems) + ".")


def state_problems(
    expected: Mapping[str, torch.Tensor],
    state: Mapping[str, torch.Tensor],
    names: Mapping[str, str] | None = None,
    source: Mapping[str, torch.Tensor] | None = None,
) -> list[str]:
    """What keeps ``state`` from loading into a module whose state dict is ``expected``, as readable phrases.

    Parameters
    ----------
    expected, state : mapping of str to torch.Tensor
        Our keys.
    names : mapping of str to str, optional
        The checkpoint's key for each of ours, so that messages name what the user's file holds.
    source : mapping of str to torch.Tensor, optional
        The checkpoint itself: a wrongly shaped key is reported with the shape it has there.

    Returns
    -------
    list of str
        ``"missing [...]"``, ``"unexpected [...]"``, ``"wrongly shaped [...]"``, ``"of another
        kind of number [...]"`` and ``"holding NaN or infinite values [...]"``, where not empty.
    """
    names = names or {}

    def label(key: str) -> str:
        return names.get(key, key)

    def shape(key: str) -> tuple[int, ...]:
        theirs = names.get(key)
        return tuple(source[theirs].shape) if source is not None and theirs in source else tuple(state[key].shape)

    missing = sorted(label(k) for k in expected if k not in state)
    unexpected = sorted(label(k) for k in state if k not in expected)
    wrong = sorted(
        f"{label(k)}: {shape(k)} instead of {tuple(expected[k].shape)}" + (f" (our {k})" if label(k) != k else "")
        for k in state
        if k in expected and tuple(state[k].shape) != tuple(expected[k].shape)
    )
    common = [k for k in state if k in expected]
    mistyped = sorted(
        f"{label(k)}: {state[k].dtype} instead of {expected[k].dtype}"
        for k in common
        if _number_kind(state[k].dtype) != _number_kind(expected[k].dtype)
    )
    not_finite = sorted(label(k) for k in common if state[k].is_floating_point() and not bool(state[k].isfinite().all()))
    return [
        f"{what} {items}"
        for what, items in (
            ("missing", missing),
            ("unexpected", unexpected),
            ("wrongly shaped", wrong),
            ("of another kind of number", mistyped),
            ("holding NaN or infinite values", not_finite),
        )
        if items
    ]


def _number_kind(dtype: torch.dtype) -> str:
    """``"bool"``, ``"integer"``, ``"floating"`` or ``"complex"``: what a tensor may be loaded as (any width)."""
    if dtype == torch.bool:
        return "bool"
    if dtype.is_complex:
        return "complex"
    return "floating" if dtype.is_floating_point else "integer"
