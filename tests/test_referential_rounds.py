"""The referential game with ``rounds > 1``: one target per game, only the last round's guess scores."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from convoy.envs.particle import make_referential, make_referential_batch
from convoy.validation import ConfigError


def test_rounds_one_is_the_one_step_game_bit_for_bit() -> None:
    """An explicit ``rounds=1`` and the default give identical streams of obs, rewards, flags and targets."""
    a, b = make_referential_batch(32, n_targets=5), make_referential_batch(32, n_targets=5, rounds=1)
    assert a.spec == b.spec and a.spec.max_steps == 1
    np.testing.assert_array_equal(a.reset(seed=7), b.reset(seed=7))
    rng = np.random.default_rng(0)
    for _ in range(6):
        acts = np.stack([np.zeros(32, np.int64), rng.integers(0, 5, 32)], axis=1)
        ra, rb = a.step(acts), b.step(acts)
        for field in ("obs", "reward", "terminated", "truncated", "final_obs"):
            np.testing.assert_array_equal(getattr(ra, field), getattr(rb, field))
        np.testing.assert_array_equal(ra.info["target"], rb.info["target"])
        assert ra.terminated.all()


@pytest.mark.parametrize("rounds", [2, 3])
def test_target_fixed_only_last_round_scores(rounds: int) -> None:
    k, n = 4, 256
    env = make_referential_batch(n, n_targets=k, rounds=rounds)
    assert env.spec.max_steps == rounds
    obs = env.reset(seed=1)
    for _game in range(3):
        targets = env.targets
        for r in range(rounds):
            np.testing.assert_array_equal(obs[:, 0].argmax(axis=1), targets)  # the speaker sees it every round
            assert not obs[:, 1].any()  # the listener never sees anything
            oracle = np.stack([np.zeros(n, np.int64), targets], axis=1)
            res = env.step(oracle)
            last = r == rounds - 1
            assert (res.terminated == last).all() and not res.truncated.any()
            np.testing.assert_array_equal(res.info["target"], targets)
            np.testing.assert_array_equal(res.reward, 1.0 if last else 0.0)  # the right guess pays only at the end
            np.testing.assert_array_equal(res.final_obs[:, 0].argmax(axis=1), targets)
            if not last:
                np.testing.assert_array_equal(res.obs, res.final_obs)
                np.testing.assert_array_equal(env.targets, targets)
            obs = res.obs


def test_only_the_last_guess_counts() -> None:
    """Right on round 1 but wrong on the last: 0; wrong first, right last: 1."""
    k, n = 4, 64
    env = make_referential_batch(n, n_targets=k, rounds=2)
    env.reset(seed=2)

    def guesses(offset: int) -> np.ndarray:
        return np.stack([np.zeros(n, np.int64), (env.targets + offset) % k], axis=1)

    assert env.step(guesses(0)).reward.sum() == 0.0
    assert env.step(guesses(1)).reward.sum() == 0.0
    env.step(guesses(1))
    np.testing.assert_array_equal(env.step(guesses(0)).reward, 1.0)


def test_random_listener_is_at_chance_over_games() -> None:
    k, n, rounds = 4, 4000, 3
    env = make_referential_batch(n, n_targets=k, rounds=rounds)
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    rewards = [env.step(np.stack([np.zeros(n, np.int64), rng.integers(0, k, n)], axis=1)).reward for _ in range(rounds)]
    assert abs(rewards[-1][:, 1].mean() - 1 / k) < 0.03


def test_reset_restarts_the_round_count() -> None:
    env = make_referential_batch(8, n_targets=3, rounds=3)
    env.reset(seed=0)
    env.step(np.zeros((8, 2), np.int64))
    env.reset(seed=0)
    for r in range(3):
        assert env.step(np.zeros((8, 2), np.int64)).terminated.all() == (r == 2)


def test_pettingzoo_wrapper_keeps_agents_until_the_last_round() -> None:
    parallel_api_test(make_referential(n_targets=5, rounds=2), num_cycles=10)
    parallel_seed_test(lambda: make_referential(n_targets=5, rounds=2), num_cycles=10)
    env = make_referential(n_targets=5, rounds=3)
    assert env.spec.max_steps == 3
    obs, _ = env.reset(seed=4)
    target = int(obs["speaker"].argmax())
    for r in range(3):
        assert env.agents == ["speaker", "listener"]
        obs, rew, term, trunc, info = env.step({"speaker": 0, "listener": target})
        last = r == 2
        assert all(v == last for v in term.values()) and not any(trunc.values())
        assert rew == {"speaker": float(last), "listener": float(last)}
        assert info["listener"]["target"] == target and int(obs["speaker"].argmax()) == target
    assert env.agents == []
    with pytest.raises(RuntimeError):
        env.step({"speaker": 0, "listener": 0})


@pytest.mark.parametrize("rounds", [0, 65])
def test_bad_rounds_names_the_field(rounds: int) -> None:
    with pytest.raises(ConfigError, match="rounds"):
        make_referential_batch(2, rounds=rounds)
