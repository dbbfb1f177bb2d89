"""A referential game: the speaker sees a target, the listener must name it without seeing it.

This is the smallest environment in which communication is both necessary and sufficient: a listener that hears
nothing succeeds with probability 1/K, one that is told the target succeeds always. It is batched natively in numpy
(``ReferentialBatch``); ``ReferentialEnv`` wraps a batch of one as a PettingZoo ``ParallelEnv``.

By default a game is one step. ``rounds = R > 1`` keeps the same target for R steps, so that algorithms whose
messages arrive one step late (DIAL sends at t−1, as the paper notes) can communicate at all: the speaker sees the
target on every round, the listener still sees zeros, and only the listener's guess on the last round is scored.
With ``rounds=1`` the game is exactly the one-step game, draw for draw.

``listener_glimpse`` (needs ``rounds ≥ 2``) shows the listener the target on the first round only. A feed-forward
listener has forgotten it by the scored last round, so it still needs the speaker's message; a listener with a
memory of its own observations does not. This is the smallest game in which the memory-module variants
(MA-MeSN-MM) can replace the channel by a prediction from the agent's own history, as the paper's cars predict
their neighbours' messages from what they have seen.

Choices made where the paper is silent:

* Observations are ``[K]`` float32 for both agents: the speaker's is the target's one-hot, the listener's is all
  zeros (it carries no information; the width only matches the speaker's so the batch needs no extra padding).
* The speaker has a single no-op action (``Discrete(1)``): its message travels through the learning algorithm's
  message path, which lives outside the env, so the env cannot be solved by an env-level "say" action.
* Reward is shared: 1.0 to both agents if the listener's action on the last round equals the target, else 0.0;
  earlier rounds pay 0.0 whatever the guess. Every episode is exactly ``rounds`` steps long (``spec.max_steps``) and
  ends with ``terminated=True`` after the last round (a real end, so no bootstrapping past it); ``truncated`` is
  never set. Observations carry no round counter (the listener's stays all zeros).
* All games of a batch start together (``reset`` resets every env) and last the same number of steps, so they stay
  in lockstep: one round counter serves the whole batch and new targets are drawn for every env at once.
* Targets are uniform over K, drawn from the counter-based generator of ``envs.rng`` (as the treadmill's), so each
  env's targets depend only on its own seed: an int seed is expanded per env by ``envs.batched.env_seeds``, an array
  gives each env its seed, ``reset(None)`` continues the streams (fresh entropy on the very first reset).
* ``info["target"]`` (``[B]`` int64) holds the target of the episode just played (ended, on the last round), for
  evaluation only.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pydantic import BaseModel, ConfigDict, Field, model_validator

from convoy.envs import rng
from convoy.envs.batched import EnvSpec, StepResult, check_actions
from convoy.validation import ConfigError, build_config

SPEAKER, LISTENER = "speaker", "listener"
AGENTS: tuple[str, ...] = (SPEAKER, LISTENER)


class ReferentialConfig(BaseModel):
    """Referential game parameters: the number of candidate targets K and of rounds per game (more than one round
    lets messages sent one step late, as DIAL's are, reach the listener before its scored guess)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_targets: int = Field(4, ge=2, le=64, description="Number of candidate targets K; chance success is 1/K.")
    rounds: int = Field(1, ge=1, le=64, description="Steps per game with one target; the last guess is scored.")
    listener_glimpse: bool = Field(
        False,
        description="The listener also sees the target, on the first round only (needs rounds ≥ 2): solvable "
        "without messages by a listener that remembers its own observations.",
    )

    @model_validator(mode="after")
    def _glimpse(self) -> ReferentialConfig:
        if self.listener_glimpse and self.rounds < 2:
            raise ConfigError(
                "listener_glimpse", "needs rounds ≥ 2 (with one round the listener would see the scored target)"
            )
        return self


def _spec(cfg: ReferentialConfig) -> EnvSpec:
    k = cfg.n_targets
    return EnvSpec(name="referential", agent_ids=AGENTS, obs_dims=(k, k), n_actions=(1, k), max_steps=cfg.rounds)


class ReferentialBatch:
    """B independent referential games as arrays (implements ``BatchedEnv``)."""

    def __init__(self, config: ReferentialConfig | None = None, num_envs: int = 1) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs: must be ≥ 1 (got {num_envs})")
        self.config = config if config is not None else ReferentialConfig()
        self.num_envs = num_envs
        self.spec = _spec(self.config)
        self._streams = rng.EnvStreams(num_envs)
        self._streams.seed(None)  # usable before any reset: fresh entropy
        self._targets = np.zeros(num_envs, dtype=np.int64)
        self._obs: np.ndarray | None = None
        self._round = 0  # rounds already played in the current games (the batch moves in lockstep)

    @property
    def targets(self) -> np.ndarray:
        """Current targets ``[B]`` (for tests and oracles; agents should read them from the speaker's obs)."""
        return self._targets.copy()

    def _draw(self) -> np.ndarray:
        u = self._streams.uniform(rng.STREAM_TARGET, 1)[:, 0]
        self._streams.advance()
        self._targets = (u * self.config.n_targets).astype(np.int64)
        obs = np.zeros((self.num_envs, 2, self.config.n_targets), dtype=np.float32)
        obs[np.arange(self.num_envs), 0, self._targets] = 1.0
        if self.config.listener_glimpse:
            obs[np.arange(self.num_envs), 1, self._targets] = 1.0
        return obs

    def reset(self, seed: int | np.ndarray | None = None) -> np.ndarray:
        """Draw new targets for every game; returns obs ``[B, 2, K]``."""
        self._streams.seed(seed)
        self._obs = self._draw()
        self._round = 0
        return self._obs.copy()

    def step(self, actions: np.ndarray) -> StepResult:
        """Play one round; on the last one score the listener's guesses ``actions[:, 1]``, end every game and draw
        new targets (earlier rounds pay nothing and keep the target)."""
        if self._obs is None:
            raise RuntimeError("step() before reset()")
        acts = check_actions(actions, self.num_envs, self.spec.n_actions)
        targets = self._targets
        self._round += 1
        last = self._round >= self.config.rounds
        final_obs = self._obs
        if last:
            hit = (acts[:, 1] == targets).astype(np.float32)
            self._obs = self._draw()
            self._round = 0
        else:
            hit = np.zeros(self.num_envs, dtype=np.float32)
            final_obs = final_obs.copy()  # the game goes on with this obs; the caller may keep final_obs
            if self.config.listener_glimpse:
                self._obs = self._obs.copy()
                self._obs[:, 1] = 0.0  # the glimpse was the first round's only
        return StepResult(
            obs=self._obs.copy(),
            reward=np.repeat(hit[:, None], 2, axis=1),
            terminated=np.full(self.num_envs, last, dtype=bool),
            truncated=np.zeros(self.num_envs, dtype=bool),
            final_obs=final_obs,
            info={"target": targets.copy()},
        )

    def close(self) -> None:
        """Nothing to release (part of the ``BatchedEnv`` API)."""


class ReferentialEnv(ParallelEnv):
    """The referential game as a PettingZoo parallel env (a ``ReferentialBatch`` of one)."""

    metadata: ClassVar[dict[str, Any]] = {"name": "referential_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, config: ReferentialConfig | None = None) -> None:
        self.config = config if config is not None else ReferentialConfig()
        self.render_mode = None
        self._batch = ReferentialBatch(self.config, num_envs=1)
        self.spec = self._batch.spec
        self.possible_agents = list(AGENTS)
        self.agents: list[str] = []
        k = self.config.n_targets
        self._obs_spaces = {a: spaces.Box(0.0, 1.0, shape=(k,), dtype=np.float32) for a in AGENTS}
        self._act_spaces = {SPEAKER: spaces.Discrete(1), LISTENER: spaces.Discrete(k)}

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_spaces[agent]  # the identical object every call, as PettingZoo requires

    def action_space(self, agent: str) -> spaces.Discrete:
        return self._act_spaces[agent]

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        obs = self._batch.reset(seed)[0]
        self.agents = list(AGENTS)
        return {a: obs[i] for i, a in enumerate(AGENTS)}, {a: {} for a in AGENTS}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() called on a finished episode; call reset() first")
        row = []
        for agent in AGENTS:
            if agent not in actions:
                raise ValueError(f"actions: missing action for {agent}")
            a = actions[agent]
            if not self.action_space(agent).contains(a):
                raise ValueError(
                    f"actions[{agent!r}]: expected an integer in [0, {self.action_space(agent).n}), got {a!r}"
                )
            row.append(int(a))
        res = self._batch.step(np.array([row], dtype=np.int64))
        done = bool(res.terminated[0])
        if done:  # the last round: every agent leaves until the next reset
            self.agents = []
        obs = {a: res.final_obs[0, i] for i, a in enumerate(AGENTS)}
        rewards = {a: float(res.reward[0, i]) for i, a in enumerate(AGENTS)}
        target = int(res.info["target"][0])
        infos = {a: {"target": target} for a in AGENTS}
        return obs, rewards, {a: done for a in AGENTS}, {a: False for a in AGENTS}, infos

    def render(self) -> None:
        return None


def make_referential(**params: Any) -> ReferentialEnv:
    """Build a validated referential game as a PettingZoo env (B = 1); bad params raise ``ConfigError``."""
    return ReferentialEnv(build_config(ReferentialConfig, **params))


def make_referential_batch(num_envs: int, **params: Any) -> ReferentialBatch:
    """``num_envs`` referential games behind the ``BatchedEnv`` API; bad params raise ``ConfigError``."""
    return ReferentialBatch(build_config(ReferentialConfig, **params), num_envs)
