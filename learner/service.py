"""The learner process: ingests actors' chunks from Zenoh, runs the job's algorithm, broadcasts weights.

* Chunks arrive on Zenoh's thread and go through an :class:`~protocol.inbox.Inbox` (decoded and validated there,
  bounded, never blocking the network); this loop drains it, checks each chunk against the job's transition schema
  (field names, dtypes and per-step shapes of a probe step) and its values (actions in range, finite floats) —
  anything else is dropped and counted per reason — and inserts it into the algorithm's replay.
* Updates follow the data (``replay_ratio``: sampled per inserted transition), exactly as in-process. When the
  learner falls behind, the ``budget`` it publishes stops growing and actors wait: the samples-per-insert ratio
  holds and nothing grows without bound (replay capacity is fixed, the inbox is bounded). The budget goes out as
  soon as a chunk is taken in, *before* that chunk's updates: an actor waiting for credit resumes while the learner
  updates, instead of one update (milliseconds) later. Otherwise it is repeated every ``BUDGET_EVERY_S`` (actors that
  join, or wait, hear it).
* Weights (version = update count) go out every ``weights_every`` updates and at least every second — every 0.1 s
  while no chunk comes in (at start, actors that subscribed after a broadcast are waiting for their first weights),
  so a new or respawned actor gets them at once. Checkpoints are atomic; a restarted learner resumes from the last
  one (update counter, optimizer, ε schedule, metric history cut at that step) and its actors carry on.
"""

from __future__ import annotations

import collections
import logging
import signal
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from convoy.actors.stepping import EnvStepper
from convoy.algos.agent import make_agent
from convoy.algos.algorithm import Agent
from convoy.algos.checkpoint import REPLAY_FILE
from convoy.config import DemonstrationFields, JobConfig
from convoy.envs import make_batched
from convoy.learner.imitation import DemonstrationStopped, start_from_demonstrations
from convoy.learner.population import PopulationCore, mean_row
from convoy.learner.resume import restore
from convoy.learner.runtime import configure_learner
from convoy.protocol import keys, wire
from convoy.protocol.exitcodes import DIVERGED, NO_DATA, STOPPED, ParentWatch, dump_stacks_on_sigusr1
from convoy.protocol.inbox import Inbox
from convoy.protocol.session import SessionAbandoned, ZenohSettings, open_session
from convoy.transition import Transition
from convoy.transition import schema as declared_schema

log = logging.getLogger(__name__)

WEIGHTS_EVERY_S = 1.0
WEIGHTS_IDLE_EVERY_S = 0.1  # while no chunk has come in for that long: an actor may be waiting for its first weights
BUDGET_EVERY_S = 0.02


