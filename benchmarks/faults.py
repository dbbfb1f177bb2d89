"""Fault benchmark: what a crash, churn, a dead API or a cut link costs a running job, measured on this machine.

Five figures, one Markdown table each, printed in one run (the tests assert the outcomes; this measures them):

1. **Actor respawn** — ``JobRunner`` (what ``convoy train`` runs) with 1 actor; the actor is killed with SIGKILL
   ``--kills`` times (default 40), each time after the replacement has delivered new data. Per kill: seconds until
   the supervisor has started the replacement, and until the replacement's liveliness token is up. The kills come
   seconds apart, which the restart policy reads as a crash loop and slows with ``restart_backoff_s``; the job sets
   it to 0 so that the figure is the respawn itself (an actor that ran ≥ 10 s is respawned at once whatever it is).
2. **Learner memory over actor churn** — in the same job, the learner's RSS (``/proc/PID/status`` VmRSS) and its
   shared-memory mappings before the first kill and after the last (goal: RSS within 10 %). The replay buffer is
   made small (``--replay``, default 20,000) and full before the first reading, so its growth is not counted as churn.
3. **Learner kill** — independent DQN (hidden 64) on the default treadmill, 80,000 env steps, a checkpoint every
   4,000; the learner is killed with SIGKILL at 50,000.
   Steps lost = the last env-step count it reported before the kill − the count it resumed at (its checkpoint's).
   Beside it: the ε-greedy training return of the last 3 metric rows before the kill and the first 3 after the
   resume (a replay buffer restored with the checkpoint should keep the second near the first).
4. **API down** — ``convoy serve`` with one running job; the API is killed with SIGKILL for ``--api-down`` seconds
   (default 10). The job's env steps in its ``metrics.jsonl`` over that window vs over the same window just before
   the kill; then the seconds until a new API on the same data reports the job running.
5. **Link cut** (root and iproute2 only) — a router, a learner host and two actor hosts, each in its own network
   namespace (``tests/multihost.py``); one actor host's link is down for 10 s. Figures from the router's view of
   every metrics message: seconds from the restore until the cut host delivers again, and the longest silence of
   the host that was not cut (how long the cut stalls the rest of the job).
6. **Stop while starting** — ``convoy serve``; ``--stops`` jobs (default 5) are each stopped the moment the API
   shows them ``starting``; seconds until they are ``stopped`` (goal ≤ 2 s; without the signal to the starting
   host the stop waited for the 20 s grace kill).

Run from the repository root: ``python benchmarks/faults.py`` (~5 min); ``--parts 1 4`` runs some parts (parts 1
and 2 share one job); ``--json PATH`` also saves the figures. Every process is stopped by PID; Zenoh binds to
127.0.0.1 on free ports (part 5: to the namespaces' own addresses).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import cpu_model  # noqa: E402
from convoy.config import job_config  # noqa: E402
from convoy.output import markdown_table  # noqa: E402
from convoy.services.jobrunner import JobRunner  # noqa: E402
from tests.multihost import Hosts, MultiHostJob, available  # noqa: E402
from tests.service_fixture import AUTH, SMALL_JOB, Service  # noqa: E402
from tests.test_runtime import (  # noqa: E402
    TREADMILL,
    Background,
    alive_of,
    group_of,
    learner_of,
    shm_mappings,
    wait_for,
)

MIB = 1024 * 1024


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024 / MIB
    raise RuntimeError(f"no VmRSS for PID {pid}")


def steps(runner: JobRunner) -> float:
    return runner.last_row.get("env_steps", 0.0)


def part_churn(args: argparse.Namespace, work: Path) -> tuple[str, dict[str, Any]]:
    """Parts 1 and 2: kill the only actor ``args.kills`` times; respawn times and the learner's memory."""
    hp = {**TREADMILL["algo_params"], "replay_capacity": args.replay}
    runtime = {"actors": 1, "restart_backoff_s": 0.0}  # every kill as churn: no crash-loop backoff
    job = job_config(algo="idqn", steps=100_000_000, seed=3, runtime=runtime, **{**TREADMILL, "algo_params": hp})
    runner = JobRunner("churn", job, work / "churn", progress=False)
    started, token = [], []
    with Background(runner):
        wait_for(lambda: steps(runner) > 1.5 * args.replay, 180, "the replay buffer to fill")
        learner = learner_of(runner).proc.pid
        before = {"rss_mib": rss_mib(learner), "shm": len(shm_mappings(learner))}
        t_first = time.monotonic()
        for kill in range(args.kills):
            at = steps(runner)
            os.kill(group_of(runner).actors[0].proc.pid, signal.SIGKILL)
            t0 = time.monotonic()

            def back(k: int = kill) -> bool:
                return 0 in group_of(runner).actors and group_of(runner).actors[0].generation == k + 1

            def announced(k: int = kill) -> bool:
                return f"actor-0.{k + 1}" in alive_of(runner).ids("actor")

            def fed(s: float = at) -> bool:
                return steps(runner) > s + 2_000

            wait_for(back, 30, "the respawn", every=0.005)
            started.append(time.monotonic() - t0)
            wait_for(announced, 30, "the token", every=0.005)
            token.append(time.monotonic() - t0)
            wait_for(fed, 60, "the new actor's data")
        after = {"rss_mib": rss_mib(learner), "shm": len(shm_mappings(learner))}
        churn_s = time.monotonic() - t_first
        time.sleep(churn_s)  # the control: as long again, with no kill
        control = {"rss_mib": rss_mib(learner), "shm": len(shm_mappings(learner)), "seconds": churn_s}
    figures = {"kills": args.kills, "respawn_s": started, "token_s": token, "before": before, "after": after}
    figures["control"] = control
    q = statistics.quantiles
    rows = [
        [name, f"{statistics.median(v):.2f}", f"{q(v, n=10, method='inclusive')[-1]:.2f}", f"{max(v):.2f}"]
        for name, v in (("replacement started", started), ("its liveliness token up", token))
    ]
    ratio = after["rss_mib"] / before["rss_mib"]
    text = (
        f"### 1. Actor respawn after SIGKILL ({args.kills} kills, 1 actor, treadmill idqn)\n\n"
        + markdown_table(["seconds after kill -9", "median", "p90", "max"], rows, [False, True, True, True])
        + f"\n\n### 2. Learner memory over {args.kills} actor deaths\n\n"
        + markdown_table(
            [
                "",
                "before the first kill",
                f"after kill {args.kills}",
                f"then {churn_s:.0f} s without a kill",
                "after ÷ before",
            ],
            [
                [
                    "learner RSS (MiB)",
                    f"{before['rss_mib']:.0f}",
                    f"{after['rss_mib']:.0f}",
                    f"{control['rss_mib']:.0f}",
                    f"{ratio:.3f}",
                ],
                ["shared-memory mappings", str(before["shm"]), str(after["shm"]), str(control["shm"]), ""],
            ],
            [False, True, True, True, True],
        )
        + f"\n\nGoal: RSS after ÷ before ≤ 1.10 → **{'met' if ratio <= 1.10 else 'missed'}** ({ratio:.3f}). The "
        "last column but one is the control: the same learner as long again with no actor death (growth there is "
        "not churn's)."
    )
    return text, figures


