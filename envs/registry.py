"""One table of Convoy's environments, so the CLI, the actors, ``JobConfig`` and the API (``GET /envs``) name them
alike."""

from __future__ import annotations

import time
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
    # (params, episodes, seed, report=None, round_envs=None) → {policy name: (mean return, 95 % CI)}: the hand-made
    # policies a learner is judged against beside random (the treadmill: its best constant action, a tuned driver and
    # the planners); ``report`` hears of each as it ends (``Report``); ``round_envs``: played in rounds of that many
    # envs, as a learner's evaluation on that many envs plays its episodes
    references: Callable[..., dict[str, tuple[float, float]]] | None = None
    # (lowest, highest) return an episode can have, where the rules bound it (the referential game's success rate):
    # a mean's confidence band is drawn within them
    return_bounds: tuple[float, float] | None = None


# (k, of, name, (mean, 95 % CI), seconds, about how many seconds the rest take): reference k of ``of`` is played
Report = Callable[[int, int, str, tuple[float, float], float, float | None], None]


def _treadmill_batch(num_envs: int, **params: Any) -> TreadmillEngine:
    return TreadmillEngine(build_config(TreadmillConfig, **params), num_envs)


def _treadmill_references(
    params: dict[str, Any], episodes: int, seed: int, report: Report | None = None, round_envs: int | None = None
) -> dict[str, tuple[float, float]]:
    """``summary_references``; with ``report``, the same rollouts played one policy (the constant actions: one
    group) at a time, each reported as it ends — the planners take most of the time, tens of seconds at 100
    episodes."""
    from convoy.envs.treadmill import references as refs

    cfg = build_config(TreadmillConfig, **params)
    if report is None:
        return refs.summary_references(cfg, episodes, seed, round_envs)
    played: dict[str, Any] = {}
    groups = [("random",), refs.CONSTANTS, ("private-driver",), *((name,) for name in refs.PLANNERS)]
    planners_s: list[float] = []  # the planners take nearly all the time, each about as long as the others
    for k, names in enumerate(groups, 1):
        t0 = time.perf_counter()
        played.update(refs.evaluate_references(cfg, episodes, seed, names=names, round_envs=round_envs))
        name = refs.best_constant(played) if names == refs.CONSTANTS else names[0]
        seconds = time.perf_counter() - t0
        if name in refs.PLANNERS:
            planners_s.append(seconds)
        left = (len(refs.PLANNERS) - len(planners_s)) * sum(planners_s) / len(planners_s) if planners_s else None
        report(k, len(groups), name, played[name].ci95(), seconds, left)
    best = refs.best_constant(played)  # what summary_references keeps (tests/test_train_cli.py holds them equal)
    return {name: played[name].ci95() for name in ("random", best, "private-driver", *refs.PLANNERS)}


def _particle(name: str, summary: str, config: str, return_bounds: tuple[float, float] | None = None) -> EnvEntry:
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
        return_bounds=return_bounds,
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
        "referential",
        "referential game: listener picks the speaker's target (1 or more rounds)",
        "ReferentialConfig",
        (0.0, 1.0),  # 1 when the listener's last guess is the target, else 0: a success rate
    ),
}


def env_entry(name: str) -> EnvEntry:
    """The registry entry for ``name`` (underscores accepted for hyphens)."""
    key = name.strip().lower().replace("_", "-")
    if key not in ENVS:
        raise ConfigError("env", f"unknown environment {name!r}; choose one of: {', '.join(ENVS)}")
    return ENVS[key]


def return_bounds(name: str) -> tuple[float, float] | None:
    """The returns env ``name`` allows, where its rules bound them (None: unbounded, or an unknown env)."""
    try:
        return env_entry(name).return_bounds
    except ConfigError:
        return None


def make_batched(name: str, num_envs: int = 1, **params: Any) -> BatchedEnv:
    """B copies of env ``name`` behind the batched interface."""
    if num_envs < 1:
        raise ConfigError("num_envs", f"must be ≥ 1 (got {num_envs}); allowed range 1 ≤ num_envs")
    return env_entry(name).batched(num_envs, **params)


def make_parallel(name: str, **params: Any) -> ParallelEnv:
    """Env ``name`` as a PettingZoo ParallelEnv."""
    return env_entry(name).parallel(**params)
