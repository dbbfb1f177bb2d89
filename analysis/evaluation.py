"""Greedy evaluation of a trained policy under a chosen message source: what ``convoy eval`` and the benchmarks run.

``evaluate_policy`` plays whole episodes (each env's first episode, reseeded per round, as the trainer's final
evaluation does) with the algorithm's ``listening`` set for the duration: the true messages, a lossy channel,
the memory module's predictions or white noise (``algos/listening.py``). Algorithms without discrete messages
accept only the true source, so a probe can never silently measure nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np

from convoy.actors.stepping import AgentPolicy
from convoy.algos.algorithm import Agent
from convoy.algos.listening import HearsMessages, Listening, Source
from convoy.algos.memory import MemoryModule
from convoy.envs.batched import BatchedEnv
from convoy.envs.channel import MessageChannel
from convoy.envs.rollout import random_policy, rollout
from convoy.stats import ci95_half
from convoy.validation import ConfigError


@dataclass(frozen=True)
class EvalResult:
    """Per-episode returns (mean over agents) and what the agents heard while playing them."""

    returns: np.ndarray
    messages: str
    channel: str | None

    @property
    def mean(self) -> float:
        return float(self.returns.mean())

    @property
    def ci95(self) -> float:
        return ci95_half(self.returns, single=0.0)

    def describe(self) -> str:
        heard = self.messages + (f" through channel {self.channel}" if self.channel else "")
        return f"{self.mean:.3f} ± {self.ci95:.3f} (95 % CI, {len(self.returns)} episodes, messages: {heard})"


def evaluate(env: BatchedEnv, algo: Agent, episodes: int, seed: int, epsilon: float = 0.0) -> np.ndarray:
    """Per-episode returns (mean over agents) of ``episodes`` episodes with ε-greedy acting.

    Every env contributes its *first* episode only (in rounds of B envs, reseeded each round): scoring the first
    episodes to finish would over-sample short ones, i.e. early crashes.
    """

    def play(rnd: int) -> np.ndarray:
        policy = AgentPolicy(algo, env.num_envs, epsilon)  # nothing in flight from an earlier round
        return rollout(env, policy, seed=seed + rnd, after_step=policy.after_step).mean_return

    return first_episodes(env, episodes, play)


def evaluate_reference(env: BatchedEnv, name: str, episodes: int, seed: int) -> np.ndarray:
    """Per-episode returns of the treadmill reference policy ``name`` (``envs.treadmill.references``) on the
    episodes ``evaluate`` plays with ``seed`` on ``env``: a learner and its references on the very same episodes."""
    from convoy.envs.treadmill.references import reference_policy

    def play(rnd: int) -> np.ndarray:
        return rollout(env, reference_policy(name, cast(Any, env), seed + rnd), seed=seed + rnd).mean_return

    return first_episodes(env, episodes, play)


def evaluate_random(env: BatchedEnv, episodes: int, seed: int) -> np.ndarray:
    """Per-episode returns of the uniform random policy (every agent's action uniform in its own range, no messages)
    on the episodes ``evaluate`` plays with ``seed``: the one random reference, whatever algorithm is compared to
    it (an algorithm at ε = 1 still sends its learned messages, so its "random" would differ by algorithm)."""
    return first_episodes(
        env, episodes, lambda rnd: rollout(env, random_policy(env.spec, seed + rnd), seed=seed + rnd).mean_return
    )


def first_episodes(env: BatchedEnv, episodes: int, play: Callable[[int], np.ndarray]) -> np.ndarray:
    """``episodes`` returns from rounds of ``env.num_envs`` first episodes, ``play(round)`` playing one round."""
    rounds = [play(rnd) for rnd in range(-(-episodes // env.num_envs))]
    return np.concatenate(rounds)[:episodes].astype(np.float64)


def parse_channel(spec: str, seed: int | None = None) -> MessageChannel:
    """``drop=0.3,flip=0.01,latency=1`` → a channel, or a ConfigError naming ``channel`` and the bad key."""
    try:
        return MessageChannel.from_spec(spec, seed=seed)
    except ValueError as exc:  # ConfigError included: prefix the option it came from
        raise ConfigError("channel", str(exc)) from None


def listening_for(
    algo: Agent,
    messages: Source = "sent",
    channel: str | None = None,
    seed: int | None = None,
    fill_lost: Literal["predicted", "zeros"] = "predicted",
) -> Listening | None:
    """The ``Listening`` an evaluation asks for, or a ConfigError that says which algorithms support it."""
    if messages == "sent" and not channel:
        return None
    if not isinstance(algo, HearsMessages):
        raise ConfigError(
            "messages" if messages != "sent" else "channel",
            f"{algo.name} has no discrete message channel to replace or impair; channel and message probes apply "
            "to ma-mesn, ma-bon, ma-mesn-mm and ma-bon-mm",
        )
    if messages == "predicted" and not isinstance(algo, MemoryModule):
        raise ConfigError(
            "messages", f"{algo.name} has no memory module to predict messages; train ma-mesn-mm or ma-bon-mm"
        )
    chan = parse_channel(channel, seed) if channel else None
    return Listening(messages, chan, seed=seed, fill_lost=fill_lost)


@contextmanager
def listening(algo: Agent, how: Listening | None) -> Iterator[None]:
    """Let ``algo`` hear through ``how`` inside the block (training always hears the true messages)."""
    before = getattr(algo, "listening", None)
    if isinstance(algo, HearsMessages):
        algo.listening = how
    try:
        yield
    finally:
        if isinstance(algo, HearsMessages):
            algo.listening = before


def evaluate_policy(
    algo: Agent,
    env: BatchedEnv,
    episodes: int,
    seed: int,
    messages: Source = "sent",
    channel: str | None = None,
    epsilon: float = 0.0,
    fill_lost: Literal["predicted", "zeros"] = "predicted",
) -> EvalResult:
    """Returns of ``episodes`` greedy (or ε-greedy) episodes with the agents hearing ``messages``/``channel``."""

    how = listening_for(algo, messages, channel, seed, fill_lost)
    with listening(algo, how):
        returns = evaluate(env, algo, episodes, seed=seed, epsilon=epsilon)
    return EvalResult(returns, messages, channel or None)


HELD_OUT_SEED = 777  # episodes no training run evaluates on (those are seed + 10,000 + …): where policies are re-scored
SCORING_ENVS = 256  # envs a re-scoring steps at once; more episodes are played in rounds of other episodes
