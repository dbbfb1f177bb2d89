"""IMS (CommNet) and MA-BoN: communication structure, where gradients go, learning the referential game, N-scaling."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.ims import IMS, mean_of_others
from convoy.algos.ma_bon import MABoN
from convoy.algos.nets import GroupLinear, GroupMLP
from convoy.algos.registry import make_algorithm
from convoy.config import resolve_algo
from convoy.envs import EnvSpec, make_batched
from convoy.transition import Transition, record
from tests.conftest import grad, synthetic_spec
from tests.transitions import batch

SMALL: dict[str, Any] = {"hidden": (64,), "learning_starts": 64, "batch_size": 32}


def build(algo: str, spec: EnvSpec, seed: int = 0, **params: object) -> NetworkAgent:
    torch.manual_seed(seed)
    cfg = resolve_algo(algo, "referential", {**SMALL, **params})
    return make_algorithm(algo, spec, cfg, device="cpu", seed=seed)


def build_ims(spec: EnvSpec, seed: int = 0, **params: object) -> IMS:
    algo = build("ims", spec, seed, **params)
    assert isinstance(algo, IMS)
    return algo


def build_bon(spec: EnvSpec, seed: int = 0, **params: object) -> MABoN:
    algo = build("ma-bon", spec, seed, **params)
    assert isinstance(algo, MABoN)
    return algo


def random_batch(algo: NetworkAgent, m: int = 32, seed: int = 0) -> Transition[Tensor]:
    g = torch.Generator().manual_seed(seed)
    n, d, a = algo.n_agents, algo.obs_dim, algo.n_act
    return batch(
        obs=torch.randn(1, m, n, d, generator=g),  # one run's: [R = 1, M, …]
        action=torch.randint(0, a, (1, m, n), generator=g),
        reward=torch.randn(1, m, n, generator=g),
        next_obs=torch.randn(1, m, n, d, generator=g),
        terminated=torch.rand(1, m, generator=g) < 0.3,
    )


class CallCounter:
    """Counts forward calls of a module through a forward hook."""

    def __init__(self, module: nn.Module) -> None:
        self.calls = 0
        self.handle = module.register_forward_hook(self._hook)

    def _hook(self, *_: object) -> None:
        self.calls += 1


# --------------------------------------------------------------------------- IMS (CommNet)


@pytest.mark.parametrize("p", [1, 3, 5])
def test_ims_applies_the_communication_step_p_times_per_forward(p: int) -> None:
    algo = build_ims(synthetic_spec(3), comm_iterations=p, share_params=True)
    counter = CallCounter(algo.online["comm"])
    obs = np.random.default_rng(0).normal(size=(4, 3, 5)).astype(np.float32)
    out = algo.act(obs, 0.0)
    assert counter.calls == p
    assert out.actions.shape == (4, 3) and out.messages is not None and out.messages.shape == (4, 3, algo.bits)
    assert set(np.unique(out.messages)) <= {0.0, 1.0}  # discrete bits at execution
    counter.calls = 0
    q, _ = algo.forward(algo.online, torch.as_tensor(obs)[None], train=True)  # one run's
    assert counter.calls == p and q.shape == (1, 4, 3, algo.n_act)


def test_ims_parameter_count_does_not_depend_on_p() -> None:
    assert (
        build_ims(synthetic_spec(3), comm_iterations=1).n_parameters()
        == build_ims(synthetic_spec(3), comm_iterations=5).n_parameters()
    )


def test_mean_of_others_is_the_mean_over_the_other_agents_and_zero_alone() -> None:
    x = torch.randn(2, 4, 3)
    expected = torch.stack([torch.cat([x[:, :i], x[:, i + 1 :]], dim=1).mean(dim=1) for i in range(4)], dim=1)
    torch.testing.assert_close(mean_of_others(x), expected)
    assert torch.equal(mean_of_others(x[:, :1]), torch.zeros(2, 1, 3))


def test_ims_received_overrides_what_agents_hear() -> None:
    algo = build_ims(synthetic_spec(3), comm_iterations=1)
    obs = torch.randn(1, 6, 3, 5)  # one run's
    q, sent = algo.forward(algo.online, obs, train=False)
    q_same, _ = algo.forward(algo.online, obs, train=False, received=mean_of_others(sent))
    torch.testing.assert_close(q_same, q)  # with P = 1, hearing the true mean is the unperturbed pass
    q_other, _ = algo.forward(algo.online, obs, train=False, received=1.0 - mean_of_others(sent))
    assert not torch.allclose(q_other, q)


def test_ims_single_agent_runs_and_hears_nothing() -> None:
    algo = build_ims(synthetic_spec(1), comm_iterations=3)
    out = algo.act(np.zeros((2, 1, 5), np.float32), 0.0)
    assert out.actions.shape == (2, 1)


def test_ims_continuous_messages_are_real_valued_and_trainable() -> None:
    algo = build_ims(synthetic_spec(2), comm_iterations=2, discrete=False)
    msgs = algo.act(np.random.default_rng(1).normal(size=(8, 2, 5)).astype(np.float32), 0.0).messages
    assert msgs is not None and not set(np.unique(msgs)) <= {0.0, 1.0}
    algo.agent_losses(random_batch(algo))[0, 0].backward()
    assert grad(algo.online, "comm.speak.weight").abs().sum() > 0


def test_ims_agent_loss_reaches_the_other_agents_message_weights() -> None:
    """With per-agent weights and P = 1, agent i's loss trains agent j's speaker (j ≠ i) through what i heard."""
    algo = build_ims(synthetic_spec(3), comm_iterations=1, share_params=False)
    comm = algo.online["comm"]
    for i in range(3):
        algo.updater.optimizer.zero_grad(set_to_none=True)
        algo.agent_losses(random_batch(algo, seed=i))[0, i].backward()
        speak = grad(comm, "speak.weight")[0].abs().sum(dim=(1, 2))
        for j in range(3):
            assert (speak[j] > 0) == (j != i), (i, j, speak)  # i's own message is only heard by others
        assert grad(comm, "listen.weight")[0, i].abs().sum() > 0 and grad(comm, "recur.weight")[0, i].abs().sum() > 0


# --------------------------------------------------------------------------- MA-BoN


@pytest.mark.parametrize("shared", [True, False])
def test_ma_bon_evaluates_all_agents_with_one_call_and_one_broadcast(shared: bool) -> None:
    algo = build_bon(synthetic_spec(4), share_params=shared)
    g_calls, f_calls = CallCounter(algo.online["policy"]), CallCounter(algo.online["message"])
    obs = np.random.default_rng(0).normal(size=(6, 4, 5)).astype(np.float32)
    out = algo.act(obs, 0.0)
    assert g_calls.calls == 1 and f_calls.calls == 1
    q, _, _ = algo.greedy_q(torch.as_tensor(obs)[None], None)  # one run's
    assert q.shape == (1, 6, 4, algo.n_act) and torch.isfinite(q).all()
    msgs = out.messages
    assert msgs is not None and msgs.shape == (6, 4, algo.bits)
    assert (msgs == msgs[:, :1]).all()  # one broadcast per env, heard identically by every agent
    assert set(np.unique(msgs)) <= {0.0, 1.0}
    _, sent = algo.forward(algo.online, torch.as_tensor(obs)[None], train=True)
    assert torch.equal(sent, sent[:, :, :1].expand_as(sent))


def test_ma_bon_received_overrides_the_broadcast() -> None:
    algo = build_bon(synthetic_spec(3))
    obs = torch.randn(1, 6, 3, 5)  # one run's
    q, sent = algo.forward(algo.online, obs, train=False)
    torch.testing.assert_close(algo.forward(algo.online, obs, train=False, received=sent)[0], q)
    assert not torch.allclose(algo.forward(algo.online, obs, train=False, received=1.0 - sent)[0], q)


@pytest.mark.parametrize("shared", [True, False])
def test_ma_bon_every_agent_loss_trains_the_message_network_and_the_encoders(shared: bool) -> None:
    algo = build_bon(synthetic_spec(3), share_params=shared)
    for i in range(3):
        algo.updater.optimizer.zero_grad(set_to_none=True)
        algo.agent_losses(random_batch(algo, seed=i))[0, i].backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in algo.online["message"].parameters())
        enc = algo.online.get_parameter("encoder.layers.0.weight").grad
        assert enc is not None and (enc[0].abs().sum(dim=(1, 2)) > 0).all()  # every agent's encoder feeds bm


def test_ma_bon_per_agent_heads_only_see_their_own_agents_loss() -> None:
    algo = build_bon(synthetic_spec(3), share_params=False)
    for i in range(3):
        algo.updater.optimizer.zero_grad(set_to_none=True)
        algo.agent_losses(random_batch(algo, seed=i))[0, i].backward()
        policy = algo.online["policy"]
        assert isinstance(policy, GroupMLP)
        for layer in policy.layers:
            assert isinstance(layer, GroupLinear)
            reached = grad(layer, "weight")[0].abs().sum(dim=(1, 2)) > 0
            assert reached.tolist() == [j == i for j in range(3)], (i, reached)


def test_ma_bon_parameters_grow_linearly_in_n_and_g_prime_is_independent_of_n() -> None:
    """Section 6.2: with shared weights only f′'s input (N·encoding) and the id columns grow with N."""

    def g_params(n: int, agent_id: bool) -> int:
        algo = build_bon(synthetic_spec(n), share_params=True, agent_id=agent_id)
        return sum(p.numel() for p in algo.online["policy"].parameters())

    assert g_params(2, False) == g_params(4, False) == g_params(8, False)
    width = SMALL["hidden"][0]
    assert g_params(8, True) - g_params(4, True) == 4 * width  # only the one-hot id's input columns
    totals = [build_bon(synthetic_spec(n), share_params=True).n_parameters() for n in (2, 4, 6, 8)]
    steps = np.diff(totals)
    assert (steps > 0).all() and (steps == steps[0]).all()  # exactly affine in N: linear space


