"""A demonstration start (``demonstrator``): DAgger of a planner into the Q-network, then Q-learning from there.

Why: on the charger rules no from-scratch recipe brings the own-sensor learner past ~0.8 × the planner of its
information, while the same network, trained to reproduce the planner's action, drives at ~0.97 × it and
Q-learning keeps that level (docs/treadmill.md, "Learners on the charger rules"). A learner that starts from the
planner of its information is what turns a planner's use of that information into a learned policy — as DQfD
(Hester et al. 2018) and AlphaStar start from demonstrations.

DAgger (Ross et al. 2011): in round k the teacher drives each env step with probability ``β = 0.5^k`` (all of round
0), else the student ε-greedily; the teacher labels every state visited, so the student learns what to do after its
own mistakes. After each round every run's network is trained by cross-entropy to the teacher's actions on all of
its own states so far. Each run plays its own share of the envs and learns from its own states only, so runs stay
independent. The states are the tuning episodes (``TUNING_SEED``), never the held-out ones a learner is scored on.
The env steps played here are not counted in the job's ``steps``: they are reported per run (``demo_env_steps``)
and belong in any statement of a run's budget.

MA-MeSN and MA-BoN clone through their channel as they train (straight-through bits, ``imitation_logits``): a
listener imitating a teacher that knows what its teammates see can match it only through what they say, so the
cross-entropy's gradient teaches the speakers what to say — the channel-cut twin, cloned alike, shows what that is
worth.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from convoy.algos.updater import clip_grad_norm_per_run
from convoy.config import DemonstrationFields, JobConfig
from convoy.envs import make_batched
from convoy.envs.batched import StepResult
from convoy.envs.rollout import rollout

TUNING_SEED = 1  # the episodes a student learns on; learners are scored on the held-out seed's
EPSILON = 0.05  # the student's exploration while it drives a DAgger round
BATCH = 256  # env steps (each run's) per gradient step
LR = 5e-4  # Adam's step size for the clone
CLIP = 10.0  # each run's gradient norm, as the Q-learning update's
PLANNER = "planner"  # the demonstrator that stands for the planner of the learner's information


class DemonstrationStopped(Exception):
    """A stop (SIGTERM, an orphaned learner) between DAgger rounds: the rounds are minutes each, and a learner whose
    job was stopped must not go on cloning for half an hour; nothing was checkpointed, a resumed job clones again."""


class Dagger:
    """A rollout policy over R runs' envs (run k's are ``k·E … (k+1)·E − 1``): records each running env's
    observation and the teacher's action there, and plays the teacher's action with probability ``beta`` per env
    and step, else the student's (ε-greedy)."""

    def __init__(
        self,
        teacher: Callable,
        student: Callable,
        beta: float,
        n_actions: int,
        envs: int,
        seed: int,
        epsilon: float = EPSILON,
    ) -> None:
        self.teacher, self.student, self.beta, self.n_actions = teacher, student, beta, n_actions
        self.epsilon = epsilon
        self.rng = np.random.default_rng(seed)
        self.running = np.ones(envs, bool)
        self.obs: list[tuple[np.ndarray, np.ndarray]] = []  # (observations, their envs' indices)
        self.labels: list[np.ndarray] = []

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        label = self.teacher(obs)
        self.obs.append((obs[self.running].copy(), np.flatnonzero(self.running)))
        self.labels.append(label[self.running].copy())
        if self.beta >= 1.0:
            return label
        acted = self.student(obs)
        explore = self.rng.random(size=acted.shape) < self.epsilon
        acted = np.where(explore, self.rng.integers(0, self.n_actions, acted.shape), acted)
        teach = self.rng.random(size=(len(obs), 1)) < self.beta
        return np.where(teach, label, acted)

    def after_step(self, res: StepResult) -> None:
        self.running &= ~res.done

    def per_run(self, runs: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The round's states and labels split by run."""
        obs = np.concatenate([o for o, _ in self.obs])
        envs = np.concatenate([e for _, e in self.obs])
        labels = np.concatenate(self.labels)
        run = envs // (len(self.running) // runs)
        return [obs[run == k] for k in range(runs)], [labels[run == k] for k in range(runs)]


def clone(agent: Any, obs: list[np.ndarray], labels: list[np.ndarray], epochs: int, seed: int) -> list[float]:
    """``epochs`` passes of cross-entropy between run k's Q-values (as logits) and the teacher's actions on run k's
    own states, all runs in one batched step; then target and judged networks take the clone. Each run's share of
    correct actions in the last pass."""
    runs, device = agent.runs, agent.device
    params = list(agent.online.parameters())
    opt = torch.optim.Adam(params, lr=LR)
    xs = [torch.as_tensor(o, dtype=torch.float32) for o in obs]
    ys = [torch.as_tensor(y, dtype=torch.int64) for y in labels]
    gen = torch.Generator().manual_seed(seed)
    steps = -(-max(len(x) for x in xs) // BATCH)
    correct = torch.zeros(runs)
    for _ in range(epochs):
        # each run's own states in a fresh order, repeated to the longest run's count (every run takes each step)
        order = [torch.randperm(len(x), generator=gen).repeat(-(-steps * BATCH // len(x)))[: steps * BATCH]
                 for x in xs]  # fmt: skip
        correct.zero_()
        for i in range(steps):
            idx = [o[i * BATCH : (i + 1) * BATCH] for o in order]
            x = torch.stack([xk[ik] for xk, ik in zip(xs, idx, strict=True)]).to(device)  # [R, b, N, D]
            y = torch.stack([yk[ik] for yk, ik in zip(ys, idx, strict=True)]).to(device)  # [R, b, N]
            logits = agent.imitation_logits(x)  # [R, b, N, A]
            loss = F.cross_entropy(logits.flatten(0, -2), y.flatten()) * runs  # each run's mean, summed over runs
            opt.zero_grad(set_to_none=True)
            loss.backward()
            clip_grad_norm_per_run([p.grad for p in params if p.grad is not None], CLIP)  # runs stay apart
            opt.step()
            correct += (logits.argmax(-1) == y).flatten(1).float().mean(1).cpu()
    for nets in (agent.target, agent.average):  # the clone is also what Q-learning bootstraps from and is judged by
        if nets is not None:
            nets.load_state_dict(agent.online.state_dict())
    return (correct / steps).tolist()


def teacher_for(demonstrator: str, env_params: dict[str, Any], speaks: bool = False) -> str:
    """The reference policy a ``demonstrator`` names: ``planner`` is the planner of the learner's information (the
    team planner for a learner told teammates' observations or sightings, the 16-bit one for a learner told their
    words or one that hears teammates over an open channel (``speaks``: MA-MeSN, MA-BoN; 16 bits a teammate is what
    their 2-byte messages can carry), else the private planner), so that one recipe serves every information level
    and a channel-cut twin starts from the best policy its own sensor allows."""
    if demonstrator != PLANNER:
        return demonstrator
    if env_params.get("team_observations") or env_params.get("team_sightings"):
        return "team-planner"
    return "team16-planner" if env_params.get("team_words") or speaks else "private-planner"


def job_teacher(job: JobConfig) -> str | None:
    """The reference policy ``job`` starts from (its ``demonstrator`` resolved), or None: two jobs that name it
    differently (``planner``, ``private-planner``) follow one recipe when this is the same."""
    cfg = job.algo_config()
    if not isinstance(cfg, DemonstrationFields) or not cfg.demonstrator:
        return None
    speaks = getattr(cfg, "channel_control", None) == "open"  # a communicating learner whose channel is not cut
    return teacher_for(cfg.demonstrator, job.env_params, speaks)


def demonstration_start(
    agent: Any,
    job: JobConfig,
    say: Callable[[str], None] | None = None,
    after_round: Callable[[list[dict[str, Any]]], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> list[dict[str, Any]] | None:
    """Clone the job's ``demonstrator`` into every run of ``agent`` (a fresh one) by DAgger; each run's figures
    (rounds, states, accuracy, seconds, ``demo_env_steps``, ``demo_s``), or None when the job names no
    demonstrator. ``after_round`` sees each round's per-run figures (a benchmark scores the clones there and adds to
    them); ``stop`` is asked before each round (DemonstrationStopped when it says so)."""
    teacher_name = job_teacher(job)
    if teacher_name is None:
        return None
    cfg = job.algo_config()
    assert isinstance(cfg, DemonstrationFields)
    from convoy.envs.treadmill.references import reference_policy

    runs = agent.runs
    env = make_batched(job.env, cfg.demo_episodes * runs, **job.env_params)
    device = agent.device

    def student(obs: np.ndarray) -> np.ndarray:  # greedy, as the run acts (MA-MeSN, MA-BoN: argmax messages)
        with torch.no_grad():
            x = torch.as_tensor(obs, dtype=torch.float32, device=device).reshape(runs, -1, *obs.shape[1:])
            return agent.greedy_q(x, None)[0].argmax(-1).reshape(obs.shape[:2]).cpu().numpy()

    obs: list[list[np.ndarray]] = [[] for _ in range(runs)]
    labels: list[list[np.ndarray]] = [[] for _ in range(runs)]
    figures: list[dict[str, Any]] = [{"demonstrator": teacher_name, "rounds": []} for _ in range(runs)]
    began = time.perf_counter()
    try:
        for k in range(cfg.demo_rounds):
            if stop is not None and stop():
                raise DemonstrationStopped(f"stopped before demonstration round {k + 1}/{cfg.demo_rounds}")
            start = time.perf_counter()
            teacher = reference_policy(teacher_name, env)
            policy = Dagger(teacher, student, 0.5**k, max(env.spec.n_actions), env.num_envs, seed=job.seed * 1000 + k)
            rollout(env, policy, seed=TUNING_SEED * 100_000 + k, after_step=policy.after_step)
            for r, (o, y) in enumerate(zip(*policy.per_run(runs), strict=True)):
                obs[r].append(o)
                labels[r].append(y)
            data = [np.concatenate(o) for o in obs], [np.concatenate(y) for y in labels]
            accuracy = clone(agent, *data, epochs=cfg.demo_epochs, seed=job.seed * 1000 + k)
            seconds = round(time.perf_counter() - start, 1)
            rows = [{"round": k, "beta": 0.5**k, "states": len(data[0][r]), "accuracy": accuracy[r],
                     "seconds": seconds} for r in range(runs)]  # fmt: skip
            if after_round is not None:
                after_round(rows)
            for r in range(runs):
                figures[r]["rounds"].append(rows[r])
            if say is not None:
                say(f"demonstration round {k + 1}/{cfg.demo_rounds} ({teacher_name}): "
                    f"{sum(len(o) for o in data[0]) // runs:,} states per run, accuracy "
                    f"{np.mean(accuracy):.3f} ({seconds:.0f} s)")  # fmt: skip
    finally:
        env.close()
    if agent.demo_margin > 0:  # DQfD's margin keeps the clone's states and labels for Q-learning
        agent.keep_demonstrations(*data)
    for r in range(runs):
        figures[r]["demo_env_steps"] = figures[r]["rounds"][-1]["states"]
        figures[r]["demo_s"] = round(time.perf_counter() - began, 1)
    return figures


DEMONSTRATION_FILE = "demonstration.json"


def start_from_demonstrations(
    agent: Any,
    job: JobConfig,
    dirs: list[Path] | list[Path | None],
    say: Callable[[str], None] | None = None,
    stop: Callable[[], bool] | None = None,
    after_round: Callable[[list[dict[str, Any]]], None] | None = None,
) -> float | None:
    """A fresh population ``agent`` of ``job`` (its runs' folders ``dirs``) cloned from the job's demonstrator, if it
    names one, each run's DAgger figures in its folder's ``demonstration.json``; the seconds it took, None when the
    job names no demonstrator (after a clone the caller checkpoints at step 0, so that a stop before the first
    checkpoint does not repeat it, and counts those seconds in each run's wall clock: they are the run's cost)."""
    figures = demonstration_start(agent, job, say, after_round=after_round, stop=stop)
    for run_figures, out in zip(figures or [], dirs, strict=False):
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            (out / DEMONSTRATION_FILE).write_text(json.dumps(run_figures, indent=1) + "\n")
    return None if figures is None else float(figures[0]["demo_s"])