def part_learner_kill(args: argparse.Namespace, work: Path) -> tuple[str, dict[str, Any]]:
    every = 4_000
    job = job_config(
        algo="idqn",
        env="treadmill",
        steps=80_000,
        seed=2,
        checkpoint_every=every,
        log_every=1_000,
        eval_episodes=0,
        num_envs=16,
        algo_params={"hidden": [64]},
        runtime={"actors": 1},
    )
    out = work / "learner-kill"
    runner = JobRunner("killlearner", job, out, progress=False)
    with Background(runner) as bg:
        wait_for(lambda: steps(runner) > 50_000, 600, "50 k env steps")
        reported = steps(runner)
        os.kill(learner_of(runner).proc.pid, signal.SIGKILL)
        t0 = time.monotonic()
        wait_for(lambda: bool(runner.resumes), 60, "the resume")
        resume_s = time.monotonic() - t0
        bg.join(600)
    resumed = runner.resumes[0]
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    pre = [r["return"] for r in rows if r["env_steps"] <= reported][-3:]
    post = [r["return"] for r in rows if r["env_steps"] > resumed["resumed_env_steps"]][:3]
    figures = {
        "reported_env_steps": reported,
        "resumed_env_steps": resumed["resumed_env_steps"],
        "resumed_replay_rows": resumed.get("resumed_replay_rows", 0),
        "lost_env_steps": reported - resumed["resumed_env_steps"],
        "checkpoint_every": every,
        "resume_s": resume_s,
        "return_before": statistics.fmean(pre),
        "return_after": statistics.fmean(post),
    }
    text = "### 3. Learner kill -9 at 50 k env steps (default treadmill, checkpoint every 4,000)\n\n" + markdown_table(
        ["last reported", "resumed at", "steps lost", "replay rows restored", "resume s", "return: before → after"],
        [
            [
                f"{reported:,.0f}",
                f"{figures['resumed_env_steps']:,.0f}",
                f"{figures['lost_env_steps']:,.0f}",
                f"{figures['resumed_replay_rows']:,.0f}",
                f"{resume_s:.1f}",
                f"{figures['return_before']:.1f} → {figures['return_after']:.1f}",
            ]
        ],
        [True] * 5 + [False],
    )
    text += (
        "\n\nReturn = ε-greedy training return per completed episode, mean of the last 3 metric rows before the "
        "kill and the first 3 after the resume."
    )
    return text, figures


