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
from mpe2 import simple_speaker_listener_v4
from pydantic import BaseModel, ConfigDict, Field

from convoy.envs.batched import EnvSpec
from convoy.envs.particle.batch import ParallelEnvBatch
from convoy.envs.particle.mpe_env import MpeParallelEnv
from convoy.validation import build_config

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


class SpeakerListenerEnv(MpeParallelEnv):
    """PettingZoo parallel env over MPE2 speaker-listener; ``self.world`` is the MPE2 world for inspection."""

    metadata: ClassVar[dict[str, Any]] = {
        "name": "speaker_listener_v0",
        "render_modes": ["rgb_array"],
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, config: SpeakerListenerConfig | None = None, render_mode: str | None = None) -> None:
        self.config = config if config is not None else SpeakerListenerConfig()
        self._listener_dim = LISTENER_OBS_WITH_CHANNEL if self.config.keep_env_channel else LISTENER_OBS_NO_CHANNEL
        spec = EnvSpec(
            name="speaker-listener",
            agent_ids=AGENTS,
            obs_dims=(3, self._listener_dim),
            n_actions=(3, 5),
            max_steps=self.config.max_steps,
        )
        mpe = simple_speaker_listener_v4.parallel_env(
            max_cycles=self.config.max_steps, continuous_actions=False, render_mode=render_mode
        )
        super().__init__(mpe, spec, render_mode)

    def _convert(self, mpe_obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {
            SPEAKER: np.asarray(mpe_obs[SPEAKER], dtype=np.float32),
            LISTENER: np.asarray(mpe_obs[LISTENER][: self._listener_dim], dtype=np.float32),
        }

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        return self._convert(self._start_episode(seed, options)), {a: {} for a in AGENTS}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        mpe_obs, mpe_rew, _, _, _ = self._mpe.step(self._checked_actions(actions))
        rewards = {a: float(mpe_rew[a]) for a in AGENTS}
        terminations, truncations = self._finish_step()
        return self._convert(mpe_obs), rewards, terminations, truncations, {a: {} for a in AGENTS}


def make_speaker_listener(render_mode: str | None = None, **params: Any) -> SpeakerListenerEnv:
    """Build a validated speaker-listener env; unknown or out-of-range params raise ``ConfigError``."""
    return SpeakerListenerEnv(build_config(SpeakerListenerConfig, **params), render_mode=render_mode)


def make_speaker_listener_batch(num_envs: int, **params: Any) -> ParallelEnvBatch:
    """``num_envs`` speaker-listener envs behind the ``BatchedEnv`` API (params validated once, shared by all)."""
    cfg = build_config(SpeakerListenerConfig, **params)
    return ParallelEnvBatch(lambda: SpeakerListenerEnv(cfg), num_envs, "speaker-listener")
