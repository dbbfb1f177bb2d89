"""The batched interface every Convoy environment speaks.

Actors step many environments at once, so every env exposes the same array-shaped API:
observations ``[B, N, D]`` (float32, per-agent observations zero-padded to the widest agent),
actions ``[B, N]`` (int64, each agent's own ``Discrete`` range), rewards ``[B, N]`` and per-env
``terminated`` / ``truncated`` flags ``[B]``. Finished envs reset themselves inside ``step``
(same-step auto-reset): ``obs`` already holds the first observation of the next episode and
``final_obs`` holds the observation the finished episode ended on, which is what a replay
buffer needs as ``s_{t+1}``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, get_args, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class StepResult:
    """One batched step. ``final_obs`` equals ``obs`` for envs that did not finish."""

    obs: np.ndarray  # [B, N, D] float32, after auto-reset
    reward: np.ndarray  # [B, N] float32
    terminated: np.ndarray  # [B] bool
    truncated: np.ndarray  # [B] bool
    final_obs: np.ndarray  # [B, N, D] float32, before auto-reset
    info: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def done(self) -> np.ndarray:
        """Episode over for whatever reason: ``terminated | truncated``."""
        return self.terminated | self.truncated


EntitySource = Literal["sensor", "told"]  # the agent's own sensor, or what its teammates tell it
ENTITY_SOURCES: tuple[str, ...] = get_args(EntitySource)


@dataclass(frozen=True)
class EntitySlots:
    """``count`` slots of ``width`` columns from column ``start`` of an observation, each one other car; an empty slot
    is all zeros. ``present`` … ``adversary`` are columns within a slot, None where the block does not say (a told
    sighting has no heading, a sensor no adversary flag). Every block gives offsets in sensor-range units and speeds
    as a fraction of the top speed, so one network reads a car the same whichever block it sits in."""

    source: EntitySource
    start: int
    count: int
    width: int
    present: int  # 1 = a car is there, 0 = an empty slot
    dx: int  # offset along the road
    dy: int  # offset across it
    speed: int
    heading: int | None = None  # first column of a heading one-hot (``ObsLayout.headings`` wide)
    adversary: int | None = None  # 1 = an adversary


@dataclass(frozen=True)
class WordSlots:
    """``count`` words of ``bits`` columns (0/1) from column ``start``: what teammates say in a fixed code, each
    read as one entity, as a heard message is."""

    start: int
    count: int
    bits: int


@dataclass(frozen=True)
class ObsLayout:
    """Where the parts of an agent's observation lie, for networks that read the other cars as a set
    (``encoder=entity``); an env whose observations are not made of cars has none."""

    own: int  # columns 0 … own−1: the agent's own state
    headings: int  # width of a heading one-hot
    cars: tuple[EntitySlots, ...]
    unread: tuple[str, ...] = ()  # blocks not laid out as cars, by the env parameter that adds them
    words: WordSlots | None = None

    @property
    def width(self) -> int:
        """Columns the own features, the car slots and the words span (the observation's width when nothing is
        unread)."""
        words = [self.words.start + self.words.count * self.words.bits] if self.words else []
        return max([self.own, *(b.start + b.count * b.width for b in self.cars), *words])


@dataclass(frozen=True)
class EnvSpec:
    """Static shape facts an actor or learner needs before the first step."""

    name: str
    agent_ids: tuple[str, ...]
    obs_dims: tuple[int, ...]  # each agent's true observation width (before padding)
    n_actions: tuple[int, ...]  # each agent's Discrete action count
    max_steps: int
    # what the observation's columns are, where the env says (the treadmill); derived from the env's parameters, so
    # not compared: a spec read from a checkpoint written before layouts existed still equals the env's
    layout: ObsLayout | None = field(default=None, compare=False)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EnvSpec:
        """The spec ``dataclasses.asdict`` wrote (a checkpoint's), lists read back as tuples."""
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        layout = values.get("layout")
        if isinstance(layout, dict):
            cars = tuple(EntitySlots(**c) for c in layout["cars"])
            words = WordSlots(**layout["words"]) if isinstance(layout.get("words"), dict) else None
            unread = tuple(layout.get("unread", ()))
            values["layout"] = ObsLayout(**{**layout, "cars": cars, "unread": unread, "words": words})
        return cls(**values)

    @property
    def n_agents(self) -> int:
        return len(self.agent_ids)

    @property
    def obs_dim(self) -> int:
        """Padded observation width D of the batched arrays."""
        return max(self.obs_dims)

    @property
    def max_actions(self) -> int:
        return max(self.n_actions)


@runtime_checkable
class BatchedEnv(Protocol):
    """What actors program against: B envs × N agents as arrays."""

    spec: EnvSpec
    num_envs: int

    def reset(self, seed: int | np.ndarray | None = None) -> np.ndarray:
        """Reset all envs; returns obs ``[B, N, D]``. An int is expanded with ``env_seeds``; None continues."""
        ...

    def step(self, actions: np.ndarray) -> StepResult:
        """Advance every env one step with actions ``[B, N]``; finished envs auto-reset."""
        ...

    def close(self) -> None:
        """Release whatever the envs hold (windows, pygame)."""
        ...


def env_seeds(seed: int | np.ndarray, num_envs: int) -> np.ndarray:
    """Per-env seeds ``[B]`` (int64) for a batch reset with ``seed``.

    An int is expanded through ``np.random.SeedSequence`` rather than ``seed + b`` so that two
    batches seeded s and s + 1 (two actors, say) share no env. The expansion is prefix-stable:
    env b gets the same seed whatever B is, and ``env_seeds(s, B)[b]`` passed as a one-element
    array reproduces env b on its own. An array is taken as the seeds themselves.
    """
    seeds = np.asarray(seed)
    if seeds.ndim == 0:
        if not np.issubdtype(seeds.dtype, np.integer) or int(seeds) < 0:
            raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
        words = np.random.SeedSequence(int(seeds)).generate_state(num_envs, dtype=np.uint64)
        return (words & np.uint64((1 << 62) - 1)).astype(np.int64)
    if seeds.shape != (num_envs,) or not np.issubdtype(seeds.dtype, np.integer):
        raise ValueError(f"seed: expected an int or {num_envs} integer seeds, got a {seeds.dtype} array {seeds.shape}")
    return seeds.astype(np.int64)


def check_actions(actions: np.ndarray, num_envs: int, n_actions: tuple[int, ...]) -> np.ndarray:
    """Validate a batched action array once, at the API boundary, and return it as int64."""
    a = np.asarray(actions)
    n_agents = len(n_actions)
    if a.shape != (num_envs, n_agents):
        raise ValueError(f"actions: expected shape (num_envs, n_agents) = ({num_envs}, {n_agents}), got {a.shape}")
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"actions: expected integer action indices, got dtype {a.dtype}")
    a = a.astype(np.int64, copy=False)
    high = np.asarray(n_actions)
    if (a < 0).any() or (a >= high).any():
        raise ValueError(f"actions: each agent's action must lie in [0, n_actions) with n_actions = {list(n_actions)}")
    return a