def part_api_down(args: argparse.Namespace, work: Path) -> tuple[str, dict[str, Any]]:
    data = work / "svc"
    svc, again = Service(data).start(), None
    metrics = None

    def job_steps() -> float:
        lines: list[str] = metrics.read_text().splitlines() if metrics and metrics.exists() else []
        return json.loads(lines[-1])["env_steps"] if lines else 0.0

    try:
        resp = svc.client.post("/jobs", json={**SMALL_JOB, "steps": 100_000_000, "actors": 1}, headers=AUTH)
        resp.raise_for_status()
        job = resp.json()["id"]
        metrics = data / "jobs" / job / "metrics.jsonl"
        svc.wait(job, lambda v: v["progress"]["env_steps"] >= 8000, timeout=120, what="some progress")
        s0 = job_steps()
        time.sleep(args.api_down)
        s1 = job_steps()
        svc.kill()
        time.sleep(args.api_down)
        s2 = job_steps()
        deadline = time.monotonic() + 60  # a loaded machine may log no row in a short window: wait for one
        while job_steps() <= s1 and time.monotonic() < deadline:
            time.sleep(0.2)
        kept_stepping = job_steps() > s1  # the job trained on with no API (each actor and learner alone)
        t0 = time.monotonic()
        again = Service(data, port=svc.port).start()
        view = again.wait(job, lambda v: v["state"] == "running" and v["progress"]["env_steps"] >= s2, what="running")
        back_s = time.monotonic() - t0
    finally:
        if again is not None:
            again.stop()
        svc.stop()
    figures = {"window_s": args.api_down, "steps_api_up": s1 - s0, "steps_api_down": s2 - s1, "reattach_s": back_s,
               "kept_stepping": kept_stepping}  # fmt: skip
    ratio = (s2 - s1) / max(1.0, s1 - s0)
    text = f"### 4. API down (SIGKILL of `convoy serve` for {args.api_down:g} s)\n\n" + markdown_table(
        ["env steps in the window: API up", "API down", "down ÷ up", "new API reports the job running after (s)"],
        [[f"{s1 - s0:,.0f}", f"{s2 - s1:,.0f}", f"{ratio:.2f}", f"{back_s:.1f}"]],
        [True] * 4,
    )
    figures["state_after"] = view["state"]
    return text, figures


