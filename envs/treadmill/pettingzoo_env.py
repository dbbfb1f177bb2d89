"""PettingZoo ``ParallelEnv`` over the batched engine with B = 1 (one physics, many front ends).

Agents are ``agent_0 … agent_{N−1}``; adversaries are part of the env, not agents. When an
episode ends (crash or truncation) every agent is done at once and ``agents`` becomes empty, as
PettingZoo expects; call ``reset`` to start the next one (the engine runs without auto-reset here,
so ``render`` after the last step still shows how the episode ended). ``infos[agent]["crashed"]`` tells who
crashed.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from convoy.envs.treadmill.config import N_ACTIONS, TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.envs.treadmill.render import render_frame
from convoy.validation import build_config


class TreadmillParallelEnv(ParallelEnv):
    """The treadmill highway for N cooperative agents (and M scripted adversaries)."""

    metadata: ClassVar[dict[str, Any]] = {
        "name": "treadmill_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 15,
        "is_parallelizable": True,
    }

    def __init__(self, render_mode: str | None = None, config: TreadmillConfig | None = None, **params: Any) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.config = config or build_config(TreadmillConfig, **params)
        self.engine = TreadmillEngine(self.config, num_envs=1, autoreset=False)
        self.possible_agents = list(self.engine.spec.agent_ids)
        self.agents: list[str] = []
        dim = self.config.obs_dim
        self._obs_space = spaces.Box(-1.0, 1.0, (dim,), np.float32)
        self._act_space = spaces.Discrete(N_ACTIONS)
        self.observation_spaces = {a: self._obs_space for a in self.possible_agents}
        self.action_spaces = {a: self._act_space for a in self.possible_agents}

    def observation_space(self, agent: str) -> spaces.Box:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Discrete:
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs = self.engine.reset(seed)[0]
        self.agents = self.possible_agents[:]
        return self._dict(obs), {a: {} for a in self.agents}

    def step(self, actions: dict[str, int]):
        if not self.agents:
            raise RuntimeError("step() called after the episode ended: call reset() first")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: missing an action for {missing}")
        act = np.array([[int(actions[a]) for a in self.possible_agents]], dtype=np.int64)
        r = self.engine.step(act)
        obs = self._dict(r.final_obs[0])
        rewards = {a: float(r.reward[0, i]) for i, a in enumerate(self.possible_agents)}
        term, trunc = bool(r.terminated[0]), bool(r.truncated[0])
        terminations = dict.fromkeys(self.possible_agents, term)
        truncations = dict.fromkeys(self.possible_agents, trunc)
        infos = {a: {"crashed": bool(r.info["crashed"][0, i])} for i, a in enumerate(self.possible_agents)}
        if term or trunc:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        e, cfg = self.engine, self.config
        return render_frame(e.x[0], e.y[0], e.heading[0], cfg.n_agents, cfg.length, cfg.width)

    def state(self) -> np.ndarray:
        """Global state: every car's (x, y, heading, speed), for centralised critics and debugging."""
        e = self.engine
        return np.stack([e.x[0], e.y[0], e.heading[0], e.speed[0]], axis=1).astype(np.float32).ravel()

    def close(self) -> None:
        pass

    def _dict(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}
