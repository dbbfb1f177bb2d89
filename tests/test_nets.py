"""``algos/nets.py``'s building blocks: what ``GroupMLP`` computes and the parameter layout checkpoints hold."""

from __future__ import annotations

import pytest
import torch

from convoy.algos.nets import GroupMLP


@pytest.mark.parametrize("groups", [1, 3])
@pytest.mark.parametrize("hidden", [(), (64,), (64, 12), (5, 40, 7)])  # widening, narrowing and equal layers
def test_group_mlp_is_linear_relu_with_one_weight_set_per_agent_group(groups: int, hidden: tuple[int, ...]) -> None:
    """``Linear → ReLU → … → Linear``: with one group every agent uses the same weights, with N groups agent i uses
    group i's."""
    torch.manual_seed(0)
    m = GroupMLP(groups, 9, hidden, 4).double()
    x = torch.randn(6, 3, 9, dtype=torch.double)
    got = m(x)
    assert got.shape == (6, 3, 4)
    for agent in range(3):
        g = 0 if groups == 1 else agent
        h = x[:, agent]
        for i, layer in enumerate(m.layers):
            h = h @ layer.weight[g] + layer.bias[g]
            h = torch.relu(h) if i < len(m.layers) - 1 else h
        torch.testing.assert_close(got[:, agent], h)


def test_group_mlp_keeps_the_state_dict_layout_checkpoints_hold() -> None:
    """Checkpoints store ``layers.<i>.weight [G, in, out]`` and ``layers.<i>.bias [G, out]``; another layout would
    make every saved run unloadable."""
    torch.manual_seed(0)
    original = GroupMLP(3, 9, (64, 12), 4)
    state = original.state_dict()
    assert {k: tuple(v.shape) for k, v in state.items()} == {
        "layers.0.weight": (3, 9, 64),
        "layers.0.bias": (3, 64),
        "layers.1.weight": (3, 64, 12),
        "layers.1.bias": (3, 12),
        "layers.2.weight": (3, 12, 4),
        "layers.2.bias": (3, 4),
    }
    again = GroupMLP(3, 9, (64, 12), 4)
    again.load_state_dict(state)
    x = torch.randn(5, 3, 9)
    torch.testing.assert_close(again(x), original(x), rtol=0, atol=0)