def transition_schema(job: JobConfig, algo: Agent) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Field → (dtype, per-step shape after [T, B]) of the chunks this job's actors send: the declared transition
    (``convoy.transition``) for this env, and the algorithm's extras from one probe step (one env per run; a
    chunk ``[T, R, B, …]`` goes on the wire as ``[T, R·B, …]``)."""
    env = make_batched(job.env, len(job.run_seeds()), **job.env_params)
    try:
        stepper = EnvStepper(env, algo, seed=0)
        stepper.step(1.0)
        chunk = stepper.take_chunk()
    finally:
        env.close()
    extras = {k: (v.dtype.str, v.shape[3:]) for k, v in chunk.extras.items()}
    return {**declared_schema(algo.spec.n_agents, algo.spec.obs_dim), **extras}


# Finite floats beyond this are hostile or broken on every env here (rewards and observations are O(1)–O(crash
# penalty ≤ 1e6)); squared in a loss they would overflow float32.
MAX_ABS_VALUE = 1e6
# Fields that hold probabilities or relaxed bits: DIAL's behaviour probability and the messages it heard.
UNIT_INTERVAL_FIELDS = ("mu", "msg_in")


def chunk_problem(
    chunk: Transition[np.ndarray], schema: dict[str, tuple[str, tuple[int, ...]]], n_actions: tuple[int, ...]
) -> str | None:
    """Why a decoded chunk must not reach replay (a drop-counter reason), or None when it may.

    The wire layer checked that it is a chunk of arrays; this checks it is *this job's* chunk (field names, dtypes,
    per-step shapes of a probe step) and that its values are possible: actions within each agent's action count,
    finite floats of sane magnitude, probabilities in [0, 1]. One out-of-range action would index past a Q-row,
    one NaN reward would turn every later loss and weight into NaN.
    """
    arrays = chunk.columns()
    if set(arrays) != set(schema):
        return "schema"
    if not all(a.dtype.str == schema[k][0] and a.shape[2:] == schema[k][1] for k, a in arrays.items()):
        return "schema"
    action = chunk.action
    if action.size and ((action < 0).any() or (action >= np.asarray(n_actions)).any()):
        return "action-range"
    for name, a in arrays.items():
        if a.dtype.kind != "f" or not a.size:
            continue
        # the max as a Python float: compared in the array's dtype, 1e6 overflows float16
        if not np.isfinite(a).all() or float(np.abs(a).max()) > MAX_ABS_VALUE:
            return "non-finite"
        if name in UNIT_INTERVAL_FIELDS and (a.min() < 0.0 or a.max() > 1.0):
            return "out-of-range"
    return None


class Learner:
    def __init__(
        self,
        job_id: str,
        job: JobConfig,
        out_dir: str | Path,
        settings: ZenohSettings,
        on_data: Callable[[], None] | None = None,
    ) -> None:
        """``on_data``: called once the job has its steps, before the actors are told (the local supervisor's
        word, which no peer on the job's keys can forge: ``ProcessGroup.poll`` then takes the actors' exits as the
        job's end, however long the last chunk's updates, the final evaluation and the references take)."""
        self.job_id, self.job, self.out_dir, self.settings = job_id, job, Path(out_dir), settings
        self.on_data = on_data
        self.stopping = False
        self.cloned_s: float | None = None  # the seconds its start from its demonstrator took (learner/imitation.py)
        self.rejected: dict[str, int] = {}  # chunks that decoded but are not this job's or hold impossible values

    def stop(self, *_: Any) -> None:
        self.stopping = True

    def dropped_by_reason(self, inbox: Inbox) -> dict[str, int]:
        """Every chunk-key message this learner refused so far, by reason (the inbox's and its own value checks)."""
        return dict(collections.Counter(inbox.dropped) + collections.Counter(self.rejected))

    def run(self) -> int:
        job = self.job
        configure_learner(job.torch_threads)
        torch.manual_seed(job.seed)
        probe = make_batched(job.env, 1, **job.env_params)
        spec = probe.spec
        probe.close()
        algo = make_agent(job, spec)
        schema = transition_schema(job, algo)
        counters = restore(algo, job, self.out_dir)  # the last checkpoint, after a crash or a stop
        watch = ParentWatch()
        try:
            session = open_session(self.settings, give_up=lambda: self.stopping or watch.orphaned())
        except SessionAbandoned:
            return STOPPED  # nothing learnt since the last checkpoint: no session, no chunk
        # alive and reporting before a demonstration start: its DAgger rounds take minutes each, at 0 env steps
        self._keep = [session.liveliness().declare_token(keys.alive(self.job_id, "learner", "0"))]
        self.pub_metrics = session.declare_publisher(keys.metrics(self.job_id, "learner", "0"))
        try:
            if counters is None:
                algo = make_agent(job, spec)  # not what a failed restore may have half-loaded
                try:
                    self.cloned_s = start_from_demonstrations(
                        algo, job, job.member_dirs(self.out_dir), log.info,
                        stop=lambda: self.stopping or watch.orphaned(), after_round=self._publish_round,
                    )  # fmt: skip
                except DemonstrationStopped as exc:
                    log.info("%s", exc)
                    return STOPPED
            return self._serve(session, algo, schema, counters, watch)
        finally:
            session.close()

    def _publish_round(self, rows: list[dict[str, Any]]) -> None:
        """A DAgger round's figures, for the job service to show while the job is at 0 env steps."""
        cfg = self.job.algo_config()
        assert isinstance(cfg, DemonstrationFields)  # only a learner that can clone plays rounds
        values = {"demo_round": rows[0]["round"] + 1, "demo_rounds": cfg.demo_rounds,
                  "demo_accuracy": float(np.mean([r["accuracy"] for r in rows]))}  # fmt: skip
        self._report(values)

    def _serve(self, session: Any, algo: Agent, schema: dict, counters: Any, watch: ParentWatch) -> int:
        """The training loop's channels (chunks in; weights, budget out), then the loop."""
        import zenoh

        block, rt = zenoh.CongestionControl.BLOCK, self.job.runtime
        inbox = Inbox({"chunk"}, maxlen=rt.inbox)
        self._keep.append(session.declare_subscriber(keys.exp_all(self.job_id), inbox))
        self.pub_weights = session.declare_publisher(keys.weights(self.job_id), congestion_control=block)
        self.pub_budget = session.declare_publisher(keys.ctl(self.job_id, "budget"), congestion_control=block)
        if counters:  # say so: the supervisor reports it, tests check how far back the restart went
            first = counters[0]
            values = {
                "resumed_updates": algo.updates,
                "resumed_env_steps": first.get("env_steps", 0),
                "resumed_replay_rows": first["replay_rows"],
            }
            self._report(values)
        return self._loop(algo, schema, inbox, counters, watch)

    def _report(self, values: dict[str, Any]) -> None:
        """One metrics message of this learner's (a row, a resume, a DAgger round, its last words)."""
        self.pub_metrics.put(wire.encode("metrics", wire.metrics_body("learner", "0", values), "learner"))

    def _publish_weights(self, algo: Agent) -> None:
        state = {k: v.numpy() for k, v in algo.policy_state().items()}
        body = wire.weights_body(algo.updates, algo.name, state)
        self.pub_weights.put(wire.encode("weights", body, "learner"))

    def _publish_budget(self, allowed: int, ingested: int, version: int) -> None:
        """The actors' budget; one that says the job has its steps (actors leave on it) goes after ``on_data``.
        The chunk that completes the job is credited at once (``_ingest``), before its updates, the end-of-run
        curve point and checkpoint: on a loaded machine those take seconds, and the supervisor must not be left to
        judge the actors' exits meanwhile."""
        if ingested >= self.job.steps and self.on_data is not None:
            self.on_data()
        body = {"allowed_steps": int(allowed), "ingested_steps": int(ingested), "version": int(version)}
        self.pub_budget.put(wire.encode("budget", body, "learner"))

    def _core(self, algo: Agent, counters: Any) -> PopulationCore:
        """The trainer core of this job's runs (one run in ``DIR``, a population's each in ``DIR/seed-N``)."""
        job = self.job

        def make_eval_env(n: int) -> Any:
            return make_batched(job.env, n, **job.env_params)

        replay_bytes = job.runtime.replay_checkpoint_mb << 20
        say = log.info  # the final evaluation's lines (the treadmill's references) in the host's log
        dirs, replay = job.member_dirs(self.out_dir), (self.out_dir / REPLAY_FILE, replay_bytes)
        return PopulationCore(job.members(), algo, dirs, make_eval_env, counters=counters or None,
                              replay=replay, say=say)  # fmt: skip

    def _take(self, core: PopulationCore, chunk: Transition[np.ndarray], body: dict[str, Any]) -> str | None:
        """A chunk ``[T, R·B, …]`` into the core (its transitions, and from its ``body`` its steps and finished
        episodes), or why not (a drop reason)."""
        returns, runs = list(body["returns"]), len(core.jobs)
        t_len, b = chunk.obs.shape[:2]
        # each return's run; a chunk that names none is a single run's (R = 1)
        named = body.get("return_runs", [] if runs > 1 else [0] * len(returns))
        return_runs = np.asarray(named, dtype=np.int64)
        if b % runs or len(return_runs) != len(returns):
            return "schema"  # not a chunk of this population's runs
        if return_runs.size and (return_runs.min() < 0 or return_runs.max() >= runs):
            return "out-of-range"
        chunk = chunk.map(lambda v: v.reshape(t_len, runs, b // runs, *v.shape[2:]))
        episode = np.broadcast_to(core.episodes[:, None], chunk.episode.shape).copy()  # the learner's count
        core.set_progress()
        core.observe(replace(chunk, episode=episode), t_len * (b // runs))
        core.stepped(t_len * (b // runs), returns, return_runs)
        return None

    def _loop(self, algo: Agent, schema: dict, inbox: Inbox, counters: Any, watch: ParentWatch) -> int:
        """Until the job has its steps: keep actors fed with weights and budget, take in a chunk, train on it."""
        job, rt = self.job, self.job.runtime
        t_len = rt.chunk_len(algo.chunk_len)
        s = _Ingest(self._core(algo, counters), job.num_envs * t_len, rt.slack(job.num_envs, t_len), inbox)
        if self.cloned_s is not None:  # a demonstration start's clone: minutes of work a stop should not lose
            s.core.started_after(self.cloned_s)
            s.core.checkpoint()
        try:
            while not s.core.done and not self.stopping:
                if watch.orphaned():
                    self.stopping = True
                    break
                self._heartbeat(algo, s)
                msg = inbox.get(timeout=0.01)
                if msg is None:
                    if time.perf_counter() - max(s.t_chunk, s.t_start) > rt.data_timeout_s:
                        return self._give_up(s.core)
                    continue
                if self._ingest(msg, schema, algo, s):
                    self._train(s)
            if self.stopping:  # a signal before the job had its steps: not "done" (143 = killed by SIGTERM)
                s.core.checkpoint()
                return STOPPED
            # tells actors the job has its data (again: the last chunk's budget did, after telling the supervisor)
            self._publish_budget(job.steps, s.core.env_steps, algo.updates)
        finally:
            s.core.close()  # the metric files, whichever way the loop ends
        return self._finish(algo, s)

    def _heartbeat(self, algo: Agent, s: _Ingest) -> None:
        """Weights every ``weights_every`` updates and at least every second (every 0.1 s while no chunk comes),
        the budget every ``BUDGET_EVERY_S``."""
        now = time.perf_counter()
        heartbeat = WEIGHTS_IDLE_EVERY_S if now - s.t_chunk > WEIGHTS_IDLE_EVERY_S else WEIGHTS_EVERY_S
        if algo.updates - s.weights_version >= self.job.runtime.weights_every or now - s.t_weights >= heartbeat:
            self._publish_weights(algo)
            s.weights_version, s.t_weights = algo.updates, now
        if now - s.t_budget >= BUDGET_EVERY_S:
            self._publish_budget(s.allowance(), s.core.env_steps, algo.updates)
            s.t_budget = now

    def _give_up(self, core: PopulationCore) -> int:
        """No chunk for ``data_timeout_s``: keep what was learnt and say why (the job service reads the error)."""
        rt, job = self.job.runtime, self.job
        core.checkpoint()
        log.error(
            f"no chunk from any actor for {rt.data_timeout_s:g} s at {core.env_steps:,} of "
            f"{job.steps:,} env steps; are the job's actors running? (convoy jobs logs ID, or "
            "the actor hosts' logs) — raise runtime.data_timeout_s if they are slow to start"
        )
        return NO_DATA

    def _ingest(self, msg: wire.Message, schema: dict, algo: Agent, s: _Ingest) -> bool:
        """Take a chunk into the replay if it is this job's and its values are possible (else count why not), and
        credit the actors at once, before the chunk's updates."""
        chunk = wire.chunk_transitions(msg.body)
        problem = chunk_problem(chunk, schema, algo.spec.n_actions) or self._take(s.core, chunk, msg.body)
        if problem is not None:
            self.rejected[problem] = self.rejected.get(problem, 0) + 1
            return False
        self._publish_budget(s.allowance(), s.core.env_steps, algo.updates)
        s.t_budget = s.t_chunk = time.perf_counter()
        s.lags.append(algo.updates - msg.body["policy_version"])
        s.chunks += 1
        return True

    def _train(self, s: _Ingest) -> None:
        """The updates the new data owes, a metrics row when one is due, a checkpoint when one is due."""
        s.core.update()
        rows = s.core.row(lambda _: s.transport(self.dropped_by_reason(s.inbox)))  # computed only for a row
        if rows:  # the runs' mean (each run's rows are in its folder)
            row = rows[0] if len(rows) == 1 else mean_row(rows)
            self._report(row)
            s.lags = []
        s.core.maybe_checkpoint()

    def _finish(self, algo: Agent, s: _Ingest) -> int:
        """The final greedy evaluation and summary (each run's, for a population), then the last metrics row."""
        core = s.core
        dropped = self.dropped_by_reason(s.inbox)
        counts: dict[str, Any] = {"dropped": sum(dropped.values()), "dropped_by_reason": dropped}
        several = len(core.jobs) > 1  # a population's runs say their seed in their titles
        runs = core.finish(lambda j: f"{j.algo} on {j.env}" + (f", seed {j.seed} (distributed population)"
                                                               if several else " (distributed)"), **counts)  # fmt: skip
        eval_return = float(np.mean([r["eval_return"] for r in runs]))
        done = {"done": 1.0, "eval_return": eval_return, "env_steps": core.env_steps, "updates": algo.updates}
        self._report(done)
        return 0


class _Ingest:
    """What the learner's loop keeps between chunks: its core, clocks, the actors' credit and transport figures."""

    def __init__(self, core: PopulationCore, chunk_steps: int, slack: int, inbox: Inbox) -> None:
        self.core, self.chunk_steps, self.slack, self.inbox = core, chunk_steps, slack, inbox
        self.t_weights = self.t_budget = self.t_chunk = 0.0
        self.t_start = time.perf_counter()
        self.weights_version = -1
        self.lags: list[float] = []
        self.chunks = 0

    def allowance(self) -> int:
        """Steps actors may have sent: chunks still queued count as taken, so actors wait while the learner
        catches up."""
        return self.core.env_steps + max(0, self.slack - len(self.inbox) * self.chunk_steps)

    def transport(self, dropped: dict[str, int]) -> dict[str, float]:
        """The transport figures of a metrics row: policy lag, chunks taken, drops by reason."""
        return {
            "policy_lag": float(np.mean(self.lags)) if self.lags else 0.0,
            "dropped": float(sum(dropped.values())),
            "chunks": float(self.chunks),
            **{f"{wire.DROPPED_PREFIX}{r}": float(n) for r, n in dropped.items()},
        }


def run_learner(
    job_id: str, job: JobConfig, out_dir: str, settings: ZenohSettings, on_data: Callable[[], None] | None = None
) -> int:
    """Process entry point (spawned by a host agent or run by ``convoy learner``); SIGTERM checkpoints and exits."""
    learner = Learner(job_id, job, out_dir, settings, on_data)
    dump_stacks_on_sigusr1()
    signal.signal(signal.SIGTERM, learner.stop)
    signal.signal(signal.SIGINT, learner.stop)
    try:
        return learner.run()
    except FloatingPointError as exc:  # Agent.update gave up after many non-finite losses in a row
        log.error("training diverged: %s", exc)
        return DIVERGED
