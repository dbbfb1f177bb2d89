"""What runs the job service's jobs: ``JobService`` starts, watches, scales, stops and resumes them, and keeps the
store current — the ``JobControl`` that ``api.app`` drives.

How a job runs. Each job is one ``convoy host`` process (the host agent of the distributed runtime, roles learner +
actors) that roots the job's own Zenoh network (a router on loopback, its processes clients), started in its own
session (``start_new_session``) with its PID recorded in the store. The service opens one Zenoh session per job,
listening on a loopback port recorded in the store, which the host links to: through it the service hears the job's
metrics and liveliness tokens and sends it ``scale``/``stop`` commands — the same wire messages a multi-host
deployment uses. Every session of a job, the service's included, authenticates with the job's own user/password and
admits only holders of it (a usrpwd dictionary, 0600, in the job's directory; the password reaches the host through
its environment, never a file it writes): a process without the credential cannot connect to the job, so it cannot
publish a command or data that bypasses the API's token. The job's traffic never passes through the service: killing
the service leaves the job running; a restarted service reopens the job's session on the same port, the host links
to it again by itself, the service finds the PID alive and *reattaches*, back-filling the metric rows it missed from
the job's ``metrics.jsonl``. A job whose processes died meanwhile is failed with the reason and queued again, so it
resumes from its last checkpoint: no job is forgotten.

Scheduling: a job needs ``actors + 2`` processes (learner, host agent, actors); jobs start in submission order
while the ``max_processes`` budget allows, the others wait with a visible queue position.

Packed sweeps. A sweep's jobs that differ only in seed run as *population jobs* (``api/sweeps.packs``: at most the
sweep's ``pack`` seeds each, fewer where the service's resource limits, which count every run, allow fewer): one
host, one learner updating every seed at once. Each seed stays a job of its own — its record, state, metrics,
folder (the population's ``seed-N``), checkpoints and summary — so the sweep's view, summary, CLI and dashboard
are those of an unpacked sweep. The population job alone is scheduled and watched; its seeds move with it (their
``progress.packed_in`` names it), take their metric rows from their own ``metrics.jsonl`` whenever the
population's row arrives, and stop, resume and scale through it.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from convoy.api.lifecycle import ACTIVE_STATES, InvalidTransition, JobRecord, JobState, StoreError, SweepRecord
from convoy.api.models import EvalRequest, SweepSubmit
from convoy.api.remedy import Fix, Step
from convoy.api.sweeps import expand, group_name, packs, population
from convoy.config import ConfigError, JobConfig, ResourceLimits, job_config
from convoy.learner.metrics import read_rows
from convoy.protocol import keys, reports, wire
from convoy.protocol.inbox import Inbox
from convoy.protocol.reports import REPORTS_FILE, Report, ReportTail
from convoy.protocol.session import (
    ZenohSettings,
    free_port,
    loopback,
    open_session,
    read_credentials,
    write_credentials,
)
from convoy.services import evaluations
from convoy.services.jobrunner import AliveSet, MetricReports
from convoy.services.procs import pid_alive
from convoy.services.store import JobStore

PROGRESS_KEYS = ("env_steps", "updates", "return", "eval_return", "loss", "env_steps_per_s", "updates_per_s",
                 "policy_lag")  # fmt: skip
STOP_GRACE_S = 20.0
CREDENTIALS_FILE = "zenoh-credentials"  # in the job's directory: its usrpwd dictionary (0600)


log = logging.getLogger(__name__)
SAID = ("crashed", "respawned", "backoff", "failed")  # the host's process events the service's log repeats


def say(line: str) -> None:
    """One line of the service's own log: job submissions and every state change, with the reason."""
    log.info(line)


