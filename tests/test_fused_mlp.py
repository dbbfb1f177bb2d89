"""The fused MLP node computes exactly Linear → ReLU → … → Linear: values and every gradient."""

from __future__ import annotations

import pytest
import torch

from convoy.algos.fused_mlp import FusedMLP, fused_mlp
from convoy.algos.nets import GroupMLP


def reference(m: GroupMLP, x: torch.Tensor) -> torch.Tensor:
    """Autograd's own layer-by-layer graph of the same weights."""
    groups = m.layers[0].groups
    n = x.shape[-2]
    h = x.reshape(-1, x.shape[-1]) if groups == 1 else x.reshape(-1, n, x.shape[-1]).transpose(0, 1)
    last = len(m.layers) - 1
    for i, layer in enumerate(m.layers):
        h = h @ layer.weight[0] + layer.bias[0] if groups == 1 else torch.bmm(h, layer.weight) + layer.bias.unsqueeze(1)
        if i < last:
            h = torch.relu(h)
    out = h if groups == 1 else h.transpose(0, 1)
    return out.reshape(*x.shape[:-1], out.shape[-1])


@pytest.mark.parametrize("groups", [1, 3])
@pytest.mark.parametrize("hidden", [(), (64,), (64, 12), (5, 40, 7)])  # widening, narrowing and equal layers
@pytest.mark.parametrize("input_grad", [False, True])
def test_values_and_gradients_match_autograd(groups: int, hidden: tuple[int, ...], input_grad: bool) -> None:
    torch.manual_seed(0)
    m = GroupMLP(groups, 9, hidden, 4).double()
    x = torch.randn(6, 3, 9, dtype=torch.double, requires_grad=input_grad)
    w = torch.randn(6, 3, 4, dtype=torch.double)
    (m(x) * w).sum().backward()
    fused = [p.grad.clone() for p in m.parameters()]
    fused_x = x.grad.clone() if input_grad else None
    m.zero_grad(set_to_none=True)
    if input_grad:
        x.grad = None
    y = reference(m, x)
    assert torch.allclose(m(x), y)
    (y * w).sum().backward()
    for got, p in zip(fused, m.parameters(), strict=True):
        assert torch.allclose(got, p.grad)
    if input_grad:
        assert torch.allclose(fused_x, x.grad)


def test_gradcheck_through_the_fused_node() -> None:
    torch.manual_seed(1)
    x = torch.randn(5, 7, dtype=torch.double, requires_grad=True)

    def leaf(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, dtype=torch.double, requires_grad=True)

    flat = [leaf(7, 16), leaf(16), leaf(16, 3), leaf(3)]
    assert torch.autograd.gradcheck(lambda x, *f: FusedMLP.apply(x, *f), (x, *flat))


def test_no_graph_without_gradients() -> None:
    m = GroupMLP(1, 4, (8,), 2)
    with torch.no_grad():
        y = m(torch.randn(3, 4))
    assert y.grad_fn is None
    y = fused_mlp(torch.randn(3, 4), [(torch.randn(4, 8), torch.randn(8)), (torch.randn(8, 2), torch.randn(2))])
    assert y.grad_fn is None  # nothing requires grad: the plain forward, no autograd node
