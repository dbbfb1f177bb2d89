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
        """Until the learner has the job's steps or a stop comes: the newest weights in, keep to the learner's
        budget, step the envs, publish each full chunk, report metrics every second."""
        job = self.job
        env = make_batched(job.env, job.num_envs * (job.runs or 1), **job.env_params)
        try:
            s = self._start(env)
            while not self.stopping and not watch.orphaned():
                if stop_in.drain():
                    return 0
                self._take_weights(weights_in, s)
                for msg in budget_in.drain():
                    s.budget, s.sent_since_budget = msg, 0
                if s.version < 0 or s.budget is None:  # no weights yet: the learner is starting
                    time.sleep(0.01)
                    continue
                if s.budget.body["ingested_steps"] >= job.steps:
                    return 0  # the learner has all the data the job asked for
                if s.stepper.chunk_steps == 0 and self._over_budget(s):
                    self._wait_for_budget(budget_in, s)
                    continue
                self._step(s)
                if s.stepper.chunk_steps >= s.t_len:
                    self._publish_chunk(pub, s)
                self._report(metrics_pub, (weights_in, budget_in, stop_in), s)
        finally:
            env.close()
        return STOPPED  # a signal, not the end of the job: a supervisor that still wants this actor respawns it

    def _start(self, env: Any) -> _Acting:
        """The acting policy (the actor's own seeds for exploration: make_agent seeds ε-greedy with the job's)."""
        job = self.job
        own = {"seed": self.seed, "seeds": self.seeds if job.runs else []}
        algo = make_agent(job.model_copy(update=own), env.spec, device=job.runtime.actor_device)
        t_len = job.runtime.chunk_len(algo.chunk_len)
        return _Acting(algo, EnvStepper(env, algo, self.seed), t_len, job.num_envs, job.algo_config())

    def _take_weights(self, weights_in: Inbox, s: _Acting) -> None:
        """Only the newest weights matter; a restarted learner may go back a version."""
        newest = weights_in.latest()
        if newest is not None and newest.body["version"] != s.version:
            try:
                load_weights(s.algo, newest.body["state"])
                s.version = newest.body["version"]
            except (RuntimeError, KeyError, ValueError, TypeError):  # well-formed, but not this job's nets
                self.bad_weights += 1

    @staticmethod
    def _over_budget(s: _Acting) -> bool:
        """Whether a new chunk would take the actors past the steps the learner allows (checked between chunks)."""
        assert s.budget is not None
        allowed, ingested = s.budget.body["allowed_steps"], s.budget.body["ingested_steps"]
        return ingested + s.sent_since_budget + s.t_len * s.b > allowed

    def _wait_for_budget(self, budget_in: Inbox, s: _Acting) -> None:
        t0 = time.perf_counter()
        msg = budget_in.get(timeout=0.05)
        if msg is not None:
            s.budget, s.sent_since_budget = msg, 0
        self.stats.throttled_s += time.perf_counter() - t0

    def _step(self, s: _Acting) -> None:
        """One step of every env with ε-greedy actions (the actor's own ε on the job's schedule)."""
        job, rt = self.job, self.job.runtime
        assert s.budget is not None
        ingested = s.budget.body["ingested_steps"]
        s.algo.progress = Progress(ingested, s.stepper.episodes, job.steps, training=True)  # schedules, fingerprints
        s.eps = actor_epsilon(epsilon_at(s.cfg, ingested, job.steps), self.index, rt.actors, rt.epsilon_spread)
        s.chunk_returns.extend(s.stepper.step(s.eps))
        s.chunk_runs.extend(s.stepper.ended_runs.tolist())

    def _publish_chunk(self, pub: Any, s: _Acting) -> None:
        # [T, R, B, …] → [T, R·B, …]: the wire's chunks are [T, B, …]
        arrays = {k: v.reshape(v.shape[0], -1, *v.shape[3:]) for k, v in s.stepper.take_chunk().items()}
        body = wire.chunk_body(arrays, self.ident, s.version, s.t_len * s.b, s.chunk_returns, s.chunk_runs)
        s.seq += 1
        pub.put(wire.encode("chunk", body, self.ident, s.seq))
        self.stats.env_steps += s.t_len * s.stepper.env.num_envs  # every run's: the actor's throughput
        self.stats.returns.extend(s.chunk_returns)
        s.sent_since_budget += s.t_len * s.b
        s.chunk_returns, s.chunk_runs = [], []

    def _report(self, metrics_pub: Any, inboxes: tuple[Inbox, ...], s: _Acting) -> None:
        """Env-steps/s, policy lag, returns, throttling and drops, every ``METRICS_EVERY_S``."""
        now = time.perf_counter()
        if now - s.t_metrics < METRICS_EVERY_S:
            return
        assert s.budget is not None
        values = {
            "env_steps": self.stats.env_steps,
            "env_steps_per_s": (self.stats.env_steps - s.steps_at_metrics) / (now - s.t_metrics),
            "policy_version": s.version,
            "policy_lag": max(0, s.budget.body["version"] - s.version),
            "episodes": s.stepper.episodes,
            "return": float(np.mean(self.stats.returns)) if self.stats.returns else float("nan"),
            "throttled_s": self.stats.throttled_s,
            "epsilon": s.eps,
            **_drop_counts(inboxes, self.bad_weights),
        }
        metrics_pub.put(wire.encode("metrics", wire.metrics_body("actor", self.ident, values), self.ident))
        self.stats.returns = []
        s.t_metrics, s.steps_at_metrics = now, self.stats.env_steps


@dataclass
class _Acting:
    """What the actor's loop keeps between steps: its policy and stepper, the weights version it acts with, the
    learner's last budget and what was sent since, the chunk being filled, the metrics clock."""

    algo: Agent
    stepper: EnvStepper
    t_len: int  # steps per chunk
    b: int  # env steps of one run per env step (the budget counts each run's steps)
    cfg: Any  # the job's algorithm config: its ε schedule
    version: int = -1
    budget: wire.Message | None = None
    sent_since_budget: int = 0
    seq: int = 0
    eps: float = 1.0
    chunk_returns: list[float] = field(default_factory=list)
    chunk_runs: list[int] = field(default_factory=list)
    t_metrics: float = field(default_factory=time.perf_counter)
    steps_at_metrics: int = 0


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