class Tracked:
    """A job this service is watching: its host process, Zenoh subscriptions and what it last reported."""

    def __init__(self, rec: JobRecord, session: Any, proc: subprocess.Popen | None) -> None:
        self.pid: int = int(proc.pid if proc is not None else rec.progress.get("host_pid", 0))
        self.proc, self.session = proc, session
        self.alive = AliveSet(session, rec.id)
        self.inbox = Inbox({"metrics"}, maxlen=4096)
        self.sub = session.declare_subscriber(keys.metrics_all(rec.id), self.inbox)
        self.stop_asked: float | None = None
        # the actor count the host was told (its --actors at start; unknown after a reattach): a PATCH while the
        # host cannot hear commands yet (starting, or linking back to a restarted service) is told once it can
        self.told_actors: int | None = rec.actors if proc is not None else None
        self.ckpt_mtime: dict[str, float] = {}  # per job: a population's are its seeds'
        self.reports = MetricReports()
        self.events = ReportTail(Path(rec.out_dir or "") / REPORTS_FILE)  # its processes' reports from now on

    def process_events(self) -> list[str]:
        """The host's new crash, respawn, back-off and failure events (``crashed h-ID.actor-3 exit code -9``)."""
        return [f"{r.kind} {r.source} {r.detail}".rstrip() for r in self.events.new() if r.kind in SAID]

    def exited(self) -> int | None:
        """The host's exit code once it has exited (−1 when it was not our child), else None."""
        if self.proc is not None:
            return self.proc.poll()
        return None if pid_alive(self.pid) else -1

    def close(self) -> None:
        self.sub.undeclare()
        self.alive.close()
        self.session.close()


