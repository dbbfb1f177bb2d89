"""``examples/ma_mesn_single.py`` computes the product's MA-MeSN update (``algos/ma_mesn.py``): given the same weights,
the same batch and the same Gumbel noise, both give the same per-agent losses, the same gradients and the same
weights after Adam steps (to 1e-5). The single file is the reference a reader starts from; if the product's update
changes, this test says which number moved."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.nets import GroupLinear
from convoy.algos.registry import make_algorithm
from convoy.config import MeSNConfig, resolve_algo
from convoy.envs.batched import EnvSpec
from convoy.envs.particle.referential import make_referential_batch
from convoy.transition import from_columns

ROOT = Path(__file__).resolve().parents[1]
# the run docs/algorithms.md shows for MA-MeSN on the referential game ($REF), whose settings the file's defaults are
REF = {"hidden": 64, "learning_starts": 256, "replay_ratio": 2, "target_update": 50}
# every switch of the update away from REF: no Gumbel noise (deterministic straight-through, as on speaker-listener)
# at another temperature, no double Q, squared error, a clip that bites, a target synced after every update
PLAIN = {**REF, "gumbel_noise": 0.0, "gumbel_tau": 0.5, "double_q": False, "huber": False, "grad_clip": 0.05,
         "target_update": 1}  # fmt: skip
SHARED = ("lr", "gamma", "batch_size", "target_update", "grad_clip", "huber", "double_q", "message_bits", "gumbel_tau",
          "gumbel_noise", "hidden", "eps_start", "eps_end", "eps_decay_fraction", "eps_decay_max_steps",
          "replay_ratio", "learning_starts", "replay_capacity")  # fmt: skip
# what the single file leaves out, at the value that makes it a no-op in the product
OFF = {"share_params": False, "message_logit_bound": None, "signalling_coef": 0.0, "channel_control": "open",
       "n_step": 1, "advantage_learning": 0.0, "policy_ema": 1.0, "target_tau": 1.0, "layer_norm": False,
       "encoder": "mlp", "lr_end": None}  # fmt: skip


@pytest.fixture(scope="module")
def single() -> ModuleType:
    """The example file as a module (it is a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location("ma_mesn_single", ROOT / "examples" / "ma_mesn_single.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def env_spec() -> EnvSpec:
    return make_referential_batch(1).spec


def product(params: dict) -> NetworkAgent:
    """The product's MA-MeSN with ``params`` on the referential game; its target holds other weights (those of
    seed 1), so the test sees whether the bootstrap reads the target networks."""
    cfg = resolve_algo("ma-mesn", "referential", params)
    agent = make_algorithm("ma-mesn", env_spec(), cfg, device="cpu", seed=0)
    other = make_algorithm("ma-mesn", env_spec(), cfg, device="cpu", seed=1)
    agent.target.load_state_dict(other.online.state_dict())
    return agent


def args_for(single: ModuleType, agent: NetworkAgent) -> Any:
    """The single file's ``Args`` for the product's config; every field both have must agree."""
    cfg = agent.cfg
    assert isinstance(cfg, MeSNConfig)
    args = single.Args(**{k: getattr(cfg, k) for k in ("gumbel_noise", "gumbel_tau", "double_q", "huber", "grad_clip",
                                                      "target_update", "hidden")})  # fmt: skip
    for name in SHARED:
        assert getattr(args, name) == getattr(cfg, name), f"{name}: the file's {getattr(args, name)!r} vs {cfg}"
    for name, value in OFF.items():
        assert getattr(cfg, name) == value, f"{name}: the product runs {getattr(cfg, name)!r}, the file {value!r}"
    return args


def as_single(nets: nn.ModuleDict, grad: bool = False) -> dict[str, Tensor]:
    """The product's stacked weights (``GroupLinear`` ``[R = 1, N, in, out]``), or their gradients, in the single
    file's per-agent ``nn.Linear`` layout (``[out, in]``; the ReLUs sit at the odd indices of each
    ``nn.Sequential``)."""
    out = {}
    for part in ("message", "policy"):
        layers = [m for m in nets[part].modules() if isinstance(m, GroupLinear)]  # in layer order
        for k, layer in enumerate(layers):
            weight, bias = (layer.weight.grad, layer.bias.grad) if grad else (layer.weight, layer.bias)
            assert weight is not None and bias is not None
            weight, bias = weight[0], bias[0]  # the run's
            for i in range(layer.groups):
                out[f"{part}.{i}.{2 * k}.weight"] = weight[i].T
                out[f"{part}.{i}.{2 * k}.bias"] = bias[i]
    return out


def twins(single: ModuleType, agent: NetworkAgent) -> tuple[Any, Any, Any]:
    """(args, online, target) of the single file holding the product agent's online and target weights."""
    args, spec = args_for(single, agent), agent.spec
    online, target = (single.MeSN(spec.obs_dim, spec.n_actions, args.message_bits, args.hidden) for _ in range(2))
    online.load_state_dict(as_single(agent.online))
    target.load_state_dict(as_single(agent.target))
    target.requires_grad_(False)
    return args, online, target


def batch(spec: EnvSpec, m: int = 64, seed: int = 0) -> dict[str, Tensor]:
    """A joint batch with valid actions per agent and ~30 % terminal rows (the others bootstrap)."""
    g = torch.Generator().manual_seed(seed)
    n, d = spec.n_agents, spec.obs_dim
    action = torch.stack([torch.randint(0, a, (m,), generator=g) for a in spec.n_actions], dim=1)
    return {
        "obs": torch.randn(m, n, d, generator=g),
        "action": action,
        "reward": torch.randn(m, n, generator=g),
        "next_obs": torch.randn(m, n, d, generator=g),
        "terminated": torch.rand(m, generator=g) < 0.3,
        "truncated": torch.zeros(m, dtype=torch.bool),
        "episode": torch.zeros(m, dtype=torch.long),
    }


def same_noise(agent: NetworkAgent, seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """The agent's message noise from a torch generator of ``seed``, as the single file draws it (the agent's own
    streams are another generator: ``algos.streams``)."""
    gen = torch.Generator().manual_seed(seed)
    monkeypatch.setattr(agent, "rand_like", lambda x, normal=False: torch.rand(x.shape, generator=gen, dtype=x.dtype))


@pytest.mark.parametrize("params", [REF, PLAIN], ids=["ref", "plain"])
def test_losses_and_gradients_equal_the_products(
    single: ModuleType, params: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    agent = product(params)
    args, online, target = twins(single, agent)
    data = batch(agent.spec)
    same_noise(agent, 7, monkeypatch)  # the same Gumbel noise: both draw one uniform per bit from this state
    gen = torch.Generator().manual_seed(7)

    theirs = agent.loss(from_columns({k: v[None] for k, v in data.items()})).agents[0]  # the product's: one run's
    ours = single.td_losses(online, target, data, args, gen)
    assert ours.shape == (agent.n_agents,) and bool((ours > 0).all())
    torch.testing.assert_close(ours, theirs.detach(), rtol=1e-5, atol=1e-5)

    agent.updater.optimizer.zero_grad(set_to_none=True)
    theirs.sum().backward()
    ours.sum().backward()
    grads = {name: p.grad for name, p in online.named_parameters()}
    torch.testing.assert_close(grads, as_single(agent.online, grad=True), rtol=1e-5, atol=1e-5)  # names the weight
    # real numbers were compared: the listener's TD loss reaches the speaker's message network (l. 18–19)
    assert online.message[0][0].weight.grad.abs().sum() > 0 and online.policy[1][0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("params", [REF, PLAIN], ids=["ref", "plain"])
def test_weights_after_adam_steps_equal_the_products(
    single: ModuleType, params: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three steps on three batches (Adam's moments, the clip and the target sync included)."""
    agent = product(params)
    args, online, target = twins(single, agent)
    start = {k: v.clone() for k, v in online.state_dict().items()}
    optimizer = torch.optim.Adam(online.parameters(), lr=args.lr)
    same_noise(agent, 3, monkeypatch)
    gen = torch.Generator().manual_seed(3)
    updates = 0
    for step in range(3):
        data = batch(agent.spec, seed=10 + step)
        monkeypatch.setattr(agent, "sample", lambda data=data: from_columns({k: v[None] for k, v in data.items()}))
        (figures,) = agent.update().read()
        loss, updates = single.train_step(online, target, optimizer, data, args, gen, updates)
        assert isinstance(figures, dict) and updates == agent.updates
        assert loss == pytest.approx(figures["loss"], rel=1e-5, abs=1e-5)
        if args.grad_clip < 1:
            assert figures["grad_norm"] > args.grad_clip  # the clip acted
    for mine, theirs in ((online, agent.online), (target, agent.target)):
        torch.testing.assert_close(dict(mine.state_dict()), as_single(theirs), rtol=1e-5, atol=1e-5)
    moved = max(float((online.state_dict()[k] - v).abs().max()) for k, v in start.items())
    assert moved > 1e-4  # the steps changed the weights: equal after them is not equal by standing still


def test_the_script_runs_end_to_end_and_parses_its_flags(single: ModuleType) -> None:
    args = single.parse_args(["--steps", "768", "--no-huber", "--hidden", "16", "16", "--gumbel-noise", "0"])
    assert args.steps == 768 and args.huber is False and args.hidden == (16, 16) and args.gumbel_noise == 0.0
    small = single.Args(steps=768, num_envs=32, learning_starts=64, eval_episodes=64, log_every=256, hidden=(16,))
    out = single.main(small)
    assert out["updates"] > 0 and all(np.isfinite(v) for v in out.values())
    assert 0.0 <= out["greedy"] <= 1.0 and 0.0 <= out["random"] <= 1.0


@pytest.mark.slow
def test_the_documented_run_beats_random(single: ModuleType) -> None:
    """`python examples/ma_mesn_single.py --steps 25000` (docs/algorithms.md): the listener names the target."""
    out = single.main(single.Args(steps=25_000))
    assert out["greedy"] >= 0.9 and out["greedy"] - out["greedy_ci"] > out["random"] + out["random_ci"]
