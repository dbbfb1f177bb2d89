"""Bootstrapped DQN (``heads`` > 1, ``algos/idqn.py``): K heads on one encoder, a head per exploring episode.

An exploring env draws a head at its episode's first exploring act, from its run's exploration stream, and keeps it
until the episode ends; greedy acting draws nothing and acts on the heads' mean; every head learns towards its own
target; a population's run k is the single run of its seed; the heads need shared weights.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import Progress
from convoy.algos.idqn import IndependentDQN
from convoy.algos.registry import make_algorithm
from convoy.config import AlgoConfig, ConfigError, resolve_algo
from convoy.envs.batched import EnvSpec
from tests.test_population import SEEDS, chunk, feed, max_weight_gap

SPEC = EnvSpec(name="toy", agent_ids=("a", "b", "c"), obs_dims=(6, 6, 6), n_actions=(5, 5, 5), max_steps=10)
K = 4


def config(name: str = "idqn", **extra: object):
    hp = {"hidden": (32, 32), "batch_size": 16, "learning_starts": 0, "replay_capacity": 500, "lr": 1e-3,
          "target_update": 20, "share_params": True, "heads": K, **extra}  # fmt: skip
    return resolve_algo(name, "treadmill", hp)


def obs_of(g: np.random.Generator, runs: int, envs: int) -> np.ndarray:
    return g.normal(size=(runs, envs, SPEC.n_agents, SPEC.obs_dim)).astype(np.float32)


def dqn(cfg: AlgoConfig, seed: int) -> IndependentDQN:
    agent = make_algorithm("idqn", SPEC, cfg, device="cpu", seed=seed)
    assert isinstance(agent, IndependentDQN)
    return agent


def test_an_exploring_episode_follows_one_head_and_an_evaluation_the_heads_mean() -> None:
    agent = dqn(config(eps_end=0.0), 3)
    g = np.random.default_rng(0)
    obs = obs_of(g, 1, 64)
    with torch.no_grad():
        q = agent.online["q"](agent.features(torch.as_tensor(obs)))  # [1, B, N, K, A]
    assert q.shape == (1, 64, SPEC.n_agents, K, SPEC.max_actions)
    explore = agent.streams["explore"]
    # greedy acting: no head, no draw, the mean of the heads' Q
    fresh = agent.initial_state(64)
    greedy = agent.act(obs[0], 0.0, fresh)
    assert explore.state(0) == 0 and (greedy.state == -1).all()
    np.testing.assert_array_equal(greedy.actions, q.mean(dim=-2).argmax(dim=-1)[0].numpy())
    # exploring (ε tiny, so the greedy action of the env's head): one head per env, drawn once
    out = agent.act(obs[0], 1e-9, fresh)
    heads = out.state[0]
    assert explore.state(0) > 0 and ((heads >= 0) & (heads < K)).all() and len(heads.unique()) == K
    on_head = q[0].gather(-2, heads[:, None, None, None].expand(64, SPEC.n_agents, 1, SPEC.max_actions))
    np.testing.assert_array_equal(out.actions, on_head.squeeze(-2).argmax(dim=-1).numpy())
    # the head stays for the episode; an ended episode's env draws a new one at its next exploring act
    again = agent.act(obs_of(g, 1, 64)[0], 1e-9, out.state)
    assert torch.equal(again.state, out.state)
    done = np.zeros(64, dtype=bool)
    done[:32] = True
    reset = agent.reset_state(again.state, done)
    assert (reset[0, :32] == -1).all() and torch.equal(reset[0, 32:], heads[32:])
    redrawn = agent.act(obs[0], 1e-9, reset).state[0]
    assert (redrawn >= 0).all() and torch.equal(redrawn[32:], heads[32:])
    assert not torch.equal(redrawn[:32], heads[:32])


def test_each_head_learns_towards_its_own_target() -> None:
    agent = dqn(config(), 7)
    agent.progress = Progress(100, 1, 1000, training=True)
    feed(agent, [agent], np.random.default_rng(1))  # a single run fed as its own population
    batch = agent.sample()
    q, y = agent.q_and_y(batch)
    assert q.shape == y.shape == (K, 1, 16, SPEC.n_agents)
    assert not torch.allclose(y[0], y[1])  # different initial heads: different targets
    before = {n: w.clone() for n, w in agent.online.state_dict().items()}
    for _ in range(5):
        agent.update()
    last = [n for n in before if n.endswith("weight")][-1]  # the heads' last layer [1, K, in, A]
    gap = (agent.online.state_dict()[last] - before[last]).abs().amax(dim=(0, 2, 3))
    assert last.startswith("q.mlp.") and (gap > 0).all()  # every head stepped


def test_member_k_of_a_population_with_heads_is_the_single_run_of_seed_k() -> None:
    torch.set_num_threads(1)
    cfg = config()
    pop = make_algorithm("idqn", SPEC, cfg, device="cpu", seed=SEEDS)
    singles = [make_algorithm("idqn", SPEC, cfg, device="cpu", seed=s) for s in SEEDS]
    g = np.random.default_rng(0)
    feed(pop, singles, g)
    obs = obs_of(g, len(SEEDS), 8)
    eps = np.array([0.0, 0.3, 1.0])
    acted = pop.act(obs, eps, pop.initial_state(8))
    for k, single in enumerate(singles):
        alone = single.act(obs[k], eps[k], single.initial_state(8))
        np.testing.assert_array_equal(acted.actions[k], alone.actions)
        assert torch.equal(acted.state[k], alone.state[0])
    for _ in range(100):
        pop.update()
        for single in singles:
            single.update()
    assert max_weight_gap(pop, singles) < 1e-5


def test_heads_need_shared_weights_and_stabilised_replay_takes_them() -> None:
    with pytest.raises(ConfigError, match=r"heads.*share_params=true"):
        make_algorithm("idqn", SPEC, config(share_params=False), device="cpu", seed=0)
    ser = make_algorithm("dqn-ser", SPEC, config("dqn-ser"), device="cpu", seed=0)
    ser.progress = Progress(100, 5, 1000, training=True)
    ser.observe(chunk(np.random.default_rng(2), 1))
    assert np.isfinite(ser.update().read()[0]["loss"])
