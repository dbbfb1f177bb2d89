"""Run whole episodes of any batched env under a policy and collect per-episode statistics.

Each of the B envs plays exactly one episode (so B = the number of episodes asked for); steps
taken by an env after its episode ended are ignored. This is what ``convoy env rollout`` and,
later, evaluation use, for every env alike.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from convoy.envs.batched import BatchedEnv, EnvSpec, StepResult
from convoy.stats import ci95_half

Policy = Callable[[np.ndarray], np.ndarray]  # obs [B, N, D] -> actions [B, N]


@dataclass
class RolloutResult:
    """Per-episode figures, one row per env."""

    returns: np.ndarray  # [episodes, N] undiscounted return of each agent
    lengths: np.ndarray  # [episodes]
    terminated: np.ndarray  # [episodes] ended by the env (a crash on the treadmill), not by truncation
    env_steps_per_s: float
    frames: list[np.ndarray]

    @property
    def mean_return(self) -> np.ndarray:
        """Each episode's return averaged over its agents."""
        return self.returns.mean(axis=1)

    def ci95(self) -> tuple[float, float]:
        """Mean of the per-episode return and the half-width of its 95 % normal confidence interval."""
        r = self.mean_return
        return float(r.mean()), ci95_half(r, single=0.0)

    @classmethod
    def joined(cls, rounds: list[RolloutResult], episodes: int) -> RolloutResult:
        """The first ``episodes`` episodes of ``rounds`` played one after another (no frames)."""
        returns, lengths, terminated = (np.concatenate([getattr(r, name) for r in rounds])[:episodes]
                                        for name in ("returns", "lengths", "terminated"))  # fmt: skip
        return cls(returns, lengths, terminated, float(np.mean([r.env_steps_per_s for r in rounds])), [])


def random_policy(spec: EnvSpec, seed: int | None = None) -> Policy:
    """Uniform actions within each agent's own action range."""
    rng = np.random.default_rng(seed)
    high = np.asarray(spec.n_actions)

    def act(obs: np.ndarray) -> np.ndarray:
        return (rng.random(obs.shape[:2]) * high).astype(np.int64)

    return act


def rollout(
    env: BatchedEnv,
    policy: Policy,
    seed: int | None = None,
    render: Callable[[], np.ndarray] | None = None,
    max_frames: int = 1000,
    after_step: Callable[[StepResult], None] | None = None,
) -> RolloutResult:
    """Play one episode in each of the env's B slots; ``render`` (if given) draws env 0 each step and
    ``after_step`` sees every step's result (a policy with memory forgets the envs whose episode ended)."""
    b, n = env.num_envs, env.spec.n_agents
    returns = np.zeros((b, n), np.float64)
    lengths = np.zeros(b, np.int64)
    terminated = np.zeros(b, bool)
    running = np.ones(b, bool)
    frames: list[np.ndarray] = []
    obs = env.reset(seed)
    if render is not None:
        frames.append(render())
    steps = 0
    start = time.perf_counter()
    while running.any():
        r = env.step(policy(obs))
        if after_step is not None:
            after_step(r)
        steps += 1
        returns[running] += r.reward[running]
        lengths[running] += 1
        terminated |= running & r.terminated
        if render is not None and running[0] and len(frames) < max_frames:
            frames.append(render())
        running &= ~r.done
        obs = r.obs
        if steps > 10 * env.spec.max_steps + 10:
            raise RuntimeError("rollout: an episode ran past 10 × max_steps; the env never ends its episodes")
    elapsed = time.perf_counter() - start
    return RolloutResult(returns, lengths, terminated, steps * b / max(elapsed, 1e-9), frames)
