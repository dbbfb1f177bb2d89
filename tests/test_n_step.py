"""Multi-step returns (``n_step``): each row's return, bootstrap observation and discount, against a plain loop
over steps; and the jobs that cannot use them say so."""

from __future__ import annotations

import numpy as np
import pytest

from convoy.algos.agent import make_agent
from convoy.algos.algorithm import NetworkAgent, n_step_rows
from convoy.algos.registry import make_algorithm
from convoy.config import job_config, resolve_algo
from convoy.envs import make_batched
from convoy.transition import record
from convoy.validation import ConfigError
from tests.conftest import single_update


def loop_rows(chunk: dict[str, np.ndarray], n: int, gamma: np.ndarray) -> dict[str, np.ndarray]:
    """The same rows, one (t, lead index) at a time: the definition."""
    reward, done = chunk["reward"], chunk["terminated"] | chunk["truncated"]
    t_len, lead = reward.shape[0], done.shape[1:]
    out = {k: np.array(chunk[k]) for k in ("reward", "next_obs", "terminated", "truncated")}
    out["discount"] = np.ones((t_len, *lead), np.float32)
    for t in range(t_len):
        for i in np.ndindex(*lead):
            g = float(gamma[i[0]]) if gamma.ndim else float(gamma)
            ret, disc, k = np.zeros_like(reward[t][i]), 1.0, t
            for k in range(t, min(t + n, t_len)):
                ret = ret + disc * reward[k][i]
                disc *= g
                if done[k][i]:
                    break
            out["reward"][t][i], out["discount"][t][i] = ret, disc
            for name in ("next_obs", "terminated", "truncated"):
                out[name][t][i] = chunk[name][k][i]
    return out


def random_chunk(lead: tuple[int, ...], t_len: int = 9, n_agents: int = 2, seed: int = 0) -> dict[str, np.ndarray]:
    g = np.random.default_rng(seed)
    obs = g.normal(size=(t_len, *lead, n_agents, 3)).astype(np.float32)
    return {"obs": obs, "next_obs": obs + 1, "action": g.integers(0, 4, (t_len, *lead, n_agents)),
            "reward": g.normal(size=(t_len, *lead, n_agents)).astype(np.float32),
            "terminated": g.random((t_len, *lead)) < 0.15, "truncated": g.random((t_len, *lead)) < 0.1,
            "episode": np.zeros((t_len, *lead), np.int64)}  # fmt: skip


@pytest.mark.parametrize("n", [1, 2, 4, 20])
@pytest.mark.parametrize(("lead", "gamma"), [((5,), np.float32(0.9)), ((3, 4), np.array([0.9, 0.5, 0.99]))])
def test_rows_match_the_definition(n: int, lead: tuple[int, ...], gamma: np.ndarray) -> None:
    chunk = random_chunk(lead)
    got, want = n_step_rows(chunk, n, gamma), loop_rows(chunk, n, gamma)
    for name in want:
        np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-6, err_msg=name)
    assert got["obs"] is chunk["obs"] and got["action"] is chunk["action"]  # step t's own fields untouched


def test_an_agent_learns_from_n_step_rows_and_keeps_them_apart_from_one_step() -> None:
    env = make_batched("referential", 4)
    rows = {}
    for n in (1, 3):
        cfg = resolve_algo("idqn", "referential", {"hidden": (8,), "learning_starts": 0, "batch_size": 8,
                                                   "n_step": n})  # fmt: skip
        algo = make_algorithm("idqn", env.spec, cfg, device="cpu", seed=0)
        obs = env.reset(seed=0)
        steps = []
        for _ in range(4):
            out = algo.act(obs, 1.0)
            res = env.step(out.actions)
            steps.append(record(obs, out.actions, res.reward, res.final_obs, res.terminated, res.truncated,
                                np.zeros(4, np.int64), out.extras))  # fmt: skip
            obs = res.obs
        algo.observe({k: np.stack([s[k] for s in steps]) for k in steps[0]})
        assert np.isfinite(single_update(algo)["loss"])
        rows[n] = algo.replay.sample(8, algo.streams["replay"])
    assert "discount" not in rows[1] and "discount" in rows[3]


@pytest.mark.parametrize(("algo", "hierarchical"), [("dial", False), ("idqn", True)])
def test_jobs_that_cannot_use_n_step_say_so(algo: str, hierarchical: bool) -> None:
    with pytest.raises(ConfigError, match="n_step"):
        job_config(algo=algo, env="treadmill", hierarchical=hierarchical, algo_params={"n_step": 3})


def test_the_trainer_collects_chunks_long_enough_for_n_steps(tmp_path) -> None:
    from convoy.learner.inprocess import Trainer
    from convoy.services.training import make_env

    job = job_config(algo="idqn", env="treadmill", env_params={"n_agents": 2, "max_steps": 50}, steps=400,
                     num_envs=4, eval_every=0, eval_episodes=2, device="cpu",
                     algo_params={"hidden": [8], "n_step": 3, "learning_starts": 0, "gamma": 0.5})  # fmt: skip
    env = make_env(job)
    algo = make_agent(job, env.spec)
    assert isinstance(algo, NetworkAgent) and algo.chunk_len == 12
    try:
        Trainer(job, env, algo, make_eval_env=lambda n: make_env(job, n), out_dir=tmp_path, progress=False).run()
    finally:
        env.close()
    discount = algo.replay.sample(256, algo.streams["replay"])["discount"].cpu().numpy()
    assert np.mean(np.isclose(discount, 0.125)) > 0.5  # most rows span all three steps: γ³