class JobService:
    """Runs the jobs of one store on this machine (``convoy serve``)."""

    def __init__(
        self,
        data_dir: str | Path,
        max_processes: int = 8,
        python: str = sys.executable,
        limits: ResourceLimits | None = None,
    ) -> None:
        self.data_dir = Path(data_dir)
        self.limits = limits or ResourceLimits()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.store = JobStore(self.data_dir / "jobs.sqlite")
        self.max_processes, self.python = max_processes, python
        self.tracked: dict[str, Tracked] = {}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._reconcile()
        self._thread = threading.Thread(target=self._loop, name="jobservice", daemon=True)
        self._thread.start()

    # --- JobControl ----------------------------------------------------------------------------------------------
    def submit(self, job: JobConfig, actors: int, name: str | None) -> JobRecord:
        self.limits.check(job, "convoy serve")
        check_job_files(job)
        need = actors + 2
        if need > self.max_processes:
            raise ConfigError(
                "actors",
                f"{actors} actors need {need} processes; this service runs at most {self.max_processes} "
                "(convoy serve --max-processes)",
            )
        job_id = f"{name or job.algo}-{secrets.token_hex(3)}"
        out = self.data_dir / "jobs" / job_id
        rec = self.store.create(job_id, job.model_dump(mode="json"), actors, out_dir=str(out))
        what = f"{job.algo} on {job.env}, {job.steps:,} env steps, {actors} actor{'' if actors == 1 else 's'}"
        say(f"job {job_id}: submitted ({what}), queued")
        return rec

    def submit_sweep(self, spec: SweepSubmit) -> SweepRecord:
        """Every job of the grid, queued at once in one transaction (so a restart finds all or none of them)."""
        jobs = expand(spec)
        for job in jobs:
            self.limits.check(job.config, "convoy serve")
        checked: set[str] = set()
        for job in jobs:  # each file once: a grid's jobs mostly name the same ones
            key = json.dumps([job.config.algo, job.config.env, job.config.env_params, job.config.algo_params,
                              job.config.hierarchical, job.config.loggers], sort_keys=True, default=str)  # fmt: skip
            if key not in checked:
                checked.add(key)
                check_job_files(job.config)
        if spec.actors + 2 > self.max_processes:
            raise ConfigError("actors", f"{spec.actors} actors need {spec.actors + 2} processes; this service runs "
                              f"at most {self.max_processes} (convoy serve --max-processes)")  # fmt: skip
        sweep_id = f"{spec.name}-{secrets.token_hex(3)}"
        ids = [f"{sweep_id}-{i:03d}" for i in range(len(jobs))]
        outs = [self.data_dir / "jobs" / job_id for job_id in ids]
        progress: dict[str, dict[str, Any]] = {}
        populations: list[tuple[str, dict[str, Any], int, str]] = []
        for pack in (p for p in packs(jobs, spec.pack, self._fits) if len(p) > 1):
            pop_id, config = f"{sweep_id}-pop{len(populations):02d}", population([jobs[i].config for i in pack])
            pop_out = self.data_dir / "jobs" / pop_id
            populations.append((pop_id, config.model_dump(mode="json"), spec.actors, str(pop_out)))
            progress[pop_id] = {"members": [ids[i] for i in pack]}
            for i, member_out in zip(pack, config.member_dirs(pop_out), strict=True):
                outs[i], progress[ids[i]] = member_out, {"packed_in": pop_id}
        rows = [(job_id, job.config.model_dump(mode="json"), spec.actors, str(out), job.point)
                for job_id, job, out in zip(ids, jobs, outs, strict=True)]  # fmt: skip
        sweep = self.store.create_sweep(sweep_id, spec.model_dump(mode="json"), rows, progress, populations)
        groups = len({group_name(job.point) for job in jobs})
        packed = f", their seeds in {len(populations)} population jobs" if populations else ""
        say(f"sweep {sweep_id}: submitted ({len(jobs)} jobs in {groups} group{'' if groups == 1 else 's'}"
            f"{packed}), queued")  # fmt: skip
        return sweep

    def _fits(self, job: JobConfig) -> bool:
        try:
            self.limits.check(job, "convoy serve")
        except ConfigError:
            return False
        return True

    def _runner(self, job_id: str) -> str:
        """The job whose processes run ``job_id``: its population job when it is a packed seed of a sweep."""
        return str(self.store.get(job_id).progress.get("packed_in") or job_id)

    def _members(self, rec: JobRecord) -> list[str]:
        """The packed jobs a population job runs (that still exist)."""
        return [m for m in rec.progress.get("members", []) if self.store.exists(m)]

    def stop_sweep(self, sweep_id: str) -> SweepRecord:
        """Stop every job of the sweep that is still queued or running (each checkpoints first)."""
        sweep = self.store.sweep(sweep_id)
        for member in sweep.jobs:
            if self.store.exists(member["id"]) and self.store.get(member["id"]).state in ACTIVE_STATES - {
                JobState.stopping
            }:
                self.stop(member["id"])
        return sweep

    def resume_sweep(self, sweep_id: str) -> SweepRecord:
        """Queue again every stopped or failed job of the sweep (each from its last checkpoint)."""
        sweep = self.store.sweep(sweep_id)
        for member in sweep.jobs:
            if self.store.exists(member["id"]) and self.store.get(member["id"]).state in (
                JobState.stopped, JobState.failed
            ):  # fmt: skip
                self.resume(member["id"], None, None)
        return sweep

    def delete_sweep(self, sweep_id: str) -> None:
        """Delete the sweep with every job of it (processes, history, files)."""
        sweep = self.store.sweep(sweep_id)
        for member in sweep.jobs:
            if self.store.exists(member["id"]):
                self.delete(self._runner(member["id"]))  # a population job deletes its packed seeds with it
        self.store.delete_sweep(sweep_id)

    def scale(self, job_id: str, actors: int) -> JobRecord:
        with self._lock:
            rec = self.store.get(job_id)
            if rec.state in ACTIVE_STATES and self._runner(job_id) != job_id:  # a packed seed: its population
                self.scale(self._runner(job_id), actors)
                return self.store.get(job_id)
            if rec.state not in ACTIVE_STATES:  # named as the caller named it (resuming a seed resumes its population)
                resume = Step("POST /jobs/{id}/resume", job_id, {"actors": actors})
                raise StoreError(f"job {job_id!r} is {rec.state}", Fix("scale it by resuming: {}", resume))
            if actors + 2 > self.max_processes:
                raise ConfigError("actors", f"{actors} actors need {actors + 2} processes; the limit is "
                                  f"{self.max_processes} (convoy serve --max-processes)")  # fmt: skip
            rec = self.store.update(job_id, actors=actors)
            say(f"job {job_id}: scaled to {actors} actor{'' if actors == 1 else 's'}")
            for member in self._members(rec):
                self.store.update(member, actors=actors)
            if job_id in self.tracked:
                self._tell_actors(rec, self.tracked[job_id])
            return rec

    def stop(self, job_id: str) -> JobRecord:
        with self._lock:
            if self._runner(job_id) != job_id:  # a packed seed stops with its population
                self.stop(self._runner(job_id))
                return self.store.get(job_id)
            rec = self.store.get(job_id)
            if rec.state == JobState.queued:
                return self._move(job_id, JobState.stopped, "stopped before it started")
            starting = rec.state == JobState.starting
            rec = self._move(job_id, JobState.stopping, "stop requested")
            if job_id in self.tracked:
                tracked = self.tracked[job_id]
                tracked.stop_asked = time.monotonic()
                self._command(job_id, "stop", {})
                if starting:  # its host may not hear commands yet: SIGTERM stops it the same way (checkpoint first)
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(tracked.pid, signal.SIGTERM)
            return rec

    def resume(self, job_id: str, actors: int | None, steps: int | None) -> JobRecord:
        with self._lock:
            if self._runner(job_id) != job_id:  # a packed seed resumes with its population
                self.resume(self._runner(job_id), actors, steps)
                return self.store.get(job_id)
            rec = self.store.get(job_id)
            if rec.state in ACTIVE_STATES:
                raise StoreError(f"job {job_id!r} is {rec.state}; only a stopped, failed or completed job resumes")
            lost = [m for m in rec.progress.get("members", []) if not self.store.exists(m)]
            if lost:
                raise StoreError(f"population job {job_id!r} cannot resume: its seed jobs {lost} were deleted and "
                                 "its runs resume together; submit the remaining seeds again")  # fmt: skip
            n = actors or rec.actors
            if n + 2 > self.max_processes:
                raise ConfigError("actors", f"{n} actors need {n + 2} processes; the limit is {self.max_processes}")
            for each in [job_id, *self._members(rec)]:
                config = dict(self.store.get(each).config)
                if steps is not None:
                    config = job_config(**{**config, "steps": steps}).model_dump(mode="json")
                self.store.update(each, actors=n, config=config)
            return self._move(job_id, JobState.queued, "resume requested")

    def delete(self, job_id: str) -> None:
        with self._lock:
            rec = self.store.get(job_id)
            runner = self._runner(job_id)
            if runner != job_id and self.store.exists(runner) and self.store.get(runner).state in ACTIVE_STATES:
                raise StoreError(f"job {job_id!r} is one seed of population job {runner!r}, which is "
                                 f"{self.store.get(runner).state}: stop {runner!r} first, or delete the whole "
                                 "sweep")  # fmt: skip
            tracked = self.tracked.pop(job_id, None)
            if tracked is not None:
                self._kill(tracked)
                tracked.close()
            for member in self._members(rec):
                self.store.delete(member)
            self.store.delete(job_id)
            say(f"job {job_id}: deleted ({rec.state} before; its processes, history and files)")
        if rec.out_dir and Path(rec.out_dir).is_dir():
            shutil.rmtree(rec.out_dir, ignore_errors=True)

    def actors_alive(self, job_id: str) -> int:
        tracked = self.tracked.get(job_id)
        return tracked.alive.count("actor") if tracked is not None else 0

    def checkpoints(self, job_id: str) -> list[dict[str, Any]]:
        out = self._out(job_id)
        files = sorted(out.glob("*.pt")) if out.is_dir() else []
        stats = [(f, f.stat()) for f in files]
        return [
            {"name": f.name, "bytes": st.st_size, "modified": st.st_mtime, "url": f"checkpoints/{f.name}"}
            for f, st in stats
        ]

    def checkpoint_file(self, job_id: str, name: str) -> Path:
        path = self._out(job_id) / name
        if not name.endswith(".pt") or not path.is_file():
            raise FileNotFoundError(f"job {job_id!r} has no checkpoint {name!r}")  # the API's fix lists them
        return path

    def evaluate(self, job_id: str, request: EvalRequest) -> dict[str, Any]:
        """Start ``convoy eval`` of the job's checkpoint as its own process (``services/evaluations.py``)."""
        with self._lock:
            running = sum(
                e["state"] == "running"
                for rec in self.store.list()
                for e in evaluations.listing(self._out(rec.id), rec.id)
            )
            started = evaluations.start(self._out(job_id), job_id, request, running, self.python)
        say(f"job {job_id}: evaluation {started['id']} started ({request.episodes} episodes, {request.messages})")
        return started

    def evaluations(self, job_id: str) -> list[dict[str, Any]]:
        return evaluations.listing(self._out(job_id), job_id)

    def evaluation(self, job_id: str, eval_id: str) -> dict[str, Any]:
        return evaluations.find(self._out(job_id), job_id, eval_id)

    def close(self) -> None:
        """Stop watching (the jobs keep running; a restarted service reattaches them)."""
        self._stop.set()
        self._thread.join(timeout=5)
        with self._lock:
            for tracked in self.tracked.values():
                tracked.close()
            self.tracked.clear()
        self.store.close()

    # --- the watch loop ------------------------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.wait(0.2):
            try:
                with self._lock:
                    self._tick()
            except Exception as exc:  # never let one bad tick kill the watcher; say why
                log.exception("jobservice: %s: %s", type(exc).__name__, exc)

    def _tick(self) -> None:
        evaluations.reap()
        for job_id, tracked in list(self.tracked.items()):
            if not self.store.exists(job_id):
                continue
            self._ingest(job_id, tracked)
            for event in tracked.process_events():
                say(f"job {job_id}: {event}")
            rec = self.store.get(job_id)
            if rec.state == JobState.starting and tracked.alive.count("learner"):
                rec = self._move(job_id, JobState.running, "learner alive")
            self._tell_actors(rec, tracked)
            self._note_checkpoint(rec, tracked)
            code = tracked.exited()
            if code is not None:
                self._finished(rec, tracked, code)
            elif (
                rec.state == JobState.stopping
                and tracked.stop_asked is not None
                and time.monotonic() - tracked.stop_asked > STOP_GRACE_S
            ):
                self._kill(tracked)
        self._schedule()

    def _ingest(self, job_id: str, tracked: Tracked) -> None:
        rows = []
        progress: dict[str, Any] = {}
        messages = tracked.inbox.drain()
        live = tracked.alive.ids("actor") if messages else set()
        for msg in messages:
            kind, values = tracked.reports.take(msg, live), msg.body["values"]
            if kind == "resumed":
                self.store.cut_metrics(job_id, int(values["resumed_env_steps"]))
                say(f"job {job_id}: its learner resumed from its checkpoint at {int(values['resumed_env_steps']):,} "
                    f"env steps ({int(values.get('resumed_replay_rows', 0)):,} replay rows)")  # fmt: skip
            elif kind == "demonstration":
                demo = {"demo_round": int(values["demo_round"]), "demo_rounds": int(values["demo_rounds"])}
                progress.update(demo)
                for member in self._members(self.store.get(job_id)):  # the seeds a sweep shows: where their run is
                    self.store.update(member, progress=demo)
                accuracy = values.get("demo_accuracy")
                said = f", clone accuracy {accuracy:.3f}" if isinstance(accuracy, float) and 0 <= accuracy <= 1 else ""
                say(f"job {job_id}: demonstration round {demo['demo_round']}/{demo['demo_rounds']}{said}")
            elif kind == "row":
                row = {**values, "env_steps": int(values["env_steps"]), "actors_alive": tracked.alive.count("actor")}
                rows.append(row)
                progress.update({k: row[k] for k in PROGRESS_KEYS if k in row})
        if messages:
            progress["dropped"] = tracked.reports.dropped("service", tracked.inbox.dropped)
        if rows:
            last = self.store.last_step(job_id) or 0
            every = int(self.store.get(job_id).config.get("log_every", 0)) or 1
            if rows[0]["env_steps"] > last + every:  # rows went by unheard (service down, reconnecting): the file
                self._backfill(job_id)
                last = self.store.last_step(job_id) or 0
            rows = [r for r in rows if r["env_steps"] > last]
        if rows:
            self.store.append_metrics(job_id, rows)
            for member in self._members(self.store.get(job_id)):  # each seed's rows: from its own metrics file
                self._backfill(member)
        if progress:
            self.store.update(job_id, progress=progress)

    def _note_checkpoint(self, rec: JobRecord, tracked: Tracked) -> None:
        for job_id in self._members(rec) or [rec.id]:  # a population's checkpoints are its seeds'
            path = self._out(job_id) / "checkpoint.pt"
            try:
                mtime = path.stat().st_mtime
            except OSError:
                continue
            if mtime != tracked.ckpt_mtime.get(job_id):
                tracked.ckpt_mtime[job_id] = mtime
                self.store.update(job_id, last_checkpoint=str(path))

    def _move(self, job_id: str, to: JobState, reason: str) -> JobRecord:
        """A state change in the store, and one line of it in the service's log; a population job's packed seeds
        move with it."""
        before = self.store.get(job_id).state
        rec = self.store.transition(job_id, to, reason)
        say(f"job {job_id}: {before} → {to} ({reason})")
        for member in self._members(rec):
            with contextlib.suppress(InvalidTransition):
                self.store.transition(member, to, f"{reason} (population job {job_id})")
        return rec

    def _finished(self, rec: JobRecord, tracked: Tracked, code: int) -> None:
        self._ingest(rec.id, tracked)
        runs = self._members(rec) or [rec.id]  # a population job's runs are its packed seeds
        for job_id in runs:
            self._backfill(job_id)
        summaries = [self._out(job_id) / "summary.json" for job_id in runs]
        started = float(rec.progress.get("started_at", 0.0))
        done = all(p.is_file() and p.stat().st_mtime >= started for p in summaries)
        if rec.state == JobState.stopping:
            self._move(rec.id, JobState.stopped, f"host exited ({code})")
        elif done and code in (0, -1):
            results = [json.loads(p.read_text()) for p in summaries]
            for job_id, result in zip(runs, results, strict=True):
                self.store.update(job_id, progress=final_progress(result))
            if runs != [rec.id]:  # the population's own record: its seeds' mean
                mean = {k: float(np.mean([r[k] for r in results])) for k in ("eval_return", "env_steps", "updates")}
                self.store.update(rec.id, progress=mean)
            self._move(rec.id, JobState.completed, "the learner has all its steps")
        else:
            self._move(rec.id, JobState.failed, f"host exited with code {code}: {self._log_tail(rec.id)}")
        tracked.close()
        self.tracked.pop(rec.id, None)

    def _schedule(self) -> None:
        used = sum(self.store.get(j).actors + 2 for j in self.tracked if self.store.exists(j))
        for rec in self.store.list(JobState.queued):
            if rec.progress.get("packed_in"):
                continue  # its population job runs it
            if used + rec.actors + 2 > self.max_processes:
                break  # first come, first served: later jobs wait behind this one
            self._start(rec)
            used += rec.actors + 2

    def _start(self, rec: JobRecord) -> None:
        out = self._out(rec.id)
        out.mkdir(parents=True, exist_ok=True)
        config = dict(rec.config)
        runtime = dict(config.get("runtime", {}))
        # The host roots its job's own network: a Zenoh router admitting only holders of the job's credential,
        # its learner and actors its clients. That router also links to the service's router for this job, which
        # receives only what the service subscribes to (metrics, liveliness): the job's chunks never pass through
        # the service, so when the API process dies the job keeps training, and the link returns with the API.
        credentials = out / CREDENTIALS_FILE
        password = write_credentials(credentials, rec.id)
        endpoint = loopback(free_port())
        session = self._job_session(rec.id, endpoint)
        zenoh = {**runtime.get("zenoh", {}), "mode": "peer", "connect": [endpoint], "user": rec.id,
                 "credentials_file": str(credentials)}  # fmt: skip
        zenoh.pop("password", None)
        runtime.update(actors=rec.actors, zenoh=zenoh)
        config["runtime"] = runtime
        (out / "job.json").write_text(json.dumps(config, indent=2))
        cmd = [
            self.python, "-m", "convoy.cli", "host", "--job-id", rec.id, "--name", host_name(rec.id),
            "--roles", "learner,actor", "--actors", str(rec.actors), "--out", str(out),
            "--config", str(out / "job.json"),
        ]  # fmt: skip
        log = open(out / "host.log", "ab")  # noqa: SIM115 (the child owns it; closed below, the fd is inherited)
        try:
            env = {**os.environ, "CONVOY_ZENOH_PASSWORD": password.get_secret_value()}
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=env)
        except BaseException:
            session.close()
            raise
        finally:
            log.close()
        started = time.time()
        self.store.update(rec.id, progress={"host_pid": proc.pid, "started_at": started, "zenoh": endpoint})
        for member in self._members(rec):
            self.store.update(member, progress={"started_at": started})
        rec = self._move(rec.id, JobState.starting, f"host pid {proc.pid}")
        self.tracked[rec.id] = Tracked(rec, session, proc)

    def _job_session(self, job_id: str, endpoint: str) -> Any:
        """The service's session for one job: on ``endpoint``, authenticated as the job and admitting only it."""
        credentials = self._out(job_id) / CREDENTIALS_FILE
        user, password = read_credentials(credentials)
        settings = ZenohSettings(
            mode="router", listen=(endpoint,), user=user, password=password, credentials_file=str(credentials)
        )
        return open_session(settings)

    def _reconcile(self) -> None:
        """After a (re)start: reattach jobs whose host still runs, fail and requeue those whose host is gone."""
        for rec in self.store.list():
            if rec.state not in (JobState.starting, JobState.running, JobState.stopping):
                continue
            if rec.progress.get("packed_in"):
                continue  # its population job's reconciliation moves it
            pid = int(rec.progress.get("host_pid", 0))
            if pid_alive(pid):
                self._backfill(rec.id)
                self.tracked[rec.id] = Tracked(rec, self._job_session(rec.id, rec.progress["zenoh"]), None)
                if rec.state == JobState.stopping:
                    self.tracked[rec.id].stop_asked = time.monotonic()
            elif rec.state == JobState.stopping:
                self._move(rec.id, JobState.stopped, "its processes ended while the service was down")
            else:
                self._move(rec.id, JobState.failed, "its processes ended while the service was down")
                self._move(rec.id, JobState.queued, "resuming from its last checkpoint")

    def _backfill(self, job_id: str) -> None:
        """Rows the learner wrote while nobody listened (service down, messages lost) from its metrics.jsonl."""
        last = self.store.last_step(job_id) or 0
        rows = [r for r in read_rows(self._out(job_id)) if int(r.get("env_steps", 0)) > last]
        if rows:
            self.store.append_metrics(job_id, [{**r, "env_steps": int(r["env_steps"])} for r in rows])
            self.store.update(job_id, progress={k: rows[-1][k] for k in PROGRESS_KEYS if k in rows[-1]})

    # --- helpers -------------------------------------------------------------------------------------------------
    def _out(self, job_id: str) -> Path:
        rec = self.store.get(job_id)
        return Path(rec.out_dir) if rec.out_dir else self.data_dir / "jobs" / job_id

    def _tell_actors(self, rec: JobRecord, tracked: Tracked) -> None:
        """Tell the job's host the actor count it should run, once it can hear it and unless it was told: its
        liveliness token is declared after its command subscriber, so a host whose token is seen hears commands. A
        scale sent before then (the host still starting, or not yet linked back to a restarted service) would be
        lost, and the job would run on with its old count."""
        if rec.state not in (JobState.starting, JobState.running) or tracked.told_actors == rec.actors:
            return
        if host_name(rec.id) in tracked.alive.ids("host"):
            self._command(rec.id, "scale", {"actors": rec.actors})
            tracked.told_actors = rec.actors

    def _command(self, job_id: str, op: str, args: dict[str, Any]) -> None:
        session = self.tracked[job_id].session
        session.put(keys.host(host_name(job_id), "cmd"), wire.encode("command", {"op": op, "args": args}, "api"))

    def _kill(self, tracked: Tracked) -> None:
        """SIGTERM the host's process group (it stops its children and checkpoints), SIGKILL if it lingers."""
        for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
            try:
                os.killpg(tracked.pid, sig)
            except (ProcessLookupError, PermissionError):
                return
            t_end = time.monotonic() + wait
            while time.monotonic() < t_end:
                if tracked.exited() is not None:
                    return
                time.sleep(0.1)

    def logs(self, job_id: str, lines: int) -> list[str]:
        """The last ``lines`` lines of the job's process output (``host.log``: starts, crashes, tracebacks; a
        packed seed's are its population's)."""
        path = self._out(self._runner(job_id)) / "host.log"
        try:
            with path.open(errors="replace") as fh:
                return [ln.rstrip("\n") for ln in collections.deque(fh, maxlen=lines)]
        except OSError:
            return []

    def _log_tail(self, job_id: str) -> str:
        return failure_summary(job_id, reports.read(self._out(self._runner(job_id)) / REPORTS_FILE, last=400))


