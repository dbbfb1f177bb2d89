"""Gymnasium single-agent treadmill, registered as ``convoy/Treadmill-v0``.

The learner drives ``agent_0``; any further cooperative cars (``n_agents`` > 1) are driven by
the scripted policy of ``envs.treadmill.scripted``, and the adversaries by their own rule. The
default is the paper's single-agent setting (appendix A.3): one agent and one adversary.
``info["crashed"]`` says whether the controlled car crashed.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from convoy.envs.treadmill.config import N_ACTIONS, TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.envs.treadmill.render import render_frame
from convoy.envs.treadmill.scripted import scripted_actions
from convoy.validation import build_config


class TreadmillGymEnv(gym.Env):
    """One learning car on the treadmill highway."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 15}  # noqa: RUF012  (gymnasium's instance attribute)

    def __init__(self, render_mode: str | None = None, config: TreadmillConfig | None = None, **params: Any) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: must be None or 'rgb_array', got {render_mode!r}")
        params.setdefault("n_agents", 1)
        self.render_mode = render_mode
        self.config = config or build_config(TreadmillConfig, **params)
        self.engine = TreadmillEngine(self.config, num_envs=1, autoreset=False)
        self.observation_space = spaces.Box(-1.0, 1.0, (self.config.obs_dim,), np.float32)
        self.action_space = spaces.Discrete(N_ACTIONS)
        self._obs = np.zeros((1, self.config.n_agents, self.config.obs_dim), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._obs = self.engine.reset(seed)
        return self._obs[0, 0].copy(), {}

    def step(self, action: int):
        if not self.action_space.contains(action):
            raise ValueError(f"action: must be an int in [0, {N_ACTIONS}), got {action!r}")
        acts = scripted_actions(self._obs, self.config)
        acts[0, 0] = int(action)
        r = self.engine.step(acts)
        self._obs = r.final_obs
        info = {"crashed": bool(r.info["crashed"][0, 0])}
        return self._obs[0, 0].copy(), float(r.reward[0, 0]), bool(r.terminated[0]), bool(r.truncated[0]), info

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        e, cfg = self.engine, self.config
        return render_frame(e.x[0], e.y[0], e.heading[0], cfg.n_agents, cfg.length, cfg.width)
