"""The treadmill behind the ecosystem's APIs: PettingZoo's and Gymnasium's own checkers."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

import convoy.envs as envs
from convoy.envs.treadmill import TreadmillGymEnv, TreadmillParallelEnv


@pytest.mark.parametrize(("n", "m"), [(1, 1), (3, 1), (8, 3)])
def test_pettingzoo_parallel_api(n: int, m: int) -> None:
    parallel_api_test(TreadmillParallelEnv(n_agents=n, n_adversaries=m), num_cycles=400)


@pytest.mark.parametrize(("n", "m"), [(1, 1), (3, 1), (8, 3)])
def test_pettingzoo_seed(n: int, m: int) -> None:
    parallel_seed_test(lambda: TreadmillParallelEnv(n_agents=n, n_adversaries=m), num_cycles=400)


def test_gymnasium_check_env_through_registry() -> None:
    env = gymnasium.make(envs.TREADMILL_GYM_ID, render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs)
    frame = env.render()
    assert isinstance(frame, np.ndarray)
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3


def test_gym_env_rejects_bad_action() -> None:
    env = TreadmillGymEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(9)


def test_parallel_env_renders_the_crash_not_the_next_episode() -> None:
    env = TreadmillParallelEnv(render_mode="rgb_array", n_agents=2, n_adversaries=0)
    env.reset(seed=0)
    e = env.engine
    e.x[0], e.y[0], e.heading[0], e.speed[0] = [10, 11], [5, 5], [0, 4], [1, 1]  # head-on: swap cells
    _, rewards, terms, _, infos = env.step({"agent_0": 4, "agent_1": 4})
    assert all(terms.values()) and env.agents == []
    assert infos["agent_0"]["crashed"] and rewards["agent_0"] == -env.config.crash_penalty
    assert e.y[0].tolist() == [5, 5]  # still the crash scene, not a fresh spawn
    frame = env.render()
    assert frame is not None and frame.shape == (env.config.width * 4, env.config.length * 4, 3)
