"""Cooperative communication: MPE2 ``simple_speaker_listener_v4`` with the env's own channel removed, as in the paper.

The speaker (``speaker_0``) sees the goal landmark's colour (3 floats) and cannot move; the listener (``listener_0``)
sees its velocity and the three landmarks' relative positions and must reach the goal landmark. Both earn the
same reward, minus the squared listener-goal distance, every step.

Choices made where the paper is silent:

* MPE2 gives the speaker a ``Discrete(3)`` "say" action that shows up in the listener's observation (the last 3 of
  its 11 floats). The paper studies learned communication through the algorithm's message path, so by default that
  built-in channel is cut: the listener observes only its first 8 floats and the speaker's action is inert. Set
  ``keep_env_channel=True`` to restore MPE2's original 11-float observation (a baseline where the env carries the
  message).
* Physics, rewards and the 25-step episode are MPE2's unchanged; ``max_steps`` only changes the episode length.

Reference numbers (per-agent return per 25-step episode): without communication no listener can beat about −16 (the
best it can do is head for the landmarks' centroid); an oracle listener that knows the goal gets about −7.7.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from mpe2 import simple_speaker_listener_v4
from pettingzoo import ParallelEnv
from pydantic import BaseModel, ConfigDict, Field

from envs.batched import EnvSpec
from envs.config import ConfigError, build_config
from envs.particle.batch import ParallelEnvBatch

SPEAKER, LISTENER = "speaker_0", "listener_0"
AGENTS: tuple[str, ...] = (SPEAKER, LISTENER)
LISTENER_OBS_NO_CHANNEL = 8  # velocity 2 + three landmark relative positions 6
LISTENER_OBS_WITH_CHANNEL = 11  # ... + the speaker's env message 3


class SpeakerListenerConfig(BaseModel):
    """Speaker-listener parameters. Defaults reproduce the paper: 25-step episodes, env message channel removed."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_steps: int = Field(25, ge=1, le=10_000, description="Episode length; episodes truncate, never terminate.")
    keep_env_channel: bool = Field(
        False, description="Keep MPE2's built-in speaker→listener channel in the listener's observation (11 floats)."
    )


class SpeakerListenerEnv(ParallelEnv):
    """PettingZoo parallel env over MPE2 speaker-listener; ``self.world`` is the MPE2 world for inspection."""

    metadata: ClassVar[dict[str, Any]] = {
        "name": "speaker_listener_v0",
        "render_modes": ["rgb_array"],
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, config: SpeakerListenerConfig | None = None, render_mode: str | None = None) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ConfigError("render_mode", f"must be None or 'rgb_array' (got {render_mode!r})")
        self.config = config if config is not None else SpeakerListenerConfig()
        self.render_mode = render_mode
        self.possible_agents = list(AGENTS)
        self.agents: list[str] = []
        self._listener_dim = LISTENER_OBS_WITH_CHANNEL if self.config.keep_env_channel else LISTENER_OBS_NO_CHANNEL
        self.spec = EnvSpec(
            name="speaker-listener",
            agent_ids=AGENTS,
            obs_dims=(3, self._listener_dim),
            n_actions=(3, 5),
            max_steps=self.config.max_steps,
        )
        self._mpe = simple_speaker_listener_v4.parallel_env(
            max_cycles=self.config.max_steps, continuous_actions=False, render_mode=render_mode
        )
        self.world = self._mpe.unwrapped.world
        self._obs_spaces = {
            SPEAKER: spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float32),
            LISTENER: spaces.Box(-np.inf, np.inf, shape=(self._listener_dim,), dtype=np.float32),
        }
        self._act_spaces = {SPEAKER: spaces.Discrete(3), LISTENER: spaces.Discrete(5)}
        self._steps = 0

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_spaces[agent]  # the identical object every call, as PettingZoo requires

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._act_spaces[agent]

    def _convert(self, mpe_obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {
            SPEAKER: np.asarray(mpe_obs[SPEAKER], dtype=np.float32),
            LISTENER: np.asarray(mpe_obs[LISTENER][: self._listener_dim], dtype=np.float32),
        }

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        mpe_obs, _ = self._mpe.reset(seed=seed, options=options)
        self._steps = 0
        self.agents = list(AGENTS)
        return self._convert(mpe_obs), {a: {} for a in AGENTS}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        mpe_actions: dict[str, int] = {}
        for agent in AGENTS:
            if agent not in actions:
                raise ValueError(f"actions: missing action for {agent}")
            a = actions[agent]
            space = self.action_space(agent)
            if not space.contains(a):
                raise ValueError(f"actions[{agent!r}]: expected an integer in [0, {space.n}), got {a!r}")
            mpe_actions[agent] = int(a)
        mpe_obs, mpe_rew, _, _, _ = self._mpe.step(mpe_actions)
        self._steps += 1
        truncated = self._steps >= self.config.max_steps
        rewards = {a: float(mpe_rew[a]) for a in AGENTS}
        terminations = {a: False for a in AGENTS}
        truncations = {a: truncated for a in AGENTS}
        infos: dict[str, dict[str, Any]] = {a: {} for a in AGENTS}
        if truncated:
            self.agents = []
        return self._convert(mpe_obs), rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        return self._mpe.render()

    def close(self) -> None:
        self._mpe.close()


def make_speaker_listener(render_mode: str | None = None, **params: Any) -> SpeakerListenerEnv:
    """Build a validated speaker-listener env; unknown or out-of-range params raise ``ConfigError``."""
    return SpeakerListenerEnv(build_config(SpeakerListenerConfig, **params), render_mode=render_mode)


def make_speaker_listener_batch(num_envs: int, **params: Any) -> ParallelEnvBatch:
    """``num_envs`` speaker-listener envs behind the ``BatchedEnv`` API (params validated once, shared by all)."""
    cfg = build_config(SpeakerListenerConfig, **params)
    return ParallelEnvBatch(lambda: SpeakerListenerEnv(cfg), num_envs, "speaker-listener")