def part_link_cut(args: argparse.Namespace, work: Path) -> tuple[str, dict[str, Any]]:
    if not available():
        return "### 5. Link cut\n\nSkipped: needs root and iproute2 (`ip netns`).", {"skipped": True}
    hosts = Hosts(["learner", "a1", "a2"])
    job_args = ["--env", "referential", "--steps", "100000000", "--num-envs", "32", "--hp", "hidden=64",
                "--hp", "learning_starts=256", "--eval-episodes", "0", "--log-every", "2000"]  # fmt: skip
    job = MultiHostJob(hosts, "cut", job_args, work / "link-cut", ["a1", "a2"])
    try:
        hosts.up()
        job.start()
        wait_for(lambda: bool(job.rows()) and job.rows()[-1]["env_steps"] >= 6_000, 120, "progress before the cut")
        rows_before = job.rows()[-1]
        hosts.cut("a1", down=True)
        cut_at = time.time()
        time.sleep(10.0)
        hosts.cut("a1", down=False)
        restored = time.time()
        wait_for(lambda: any("a1-host" in k and t > restored for t, k in job.heard()), 60, "the cut host's data")
        time.sleep(10.0)
        rows_after = job.rows()[-1]
    finally:
        job.stop()
        hosts.down()
    heard = job.heard()
    back = min(t for t, k in heard if "a1-host" in k and t > restored) - restored
    other = sorted(t for t, k in heard if "a2-host" in k and t > cut_at - 5)
    gaps = [b - a for a, b in itertools.pairwise(other) if a < restored + 10]
    rate = (rows_after["env_steps"] - rows_before["env_steps"]) / (rows_after["wall_s"] - rows_before["wall_s"])
    figures = {"back_s": back, "other_host_longest_silence_s": max(gaps, default=0.0), "env_steps_per_s": rate}
    text = "### 5. Link cut (one actor host of two, 10 s, network namespaces)\n\n" + markdown_table(
        ["cut host delivers again, s after restore", "uncut host's longest silence (s)", "job env-steps/s over it"],
        [[f"{back:.1f}", f"{figures['other_host_longest_silence_s']:.1f}", f"{rate:,.0f}"]],
        [True] * 3,
    )
    return text, figures


def part_stop_while_starting(args: argparse.Namespace, work: Path) -> tuple[str, dict[str, Any]]:
    """A stop sent while the job is ``starting`` (its host may not hear commands yet): seconds until ``stopped``."""
    svc = Service(work / "svc-stop").start()
    took: list[float] = []
    try:
        for _ in range(args.stops):
            resp = svc.client.post("/jobs", json={**SMALL_JOB, "steps": 100_000_000, "actors": 1}, headers=AUTH)
            resp.raise_for_status()
            job = resp.json()["id"]
            svc.wait(job, lambda v: v["state"] == "starting", what="starting", every=0.005)
            t0 = time.monotonic()
            svc.client.post(f"/jobs/{job}/stop", headers=AUTH).raise_for_status()
            svc.wait(job, lambda v: v["state"] == "stopped", timeout=60, what="stopped", every=0.01)
            took.append(time.monotonic() - t0)
    finally:
        svc.stop()
    figures = {"stop_s": took}
    worst = max(took)
    text = f"### 6. Stop while starting ({args.stops} jobs)\n\n" + markdown_table(
        ["seconds from the stop to `stopped`", "median", "max"],
        [["", f"{statistics.median(took):.2f}", f"{worst:.2f}"]],
        [False, True, True],
    )
    text += f"\n\nGoal: ≤ 2 s → **{'met' if worst <= 2.0 else 'missed'}** (the grace kill would take 20 s)."
    return text, figures


PARTS = {1: part_churn, 3: part_learner_kill, 4: part_api_down, 5: part_link_cut, 6: part_stop_while_starting}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", type=int, nargs="+", default=[1, 3, 4, 5, 6], choices=[1, 2, 3, 4, 5, 6],
                   help="parts to run (1 and 2 are one job; default: all)")  # fmt: skip
    p.add_argument("--kills", type=int, default=40, help="actor kills in parts 1-2 (default %(default)s)")
    p.add_argument("--replay", type=int, default=20_000, help="replay capacity in parts 1-2 (default %(default)s)")
    p.add_argument("--api-down", type=float, default=10.0, help="seconds the API is down (default %(default)s)")
    p.add_argument("--stops", type=int, default=5, help="jobs stopped while starting in part 6 (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = p.parse_args(argv)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"{len(os.sched_getaffinity(0))} CPU core(s) usable ({cpu_model()}); load average at start {load}.\n")
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="convoy-faults-") as tmp:
        for part in sorted({1 if x == 2 else x for x in args.parts}):
            text, figures[str(part)] = PARTS[part](args, Path(tmp))
            print(text + "\n", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
