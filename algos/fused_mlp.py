"""One autograd node for a whole ReLU MLP, with the bias of every widening layer folded into its matmul.

Why: at the paper's treadmill sizes (26–58 inputs → 4096 → 12) an update is bound by the passes over the
``[rows, 4096]`` activations, not by arithmetic (``benchmarks/learner_throughput.py``). Autograd's layer-by-layer
graph makes four of them per hidden layer beyond the matmuls: ``addmm`` copies the broadcast bias into its output
before multiplying, the bias gradient is a column sum, and ReLU's backward writes a fresh masked copy of the
gradient. Here

* a layer whose output is wider than its input multiplies ``[x, 1] @ [W; b]``: the bias rides in the matmul (one
  more input column), so neither the broadcast copy nor the column sum touches the wide activation;
* the backward pass owns the gradient buffers it creates, so the ReLU mask is applied in place;
* the input gradient is computed only when the input needs one (observations do not, messages do).

Measured on the treadmill learner (IDQN, batch 256, 1 thread): see the README's learner-throughput section. The
maths is exactly that of ``Linear → ReLU → … → Linear`` (``tests/test_fused_mlp.py`` compares both, values and
gradients).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable


def _folds(in_features: int, out_features: int) -> bool:
    """Fold the bias where the augmented input ``[x, 1]`` is cheaper to build than a broadcast of the output."""
    return out_features > in_features


def _with_ones(x: Tensor) -> Tensor:
    """``[..., rows, in]`` → ``[..., rows, in + 1]`` with a last column of ones."""
    ones = torch.ones(*x.shape[:-1], 1, dtype=x.dtype, device=x.device)
    return torch.cat([x, ones], dim=-1)


def _linear(x: Tensor, w: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """``x @ w + b`` for 2-D (shared weights) or 3-D (``[G, rows, in] @ [G, in, out]``) operands; also returns the
    matmul's left operand, which the backward pass needs (``[x, 1]`` where the bias was folded)."""
    if _folds(w.shape[-2], w.shape[-1]):
        left = _with_ones(x)
        return torch.matmul(left, torch.cat([w, b.unsqueeze(-2)], dim=-2)), left
    if x.dim() == 2:
        return torch.addmm(b, x, w), x
    return torch.baddbmm(b.unsqueeze(-2), x, w), x


def _weight_grad(left: Tensor, d: Tensor) -> Tensor:
    """``leftᵀ @ d``. For a narrow output (``[rows, 4096]ᵀ @ [rows, 12]``) BLAS is faster at ``(dᵀ @ left)ᵀ``: the
    long operand is then read row-major (measured 1.6× on the treadmill's 4096 → 12 layer)."""
    if d.shape[-1] < left.shape[-1]:
        return torch.matmul(d.transpose(-1, -2), left).transpose(-1, -2).contiguous()
    return torch.matmul(left.transpose(-1, -2), d)


def mlp_forward(x: Tensor, params: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, list[Tensor]]:
    """The MLP's output and every layer's matmul operand (ReLU on all but the last layer, in place)."""
    lefts: list[Tensor] = []
    last = len(params) - 1
    h = x
    for i, (w, b) in enumerate(params):
        h, left = _linear(h, w, b)
        lefts.append(left)
        if i < last:
            h = h.relu_()
    return h, lefts


class FusedMLP(torch.autograd.Function):
    """``apply(x, w0, b0, w1, b1, …)``: weights ``[in, out]`` / biases ``[out]`` (2-D ``x``: rows × in), or
    ``[G, in, out]`` / ``[G, out]`` (3-D ``x``: ``[G, rows, in]``)."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, *flat: Tensor) -> Tensor:
        params = list(zip(flat[0::2], flat[1::2], strict=True))
        out, lefts = mlp_forward(x, params)
        ctx.save_for_backward(*lefts, *flat)
        ctx.layers = len(params)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        saved = ctx.saved_tensors
        n = ctx.layers
        lefts, flat = saved[:n], saved[n:]
        grads: list[Tensor | None] = [None] * (2 * n)
        grad_x: Tensor | None = None
        d = grad
        for i in reversed(range(n)):
            w = flat[2 * i]
            left = lefts[i]
            g = _weight_grad(left, d)  # [..., in(+1), out]
            if _folds(w.shape[-2], w.shape[-1]):
                grads[2 * i], grads[2 * i + 1] = g[..., :-1, :], g[..., -1, :]
            else:
                grads[2 * i], grads[2 * i + 1] = g, d.sum(-2)
            if i == 0 and not ctx.needs_input_grad[0]:
                break
            wt = w.transpose(-1, -2)
            if w.shape[-1] < w.shape[-2]:  # a narrowing layer's wᵀ is small, and BLAS is faster on it row-major
                wt = wt.contiguous()
            d_in = torch.matmul(d, wt)  # fresh, so ours to mask in place
            if i == 0:
                grad_x = d_in
                break
            # the ReLU of layer i − 1: its output is this layer's input (the first columns of ``left``)
            relu_out = left[..., : w.shape[-2]] if left.shape[-1] != w.shape[-2] else left
            d = torch.ops.aten.threshold_backward.grad_input(d_in, relu_out, 0.0, grad_input=d_in)
        return (grad_x, *grads)


def fused_mlp(x: Tensor, params: list[tuple[Tensor, Tensor]]) -> Tensor:
    """The MLP through one autograd node when a gradient is wanted, the same arithmetic without one otherwise."""
    flat = [t for pair in params for t in pair]
    if torch.is_grad_enabled() and (x.requires_grad or any(t.requires_grad for t in flat)):
        return FusedMLP.apply(x, *flat)
    return mlp_forward(x, params)[0]
