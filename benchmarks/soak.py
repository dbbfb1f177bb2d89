"""Soak: a job service under a long stream of small jobs and sweeps, killed with -9 now and then.

A real ``convoy serve`` (loopback, its own data folder) receives ``--jobs`` small jobs (referential game, a few
thousand env steps each) and ``--sweeps`` sweeps spread over ``--minutes``; ``--kills`` times it is killed with
SIGKILL — the first one right after a burst of submissions, while it writes — and started again on the same port
and data. Every ``--sample`` seconds it records the service process's RSS and open file descriptors. At the end (after
waiting for the queue to drain, at most ``--drain`` more minutes) it reports:

* jobs and sweep jobs submitted (accepted with 201) against those the store still has, and how many completed,
  failed or are left;
* SQLite's ``PRAGMA integrity_check`` of the store;
* RSS and FDs over time: first (after warm-up), last and max, and last ÷ first (goal: within 10 %).

Goal: nothing lost, the store intact, RSS and FDs flat. Not a test: it runs for half an hour.

Run from the repository root: ``python benchmarks/soak.py`` (30 min, 200 jobs, 5 sweeps, 3 kills; ``--minutes 3
--jobs 12 --sweeps 1`` for a quick look); ``--json`` saves the figures.
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402
from rich.console import Console  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from tests.service_fixture import AUTH, Service  # noqa: E402

JOB = {"algo": "idqn", "env": "referential", "steps": 3_000, "num_envs": 8, "log_every": 1_000, "eval_every": 1_000,
       "eval_episodes": 8, "checkpoint_every": 1_000, "actors": 1,
       "algo_params": {"hidden": [16], "learning_starts": 200}}  # fmt: skip
SWEEP = {"base": {k: v for k, v in JOB.items() if k != "actors"}, "grid": {"algo": ["idqn", "ma-mesn"],
         "seed": [0, 1, 2]}, "actors": 1}  # fmt: skip


def usage(pid: int) -> tuple[float, int]:
    """RSS (MB) and open file descriptors of process ``pid``."""
    rss = 0.0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024
    return rss, len(os.listdir(f"/proc/{pid}/fd"))


def post(svc: Service, path: str, body: dict[str, Any]) -> str | None:
    """The new job's or sweep's id, or None when the service did not take it (down, refused)."""
    try:
        resp = svc.client.post(path, json=body, headers=AUTH)
    except httpx.TransportError:
        return None
    return resp.json()["id"] if resp.status_code == 201 else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=30.0, help="how long jobs keep coming (default %(default)s)")
    p.add_argument("--jobs", type=int, default=200, help="single jobs submitted (default %(default)s)")
    p.add_argument("--sweeps", type=int, default=5, help="sweeps submitted, 6 jobs each (default %(default)s)")
    p.add_argument("--kills", type=int, default=3, help="kill -9 of the service (default %(default)s)")
    p.add_argument("--processes", type=int, default=3, help="the service's --max-processes (default %(default)s)")
    p.add_argument("--burst", type=int, default=10, help="jobs sent just before the 1st kill (default %(default)s)")
    p.add_argument("--sample", type=float, default=10.0, help="seconds between RSS/FD samples (default %(default)s)")
    p.add_argument("--drain", type=float, default=30.0, help="minutes the queue has to drain (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = p.parse_args(argv)
    console = Console()
    work = Path(tempfile.mkdtemp(prefix="convoy-soak-"))
    svc = Service(work / "svc", max_processes=args.processes).start()
    span = args.minutes * 60
    kills_at = [span * (k + 1) / (args.kills + 1) for k in range(args.kills)]
    job_at = [span * i / max(args.jobs, 1) for i in range(args.jobs)]
    sweep_at = [span * (i + 0.5) / max(args.sweeps, 1) for i in range(args.sweeps)]
    jobs: list[str] = []
    sweeps: list[str] = []
    samples: list[tuple[float, float, int]] = []
    refused, kills = 0, 0
    t0 = time.monotonic()
    next_sample = 0.0
    try:
        while (now := time.monotonic() - t0) < span:
            while job_at and job_at[0] <= now:
                job_at.pop(0)
                got = post(svc, "/jobs", {**JOB, "seed": len(jobs), "name": "soak"})
                if got:
                    jobs.append(got)
                refused += got is None
            while sweep_at and sweep_at[0] <= now:
                sweep_at.pop(0)
                got = post(svc, "/sweeps", {**SWEEP, "name": f"soak{len(sweeps)}"})
                if got:
                    sweeps.append(got)
                refused += got is None
            if kills_at and kills_at[0] <= now:
                kills_at.pop(0)
                if kills == 0:  # the first while it writes: right after a burst of submissions
                    for i in range(args.burst):
                        got = post(svc, "/jobs", {**JOB, "seed": 10_000 + i, "name": "burst"})
                        if got:
                            jobs.append(got)
                svc.kill()
                kills += 1
                svc = Service(work / "svc", port=svc.port, max_processes=args.processes).start()
                console.print(f"{now / 60:5.1f} min: killed the service (-9) and started it again")
            if now >= next_sample and svc.proc is not None:
                rss, fds = usage(svc.proc.pid)
                samples.append((now, rss, fds))
                next_sample = now + args.sample
            time.sleep(0.2)
        t_end = time.monotonic() + args.drain * 60
        while time.monotonic() < t_end:
            by_state = svc.client.get("/healthz").json()["jobs"]
            if not by_state.get("queued") and not by_state.get("starting") and not by_state.get("running"):
                break
            time.sleep(5)
        if svc.proc is not None:
            rss, fds = usage(svc.proc.pid)
            samples.append((time.monotonic() - t0, rss, fds))
        listing = {j["id"]: j["state"] for j in svc.client.get("/jobs").json()["jobs"]}
        sweep_jobs = [m["id"] for s in sweeps for m in svc.client.get(f"/sweeps/{s}").json()["jobs"]]
    finally:
        svc.stop()
    with sqlite3.connect(work / "svc" / "jobs.sqlite") as db:
        integrity = db.execute("PRAGMA integrity_check").fetchone()[0]
    wanted = jobs + sweep_jobs
    present = [j for j in wanted if j in listing]
    states: dict[str, int] = {}
    for j in present:
        states[listing[j]] = states.get(listing[j], 0) + 1
    warm = [s for s in samples if s[0] >= min(60.0, span / 4)] or samples
    figures = {
        "minutes": args.minutes, "kills": kills, "submitted": len(wanted), "alone": len(jobs),
        "sweeps": len(sweeps), "refused_while_down": refused,
        "present": len(present), "lost": len(wanted) - len(present), "states": states, "integrity": integrity,
        "rss_mb": {"first": warm[0][1], "last": warm[-1][1], "max": max(s[1] for s in warm),
                   "ratio": warm[-1][1] / warm[0][1]},
        "fds": {"first": warm[0][2], "last": warm[-1][2], "max": max(s[2] for s in warm),
                "ratio": warm[-1][2] / warm[0][2]},
        "samples": samples,
    }  # fmt: skip
    console.print(
        f"{len(wanted)} jobs submitted ({len(jobs)} alone, {len(sweep_jobs)} in {len(sweeps)} sweeps; {refused} "
        f"refused while the service was down), {len(present)} in the store, lost {figures['lost']}; states {states}"
    )
    console.print(f"SQLite integrity_check: {integrity}; {kills} kills -9")
    for name, unit in (("rss_mb", "MB"), ("fds", "")):
        f = figures[name]
        console.print(f"service {name}: first {f['first']:.0f}{unit}, last {f['last']:.0f}{unit}, max "
                      f"{f['max']:.0f}{unit}: last/first {f['ratio']:.2f} (goal ≤ 1.10)")  # fmt: skip
    if args.json:
        write_json(args.json, figures)
    return 0 if figures["lost"] == 0 and integrity == "ok" else 1


if __name__ == "__main__":
    raise SystemExit(main())