# --------------------------------------------------------------------------- learning the referential game


def train_referential(algo_name: str, seed: int = 0, iterations: int = 300) -> tuple[float, float]:
    """Greedy success after a short training run on the K = 4 referential game (chance 0.25), and seconds taken."""
    num_envs = 64
    env = make_batched("referential", num_envs)
    torch.manual_seed(seed)
    cfg = resolve_algo(
        algo_name,
        "referential",
        {"hidden": (64,), "learning_starts": 256, "replay_capacity": 10_000, "target_update": 50},
    )
    algo = make_algorithm(algo_name, env.spec, cfg, device="cpu", seed=seed)
    obs = env.reset(seed=seed)
    start = time.perf_counter()
    for it in range(iterations):
        out = algo.act(obs, max(0.05, 1.0 - it / 100))
        res = env.step(out.actions)
        step = record(obs, out.actions, res.reward, res.final_obs, res.terminated, res.truncated,
                      np.zeros(num_envs, np.int64), out.extras)  # fmt: skip
        algo.observe(step.map(lambda v: v[None]))
        obs = res.obs
        if algo.can_update():
            for _ in range(2):
                algo.update()
    hits = []
    for _ in range(20):
        res = env.step(algo.act(obs, 0.0).actions)
        hits.append(float(res.reward[:, 1].mean()))
        obs = res.obs
    return float(np.mean(hits)), time.perf_counter() - start


@pytest.mark.slow
@pytest.mark.parametrize("algo_name", ["ims", "ma-bon"])
def test_learns_the_referential_game(algo_name: str) -> None:
    success, seconds = train_referential(algo_name)
    print(f"{algo_name}: greedy success {success:.3f} in {seconds:.1f} s")  # time printed, not asserted
    assert success >= 0.9
