"""The actor process: steps a batch of envs with the newest weights and publishes joint-transition chunks.

One torch thread and a lower CPU priority (``runtime.actor_nice``): actors share the machine with the learner, and
when cores are short the learner, which every actor waits for, should not wait for a time slice. Between env steps
the actor swaps in the newest weights it has received (only the newest matters: ``Inbox.latest``), keeps to the
learner's flow-control budget (it waits rather than run ahead of the replay ratio), explores with its own ε (Ape-X
spread, ``runtime.epsilon_spread``) and reports env-steps/s and policy lag (learner version − acting version) as
metrics every second.
"""

from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from convoy.actors.stepping import EnvStepper
from convoy.algos.agent import make_agent
from convoy.algos.algorithm import Agent, Progress, epsilon_at
from convoy.config import JobConfig
from convoy.envs import make_batched
from convoy.protocol import keys, wire
from convoy.protocol.exitcodes import STOPPED, ParentWatch, dump_stacks_on_sigusr1
from convoy.protocol.inbox import Inbox
from convoy.protocol.session import SessionAbandoned, ZenohSettings, open_session

METRICS_EVERY_S = 1.0


def actor_epsilon(base: float, index: int, actors: int, spread: float) -> float:
    """Ape-X style: actor ``index`` of ``actors`` explores with ``base^(1 + spread·index/(actors−1))``."""
    if spread <= 0 or actors <= 1 or base <= 0:
        return base
    return float(base ** (1.0 + spread * min(index, actors - 1) / (actors - 1)))


def load_weights(algo: Agent, state: dict[str, np.ndarray]) -> None:
    """Received arrays (read-only views on the payload) into the policy networks."""
    algo.load_policy_state({k: torch.from_numpy(np.array(v)) for k, v in state.items()})


@dataclass
class ActorStats:
    env_steps: int = 0
    returns: list[float] = field(default_factory=list)
    throttled_s: float = 0.0


