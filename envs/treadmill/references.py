"""The reference policies every treadmill learner is judged against, by name.

* ``random`` — uniform actions;
* ``constant-K`` — action K (0…8) at every step: an open-loop policy that ignores everything;
* ``scripted`` — the hand-written driver on private observations (``envs.treadmill.scripted``);
* ``team-information`` — the same driver told where every adversary is that some agent observes (in its
  ``observe_k`` slots), and that it is one: what perfectly decoded messages between agents could carry;
* ``full-information`` — the same driver told every car's position and which cars are adversaries.

``full-information ÷ scripted`` is the value of information; ``team-information ÷ scripted`` the part of it
that communication can reach.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from convoy.envs.rollout import RolloutResult, random_policy, rollout
from convoy.envs.treadmill.config import N_ACTIONS, TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.envs.treadmill.scripted import DANGER, full_information_actions, scripted_actions

Policy = Callable[[np.ndarray], np.ndarray]
CONSTANTS: tuple[str, ...] = tuple(f"constant-{a}" for a in range(N_ACTIONS))
REFERENCES: tuple[str, ...] = ("random", *CONSTANTS, "scripted", "team-information", "full-information")


def reference_policy(name: str, engine: TreadmillEngine, seed: int | None = None) -> Policy:
    """The policy ``name`` driving ``engine``'s agents (the full-information one reads the engine's state)."""
    if name == "random":
        return random_policy(engine.spec, seed)
    if name == "scripted":
        return lambda obs: scripted_actions(obs, engine.cfg)
    if name == "full-information":
        return lambda obs: full_information_actions(engine)
    if name == "team-information":
        return lambda obs: full_information_actions(engine, team_only=True)
    if name in CONSTANTS:
        action = int(name.rsplit("-", 1)[1])
        return lambda obs: np.full(obs.shape[:2], action, np.int64)
    raise ValueError(f"unknown reference policy {name!r}; choose one of: {', '.join(REFERENCES)}")


def evaluate_references(
    cfg: TreadmillConfig, episodes: int = 500, seed: int = 0, names: tuple[str, ...] = REFERENCES
) -> dict[str, RolloutResult]:
    """One ``episodes``-episode rollout per reference policy, every policy on the same env seeds."""
    out: dict[str, RolloutResult] = {}
    for name in names:
        engine = TreadmillEngine(cfg, episodes, autoreset=False)
        out[name] = rollout(engine, reference_policy(name, engine, seed), seed=seed)
    return out


def best_constant(results: dict[str, RolloutResult]) -> str:
    """The name of the constant action with the highest mean return."""
    return max((n for n in results if n in CONSTANTS), key=lambda n: results[n].ci95()[0])


def summary_references(cfg: TreadmillConfig, episodes: int, seed: int) -> dict[str, tuple[float, float]]:
    """What a trained policy's summary shows beside it: random, the best constant action (named), the scripted
    driver and the full-information driver (what knowing every car is worth), each as (mean, 95 % CI half-width)
    over ``episodes`` episodes."""
    results = evaluate_references(cfg, episodes, seed, names=("random", *CONSTANTS, "scripted", "full-information"))
    best = best_constant(results)
    return {name: results[name].ci95() for name in ("random", best, "scripted", "full-information")}


def who_sees_the_threat(cfg: TreadmillConfig, steps: int = 400, envs: int = 256, seed: int = 0) -> dict[str, float]:
    """Where the information messages would need sits: over the agent-steps of the scripted driver on which an
    adversary is within the scripted driver's danger distance of an agent, the fraction on which the agent observes
    some adversary itself, only a teammate does, or nobody does. Messages can help only with "only a teammate"."""
    engine = TreadmillEngine(cfg, envs)
    obs = engine.reset(seed)
    n = cfg.n_agents
    own = team = nobody = 0
    for _ in range(steps):
        rel_x, rel_y = engine.offsets()
        danger = np.hypot(rel_x[:, :, n:], rel_y[:, :, n:]).min(axis=2) < DANGER  # [E, N]
        near, near_dist, _ = engine.nearest()
        sees = ((near >= n) & np.isfinite(near_dist)).any(axis=2)  # [E, N]: the agent observes an adversary
        anyone = sees.sum(axis=1, keepdims=True)
        own += int((danger & sees).sum())
        team += int((danger & ~sees & (anyone > 0)).sum())
        nobody += int((danger & (anyone == 0)).sum())
        obs = engine.step(scripted_actions(obs, cfg)).obs
    total = max(own + team + nobody, 1)
    return {"own": own / total, "only_teammate": team / total, "nobody": nobody / total}
