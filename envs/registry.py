"""One table of Convoy's environments, so the CLI, the actors, ``JobConfig`` and the API (``GET /envs``) name them
alike."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pettingzoo import ParallelEnv
from pydantic import BaseModel

from convoy.envs.batched import BatchedEnv
from convoy.envs.treadmill import TreadmillConfig, TreadmillEngine, TreadmillParallelEnv
from convoy.validation import ConfigError, build_config


@dataclass(frozen=True)
class EnvEntry:
    """How to build one environment as a batch and as a PettingZoo env."""

    batched: Callable[..., BatchedEnv]  # (num_envs, **params)
    parallel: Callable[..., ParallelEnv]  # (**params)
    summary: str
    config: Callable[[], type[BaseModel]]  # the pydantic model of its parameters (lazy: particle envs import mpe2)
    # (params, episodes, seed) → {policy name: (mean return, 95 % CI)}: the hand-made policies a learner is judged
    # against beside random (the treadmill: its best constant action and the scripted driver)
    references: Callable[[dict[str, Any], int, int], dict[str, tuple[float, float]]] | None = None


def _treadmill_batch(num_envs: int, **params: Any) -> TreadmillEngine:
    return TreadmillEngine(build_config(TreadmillConfig, **params), num_envs)


def _treadmill_references(params: dict[str, Any], episodes: int, seed: int) -> dict[str, tuple[float, float]]:
    from convoy.envs.treadmill.references import summary_references

    return summary_references(build_config(TreadmillConfig, **params), episodes, seed)


def _particle(name: str, summary: str, config: str) -> EnvEntry:
    """Particle envs are imported on first use: mpe2 costs half a second and the treadmill never needs it."""

    def attr(attribute: str) -> Any:
        import convoy.envs.particle as particle

        return getattr(particle, attribute)

    key = name.replace("-", "_")
    return EnvEntry(
        batched=lambda *a, **kw: attr(f"make_{key}_batch")(*a, **kw),
        parallel=lambda *a, **kw: attr(f"make_{key}")(*a, **kw),
        summary=summary,
        config=lambda: attr(config),
    )


ENVS: dict[str, EnvEntry] = {
    "treadmill": EnvEntry(
        _treadmill_batch,
        TreadmillParallelEnv,
        "the paper's highway: N agents, M adversaries",
        lambda: TreadmillConfig,
        _treadmill_references,
    ),
    "predator-prey": _particle(
        "predator-prey", "2 predators chase a scripted prey (mpe2 simple_tag)", "PredatorPreyConfig"
    ),
    "speaker-listener": _particle(
        "speaker-listener", "mpe2 simple_speaker_listener, env channel removed", "SpeakerListenerConfig"
    ),
    "referential": _particle(
        "referential", "referential game: listener picks the speaker's target (1 or more rounds)", "ReferentialConfig"
    ),
}


def env_entry(name: str) -> EnvEntry:
    """The registry entry for ``name`` (underscores accepted for hyphens)."""
    key = name.strip().lower().replace("_", "-")
    if key not in ENVS:
        raise ConfigError("env", f"unknown environment {name!r}; choose one of: {', '.join(ENVS)}")
    return ENVS[key]


def make_batched(name: str, num_envs: int = 1, **params: Any) -> BatchedEnv:
    """B copies of env ``name`` behind the batched interface."""
    if num_envs < 1:
        raise ConfigError("num_envs", f"must be ≥ 1 (got {num_envs}); allowed range 1 ≤ num_envs")
    return env_entry(name).batched(num_envs, **params)


def make_parallel(name: str, **params: Any) -> ParallelEnv:
    """Env ``name`` as a PettingZoo ParallelEnv."""
    return env_entry(name).parallel(**params)
