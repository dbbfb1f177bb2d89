"""Driving a batched env with an agent: the one acting loop (the in-process trainer, the actors, ``convoy analyze``)
and the agent as a policy for the one evaluation loop, ``envs.rollout`` (greedy curves, ``convoy eval``).

:class:`EnvStepper` acts, steps every env, appends the joint transition to a chunk ``[T, B, …]`` and keeps each
env's running return and the episode stamp that stabilised experience replay weighs samples by.

The agent holds R runs (``algo.runs``; a single run is R = 1): the env holds R·B envs, run k's B envs seeded as the
single run of ``algo.seeds[k]`` seeds its own; the agent sees ``[R, B, …]``, chunks are ``[T, R, B, …]``, and episode
stamps count each run's own episodes.
"""

from __future__ import annotations

import numpy as np

from convoy.algos.algorithm import ActOutput, Agent
from convoy.envs.batched import BatchedEnv, StepResult, env_seeds
from convoy.transition import ENV_MAJOR, record


def transition(obs: np.ndarray, out: ActOutput, res: StepResult, episode: np.ndarray) -> dict[str, np.ndarray]:
    """One step of B envs as the joint transition (``convoy.transition``) every algorithm's ``observe`` expects."""
    return record(
        obs, out.actions, res.reward, res.final_obs, res.terminated, res.truncated, episode.copy(), out.extras
    )


class EnvStepper:
    """``algo`` acting in ``env`` (reset with ``seed``); ``step`` records into the chunk ``take_chunk`` returns
    (unless ``record`` is off) and keeps its act's output as ``last``, env-major like the env (``[R·B, …]``)."""

    def __init__(self, env: BatchedEnv, algo: Agent, seed: int, record: bool = True) -> None:
        self.env, self.algo, self.record = env, algo, record
        self.last: ActOutput | None = None
        b, n = env.num_envs, env.spec.n_agents
        self.runs = algo.runs
        if b % self.runs:
            raise ValueError(f"num_envs: {b} envs do not split evenly among the population's {self.runs} runs")
        # a run of one seeds its envs with ``seed`` (an actor's own, a recording's); a population's runs each with
        # their own seed, as the single run of that seed does
        seeds = algo.seeds if self.runs > 1 else (seed,)
        self.obs = env.reset(seed=np.concatenate([env_seeds(s, b // self.runs) for s in seeds]))
        self.run_of_env = np.repeat(np.arange(self.runs), b // self.runs)
        self.state = algo.initial_state(b // self.runs)
        self.ep_ret = np.zeros((b, n))
        self.episode_id = np.zeros(b, dtype=np.int64)  # episodes of its run finished when each env's episode began
        self.episodes_by_run = np.zeros(self.runs, dtype=np.int64)
        self.ended_runs = np.zeros(0, dtype=np.int64)  # the run of each return the last step reported
        self._chunk: dict[str, list[np.ndarray]] = {}

    @property
    def episodes(self) -> int:
        return int(self.episodes_by_run.sum())

    def _split(self, x: np.ndarray) -> np.ndarray:
        """``[R·B, …]`` → ``[R, B, …]``."""
        return x.reshape(self.runs, -1, *x.shape[1:])

    def step(self, epsilon: float | np.ndarray) -> list[float]:
        """One ε-greedy step of every env; the returns (mean over agents) of the episodes that just ended."""
        out = self.algo.act(self._split(self.obs), epsilon, self.state)
        res = self.env.step(out.actions.reshape(self.env.num_envs, -1))
        self.last = out.shaped((self.env.num_envs,))
        if self.record:
            for k, v in transition(self.obs, out, res, self.episode_id).items():
                self._chunk.setdefault(k, []).append(self._split(v) if k in ENV_MAJOR else v)
        self.ep_ret += res.reward
        done = res.done
        returns: list[float] = []
        self.ended_runs = self.run_of_env[done]
        if done.any():
            returns = self.ep_ret[done].mean(axis=1).tolist()
            self.ep_ret[done] = 0.0
            self.episodes_by_run += np.bincount(self.ended_runs, minlength=len(self.episodes_by_run))
            self.episode_id[done] = self.episodes_by_run[self.ended_runs]
        self.state = self.algo.reset_state(out.state, self._split(done))
        self.obs = res.obs
        return returns

    @property
    def chunk_steps(self) -> int:
        """Steps recorded since the last ``take_chunk``."""
        return len(self._chunk.get("obs", ()))

    def take_chunk(self) -> dict[str, np.ndarray]:
        """The recorded steps as arrays ``[T, B, …]``; recording starts afresh."""
        chunk = {k: np.stack(v) for k, v in self._chunk.items()}
        self._chunk = {}
        return chunk


class AgentPolicy:
    """An agent as a policy for ``envs.rollout``: ε-greedy acts that carry its recurrent state (DIAL's messages
    from t−1, a memory module's window, a channel's messages in flight), forgotten where an episode ends."""

    def __init__(self, algo: Agent, num_envs: int, epsilon: float = 0.0) -> None:
        self.algo, self.epsilon = algo, epsilon
        self.state = algo.reset_state(algo.initial_state(num_envs), np.ones(num_envs, dtype=bool))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        out = self.algo.act(obs, self.epsilon, self.state)
        self.state = out.state
        return out.actions

    def after_step(self, res: StepResult) -> None:
        self.state = self.algo.reset_state(self.state, res.done)
