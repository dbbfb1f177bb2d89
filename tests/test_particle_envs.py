"""Particle envs and the referential game: PettingZoo API compliance, the paper's rules, and the batched adapter."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from convoy.envs.batched import BatchedEnv, env_seeds
from convoy.envs.particle import (
    PredatorPreyEnv,
    evade_action,
    make_predator_prey,
    make_predator_prey_batch,
    make_referential,
    make_referential_batch,
    make_speaker_listener,
    make_speaker_listener_batch,
)
from convoy.envs.particle.predator_prey import MINUS_X, MINUS_Y, NOOP, PLUS_X, PLUS_Y
from convoy.validation import ConfigError

NOOPS = {"predator_0": 0, "predator_1": 0}

# --------------------------------------------------------------------------- predator-prey


def test_predator_prey_passes_parallel_api_test() -> None:
    parallel_api_test(make_predator_prey(max_steps=60), num_cycles=100)


def test_predator_prey_passes_parallel_seed_test() -> None:
    parallel_seed_test(lambda: make_predator_prey(max_steps=60), num_cycles=100)


def _rollout(env: PredatorPreyEnv, seed: int | None, steps: int) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(123)
    trace = [np.stack([obs["predator_0"], obs["predator_1"]])]
    for _ in range(steps):
        obs, *_ = env.step({a: int(rng.integers(5)) for a in env.agents})
        trace.append(np.stack([obs["predator_0"], obs["predator_1"]]))
    return np.stack(trace)


def test_predator_prey_is_deterministic_under_seed_across_resets() -> None:
    a, b = make_predator_prey(max_steps=60), make_predator_prey(max_steps=60)
    np.testing.assert_array_equal(_rollout(a, 7, 30), _rollout(b, 7, 30))
    np.testing.assert_array_equal(_rollout(a, None, 30), _rollout(b, None, 30))  # unseeded reset continues the stream
    assert not np.array_equal(_rollout(a, 7, 5), _rollout(b, 8, 5))


def test_predator_prey_defaults_and_truncation_at_max_steps() -> None:
    env = make_predator_prey()
    assert env.spec.max_steps == 1000 and env.config.num_obstacles == 2
    assert env.spec.name == "predator-prey" and env.spec.agent_ids == ("predator_0", "predator_1")
    assert env.spec.obs_dims == (2, 2) and env.spec.n_actions == (5, 5)
    assert env.unwrapped is env
    env.reset(seed=0)
    for t in range(1, 1001):
        _, _, term, trunc, _ = env.step(NOOPS)
        assert not any(term.values())
        assert all(trunc.values()) == (t == 1000)
    assert env.agents == []


def test_predator_observes_prey_relative_position() -> None:
    env = make_predator_prey(max_steps=60)
    obs, _ = env.reset(seed=3)
    for _ in range(2):
        prey = env.world.agents[2].state.p_pos
        for i, agent in enumerate(("predator_0", "predator_1")):
            assert obs[agent].shape == (2,) and obs[agent].dtype == np.float32
            assert env.observation_space(agent).contains(obs[agent])
            np.testing.assert_allclose(obs[agent], prey - env.world.agents[i].state.p_pos, rtol=1e-6, atol=1e-6)
        obs, *_ = env.step({"predator_0": 2, "predator_1": 3})


def _place(env: PredatorPreyEnv, pred0: tuple[float, float], pred1: tuple[float, float], prey=(0.0, 0.0)) -> None:
    """Put the three agents at rest at the given positions and the obstacles far away."""
    for agent, pos in zip(env.world.agents, (pred0, pred1, prey), strict=True):
        agent.state.p_pos = np.array(pos, dtype=np.float64)
        agent.state.p_vel = np.zeros(2)
    for k, landmark in enumerate(env.world.landmarks):
        landmark.state.p_pos = np.array([5.0 + k, 5.0])


@pytest.mark.parametrize(
    ("pred0", "pred1", "expected"),
    [
        ((0.05, 0.0), (-0.05, 0.0), [1.0, 1.0]),  # both on the prey: joint reward to EACH
        ((0.05, 0.0), (0.6, 0.6), [0.5, 0.0]),  # predator_0 alone
        ((0.6, 0.6), (0.0, 0.05), [0.0, 0.5]),  # predator_1 alone
        ((0.6, 0.6), (-0.6, -0.6), [0.0, 0.0]),  # nobody
    ],
)
def test_capture_rewards(pred0, pred1, expected) -> None:
    env = make_predator_prey(max_steps=60)
    env.reset(seed=0)
    _place(env, pred0, pred1)
    # MPE2 moves positions by the *old* velocity, which is zero, so this step scores exactly the placed positions.
    _, rew, _, _, info = env.step(NOOPS)
    assert [rew["predator_0"], rew["predator_1"]] == expected
    assert [info["predator_0"]["captures"], info["predator_1"]["captures"]] == [int(e > 0) for e in expected]


def test_capture_reward_values_are_configurable() -> None:
    env = make_predator_prey(max_steps=60, capture_reward_alone=0.25, capture_reward_joint=2.0)
    env.reset(seed=0)
    _place(env, (0.05, 0.0), (-0.05, 0.0))
    assert env.step(NOOPS)[1] == {"predator_0": 2.0, "predator_1": 2.0}
    _place(env, (0.05, 0.0), (0.6, 0.6))
    assert env.step(NOOPS)[1] == {"predator_0": 0.25, "predator_1": 0.0}


def test_scripted_prey_flees_a_nearby_predator() -> None:
    env = make_predator_prey(max_steps=60)
    env.reset(seed=0)
    _place(env, (-0.2, 0.0), (0.8, -0.8))
    assert env.prey_action() == PLUS_X
    start = np.linalg.norm(env.world.agents[2].state.p_pos - env.world.agents[0].state.p_pos)
    for _ in range(3):
        env.step(NOOPS)
    prey = env.world.agents[2].state.p_pos
    assert prey[0] > 0.05
    assert np.linalg.norm(prey - env.world.agents[0].state.p_pos) > start


def test_evade_action_rules() -> None:
    preds = np.array([[0.0, -0.3], [0.9, 0.9]])
    assert evade_action(np.array([0.0, 0.0]), preds) == PLUS_Y  # away from the nearest, along the dominant axis
    assert evade_action(np.array([0.0, 0.0]), np.array([[0.4, 0.0], [0.0, 0.3]])) == MINUS_Y  # nearest wins
    assert evade_action(np.array([0.95, 0.0]), np.array([[0.5, 0.0]] * 2)) == MINUS_X  # boundary beats fleeing
    assert evade_action(np.array([0.0, -0.97]), np.array([[0.0, -0.5]] * 2)) == PLUS_Y
    assert evade_action(np.array([0.1, 0.1]), np.array([[0.1, 0.1]] * 2)) == NOOP


def test_predator_prey_rejects_bad_actions() -> None:
    env = make_predator_prey(max_steps=60)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="predator_1"):
        env.step({"predator_0": 0, "predator_1": 5})
    with pytest.raises(ValueError, match="missing"):
        env.step({"predator_0": 0})


def test_predator_prey_renders_rgb_array() -> None:
    env = make_predator_prey(max_steps=5, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame is not None and frame.ndim == 3 and frame.shape[2] == 3
    with pytest.raises(ConfigError) as exc:
        make_predator_prey(render_mode="human")
    assert exc.value.field == "render_mode"


# --------------------------------------------------------------------------- speaker-listener


@pytest.mark.parametrize("keep", [False, True])
def test_speaker_listener_passes_parallel_api_test(keep: bool) -> None:
    parallel_api_test(make_speaker_listener(keep_env_channel=keep), num_cycles=30)


def test_speaker_listener_passes_parallel_seed_test() -> None:
    parallel_seed_test(lambda: make_speaker_listener(), num_cycles=30)


def test_listener_env_channel_is_cut_by_default() -> None:
    cut, kept = make_speaker_listener(), make_speaker_listener(keep_env_channel=True)
    assert cut.spec.name == "speaker-listener" and cut.spec.max_steps == 25
    assert cut.spec.obs_dims == (3, 8) and kept.spec.obs_dims == (3, 11) and cut.spec.n_actions == (3, 5)
    o_cut, _ = cut.reset(seed=5)
    o_kept, _ = kept.reset(seed=5)
    assert o_cut["listener_0"].shape == (8,) and o_kept["listener_0"].shape == (11,)
    assert o_cut["speaker_0"].shape == (3,)
    np.testing.assert_array_equal(o_cut["listener_0"], o_kept["listener_0"][:8])
    acts = {"speaker_0": 1, "listener_0": 2}
    o_cut, r_cut, *_ = cut.step(acts)
    o_kept, r_kept, *_ = kept.step(acts)
    np.testing.assert_array_equal(o_kept["listener_0"][8:], [0.0, 1.0, 0.0])  # the env's own "say 1"
    np.testing.assert_array_equal(o_cut["listener_0"], o_kept["listener_0"][:8])
    assert r_cut == r_kept and r_cut["speaker_0"] == r_cut["listener_0"] < 0


# --------------------------------------------------------------------------- ParallelEnvBatch


def test_batch_shapes_padding_and_spec() -> None:
    batch = make_speaker_listener_batch(3, max_steps=4)
    assert isinstance(batch, BatchedEnv)
    assert batch.spec.obs_dims == (3, 8) and batch.spec.obs_dim == 8 and batch.spec.max_steps == 4
    obs = batch.reset(seed=0)
    assert obs.shape == (3, 2, 8) and obs.dtype == np.float32
    assert np.all(obs[:, 0, 3:] == 0.0)  # the 3-float speaker row is zero-padded to the listener's 8
    assert np.any(obs[:, 0, :3] != 0.0)
    res = batch.step(np.zeros((3, 2), dtype=np.int64))
    assert res.obs.shape == res.final_obs.shape == (3, 2, 8)
    assert res.reward.shape == (3, 2) and res.reward.dtype == np.float32
    assert res.terminated.shape == res.truncated.shape == (3,)
    assert np.all(res.obs[:, 0, 3:] == 0.0)
    with pytest.raises(ValueError, match="shape"):
        batch.step(np.zeros((2, 2), dtype=np.int64))
    with pytest.raises(ValueError, match="n_actions"):
        batch.step(np.array([[3, 0]] * 3))  # speaker has 3 actions


def test_batch_auto_resets_at_max_steps_with_final_obs() -> None:
    steps, acts = 3, np.array([[0, 2], [1, 3], [2, 4]])
    batch = make_speaker_listener_batch(3, max_steps=steps)
    batch.reset(seed=10)
    for t in range(1, steps + 1):
        res = batch.step(acts)
        assert not res.terminated.any()
        assert res.truncated.all() == (t == steps) and res.done.any() == (t == steps)
        if t < steps:
            np.testing.assert_array_equal(res.obs, res.final_obs)
    # env b is seeded env_seeds(10, 3)[b]: replay it standalone to pin final_obs and the auto-reset observation
    for b in range(3):
        env = make_speaker_listener(max_steps=steps)
        env.reset(seed=int(env_seeds(10, 3)[b]))
        for _ in range(steps):
            last, *_ = env.step({"speaker_0": int(acts[b, 0]), "listener_0": int(acts[b, 1])})
        np.testing.assert_array_equal(res.final_obs[b, 1], last["listener_0"])
        np.testing.assert_array_equal(res.final_obs[b, 0, :3], last["speaker_0"])
        fresh, _ = env.reset()
        np.testing.assert_array_equal(res.obs[b, 1], fresh["listener_0"])
    assert not np.array_equal(res.obs, res.final_obs)
    assert not batch.step(acts).done.any()  # the new episode has started


def _batch_trace(batch, seed) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    out = [batch.reset(seed=seed)]
    for _ in range(7):
        res = batch.step(rng.integers(0, 5, size=(batch.num_envs, 2)))
        out += [res.obs, res.final_obs, res.reward]
    return out


def test_predator_prey_batch_is_deterministic_and_reports_captures() -> None:
    make = lambda: make_predator_prey_batch(2, max_steps=3)  # noqa: E731
    batch = make()
    assert batch.spec.name == "predator-prey" and batch.spec.max_steps == 3
    a, b = _batch_trace(batch, 4), _batch_trace(make(), 4)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], _batch_trace(make(), 5)[0])
    np.testing.assert_array_equal(make().reset(seed=env_seeds(4, 2)), a[0])  # an int seed expands to env_seeds
    res = batch.step(np.zeros((2, 2), dtype=np.int64))
    assert res.info["captures"].shape == (2, 2)


# --------------------------------------------------------------------------- referential game


def test_referential_passes_parallel_api_and_seed_tests() -> None:
    parallel_api_test(make_referential(n_targets=5), num_cycles=10)
    parallel_seed_test(lambda: make_referential(n_targets=5), num_cycles=10)


def test_referential_standalone_oracle_and_spec() -> None:
    env = make_referential(n_targets=6)
    assert env.spec.name == "referential" and env.spec.n_actions == (1, 6) and env.spec.obs_dims == (6, 6)
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        assert obs["speaker"].sum() == 1.0 and not obs["listener"].any()
        _, rew, term, trunc, _ = env.step({"speaker": 0, "listener": int(np.argmax(obs["speaker"]))})
        assert rew == {"speaker": 1.0, "listener": 1.0}
        assert all(term.values()) and not any(trunc.values()) and env.agents == []


def test_referential_random_listener_is_at_chance_and_oracle_is_perfect() -> None:
    k, n = 4, 4000
    batch = make_referential_batch(n, n_targets=k)
    obs = batch.reset(seed=0)
    assert obs.shape == (n, 2, k) and not obs[:, 1].any()
    np.testing.assert_array_equal(obs[:, 0].sum(axis=1), 1.0)
    rng = np.random.default_rng(1)
    guess = np.stack([np.zeros(n, dtype=np.int64), rng.integers(0, k, size=n)], axis=1)
    res = batch.step(guess)
    assert res.terminated.all() and not res.truncated.any()
    assert abs(res.reward[:, 1].mean() - 1 / k) < 0.05
    np.testing.assert_array_equal(res.reward[:, 0], res.reward[:, 1])
    np.testing.assert_array_equal(np.argmax(res.final_obs[:, 0], axis=1), res.info["target"])
    oracle = np.stack([np.zeros(n, dtype=np.int64), np.argmax(res.obs[:, 0], axis=1)], axis=1)
    assert batch.step(oracle).reward.min() == 1.0


def test_referential_batch_is_deterministic_under_seed() -> None:
    a, b = make_referential_batch(64, n_targets=8), make_referential_batch(64, n_targets=8)
    np.testing.assert_array_equal(a.reset(seed=3), b.reset(seed=3))
    acts = np.zeros((64, 2), dtype=np.int64)
    np.testing.assert_array_equal(a.step(acts).obs, b.step(acts).obs)
    assert not np.array_equal(a.reset(seed=3), a.reset(seed=4))


# --------------------------------------------------------------------------- configuration errors


@pytest.mark.parametrize(
    ("factory", "params", "field", "needle"),
    [
        (make_referential, {"n_targets": 1}, "n_targets", "2 ≤ n_targets ≤ 64"),
        (make_referential, {"n_targets": 65}, "n_targets", "2 ≤ n_targets ≤ 64"),
        (make_predator_prey, {"max_steps": 0}, "max_steps", "1 ≤ max_steps"),
        (make_speaker_listener, {"max_steps": 0}, "max_steps", "1 ≤ max_steps"),
        (make_predator_prey, {"num_obstacles": -1}, "num_obstacles", "0 ≤ num_obstacles"),
        (make_predator_prey, {"speed": 2}, "speed", "unknown parameter"),
        (make_referential, {"max_steps": 3}, "max_steps", "unknown parameter"),
        (lambda **p: make_predator_prey_batch(2, **p), {"max_steps": 0}, "max_steps", "1 ≤ max_steps"),
        (lambda **p: make_speaker_listener_batch(2, **p), {"colour": 1}, "colour", "unknown parameter"),
        (lambda **p: make_referential_batch(2, **p), {"n_targets": 1}, "n_targets", "2 ≤ n_targets ≤ 64"),
    ],
)
def test_bad_config_names_the_field_and_range(factory, params, field, needle) -> None:
    with pytest.raises(ConfigError) as exc:
        factory(**params)
    assert exc.value.field == field
    assert needle in str(exc.value)


def test_referential_batch_equals_games_played_one_by_one() -> None:
    batch = make_referential_batch(5, n_targets=7)
    obs = batch.reset(seed=3)
    singles = [make_referential_batch(1, n_targets=7) for _ in range(5)]
    seeds = env_seeds(3, 5)
    for b, s in enumerate(singles):
        np.testing.assert_array_equal(s.reset(seed=seeds[b : b + 1])[0], obs[b])
    acts = np.zeros((5, 2), dtype=np.int64)
    for _ in range(4):
        res = batch.step(acts)
        for b, s in enumerate(singles):
            np.testing.assert_array_equal(s.step(acts[b : b + 1]).obs[0], res.obs[b])
