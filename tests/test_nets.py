"""``algos/nets.py``'s building blocks: what ``GroupMLP`` computes and the parameter layout checkpoints hold."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from convoy.algos.nets import GroupLinear, GroupMLP
from convoy.algos.registry import make_algorithm
from convoy.config import ALGORITHMS, resolve_algo
from convoy.envs.batched import EnvSpec


@pytest.mark.parametrize("norm", [False, True], ids=["plain", "layer-norm"])
@pytest.mark.parametrize("groups", [1, 3])
@pytest.mark.parametrize("hidden", [(), (64,), (64, 12), (5, 40, 7)])  # widening, narrowing and equal layers
def test_group_mlp_is_linear_relu_with_one_weight_set_per_agent_group(
    groups: int, hidden: tuple[int, ...], norm: bool
) -> None:
    """``Linear → [LayerNorm →] ReLU → … → Linear``: with one group every agent uses the same weights, with N groups
    agent i uses group i's; ``norm`` standardises each hidden pre-activation over its units (no learned scale)."""
    torch.manual_seed(0)
    m = GroupMLP(groups, 9, hidden, 4, norm=norm).double()
    x = torch.randn(6, 3, 9, dtype=torch.double)
    got = m(x)
    assert got.shape == (6, 3, 4)
    for agent in range(3):
        g = 0 if groups == 1 else agent
        h = x[:, agent]
        for i, layer in enumerate(m.layers):
            assert isinstance(layer, GroupLinear)
            h = h @ layer.weight[g] + layer.bias[g]
            if i < len(m.layers) - 1:
                if norm:
                    h = (h - h.mean(-1, keepdim=True)) / torch.sqrt(h.var(-1, unbiased=False, keepdim=True) + 1e-5)
                h = torch.relu(h)
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


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_layer_norm_reaches_every_mlp_of_every_algorithm(name: str, tmp_path: Path) -> None:
    """``layer_norm`` is an ``AlgoConfig`` field, so no algorithm may take it and silently build plain MLPs."""
    spec = EnvSpec(name="toy", agent_ids=("a", "b"), obs_dims=(6, 6), n_actions=(5, 5), max_steps=10)
    hp: dict[str, object] = {"hidden": (16, 16), "layer_norm": True}
    if name == "codbc":  # the teacher is loaded when it first acts, not to build the student
        hp["teacher"] = str(tmp_path / "teacher.pt")
    algo = make_algorithm(name, spec, resolve_algo(name, "treadmill", hp), device="cpu", seed=0)
    mlps = [m for m in algo.online.modules() if isinstance(m, GroupMLP) and len(m.layers) > 1]
    assert mlps, f"{name} builds no GroupMLP with a hidden layer"
    assert all(m.norm for m in mlps), f"{name}: an MLP ignores layer_norm"


def test_match_parameters_widens_independent_dqn_to_ma_mesns_size_and_no_more() -> None:
    """The network-size control: the least common widening factor whose widths reach MA-MeSN's parameter count
    (one unit less per layer falls short), the same widths every time (a checkpoint rebuilds it); an unknown name is
    refused as this field."""
    from convoy.algos.registry import n_parameters
    from convoy.validation import ConfigError

    spec = EnvSpec(name="treadmill", agent_ids=("a", "b", "c"), obs_dims=(14, 14, 14), n_actions=(9, 9, 9),
                   max_steps=50)  # fmt: skip
    shared = {"hidden": (32, 32), "message_bits": 16}
    target = n_parameters("ma-mesn", spec, resolve_algo("ma-mesn", "treadmill", shared))
    cfg = resolve_algo("idqn", "treadmill", {"hidden": (32, 32), "match_parameters": "MA_MeSN"})
    algo = make_algorithm("idqn", spec, cfg, device="cpu")
    wide = algo.cfg.widths
    assert wide[0] == wide[1] > 32 and algo.n_parameters() >= target > n_parameters("idqn", spec, cfg.model_copy(
        update={"hidden": (wide[0] - 1, wide[1] - 1), "match_parameters": None}))  # fmt: skip
    assert make_algorithm("idqn", spec, cfg, device="cpu").cfg.widths == wide
    with pytest.raises(ConfigError) as bad:
        resolve_algo("idqn", "treadmill", {"match_parameters": "nope"})
    assert bad.value.field == "match_parameters" and "ma-mesn" in str(bad.value)
