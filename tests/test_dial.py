"""DIAL: the DRU, messages that arrive one step late, episode-based target syncs, checkpoints, and learning to talk."""

from __future__ import annotations

import io
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import epsilon_at
from convoy.algos.dial import DIAL, dru
from convoy.algos.registry import make_algorithm
from convoy.config import DIALConfig, resolve_algo
from convoy.envs import make_batched
from convoy.transition import Transition, from_columns
from tests.conftest import single_update
from tests.transitions import batch


def make_dial(num_envs: int = 8, rounds: int = 2, seed: int = 0, **params: Any) -> tuple[DIAL, Any]:
    torch.manual_seed(seed)
    env = make_batched("referential", num_envs, n_targets=4, rounds=rounds)
    cfg = resolve_algo("dial", "referential", {"hidden": (64,), "message_bits": 4, "unroll": 2, **params})
    algo = make_algorithm("dial", env.spec, cfg, device="cpu", seed=seed)
    assert isinstance(algo, DIAL)
    return algo, env


class Loop:
    """The trainer's contract (as in learner/inprocess.py): act, step, reset_state; observe every chunk_len steps."""

    def __init__(self, algo: DIAL, env: Any, seed: int = 0) -> None:
        self.algo, self.env = algo, env
        self.obs = env.reset(seed=seed)
        self.state = algo.initial_state(env.num_envs)
        self.owed = 0.0

    def chunk(self, eps: float) -> Transition[np.ndarray]:
        steps = []
        for _ in range(self.algo.chunk_len):
            out = self.algo.act(self.obs, eps, self.state)
            res = self.env.step(out.actions)
            steps.append(
                {
                    "obs": self.obs,
                    "action": out.actions,
                    "reward": res.reward,
                    "next_obs": res.final_obs,
                    "terminated": res.terminated,
                    "truncated": res.truncated,
                    "episode": np.zeros(self.env.num_envs, np.int64),
                    **out.extras,
                }
            )
            self.state = self.algo.reset_state(out.state, res.done)
            self.obs = res.obs
        return from_columns({k: np.stack([s[k] for s in steps]) for k in steps[0]})

    def train(self, chunks: int, total_steps: int | None = None) -> list[dict[str, float]]:
        algo, b = self.algo, self.env.num_envs
        algo.progress.total_steps = total_steps or chunks * algo.chunk_len * b
        stats = []
        for _ in range(chunks):
            eps = epsilon_at(algo.cfg, algo.progress.env_steps, algo.progress.total_steps)
            chunk = self.chunk(eps)
            algo.progress.env_steps += chunk.obs.shape[0] * b
            algo.observe(chunk)
            self.owed += algo.updates_for(chunk.obs.shape[0] * b)
            while self.owed >= 1 and algo.can_update():
                stats.append(single_update(algo))
                self.owed -= 1
        return stats

    def greedy_success(self, games: int = 10, mute: bool = False) -> float:
        """Mean listener reward on the last round of greedy (ε = 0, hard-threshold messages) games; ``mute``
        silences the channel (every agent hears zeros)."""
        obs, state, hits = self.env.reset(seed=12345), self.algo.initial_state(self.env.num_envs), []
        for _ in range(games * self.env.spec.max_steps):
            out = self.algo.act(obs, 0.0, state)
            res = self.env.step(out.actions)
            if res.terminated.all():
                hits.append(res.reward[:, 1].mean())
            state, obs = self.algo.reset_state(out.state, res.done | mute), res.obs
        self.obs, self.state = self.env.reset(seed=0), self.algo.initial_state(self.env.num_envs)  # restart training
        return float(np.mean(hits))


# --------------------------------------------------------------------------- the DRU


