"""Driving a batched env with an agent: the one acting loop (the in-process trainer, the actors, ``convoy analyze``)
and the agent as a policy for the one evaluation loop, ``envs.rollout`` (greedy curves, ``convoy eval``).

:class:`EnvStepper` acts, steps every env, appends the joint transition to a chunk ``[T, B, …]`` and keeps each
env's running return and the episode stamp that stabilised experience replay weighs samples by.
"""

from __future__ import annotations

import numpy as np

from convoy.algos.algorithm import ActOutput, Agent
from convoy.envs.batched import BatchedEnv, StepResult


def transition(obs: np.ndarray, out: ActOutput, res: StepResult, episode: np.ndarray) -> dict[str, np.ndarray]:
    """One step of B envs as the joint transition every algorithm's ``observe`` expects (plus the act's extras)."""
    return {
        "obs": obs,
        "action": out.actions,
        "reward": res.reward.astype(np.float32),
        "next_obs": res.final_obs,
        "terminated": res.terminated,
        "truncated": res.truncated,
        "episode": episode.copy(),
        **out.extras,
    }


class EnvStepper:
    """``algo`` acting in ``env`` (reset with ``seed``); ``step`` records into the chunk ``take_chunk`` returns
    (unless ``record`` is off) and keeps its act's output as ``last``."""

    def __init__(self, env: BatchedEnv, algo: Agent, seed: int, record: bool = True) -> None:
        self.env, self.algo, self.record = env, algo, record
        self.last: ActOutput | None = None
        b, n = env.num_envs, env.spec.n_agents
        self.obs = env.reset(seed=seed)
        self.state = algo.initial_state(b)
        self.ep_ret = np.zeros((b, n))
        self.episode_id = np.zeros(b, dtype=np.int64)  # episodes finished when each env's episode began
        self.episodes = 0
        self._chunk: dict[str, list[np.ndarray]] = {}

    def step(self, epsilon: float) -> list[float]:
        """One ε-greedy step of every env; the returns (mean over agents) of the episodes that just ended."""
        out = self.algo.act(self.obs, epsilon, self.state)
        res = self.env.step(out.actions)
        self.last = out
        if self.record:
            for k, v in transition(self.obs, out, res, self.episode_id).items():
                self._chunk.setdefault(k, []).append(v)
        self.ep_ret += res.reward
        done = res.done
        returns: list[float] = []
        if done.any():
            returns = self.ep_ret[done].mean(axis=1).tolist()
            self.ep_ret[done] = 0.0
            self.episodes += len(returns)
            self.episode_id[done] = self.episodes
        self.state = self.algo.reset_state(out.state, done)
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
