"""What every Convoy env built on an mpe2 scenario shares: spaces, action checks, step counting, render, close.

Our particle envs are PettingZoo ``ParallelEnv``s of their own (so ``unwrapped`` is ours, as PettingZoo's API test
requires) that hold an mpe2 parallel env inside. Subclasses say which mpe2 env, which agents, and how observations
and rewards differ from mpe2's; this base keeps the episode bookkeeping identical across them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from convoy.envs.batched import EnvSpec
from convoy.validation import ConfigError


class MpeParallelEnv(ParallelEnv):
    """Episode bookkeeping around an inner mpe2 parallel env (``self._mpe``, its world ``self.world``)."""

    def __init__(self, mpe_env: ParallelEnv, spec: EnvSpec, render_mode: str | None) -> None:
        """``spec`` gives our agents' ids, observation widths, action counts and episode length."""
        if render_mode not in (None, "rgb_array"):
            raise ConfigError("render_mode", f"must be None or 'rgb_array' (got {render_mode!r})")
        self.render_mode = render_mode
        self.spec = spec
        self.possible_agents = list(spec.agent_ids)
        self.agents: list[str] = []
        self._mpe = mpe_env
        self.world = mpe_env.unwrapped.world
        self._steps = 0
        agents = spec.agent_ids
        self._obs_spaces = {
            a: spaces.Box(-np.inf, np.inf, shape=(d,), dtype=np.float32)
            for a, d in zip(agents, spec.obs_dims, strict=True)
        }
        self._act_spaces = {a: spaces.Discrete(n) for a, n in zip(agents, spec.n_actions, strict=True)}

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_spaces[agent]  # the identical object every call, as PettingZoo requires

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._act_spaces[agent]

    def _start_episode(self, seed: int | None, options: dict[str, Any] | None) -> dict[str, np.ndarray]:
        """Reset the inner env; returns mpe2's observations."""
        mpe_obs, _ = self._mpe.reset(seed=seed, options=options)
        self._steps = 0
        self.agents = self.possible_agents[:]
        return mpe_obs

    def _checked_actions(self, actions: dict[str, Any]) -> dict[str, int]:
        """Every live agent's action, validated against its space."""
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        checked: dict[str, int] = {}
        for agent in self.possible_agents:
            if agent not in actions:
                raise ValueError(f"actions: missing action for {agent}")
            a, space = actions[agent], self.action_space(agent)
            if not space.contains(a):
                raise ValueError(f"actions[{agent!r}]: expected an integer in [0, {space.n}), got {a!r}")
            checked[agent] = int(a)
        return checked

    def _finish_step(self) -> tuple[dict[str, bool], dict[str, bool]]:
        """Count the step; returns (terminations, truncations). Episodes only truncate, at ``max_steps``."""
        self._steps += 1
        truncated = self._steps >= self.spec.max_steps
        if truncated:
            self.agents = []
        return dict.fromkeys(self.possible_agents, False), dict.fromkeys(self.possible_agents, truncated)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        return self._mpe.render()

    def close(self) -> None:
        self._mpe.close()
