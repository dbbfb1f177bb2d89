"""Decentralised execution and emergent communication, learned (CI-sized runs, fixed seeds).

The referential game with ``listener_glimpse``: the listener sees the target on the first of two rounds and must
name it on the second. Its policy network is feed-forward, so on the scored round it depends on the speaker's
message — unless a memory of its own observations can stand in for the message, which is exactly what the memory
module of the ``-mm`` variants learns. So, from one trained model each:

* with the true messages the team succeeds (≥ 0.9);
* white noise in place of the messages drops success to near chance (1/K) — the policy really uses them;
* the instantaneous coordination MI(speaker's message, listener's action) is far above its shuffled baseline;
* with the channel cut off (drop = 1) and the memory module's predictions in place of the lost messages, most of
  the success is kept, while the same policy hearing zeros for them falls to chance;
* independent DQN (feed-forward, no messages) cannot beat chance on this game;
* and plain MA-MeSN on the original one-round game passes the same communication probes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from convoy.algos.checkpoint import load_checkpoint
from convoy.analysis.evaluation import evaluate_policy
from convoy.analysis.recording import analyze
from convoy.config import job_config
from convoy.services.training import make_env, run_inprocess

K = 4
GAME = {"n_targets": K, "rounds": 2, "listener_glimpse": True}
HP = {"hidden": (64,), "learning_starts": 256, "replay_ratio": 2.0, "target_update": 50}
MEMORY = {"memory_window": 2, "memory_hidden": 32}
EPISODES = 400


def train(algo: str, out: Path, steps: int = 25_000) -> tuple:
    params = {**HP, **MEMORY} if algo.endswith("-mm") else HP
    job = job_config(
        algo=algo, env="referential", env_params=GAME, algo_params=params, steps=steps, num_envs=64, seed=0,
        eval_episodes=0, log_every=5_000,
    )  # fmt: skip
    run_inprocess(job, out_dir=out, progress=False)
    algo_obj, job2, _ = load_checkpoint(out / "checkpoint.pt", device="cpu")
    return algo_obj, make_env(job2, 200)


@pytest.fixture(scope="module", params=["ma-mesn-mm", "ma-bon-mm"])
def trained(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple:
    return train(request.param, tmp_path_factory.mktemp(request.param))


def success(trained: tuple, **how: Any) -> float:
    algo, env = trained
    return evaluate_policy(algo, env, EPISODES, seed=99, **how).mean


def test_true_messages_solve_the_game_and_white_noise_drops_it_to_chance(trained: tuple) -> None:
    assert success(trained) >= 0.9
    assert success(trained, messages="noise") < 1 / K + 0.15


def test_instantaneous_coordination_is_far_above_its_shuffled_baseline(trained: tuple, tmp_path: Path) -> None:
    algo, env = trained
    result = analyze(algo, env, "referential", steps=40, episodes=100, seed=3, out_dir=tmp_path, repeats=10)
    ic = next(f for f in result.figures if f.key == "instantaneous_coordination")
    assert ic.samples == 40 * env.num_envs
    assert ic.shuffled is not None and ic.shuffled_std is not None
    # a perfect listener on every round would reach ln K; the first round is not scored, so its guesses may wander
    assert ic.value > 0.5 * np.log(K), f"IC {ic.value:.3f} nats (ln K = {np.log(K):.3f})"
    assert ic.value > ic.shuffled + 20 * max(ic.shuffled_std, 1e-3)
    assert (tmp_path / "table.md").read_text().count("Instantaneous coordination") == 1


def test_the_memory_module_keeps_most_of_the_success_with_the_channel_cut_off(trained: tuple) -> None:
    true = success(trained)
    predicted = success(trained, messages="predicted")
    cut_with_memory = success(trained, channel="drop=1.0")
    cut_without_memory = success(trained, channel="drop=1.0", fill_lost="zeros")
    assert predicted >= 0.8 * true and cut_with_memory >= 0.8 * true, (true, predicted, cut_with_memory)
    assert cut_without_memory < 1 / K + 0.15


def test_independent_dqn_stays_at_chance_on_the_glimpse_game(tmp_path: Path) -> None:
    assert success(train("idqn", tmp_path)) < 1 / K + 0.15


def test_plain_ma_mesn_on_the_one_round_game_communicates_by_every_probe(tmp_path: Path) -> None:
    """The same probes on plain MA-MeSN and the original game (no glimpse, no memory module)."""
    job = job_config(
        algo="ma-mesn", env="referential", env_params={"n_targets": K}, algo_params=HP, steps=25_000, num_envs=64,
        seed=0, eval_episodes=0,
    )  # fmt: skip
    run_inprocess(job, out_dir=tmp_path, progress=False)
    algo, job2, _ = load_checkpoint(tmp_path / "checkpoint.pt", device="cpu")
    env = make_env(job2, 200)
    assert success((algo, env)) >= 0.9
    assert success((algo, env), messages="noise") < 1 / K + 0.15
    assert success((algo, env), channel="drop=1.0") < 1 / K + 0.15  # no memory module: lost messages are zeros
    result = analyze(algo, env, "referential", steps=20, episodes=50, seed=4, repeats=10)
    ic = next(f for f in result.figures if f.key == "instantaneous_coordination")
    assert ic.shuffled is not None and ic.shuffled_std is not None
    assert ic.value > 0.8 * np.log(K) and ic.value > ic.shuffled + 20 * max(ic.shuffled_std, 1e-3)
