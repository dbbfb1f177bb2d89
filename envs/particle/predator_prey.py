"""Two-predator, one-prey pursuit on the MPE2 ``simple_tag_v3`` physics, as in the paper.

Choices made where the paper is silent (or where MPE2 differs from it):

* Physics, sizes, speeds and obstacles are MPE2's ``simple_tag_v3`` unchanged (predators: size 0.075, max speed 1.0;
  prey: size 0.05, max speed 1.3; obstacles: size 0.2). Only the predators are learning agents.
* The prey is scripted and deterministic (see ``evade_action``) so that the only randomness is the seeded start
  state; MPE2's own rewards are ignored.
* Capture means the predator-prey distance is below the sum of their sizes, checked *after* the physics step. A
  predator that captures alone earns ``capture_reward_alone`` (0.5); when both capture in the same step EACH earns
  ``capture_reward_joint`` (1.0), so coordination pays twice as much per head. A capture does not end the episode
  (the prey is pushed away by the contact force and the chase continues); episodes only truncate at ``max_steps``.
* A predator observes only the prey's position relative to itself (2 floats), not the other predator nor the
  obstacles: coordination must come from communication or from learned conventions, not from observation.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from mpe2 import simple_tag_v3
from pydantic import BaseModel, ConfigDict, Field

from convoy.envs.batched import EnvSpec
from convoy.envs.particle.batch import ParallelEnvBatch
from convoy.envs.particle.mpe_env import MpeParallelEnv
from convoy.validation import build_config

PREDATORS: tuple[str, ...] = ("predator_0", "predator_1")
_MPE_PREDATORS: tuple[str, ...] = ("adversary_0", "adversary_1")
_MPE_PREY = "agent_0"
# MPE2 discrete movement actions (mpe2/_mpe_utils/simple_env.py, SimpleEnv._set_action).
NOOP, MINUS_X, PLUS_X, MINUS_Y, PLUS_Y = 0, 1, 2, 3, 4
BOUNDARY = 0.9  # MPE2's simple_tag starts penalising the prey beyond |x| = 0.9; our scripted prey turns back there.


class PredatorPreyConfig(BaseModel):
    """Predator-prey parameters. Defaults reproduce the paper: 1000-step episodes, 2 obstacles, 0.5 / 1.0 rewards."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_steps: int = Field(1000, ge=1, le=100_000, description="Episode length; episodes truncate, never terminate.")
    num_obstacles: int = Field(2, ge=0, le=10, description="Number of MPE2 obstacles (static discs of size 0.2).")
    capture_reward_alone: float = Field(0.5, ge=0.0, le=100.0, description="Reward to a predator capturing alone.")
    capture_reward_joint: float = Field(
        1.0, ge=0.0, le=100.0, description="Reward to EACH predator when both capture in the same step."
    )


def evade_action(prey_pos: np.ndarray, predator_pos: np.ndarray) -> int:
    """Scripted prey policy: flee the nearest predator along the dominant axis; return to centre past ±0.9.

    Deterministic (no RNG) so a seeded episode is reproducible. The boundary rule has priority because MPE2 has no
    walls and a prey fleeing forever would make capture impossible. Ties resolve to the x axis; a predator exactly
    on the prey gives a no-op.
    """
    pos = np.asarray(prey_pos, dtype=np.float64)
    out = np.abs(pos) > BOUNDARY
    if out.any():
        axis = int(np.argmax(np.where(out, np.abs(pos), -np.inf)))
        toward_centre = -np.sign(pos[axis])
        return (PLUS_X if toward_centre > 0 else MINUS_X) if axis == 0 else (PLUS_Y if toward_centre > 0 else MINUS_Y)
    preds = np.asarray(predator_pos, dtype=np.float64).reshape(-1, 2)
    away = pos - preds[int(np.argmin(np.sum((preds - pos) ** 2, axis=1)))]
    if not away.any():
        return NOOP
    axis = int(np.argmax(np.abs(away)))
    if axis == 0:
        return PLUS_X if away[0] > 0 else MINUS_X
    return PLUS_Y if away[1] > 0 else MINUS_Y