class Actor:
    """One actor of job ``job_id``; ``run`` until the learner's budget ends the job, a stop, or SIGTERM."""

    def __init__(
        self, job_id: str, job: JobConfig, index: int, ident: str, settings: ZenohSettings, seed: int | None = None
    ) -> None:
        self.job_id, self.job, self.index, self.ident = job_id, job, index, ident
        self.settings = settings
        self.seed = job.seed + 1000 * (index + 1) if seed is None else seed
        self.seeds = [s + self.seed - job.seed for s in job.run_seeds()]  # a population: each run's envs its own
        self.stopping = False
        self.stats = ActorStats()
        self.bad_weights = 0

    def stop(self, *_: Any) -> None:
        self.stopping = True

    def run(self) -> int:
        if self.job.runtime.actor_nice and hasattr(os, "nice"):
            os.nice(self.job.runtime.actor_nice)  # the learner first where cores are shared (see RuntimeConfig)
        torch.set_num_threads(1)
        torch.manual_seed(self.seed)
        watch = ParentWatch()
        try:
            session = open_session(self.settings, give_up=lambda: self.stopping or watch.orphaned())
        except SessionAbandoned:
            return STOPPED
        try:
            weights_in, budget_in, stop_in = Inbox({"weights"}, 4), Inbox({"budget"}, 16), Inbox({"command"}, 4)
            self._declared = [  # kept referenced: an undeclared token or subscriber would vanish
                session.liveliness().declare_token(keys.alive(self.job_id, "actor", self.ident)),
                session.declare_subscriber(keys.weights(self.job_id), weights_in),
                session.declare_subscriber(keys.ctl(self.job_id, "budget"), budget_in),
                session.declare_subscriber(keys.ctl(self.job_id, "stop"), stop_in),
            ]
            import zenoh

            block = zenoh.CongestionControl.BLOCK
            pub = session.declare_publisher(keys.exp(self.job_id, self.ident), congestion_control=block)
            metrics_pub = session.declare_publisher(keys.metrics(self.job_id, "actor", self.ident))
            return self._loop(weights_in, budget_in, stop_in, pub, metrics_pub, watch)
        finally:
            session.close()

    def _loop(
        self, weights_in: Inbox, budget_in: Inbox, stop_in: Inbox, pub: Any, metrics_pub: Any, watch: ParentWatch
    ) -> int:
        job, rt = self.job, self.job.runtime
        runs = job.runs
        env = make_batched(job.env, job.num_envs * (runs or 1), **job.env_params)
        # the actor's own seeds for exploration too (make_agent seeds the ε-greedy generators with the job's)
        own = {"seed": self.seed, "seeds": self.seeds if runs else []}
        algo = make_agent(job.model_copy(update=own), env.spec, device=rt.actor_device)
        cfg = job.algo_config()
        t_len = rt.chunk_len(algo.chunk_len)
        version = -1
        budget: wire.Message | None = None
        sent_since_budget = 0
        seq = 0
        b = job.num_envs  # env steps of one run per env step (the budget counts each run's steps)
        try:
            stepper = EnvStepper(env, algo, self.seed)
            chunk_returns: list[float] = []
            chunk_runs: list[int] = []
            t_metrics = time.perf_counter()
            steps_at_metrics = 0
            while not self.stopping:
                if watch.orphaned():
                    break
                if stop_in.drain():
                    return 0
                newest = weights_in.latest()
                if newest is not None and newest.body["version"] != version:  # a restarted learner may go back
                    try:
                        load_weights(algo, newest.body["state"])
                        version = newest.body["version"]
                    except (RuntimeError, KeyError, ValueError, TypeError):  # well-formed, but not this job's nets
                        self.bad_weights += 1
                for msg in budget_in.drain():
                    budget, sent_since_budget = msg, 0
                if version < 0 or budget is None:  # no weights yet: the learner is starting
                    time.sleep(0.01)
                    continue
                allowed, ingested = budget.body["allowed_steps"], budget.body["ingested_steps"]
                if ingested >= job.steps:
                    return 0  # the learner has all the data the job asked for
                if stepper.chunk_steps == 0 and ingested + sent_since_budget + t_len * b > allowed:
                    t0 = time.perf_counter()
                    msg = budget_in.get(timeout=0.05)
                    if msg is not None:
                        budget, sent_since_budget = msg, 0
                    self.stats.throttled_s += time.perf_counter() - t0
                    continue
                algo.progress = Progress(
                    ingested, stepper.episodes, job.steps, training=True
                )  # schedules, fingerprints
                eps = actor_epsilon(epsilon_at(cfg, ingested, job.steps), self.index, rt.actors, rt.epsilon_spread)
                chunk_returns.extend(stepper.step(eps))
                chunk_runs.extend(stepper.ended_runs.tolist())
                if stepper.chunk_steps >= t_len:
                    arrays = stepper.take_chunk()
                    if runs:  # [T, R, B, …] → [T, R·B, …]: the wire's chunks are [T, B, …]
                        arrays = {k: v.reshape(v.shape[0], -1, *v.shape[3:]) for k, v in arrays.items()}
                    body = wire.chunk_body(
                        arrays, self.ident, version, t_len * b, chunk_returns, chunk_runs if runs else None
                    )
                    seq += 1
                    pub.put(wire.encode("chunk", body, self.ident, seq))
                    self.stats.env_steps += t_len * env.num_envs  # every run's: the actor's throughput
                    self.stats.returns.extend(chunk_returns)
                    sent_since_budget += t_len * b
                    chunk_returns, chunk_runs = [], []
                now = time.perf_counter()
                if now - t_metrics >= METRICS_EVERY_S:
                    lag = max(0, budget.body["version"] - version)
                    values = {
                        "env_steps": self.stats.env_steps,
                        "env_steps_per_s": (self.stats.env_steps - steps_at_metrics) / (now - t_metrics),
                        "policy_version": version,
                        "policy_lag": lag,
                        "episodes": stepper.episodes,
                        "return": float(np.mean(self.stats.returns)) if self.stats.returns else float("nan"),
                        "throttled_s": self.stats.throttled_s,
                        "epsilon": eps,
                        **_drop_counts((weights_in, budget_in, stop_in), self.bad_weights),
                    }
                    metrics_pub.put(wire.encode("metrics", wire.metrics_body("actor", self.ident, values), self.ident))
                    self.stats.returns = []
                    t_metrics, steps_at_metrics = now, self.stats.env_steps
        finally:
            env.close()
        return STOPPED  # a signal, not the end of the job: a supervisor that still wants this actor respawns it


def _drop_counts(inboxes: tuple[Inbox, ...], bad_weights: int) -> dict[str, float]:
    """What this actor dropped: garbage (undecodable, foreign, well-formed but not this job's weights) apart from
    overflow (a full queue: load, not an attack); ``dropped`` is their sum."""
    overflow = sum(inbox.dropped.get("overflow", 0) for inbox in inboxes)
    garbage = sum(inbox.drops for inbox in inboxes) - overflow + bad_weights
    return {
        "dropped": float(garbage + overflow),
        "dropped_garbage": float(garbage),
        "dropped_overflow": float(overflow),
    }


def run_actor(job_id: str, job: JobConfig, index: int, ident: str, settings: ZenohSettings, seed: int | None) -> int:
    """Process entry point (spawned by a host agent or run by ``convoy actor``); SIGTERM stops it cleanly."""
    actor = Actor(job_id, job, index, ident, settings, seed)
    dump_stacks_on_sigusr1()
    signal.signal(signal.SIGTERM, actor.stop)
    signal.signal(signal.SIGINT, actor.stop)
    return actor.run()
