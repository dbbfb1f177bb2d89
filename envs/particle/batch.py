"""``ParallelEnvBatch``: the ``BatchedEnv`` protocol over B PettingZoo ``ParallelEnv``s, by looping.

Choices made here:

* The env list is stepped in a plain Python loop: MPE2 physics is per-env Python anyway, so vectorising the adapter
  would not help, and a loop keeps every PettingZoo env usable unchanged.
* Agent order, observation widths and action counts come from the first env's ``possible_agents`` and spaces
  (every env must be ``Box`` observations of rank 1 and ``Discrete`` actions). Observations are zero-padded to the
  widest agent; an agent absent from an env's observation dict (e.g. one that left early) also reads as zeros.
* An env's episode is over when its ``agents`` list is empty. ``terminated`` is set if any agent terminated on the
  last step, else ``truncated``. The env is then reset in the same ``step`` call with ``seed=None``, so its RNG
  continues the stream started by the last seeded ``reset`` and a seeded batch stays reproducible across episodes.
* Seeding: ``reset(seed)`` seeds env b with ``env_seeds(seed, B)[b]``; an array of B seeds seeds each env;
  ``None`` leaves each env's RNG where it is (a fresh env draws OS entropy).
* ``info``: every per-agent info entry whose value is a number or bool becomes an ``[B, N]`` float32 array (0 where
  an agent did not report it), e.g. predator-prey's ``captures``.
"""

from __future__ import annotations

from collections.abc import Callable
from numbers import Number

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from convoy.envs.batched import EnvSpec, StepResult, check_actions, env_seeds


class ParallelEnvBatch:
    """B copies of a PettingZoo parallel env behind the array-shaped ``BatchedEnv`` API."""

    def __init__(
        self,
        make_env: Callable[[], ParallelEnv],
        num_envs: int,
        name: str,
        max_steps: int | None = None,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs: must be ≥ 1 (got {num_envs})")
        self.envs: list[ParallelEnv] = [make_env() for _ in range(num_envs)]
        self.num_envs = num_envs
        first = self.envs[0]
        agents = tuple(first.possible_agents)
        obs_dims, n_actions = [], []
        for a in agents:
            obs_space, act_space = first.observation_space(a), first.action_space(a)
            if not (isinstance(obs_space, spaces.Box) and len(obs_space.shape) == 1):
                raise TypeError(f"{name}: agent {a} needs a rank-1 Box observation space, got {obs_space}")
            if not isinstance(act_space, spaces.Discrete):
                raise TypeError(f"{name}: agent {a} needs a Discrete action space, got {act_space}")
            obs_dims.append(int(obs_space.shape[0]))
            n_actions.append(int(act_space.n))
        if max_steps is None:
            inner = getattr(first, "spec", None)
            if not isinstance(inner, EnvSpec):
                raise ValueError(f"{name}: pass max_steps= for envs that do not expose an EnvSpec as .spec")
            max_steps = inner.max_steps
        self.spec = EnvSpec(
            name=name, agent_ids=agents, obs_dims=tuple(obs_dims), n_actions=tuple(n_actions), max_steps=max_steps
        )
        self._obs = np.zeros((num_envs, self.spec.n_agents, self.spec.obs_dim), dtype=np.float32)

    def _write_obs(self, out: np.ndarray, b: int, obs: dict) -> None:
        out[b] = 0.0
        for i, a in enumerate(self.spec.agent_ids):
            if a in obs:
                out[b, i, : self.spec.obs_dims[i]] = obs[a]

    def _seeds(self, seed: int | np.ndarray | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        return [int(s) for s in env_seeds(seed, self.num_envs)]

    def reset(self, seed: int | np.ndarray | None = None) -> np.ndarray:
        """Reset every env; returns obs ``[B, N, D]``."""
        for b, (env, s) in enumerate(zip(self.envs, self._seeds(seed), strict=True)):
            obs, _ = env.reset(seed=s)
            self._write_obs(self._obs, b, obs)
        return self._obs.copy()

    def step(self, actions: np.ndarray) -> StepResult:
        """Step all envs with actions ``[B, N]``; finished envs auto-reset (their last obs go to ``final_obs``)."""
        acts = check_actions(actions, self.num_envs, self.spec.n_actions)
        B, N = self.num_envs, self.spec.n_agents
        ids = self.spec.agent_ids
        reward = np.zeros((B, N), dtype=np.float32)
        terminated = np.zeros(B, dtype=bool)
        truncated = np.zeros(B, dtype=bool)
        final_obs = np.zeros_like(self._obs)
        info: dict[str, np.ndarray] = {}
        for b, env in enumerate(self.envs):
            live = set(env.agents)
            obs, rew, term, _, infos = env.step({a: int(acts[b, i]) for i, a in enumerate(ids) if a in live})
            for i, a in enumerate(ids):
                reward[b, i] = rew.get(a, 0.0)
                for key, val in infos.get(a, {}).items():
                    if isinstance(val, (Number, np.number, np.bool_)):
                        info.setdefault(key, np.zeros((B, N), dtype=np.float32))[b, i] = float(val)  # type: ignore[arg-type]  # numbers.Number declares no __float__ (typeshed)
            self._write_obs(final_obs, b, obs)
            if env.agents:
                self._obs[b] = final_obs[b]
                continue
            terminated[b] = any(term.values())
            truncated[b] = not terminated[b]
            obs, _ = env.reset(seed=None)
            self._write_obs(self._obs, b, obs)
        return StepResult(
            obs=self._obs.copy(),
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            final_obs=final_obs,
            info=info,
        )

    def close(self) -> None:
        for env in self.envs:
            env.close()
