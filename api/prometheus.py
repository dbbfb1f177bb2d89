"""``GET /metrics`` in the Prometheus text format, from the store (no training process is asked anything).

A custom collector builds the gauges at scrape time from the job records, so nothing has to be kept in sync: jobs per
state, and for every active job its env steps, env-steps/s, updates/s, return, policy lag, actors alive and the
messages it dropped by role and reason.
"""

from __future__ import annotations

import math
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from convoy.api.lifecycle import ACTIVE_STATES, JobReader

PER_JOB = {
    "env_steps": "Env steps the learner has ingested.",
    "env_steps_per_s": "Env steps per second over the last metric row.",
    "updates_per_s": "Learner updates per second over the last metric row.",
    "return": "Mean training return of the last metric row.",
    "policy_lag": "Mean policy lag of the actors in learner updates.",
}


class _Jobs:
    def __init__(self, store: JobReader, control: Any) -> None:
        self.store, self.control = store, control

    def collect(self) -> Any:
        states = GaugeMetricFamily("convoy_jobs", "Jobs in each state.", labels=["state"])
        for state, n in self.store.count_by_state().items():
            states.add_metric([state], n)
        yield states
        alive = GaugeMetricFamily("convoy_job_actors_alive", "Actor processes alive.", labels=["job"])
        wanted = GaugeMetricFamily("convoy_job_actors", "Actor processes requested.", labels=["job"])
        gauges = {k: GaugeMetricFamily(f"convoy_job_{k}", h, labels=["job"]) for k, h in PER_JOB.items()}
        dropped = GaugeMetricFamily(
            "convoy_job_dropped_messages",
            "Messages the job refused, by role and reason.",
            labels=("job", "role", "reason"),
        )
        for rec in self.store.list():
            if rec.state not in ACTIVE_STATES:
                continue
            alive.add_metric([rec.id], self.control.actors_alive(rec.id))
            wanted.add_metric([rec.id], rec.actors)
            for role, reasons in (rec.progress.get("dropped") or {}).items():
                for reason, n in reasons.items():
                    dropped.add_metric([rec.id, role, reason], float(n))
            for key, gauge in gauges.items():
                value = rec.progress.get(key)
                if isinstance(value, (int, float)) and math.isfinite(value):
                    gauge.add_metric([rec.id], float(value))
        yield alive
        yield wanted
        yield dropped
        yield from gauges.values()


def exposition(store: JobReader, control: Any) -> tuple[str, str]:
    """(text, content type) of one scrape."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_Jobs(store, control))
    return generate_latest(registry).decode(), CONTENT_TYPE_LATEST