def test_dru_is_noisy_in_training_and_a_hard_threshold_at_execution() -> None:
    g = torch.Generator().manual_seed(0)
    randn = lambda x: torch.randn(x.shape, generator=g)  # noqa: E731
    logits = torch.linspace(-3, 3, 64).reshape(8, 8)
    a, b = dru(logits, 2.0, train=True, randn=randn), dru(logits, 2.0, train=True, randn=randn)
    assert not torch.equal(a, b)
    assert ((a > 0) & (a < 1)).all() and ((b > 0) & (b < 1)).all()
    torch.testing.assert_close(dru(logits, 0.0, train=True), torch.sigmoid(logits))  # σ = 0: plain sigmoid
    hard = dru(logits, 2.0, train=False, randn=randn)
    assert torch.equal(hard, dru(logits, 2.0, train=False))  # deterministic
    assert set(hard.unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(hard, (logits > 0).float())


def test_training_messages_are_differentiable() -> None:
    logits = torch.zeros(4, 3, requires_grad=True)
    dru(logits, 2.0, train=True).sum().backward()
    assert logits.grad is not None and (logits.grad > 0).all()


# --------------------------------------------------------------------------- acting


def test_act_sends_bits_and_stores_what_was_heard() -> None:
    algo, env = make_dial(num_envs=6)
    obs, state = env.reset(seed=0), algo.initial_state(6)
    assert state.shape == (1, 6, 2, 4) and not state.any()  # the recurrent state keeps the run axis
    out = algo.act(obs, 0.0, state)
    assert out.messages is not None and out.messages.shape == (6, 2, 4)
    assert set(np.unique(out.messages)) <= {0.0, 1.0}
    np.testing.assert_array_equal(out.extras["msg_in"], 0.0)  # nothing heard on an episode's first step
    np.testing.assert_array_equal(out.extras["mu"], 1.0)  # greedy: every taken action has probability 1
    res = env.step(out.actions)
    state = algo.reset_state(out.state, res.done)
    out2 = algo.act(res.obs, 1.0, state)
    # Round 2: each agent hears the other's round-1 message (speaker ↔ listener).
    np.testing.assert_array_equal(out2.extras["msg_in"][:, 0], out.messages[:, 1])
    np.testing.assert_array_equal(out2.extras["msg_in"][:, 1], out.messages[:, 0])
    np.testing.assert_allclose(out2.extras["mu"], np.broadcast_to([1.0, 0.25], (6, 2)))  # ε = 1: uniform
    done = np.array([True, False, True, False, False, False])
    cleared = algo.reset_state(out2.state, done)
    assert not cleared[0, done].any() and torch.equal(cleared[0, ~done], out2.state[0, ~done])


# --------------------------------------------------------------------------- gradients through the unroll


@pytest.mark.parametrize("share", [False, True])
def test_q_at_t_depends_on_the_others_obs_at_t_minus_1_only(share: bool) -> None:
    algo, _ = make_dial(share_params=share)
    t_len, b, n, d = 5, 3, 2, algo.obs_dim
    obs = torch.randn(1, t_len, b, n, d, requires_grad=True)  # one run's sequences [R = 1, T, B, …]
    heard0 = torch.zeros(1, b, n, (n - 1) * algo.bits)
    done = torch.zeros(1, t_len, b, dtype=torch.bool)
    q, sent = algo.unroll(algo.online, obs, heard0, done, train=True)
    assert q.shape == (1, t_len, b, n, algo.n_act) and sent.shape == (1, t_len, b, n, algo.bits)
    t, i, j = 3, 0, 1  # agent j's (the listener's) Q at step 3 vs agent i's (the speaker's) observations
    (grad,) = torch.autograd.grad(q[0, t, :, j].sum(), obs)
    grad = grad[0]
    assert grad[t, :, i].abs().sum() == 0  # i's current observation is not heard yet
    assert grad[t - 1, :, i].abs().sum() > 0  # heard through the message i sent at t−1
    # Messages take one step per hop: i(t−3) → j(t−2) → i(t−1) → j(t) reaches j; i(t−2) would arrive at t+1.
    assert grad[t - 3, :, i].abs().sum() > 0 and grad[t - 2, :, i].abs().sum() == 0
    assert grad[t, :, j].abs().sum() > 0 and grad[t - 1, :, j].abs().sum() == 0 and grad[t - 2, :, j].abs().sum() > 0
    assert grad[t + 1].abs().sum() == 0  # no dependence on the future


def test_messages_do_not_cross_an_episode_boundary() -> None:
    algo, _ = make_dial()
    obs = torch.randn(1, 3, 2, 2, algo.obs_dim, requires_grad=True)  # one run's sequences [R = 1, T, B, …]
    done = torch.tensor([[[False, False], [True, False], [False, False]]])  # env 0's episode ends at step 1
    q, _ = algo.unroll(algo.online, obs, torch.zeros(1, 2, 2, algo.bits), done, train=True)
    (grad,) = torch.autograd.grad(q[0, 2, :, 1].sum(), obs)
    grad = grad[0]
    assert grad[1, 0, 0].abs().sum() == 0 and grad[0, 0].abs().sum() == 0  # env 0: new episode hears zeros
    assert grad[1, 1, 0].abs().sum() > 0  # env 1 still hears the speaker


def test_every_agent_loss_reaches_the_speaker_through_its_messages() -> None:
    """The speaker's only action is a no-op, so its C-Net's message head learns only from the listener's loss."""
    algo, env = make_dial(num_envs=16)
    data = Loop(algo, env).chunk(eps=1.0).map(lambda v: torch.as_tensor(v)[None])  # [R = 1, T, B, …]
    losses = algo.agent_losses(data)
    assert losses.shape == (1, 2)
    speaker_w = algo.online.get_parameter("cnet.layers.0.weight")
    (g,) = torch.autograd.grad(losses[0, 1], speaker_w)
    assert g[0, 0].abs().sum() > 0  # listener's TD loss → speaker's weights (group 0)


def test_truncated_steps_bootstrap_and_terminated_steps_do_not() -> None:
    algo, env = make_dial(num_envs=4, gamma=0.9)
    data = Loop(algo, env).chunk(eps=1.0).map(lambda v: torch.as_tensor(v)[None])
    data = replace(data, reward=torch.zeros_like(data.reward))
    data.terminated[:] = True
    _, _, y = algo.sequence_q(data)
    assert torch.equal(y, torch.zeros_like(y))
    data.terminated[:], data.truncated[:] = False, True
    _, _, y = algo.sequence_q(data)
    assert y.abs().sum() > 0  # γ · Q_target(final obs, messages sent on the last step)


# --------------------------------------------------------------------------- updates and target syncs


def test_each_on_policy_chunk_gets_exactly_one_update() -> None:
    algo, env = make_dial(num_envs=8)
    loop = Loop(algo, env)
    assert not algo.can_update()
    algo.observe(loop.chunk(eps=1.0))
    assert algo.updates_for(algo.chunk_len * 8) == 1.0 and algo.can_update()
    stats = single_update(algo)
    assert np.isfinite(stats["loss"]) and algo.updates == 1 and not algo.can_update()
    rows = loop.train(5)
    assert len(rows) == 5 and algo.updates == 6


def test_target_is_frozen_between_syncs_and_syncs_every_40_episodes() -> None:
    algo, env = make_dial(num_envs=4, lr=1e-2)  # rounds=2, unroll=2: every chunk ends 4 episodes
    assert algo.cfg.target_update_episodes == 40
    loop = Loop(algo, env)

    def params(nets: torch.nn.Module) -> torch.Tensor:
        return torch.cat([p.detach().flatten().clone() for p in nets.parameters()])

    frozen = params(algo.target)
    loop.train(9)  # 36 episodes, 9 updates
    assert algo.episodes_done == 36 and algo.updates == 9
    assert torch.equal(params(algo.target), frozen)
    assert not torch.equal(params(algo.online), frozen)
    algo.observe(loop.chunk(eps=1.0))  # the 40th episode ends: sync before this chunk's update
    assert algo.episodes_done == 40 and algo.synced_at == 40
    assert torch.equal(params(algo.target), params(algo.online))
    synced = params(algo.target)
    algo.update()
    loop.train(9)  # 76 episodes: no sync yet
    assert torch.equal(params(algo.target), synced) and not torch.equal(params(algo.online), synced)
    algo.observe(loop.chunk(eps=1.0))
    assert algo.synced_at == 80 and torch.equal(params(algo.target), params(algo.online))


def test_state_dict_round_trips() -> None:
    algo, env = make_dial(num_envs=4)
    Loop(algo, env).train(12)
    buf = io.BytesIO()
    torch.save(algo.state_dict(), buf)
    buf.seek(0)
    other, _ = make_dial(num_envs=4, seed=9)
    other.load_state_dict(torch.load(buf, weights_only=False))
    assert (other.updates, other.episodes_done, other.synced_at) == (algo.updates, algo.episodes_done, algo.synced_at)
    for a, b in zip(algo.state_dict()["online"].values(), other.state_dict()["online"].values(), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(algo.target.parameters(), other.target.parameters(), strict=True):
        assert torch.equal(a, b)
    logits = torch.zeros(5, 4)
    assert torch.equal(dru(logits, 2.0, True, algo.randn), dru(logits, 2.0, True, other.randn))  # same DRU noise
    obs = env.reset(seed=3)
    out_a, out_b = algo.act(obs, 0.5, algo.initial_state(4)), other.act(obs, 0.5, other.initial_state(4))
    np.testing.assert_array_equal(out_a.actions, out_b.actions)  # same exploration stream


# --------------------------------------------------------------------------- importance-sampled replay


def test_replay_variant_stores_sequences_and_updates() -> None:
    algo, env = make_dial(num_envs=8, replay=True, replay_capacity=64, learning_starts=32, batch_size=8, unroll=3)
    loop = Loop(algo, env)
    assert algo.replay.capacity == 64 // 3
    stats = loop.train(12)
    assert algo.updates > 0 and len(stats) == algo.updates
    assert all(np.isfinite(s["loss"]) for s in stats)
    assert len(algo.replay) == algo.replay.capacity  # bounded ring, full
    batch = algo.sample()
    assert batch.obs.shape == (1, 3, 8, 2, algo.obs_dim) and batch.extras["valid"].all()  # [R = 1, T, B, …]
    # A chunk of another length is split and zero-padded; the padding is marked invalid.
    rows = algo.to_sequences(loop.chunk(eps=1.0).map(lambda v: v[:2]))
    valid = rows.extras["valid"]
    assert rows.obs.shape == (8, 3, 2, algo.obs_dim) and valid[:, :2].all() and not valid[:, 2].any()


def test_a_replay_saved_before_sequences_held_every_field_loads_and_goes_on() -> None:
    """DIAL's replay kept only what its loss reads; its sequences are transitions now, ``episode`` too: a replay
    file without it loads (zeros, never read) and takes the next chunks."""
    algo, env = make_dial(num_envs=4, replay=True, replay_capacity=64, unroll=3)
    loop = Loop(algo, env)
    algo.observe(loop.chunk(eps=1.0))
    old = algo.replay.state_dict()
    del old["data"]["episode"]
    fresh, _ = make_dial(num_envs=4, replay=True, replay_capacity=64, unroll=3)
    fresh.replay.load_state_dict(old)
    fresh.observe(loop.chunk(eps=1.0))
    assert len(fresh.replay) == 2 * 4 and not fresh.sample().episode.any()


def test_importance_weights_are_clipped_joint_ratios() -> None:
    algo, _ = make_dial(replay=True, eps_start=0.2, eps_end=0.2)
    q_all = torch.zeros(1, 3, 2, 4)
    q_all[..., 2] = 1.0  # current greedy action: 2 (the speaker only has action 0)
    action = torch.tensor([[[0, 2], [0, 1], [0, 1]]])
    mu = torch.tensor([[[1.0, 0.5], [0.5, 0.1], [1.0, 0.85]]])
    w = algo.is_weights(q_all, batch(action=action, mu=mu))
    pi_other = 0.2 / 4  # current ε-greedy probability of a non-greedy action
    # greedy now but rarer before: 0.85 / 0.5 > 1 → clipped to 1; product over agents (1 / 0.5 · 0.05 / 0.1);
    # a greedy-then action that is exploratory now: 0.05 / 0.85.
    torch.testing.assert_close(w, torch.tensor([[1.0, 2.0 * pi_other / 0.1, pi_other / 0.85]]))


# --------------------------------------------------------------------------- learning


@pytest.mark.slow
def test_dial_learns_the_two_round_referential_game() -> None:
    """The speaker's round-1 message reaches the listener in round 2; only then can it beat chance (1/4)."""
    algo, env = make_dial(num_envs=64, lr=1e-3, message_bits=16, unroll=4, eps_decay_fraction=0.3)
    loop = Loop(algo, env)
    loop.train(375)  # 1500 steps × 64 envs, 375 updates
    success, muted = loop.greedy_success(), loop.greedy_success(mute=True)
    assert success >= 0.9, f"greedy success {success:.2f}"
    assert muted <= 0.5, f"greedy success without messages {muted:.2f}: the listener must be listening"


def test_config_defaults_follow_the_paper() -> None:
    cfg = DIALConfig()
    assert (cfg.dru_sigma, cfg.target_update_episodes, cfg.replay) == (2.0, 40, False)
