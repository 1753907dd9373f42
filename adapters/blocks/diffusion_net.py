"""DiffusionNet (Sharp, Attaiki, Crane and Ovsjanikov 2022): a discretisation-agnostic surface network.

Every block of the network mixes information along the surface with three per-vertex
ingredients:

1. learned diffusion: each channel is diffused by the heat equation for its own learned time
   ``t_c >= 0``, evaluated in the truncated Laplace-Beltrami eigenbasis
   (``Phi exp(-Lambda t_c) Phi^T M x``);
2. spatial gradient features: the tangent gradients of the diffused channels, as complex
   numbers ``g`` in each vertex's tangent frame, are mixed by a learned complex-linear map
   ``A`` and turned into the rotation-invariant scalars ``tanh(Re(conj(g) * (A g)))``;
3. a per-vertex MLP on ``[x, diffused x, gradient features]`` added back to ``x`` (residual).

A linear layer maps the input channels to the network width before the blocks and another
maps the width to the output channels after them. The operators of a shape (mass,
eigenpairs, gradient matrices) come from `surface_operators`.

>>> ops = surface_operators(mesh, k=128)
>>> net = DiffusionNet(in_channels=128, out_channels=256)
>>> features = net(torch.from_numpy(wks).float(), ops)  # (V, 256)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import nn

from geofeat.adapters.blocks.operators import (
    GRADIENT_REGULARIZATION,
    SurfaceOperators,
    _same_device,
    clear_operator_cache,
    gradient_matrices,
    surface_operators,
    tangent_frames,
)
from geofeat.checks import check_integer, check_number, is_boolean
from geofeat.errors import DiffusionNetError

__all__ = [
    "GRADIENT_MIXINGS",
    "GRADIENT_REGULARIZATION",
    "OUTPUTS_AT",
    "DiffusionNet",
    "DiffusionNetBlock",
    "DiffusionNetError",
    "LearnedDiffusion",
    "SpatialGradientFeatures",
    "SurfaceOperators",
    "clear_operator_cache",
    "gradient_matrices",
    "spectral_diffusion",
    "surface_operators",
    "tangent_frames",
    "tangent_gradients",
]

#: Where `DiffusionNet` can give its outputs (edge and face values average their vertices).
OUTPUTS_AT = ("vertices", "edges", "faces")
#: How `SpatialGradientFeatures` mixes the two gradient components (see its notes).
GRADIENT_MIXINGS = ("complex", "ulrssm")
#: Dropout probability used inside the block MLPs when ``dropout=True``.
DEFAULT_DROPOUT = 0.5


# ----------------------------------------------------------------------------- functional pieces


def spectral_diffusion(x: torch.Tensor, operators: SurfaceOperators, time: torch.Tensor) -> torch.Tensor:
    """Heat diffusion of every channel for its own time, in the truncated eigenbasis.

    Parameters
    ----------
    x : torch.Tensor, shape (V, C) or (B, V, C)
        Per-vertex features.
    operators : SurfaceOperators
        Mass (V,), eigenvalues (k,) and eigenvectors (V, k) of the shape.
    time : torch.Tensor, shape (C,)
        Non-negative diffusion time of each channel.

    Returns
    -------
    torch.Tensor, same shape as ``x``
        ``Phi diag(exp(-lambda t_c)) Phi^T M x[..., c]``: the identity on the span of the
        basis at ``t = 0``, the mass-weighted mean of each connected component for large ``t``.
    """
    spectral = torch.einsum("vk,...vc->...kc", operators.evecs, x * operators.mass[:, None])
    decay = torch.exp(-operators.evals[:, None] * time[None, :])  # (k, C)
    return torch.einsum("vk,...kc->...vc", operators.evecs, spectral * decay)


def tangent_gradients(x: torch.Tensor, operators: SurfaceOperators) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent gradient of every channel, in each vertex's frame.

    Parameters
    ----------
    x : torch.Tensor, shape (V, C) or (B, V, C)
        Per-vertex features.
    operators : SurfaceOperators
        Holds the sparse gradient matrices ``grad_x``, ``grad_y`` (V, V).

    Returns
    -------
    grad_x, grad_y : torch.Tensor, each the shape of ``x``
        Components along the frame axes ``X`` and ``Y`` (real and imaginary parts of the
        complex gradient).
    """
    n_vertices = x.shape[-2]
    # (..., V, C) -> (V, B*C): one sparse product for the whole batch
    flat = x.movedim(-2, 0).reshape(n_vertices, -1)
    backward = flat.requires_grad and torch.is_grad_enabled()
    transposes = operators.gradient_transposes if backward else (None, None)

    def apply(matrix: torch.Tensor, transposed: torch.Tensor | None) -> torch.Tensor:
        if transposed is None or matrix.requires_grad:
            product = torch.sparse.mm(matrix, flat)
        else:
            product = _ConstantSparseProduct.apply(matrix, transposed, flat)
        out = product.reshape((n_vertices,) + x.shape[:-2] + x.shape[-1:])
        return out.movedim(0, -2)

    return apply(operators.grad_x, transposes[0]), apply(operators.grad_y, transposes[1])