def check_job_files(job: JobConfig) -> None:
    """What a job names outside its config, tried where its processes will run before it is queued: the files it
    reads (a CoDBC teacher checkpoint: missing, unreadable or hostile) and its trackers. A ConfigError naming the
    field (422 at ``POST /jobs``), not a job whose processes refuse it later."""
    from convoy.algos.inputs import check_inputs
    from convoy.learner.trackers import check_loggers

    check_inputs(job)
    check_loggers(job.loggers)


def final_progress(summary: dict[str, Any]) -> dict[str, Any]:
    """What a finished run's ``summary.json`` adds to its job's progress: the headline figures and ``final``."""
    keep: dict[str, Any] = {k: summary[k] for k in ("eval_return", "eval_ci95", "env_steps", "updates") if k in summary}
    final = ("eval_return", "eval_ci95", "random_return", "references", "best_eval_return", "best_eval_step", "wall_s",
             "clone_s")  # fmt: skip
    keep["final"] = {k: summary[k] for k in final if k in summary}
    return keep


def failure_summary(job_id: str, records: list[Report]) -> str:
    """Why a job failed, for its error field, from its processes' reports: the role that failed for good (or the
    last crash) and the cause, the last error a process reported itself — an exception, or why it gave up (the
    learner's "no chunk from any actor ...")."""
    verdict = [r for r in records if r.kind == "failed"] or [r for r in records if r.kind == "crashed"]
    errors = [r for r in records if r.kind == "error"]
    if not verdict and not errors:
        return f"its processes reported nothing; the whole log: GET /jobs/{job_id}/logs or convoy jobs logs {job_id}"
    head = f"{verdict[-1].source} {verdict[-1].kind}: {verdict[-1].detail}" if verdict else "a process failed"
    where = f"the whole log: GET /jobs/{job_id}/logs or convoy jobs logs {job_id}"
    if verdict and errors and errors[-1].detail and errors[-1].detail in verdict[-1].detail:
        return f"{head[:800]}; {where}"  # the verdict carries the cause already (a refused configuration)
    cause = f" (cause: {errors[-1].source}: {errors[-1].detail[:300]})" if errors else ""
    return f"{head[:300]}{cause}; {where}"


def host_name(job_id: str) -> str:
    return keys.check_id(f"h-{job_id}", "host name")