def capture_rewards(captured: np.ndarray, alone: float, joint: float) -> np.ndarray:
    """Per-predator reward from per-predator capture flags: joint if all capture, alone for a lone captor."""
    captured = np.asarray(captured, dtype=bool)
    if captured.all():
        return np.full(captured.shape, joint, dtype=np.float32)
    return np.where(captured, np.float32(alone), np.float32(0.0)).astype(np.float32)


class PredatorPreyEnv(MpeParallelEnv):
    """PettingZoo parallel env: ``predator_0``/``predator_1`` chase a scripted prey in MPE2 ``simple_tag``.

    ``self.world`` is the MPE2 world (positions in ``world.agents[i].state.p_pos``; predators are indices 0 and 1,
    the prey index 2) so tests and tools can inspect or set the state.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "name": "predator_prey_v0",
        "render_modes": ["rgb_array"],
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, config: PredatorPreyConfig | None = None, render_mode: str | None = None) -> None:
        self.config = config if config is not None else PredatorPreyConfig()
        spec = EnvSpec(
            name="predator-prey",
            agent_ids=PREDATORS,
            obs_dims=(2, 2),
            n_actions=(5, 5),
            max_steps=self.config.max_steps,
        )
        mpe = simple_tag_v3.parallel_env(
            num_good=1,
            num_adversaries=2,
            num_obstacles=self.config.num_obstacles,
            max_cycles=self.config.max_steps,
            continuous_actions=False,
            render_mode=render_mode,
        )
        super().__init__(mpe, spec, render_mode)

    def _positions(self) -> tuple[np.ndarray, np.ndarray]:
        """(predator positions [2, 2], prey position [2])."""
        agents = self.world.agents
        return np.stack([agents[0].state.p_pos, agents[1].state.p_pos]), agents[2].state.p_pos

    def _observe(self) -> dict[str, np.ndarray]:
        preds, prey = self._positions()
        return {a: (prey - preds[i]).astype(np.float32) for i, a in enumerate(PREDATORS)}

    def captured(self) -> np.ndarray:
        """Per-predator capture flags [2] for the current world state."""
        preds, prey = self._positions()
        agents = self.world.agents
        dist = np.sqrt(np.sum((preds - prey) ** 2, axis=1))
        return dist < np.array([agents[0].size + agents[2].size, agents[1].size + agents[2].size])

    def prey_action(self) -> int:
        """The scripted prey's action in the current state."""
        preds, prey = self._positions()
        return evade_action(prey, preds)

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        self._start_episode(seed, options)
        return self._observe(), {a: {} for a in PREDATORS}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        checked = self._checked_actions(actions)
        mpe_actions = {mpe: checked[ours] for ours, mpe in zip(PREDATORS, _MPE_PREDATORS, strict=True)}
        mpe_actions[_MPE_PREY] = self.prey_action()
        self._mpe.step(mpe_actions)
        caught = self.captured()
        rew = capture_rewards(caught, self.config.capture_reward_alone, self.config.capture_reward_joint)
        rewards = {a: float(rew[i]) for i, a in enumerate(PREDATORS)}
        infos = {a: {"captures": int(caught[i])} for i, a in enumerate(PREDATORS)}
        terminations, truncations = self._finish_step()
        return self._observe(), rewards, terminations, truncations, infos


def make_predator_prey(render_mode: str | None = None, **params: Any) -> PredatorPreyEnv:
    """Build a validated predator-prey env; unknown or out-of-range params raise ``ConfigError``."""
    return PredatorPreyEnv(build_config(PredatorPreyConfig, **params), render_mode=render_mode)


def make_predator_prey_batch(num_envs: int, **params: Any) -> ParallelEnvBatch:
    """``num_envs`` predator-prey envs behind the ``BatchedEnv`` API (params validated once, shared by all)."""
    cfg = build_config(PredatorPreyConfig, **params)
    return ParallelEnvBatch(lambda: PredatorPreyEnv(cfg), num_envs, "predator-prey")