class _ConstantSparseProduct(torch.autograd.Function):
    """``matrix @ dense`` for a constant sparse ``matrix``, differentiable in ``dense`` only.

    The same product and gradient as ``torch.sparse.mm``, whose backward multiplies by
    ``matrix.t()``: a transpose that is not coalesced, so on CUDA every backward pass sorts
    its entries again and waits for the device to learn their number. Here the backward
    multiplies by ``transposed``, that transpose coalesced once
    (`SurfaceOperators.gradient_transposes`).
    """

    @staticmethod
    def forward(ctx, matrix: torch.Tensor, transposed: torch.Tensor, dense: torch.Tensor) -> torch.Tensor:
        """``matrix`` (V, V) sparse, ``transposed`` its coalesced transpose (V, V), ``dense`` (V, C); returns (V, C)."""
        ctx.save_for_backward(transposed)
        return torch.sparse.mm(matrix, dense)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[None, None, torch.Tensor]:
        """The gradient (V, C) of ``dense`` only."""
        (transposed,) = ctx.saved_tensors
        return None, None, torch.sparse.mm(transposed, grad)


# ----------------------------------------------------------------------------- layers


class LearnedDiffusion(nn.Module):
    """Diffusion of each channel for a learned non-negative time (spectral acceleration).

    Parameters
    ----------
    channels : int
        Number of channels C.

    Attributes
    ----------
    time : torch.nn.Parameter, shape (C,)
        Raw diffusion times, initialised to zero (the layer starts as the identity on the
        span of the basis). The time used is ``max(time, 0)``; its gradient is passed
        through unchanged, so a time pushed below zero by an optimiser can come back.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.channels = channels
        self.time = nn.Parameter(torch.zeros(channels))

    def diffusion_time(self) -> torch.Tensor:
        """The non-negative times in use, shape (C,)."""
        clipped = self.time.clamp(min=0.0)
        return self.time + (clipped - self.time).detach()

    def forward(self, x: torch.Tensor, operators: SurfaceOperators) -> torch.Tensor:
        """Diffuse ``x`` (V, C) or (B, V, C); returns the same shape."""
        return spectral_diffusion(x, operators, self.diffusion_time())


class SpatialGradientFeatures(nn.Module):
    """Rotation-invariant scalars from the tangent gradients of each channel.

    Parameters
    ----------
    channels : int
        Number of channels C.
    with_rotations : bool
        Learn a complex map ``A = A_re + i A_im`` (it can rotate gradients within the
        tangent plane; needs consistently oriented normals). False: a real map ``A``.
    mixing : {"complex", "ulrssm"}
        ``"complex"``: ``A g`` is the complex product (DiffusionNet's paper and code, DPFM).
        ``"ulrssm"``: the variant of the ULRSSM code (and of DeepShapeMatchingKit's
        ``diffusion_b`` network), whose imaginary part is ``A_re g_x + A_im g_y`` instead of
        ``A_re g_y + A_im g_x``; its released weights were trained with it. It is not
        invariant to the choice of the tangent frames.

    Notes
    -----
    With ``g`` the complex gradient (C,) at a vertex, the output is
    ``tanh(Re(conj(g) * (A g)))`` channel by channel. A change of tangent frame multiplies
    every ``g_c`` by the same unit complex number, which cancels in the product, so the
    features do not depend on the choice of the frames' ``X`` axes.
    """

    def __init__(self, channels: int, with_rotations: bool = True, mixing: str = "complex") -> None:
        super().__init__()
        if mixing not in GRADIENT_MIXINGS:
            raise DiffusionNetError(f"gradient mixing must be one of {GRADIENT_MIXINGS}; found {mixing!r}.")
        self.channels = channels
        self.with_rotations = with_rotations
        self.mixing = mixing
        self.a_re = nn.Linear(channels, channels, bias=False)
        self.a_im = nn.Linear(channels, channels, bias=False) if with_rotations else None

    def forward(self, grad_x: torch.Tensor, grad_y: torch.Tensor) -> torch.Tensor:
        """Features of shape (..., V, C) from gradient components of shape (..., V, C)."""
        if self.a_im is None:
            mixed_x, mixed_y = self.a_re(grad_x), self.a_re(grad_y)
        elif self.mixing == "ulrssm":  # both parts from the same two products
            re_x, im_y = self.a_re(grad_x), self.a_im(grad_y)
            mixed_x, mixed_y = re_x - im_y, re_x + im_y
        else:
            mixed_x, mixed_y = self.a_re(grad_x), self.a_re(grad_y)
            mixed_x, mixed_y = mixed_x - self.a_im(grad_y), mixed_y + self.a_im(grad_x)
        return torch.tanh(grad_x * mixed_x + grad_y * mixed_y)


def _mlp(sizes: Sequence[int], dropout: float) -> nn.Sequential:
    """Linear layers with ReLU between them (not after the last) and dropout before all but the first.

    The j-th linear layer is always module ``3 * j`` (an `nn.Identity` stands in for the
    dropout when there is none), so state-dict keys do not depend on the dropout setting.
    """
    layers: list[nn.Module] = []
    for index, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        if index > 0:
            layers.append(nn.Dropout(p=dropout) if dropout > 0 else nn.Identity())
        layers.append(nn.Linear(n_in, n_out))
        if index < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class DiffusionNetBlock(nn.Module):
    """One DiffusionNet block: diffusion, gradient features, MLP and residual connection.

    Parameters
    ----------
    width : int
        Number of channels C (in and out).
    mlp_hidden : sequence of int
        Hidden layer sizes of the per-vertex MLP.
    dropout : float
        Dropout probability inside the MLP (0: none).
    with_gradient_features : bool
        Use the spatial gradient features.
    with_gradient_rotations : bool
        Let the gradient features learn rotations (see `SpatialGradientFeatures`).
    gradient_mixing : {"complex", "ulrssm"}
        See `SpatialGradientFeatures`.
    """

    def __init__(
        self,
        width: int,
        mlp_hidden: Sequence[int],
        dropout: float = 0.0,
        with_gradient_features: bool = True,
        with_gradient_rotations: bool = True,
        gradient_mixing: str = "complex",
    ) -> None:
        super().__init__()
        self.width = width
        self.diffusion = LearnedDiffusion(width)
        self.gradient_features = (
            SpatialGradientFeatures(width, with_gradient_rotations, gradient_mixing) if with_gradient_features else None
        )
        n_mlp_in = (3 if with_gradient_features else 2) * width
        self.mlp = _mlp([n_mlp_in, *mlp_hidden, width], dropout)

    def forward(self, x: torch.Tensor, operators: SurfaceOperators) -> torch.Tensor:
        """Map ``x`` (..., V, C) to (..., V, C)."""
        diffused = self.diffusion(x, operators)
        parts = [x, diffused]
        if self.gradient_features is not None:
            parts.append(self.gradient_features(*tangent_gradients(diffused, operators)))
        return x + self.mlp(torch.cat(parts, dim=-1))


# ----------------------------------------------------------------------------- network


class DiffusionNet(nn.Module):
    """DiffusionNet: per-vertex features in, per-vertex (or edge, or face) features out.

    Parameters
    ----------
    in_channels : int
        Input channels C_in (e.g. the number of WKS or DINO feature channels).
    out_channels : int
        Output channels C_out.
    width : int
        Channels inside the blocks.
    n_blocks : int
        Number of `DiffusionNetBlock`.
    dropout : bool or float
        Dropout inside the block MLPs: False (none), True (`DEFAULT_DROPOUT`) or a
        probability in ``[0, 1)``.
    last_activation : callable, optional
        Applied to the output (e.g. ``torch.nn.functional.log_softmax`` with a ``dim``
        bound); None: linear output.
    outputs_at : {"vertices", "edges", "faces"}
        Where the outputs live; edge and face outputs are the mean of their vertices.
    mlp_hidden : sequence of int, optional
        Hidden layer sizes of the block MLPs (default ``[width, width]``).
    with_gradient_features : bool
        Use spatial gradient features in the blocks.
    with_gradient_rotations : bool
        Learn complex (rotating) gradient maps; set False for shapes without consistently
        oriented normals.
    gradient_mixing : {"complex", "ulrssm"}
        See `SpatialGradientFeatures` (``"ulrssm"`` for ULRSSM's released weights).

    Raises
    ------
    DiffusionNetError
        A non-positive size, a bad dropout or an unknown ``outputs_at``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        width: int = 128,
        n_blocks: int = 4,
        dropout: bool | float = False,
        last_activation: Callable[[torch.Tensor], torch.Tensor] | None = None,
        outputs_at: str = "vertices",
        *,
        mlp_hidden: Sequence[int] | None = None,
        with_gradient_features: bool = True,
        with_gradient_rotations: bool = True,
        gradient_mixing: str = "complex",
    ) -> None:
        super().__init__()
        for name, value in (("in_channels", in_channels), ("out_channels", out_channels), ("width", width)):
            _check_positive_int(name, value)
        check_integer(n_blocks, "n_blocks", low=0, error=DiffusionNetError, expected="a non-negative integer")
        if outputs_at not in OUTPUTS_AT:
            raise DiffusionNetError(f"outputs_at must be one of {OUTPUTS_AT}; found {outputs_at!r}.")
        if last_activation is not None and not callable(last_activation):
            raise DiffusionNetError(f"last_activation must be a callable or None; found {last_activation!r}.")
        hidden = [int(width), int(width)] if mlp_hidden is None else list(mlp_hidden)
        for size in hidden:
            _check_positive_int("every mlp_hidden size", size)
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.width = int(width)
        self.n_blocks = int(n_blocks)
        self.dropout = _dropout_probability(dropout)
        self.last_activation = last_activation
        self.outputs_at = outputs_at
        self.first = nn.Linear(self.in_channels, self.width)
        self.blocks = nn.ModuleList(
            DiffusionNetBlock(self.width, hidden, self.dropout, with_gradient_features, with_gradient_rotations, gradient_mixing)
            for _ in range(self.n_blocks)
        )
        self.last = nn.Linear(self.width, self.out_channels)

    def forward(self, x: torch.Tensor, operators: SurfaceOperators) -> torch.Tensor:
        """Run the network on one shape.

        Parameters
        ----------
        x : torch.Tensor, shape (V, C_in) or (B, V, C_in)
            Per-vertex input features (any floating dtype; cast to the parameters' dtype).
            A batch holds B feature sets on the same shape.
        operators : SurfaceOperators
            Operators of the shape, on the device of ``x`` and of the network.

        Returns
        -------
        torch.Tensor, shape (V, C_out) or (B, V, C_out)
            With ``outputs_at="edges"`` or ``"faces"``, E or F rows instead of V.

        Raises
        ------
        DiffusionNetError
            Wrong number of dimensions, channels or vertices, a non-floating tensor,
            operators on another device, or edge/face outputs for a point cloud.
        """
        x = self._checked_input(x, operators)
        h = self.first(x)
        for block in self.blocks:
            h = block(h, operators)
        out = self.last(h)
        if self.outputs_at != "vertices":
            elements = operators.edges if self.outputs_at == "edges" else operators.faces
            out = out[..., elements, :].mean(dim=-2)
        if self.last_activation is not None:
            out = self.last_activation(out)
        return out

    def _checked_input(self, x, operators: SurfaceOperators) -> torch.Tensor:
        if not isinstance(operators, SurfaceOperators):
            raise DiffusionNetError(
                f"operators must be a SurfaceOperators record (from surface_operators(mesh, k)); found {type(operators).__name__}."
            )
        if not isinstance(x, torch.Tensor):
            raise DiffusionNetError(f"x must be a torch.Tensor of shape (V, C_in) or (B, V, C_in); found {type(x).__name__}.")
        if x.ndim not in (2, 3):
            raise DiffusionNetError(f"x must have shape (V, C_in) or (B, V, C_in); found {x.ndim} dimensions {tuple(x.shape)}.")
        if not x.is_floating_point():
            raise DiffusionNetError(f"x must hold floating-point features; found dtype {x.dtype}.")
        if x.shape[-1] != self.in_channels:
            raise DiffusionNetError(
                f"DiffusionNet was built for in_channels={self.in_channels}, but x has {x.shape[-1]} channels "
                f"(shape {tuple(x.shape)})."
            )
        if x.shape[-2] != operators.n_vertices:
            raise DiffusionNetError(
                f"x has {x.shape[-2]} vertices (shape {tuple(x.shape)}) but the operators are for a shape with "
                f"{operators.n_vertices} vertices; build the operators of this shape."
            )
        if not _same_device(x.device, operators.device):
            raise DiffusionNetError(
                f"x is on {x.device} but the operators are on {operators.device}; move them with operators.to(x.device)."
            )
        if self.outputs_at == "edges" and operators.edges is None or self.outputs_at == "faces" and operators.faces is None:
            raise DiffusionNetError(
                f"outputs_at={self.outputs_at!r} needs a triangle mesh, but the operators are of a point cloud."
            )
        return x.to(self.first.weight.dtype)


def _check_positive_int(name: str, value) -> None:
    check_integer(value, name, low=1, error=DiffusionNetError, expected="a positive integer")


def _dropout_probability(dropout: bool | float) -> float:
    if is_boolean(dropout):
        return DEFAULT_DROPOUT if dropout else 0.0
    expected = "True, False or a probability in [0, 1)"
    return check_number(dropout, "dropout", low=0, high=1, high_open=True, error=DiffusionNetError, expected=expected)
