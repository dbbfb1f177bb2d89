"""``convoy reproduce``: run the paper's figures as sweeps through a job service and write ``docs/reproduction.md``.

Each figure is one or more files in ``experiments/`` whose ``[figure]`` table says which figure (``id``), what the
paper shows and which claims to check (``analysis/verdicts.py``). A sweep figure is submitted to the service (a
local ``convoy serve`` on this machine unless ``--service URL``), followed until its jobs end and summarised; a
benchmark figure (Fig. 4b, inference time) runs its benchmark script here; an analysis figure (Table 1) analyses
the checkpoints of another figure's sweep. A sweep already in the service with the same request is reused (resumed
when it was stopped or failed), so running the command again continues where it stopped. Each figure's figures go to
``docs/reproduction/ID.json`` and ``ID.png``; ``docs/reproduction.md`` is rendered from every JSON there, so figures
measured in separate runs share one page.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from convoy.analysis.verdicts import figure_verdict, judge_figure, judged_returns, metric_values
from convoy.api.models import SweepSubmit
from convoy.api.sweeps import group_name
from convoy.cli.args import add_command
from convoy.cli.jobs import Api, CliError, plain
from convoy.cli.ledger import Ledger, analysis_key, point_key, request
from convoy.cli.reproduction_page import FIGURES, duration, render
from convoy.cli.sweep_file import read_file, scale_table, skipped, sweep_body
from convoy.config import MAX_POPULATION
from convoy.envs.treadmill.config import RULES as TREADMILL_RULES
from convoy.validation import ConfigError, build_config

SCALES = ("quick", "mid", "paper")
POLL_S = 5.0
PRINT_EVERY_S = 60.0
SERVICE_START_S = 300.0  # a loaded 2-core machine was seen to need over a minute (torch imports, jobs reattached)
out = Console()


# --- figure files ------------------------------------------------------------------------------------------------


def figure_files(folder: Path) -> dict[str, list[tuple[Path, dict[str, Any]]]]:
    """The experiment files by figure id, in each figure's ``order``."""
    figures: dict[str, list[tuple[int, Path, dict[str, Any]]]] = {}
    for path in sorted(folder.glob("*.toml")):
        data = read_file(path)
        fig = data.get("figure")
        if fig is None:
            continue  # a plain sweep file (convoy sweep submit), no figure of the paper
        if "id" not in fig:
            raise ConfigError(f"{path}: figure.id", "a figure file names its figure, e.g. id = 'fig3'")
        figures.setdefault(str(fig["id"]), []).append((int(fig.get("order", 0)), path, data))
    return {k: [(p, d) for _, p, d in sorted(v, key=lambda t: t[0])] for k, v in figures.items()}


# --- the service -------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def local_service(data: Path, max_processes: int) -> Iterator[tuple[str, str]]:
    """A ``convoy serve`` on a free loopback port over ``data`` for the length of the block: (url, token)."""
    from convoy.protocol.session import free_port

    port, token = free_port(), secrets.token_urlsafe(16)
    data.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "convoy.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--data", str(data), "--max-processes", str(max_processes)]  # fmt: skip
    with open(data / "serve.log", "ab") as log:
        proc = subprocess.Popen(cmd, env={**os.environ, "CONVOY_API_TOKEN": token}, stdout=log, stderr=log)
    url = f"http://127.0.0.1:{port}"
    try:
        with Api(url, token, timeout=5) as api:
            t_end = time.monotonic() + SERVICE_START_S
            while True:
                if proc.poll() is not None:
                    raise CliError("--service", f"the local service exited ({proc.returncode})", f"see {log.name}")
                with contextlib.suppress(CliError):
                    api.call("GET", "/healthz")
                    break
                if time.monotonic() > t_end:
                    raise CliError("--service", f"the local service did not start in {SERVICE_START_S:.0f} s",
                                   f"see {log.name}")  # fmt: skip
                time.sleep(0.3)
        plain(out, f"local job service at {url} (data {data}, log {log.name})")
        yield url, token
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(20)
        if proc.poll() is None:
            proc.kill()


def normal(body: dict[str, Any]) -> dict[str, Any] | None:
    """A sweep request with every default filled in, so that requests stored by an older Convoy (without a field
    added since) still match the file they came from; None for one this Convoy cannot read."""
    try:
        return build_config(SweepSubmit, **body).model_dump(mode="json")
    except ConfigError:
        return None


def start_sweep(api: Api, body: dict[str, Any], label: str) -> dict[str, Any]:
    """``body``'s sweep in the service: an existing sweep with the same request that runs every point this one does
    (resumed if stopped or failed), else a new one."""
    spec = normal(body)
    if spec is None:
        raise CliError(label, "the sweep request does not validate", "check the experiment file")
    left_out = {point_key(p) for p in spec["exclude"]}
    same = [s for s in api.call("GET", "/sweeps")["sweeps"]
            if (old := normal(s["spec"])) is not None and request(old) == request(spec)
            and {point_key(p) for p in old["exclude"]} <= left_out]  # fmt: skip
    if same:  # a finished one first, then one that runs, else the newest (resumed)
        rank = {"completed": 0, "running": 1}
        sweep = min(reversed(same), key=lambda s: rank.get(s["state"], 2))
        if sweep["state"] in ("stopped", "failed"):
            sweep = api.call("POST", f"/sweeps/{sweep['id']}/resume")
        plain(out, f"{label}: continuing sweep {sweep['id']} ({sweep['state']})")
    else:
        sweep = api.call("POST", "/sweeps", json=body)
        plain(out, f"{label}: submitted sweep {sweep['id']} ({len(sweep['jobs'])} jobs)")
    return sweep


def stale_sweeps(
    sweeps: list[dict[str, Any]], plans: list[Plan], started: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """The running ``sweeps`` of the plans' files that none of the ``started`` ones is: left by an earlier run of the
    command under a request it no longer makes (a file's seeds or settings changed), they would go on training runs
    no ledger takes."""
    names, ids = {p.body["name"] for p in plans}, {s["id"] for s in started}
    return [s for s in sweeps if s["state"] == "running" and s["spec"].get("name") in names and s["id"] not in ids]


Harvest = Callable[[dict[str, Any]], None]


def follow_sweeps(
    api: Api, started: list[tuple[dict[str, Any], Harvest]], label: str, before: tuple[int, int] = (0, 0)
) -> list[dict[str, Any]]:
    """Each started sweep as ``GET /sweeps/{id}`` shows it once no job of any is queued or running; ``harvest``
    sees each member as soon as it completes; ``before``: the figure's runs its ledgers held when the command began
    and their env steps, counted in the progress line. Interrupted, every sweep still running is stopped (each job
    checkpoints), so that the same command continues them."""
    sweeps = [sweep for sweep, _ in started]
    t0, said, last, first_seen = time.monotonic(), "", 0.0, dict[str, int]()
    try:
        while True:
            for sweep, (_, harvest) in zip(sweeps, started, strict=True):
                for member in sweep["jobs"]:
                    if member["state"] == "completed":
                        harvest(member)
            if all(sweep["state"] != "running" for sweep in sweeps):
                break
            members = [m for sweep in sweeps for m in sweep["jobs"] if m["state"] != "deleted"]
            text = progress_text(label, sweeps, before)
            if text != said and time.monotonic() - last >= PRINT_EVERY_S:
                took = time.monotonic() - t0
                left = sum(m.get("steps", 0) - min(m.get("env_steps", 0), m.get("steps", 0)) for m in members)
                plain(out, f"{text} · {took / 60:.1f} min{time_left(left, stepped(members, first_seen), took)}")
                said, last = text, time.monotonic()
            time.sleep(POLL_S)
            sweeps = [s if s["state"] != "running" else api.call("GET", f"/sweeps/{s['id']}") for s in sweeps]
    except KeyboardInterrupt:
        for sweep in sweeps:
            if sweep["state"] == "running":
                api.call("POST", f"/sweeps/{sweep['id']}/stop")
                plain(out, f"{label}: stopped sweep {sweep['id']}; the same command continues it")
        raise
    for sweep in sweeps:
        if sweep["state"] == "stopped":  # by someone else: its groups are not the figure's
            raise CliError(label, f"sweep {sweep['id']} was stopped before its jobs finished",
                           f"resume it (`convoy sweep resume {sweep['id']}`) or run the command again")  # fmt: skip
    plain(out, f"{label}: {len(sweeps)} sweep(s) ended after {(time.monotonic() - t0) / 60:.1f} min")
    return sweeps


def progress_text(label: str, sweeps: list[dict[str, Any]], before: tuple[int, int]) -> str:
    """The figure's progress as its sweeps show it, with the ``before`` (runs, env steps) its ledgers held when the
    command began: a resumed study reads as far along as it is, not as a fresh start of the runs it lacks."""
    members = [m for sweep in sweeps for m in sweep["jobs"] if m["state"] != "deleted"]
    runs, steps = before
    asked = steps + sum(m.get("steps", 0) for m in members)
    done = steps + sum(min(m.get("env_steps", 0), m.get("steps", 0)) for m in members)
    states: dict[str, int] = {}
    for m in members:
        states[m["state"]] = states.get(m["state"], 0) + 1
    counts = [f"{runs} measured before"] * bool(runs) + [f"{n} {s}" for s, n in sorted(states.items())]
    text = f"{label}: {done / max(asked, 1):.0%} of its env steps · {', '.join(counts)}"
    if demo := [m for m in members if m["state"] == "running" and m.get("demo_round")]:  # before their steps
        played = sorted({f"{m['demo_round']}/{m['demo_rounds']}" for m in demo})
        text += f" ({len(demo)} in DAgger round {', '.join(played)})"
    if len(sweeps) > 1:
        text += f" · {sum(s['state'] != 'running' for s in sweeps)} of {len(sweeps)} sweeps done"
    return text


def stepped(members: list[dict[str, Any]], first_seen: dict[str, int]) -> int:
    """The env steps the sweeps' ``members`` took while this command watched them: each member's count beyond the
    first one above 0 it was seen with (``first_seen``, filled here), since a resumed run reports its checkpoint's
    steps at once and a run completed before reports all of its steps."""
    total = 0
    for m in members:
        steps = min(m.get("env_steps", 0), m.get("steps", 0))
        if steps > 0:
            total += steps - first_seen.setdefault(str(m["id"]), steps)
    return total


def time_left(left: int, done: int, seconds: float) -> str:
    """`` · ~5.2 h left``: the env steps ``left`` at the pace of this command so far (``done`` in ``seconds``), once it
    has run 10 minutes; a guess, since demonstration starts and held-out scoring add time no step counts."""
    if seconds < 600 or done <= 0:
        return ""
    return f" · ~{duration(left / done * seconds)} left at this pace"


def seed_waves(bodies: list[dict[str, Any]], size: int) -> list[list[int]]:
    """The seeds of a figure's files (their grids', sorted) in waves of ``size``. The files' sweeps are submitted
    wave by wave, the service starting queued jobs first come, first served, so every group of every file has its
    first seeds before any has its last, as each sweep already runs its groups' first seeds first: a study of days
    stopped part-way holds the same seeds in every arm, its controls included."""
    seeds = sorted({int(s) for body in bodies for s in body["grid"].get("seed", [])})
    return [seeds[i : i + size] for i in range(0, len(seeds), size)] or [[]]


def wave_body(body: dict[str, Any], seeds: list[int], first: bool) -> dict[str, Any] | None:
    """``body``'s sweep restricted to the wave's ``seeds`` (None when its grid has none of them); a file whose grid
    does not vary the seed goes whole in the first wave."""
    if "seed" not in body["grid"]:
        return body if first else None
    kept = [s for s in body["grid"]["seed"] if s in seeds]
    return {**body, "grid": {**body["grid"], "seed": kept}} if kept else None


def resolve_links(node: Any, ctx: Context) -> Any:
    """``"@fig3:algo=ma-mesn"`` → the checkpoint of that figure's group's best seed (on the service's host)."""
    if isinstance(node, dict):
        return {k: resolve_links(v, ctx) for k, v in node.items()}
    if isinstance(node, list):
        return [resolve_links(v, ctx) for v in node]
    if isinstance(node, str) and node.startswith("@"):
        fig, _, group = node[1:].partition(":")
        plain(out, f"{ctx.current} needs {fig}'s {group} checkpoints: running {fig}'s sweep first (or reusing it)")
        summary = ctx.sweep_summaries(fig)
        members = next((g for g in summary if g["group"] == group), None)
        if members is None or not members["final"]["values"]:
            raise CliError(node, f"{fig} has no completed job in group {group!r}", f"run convoy reproduce {fig}")
        best = members["jobs"][max(range(len(members["final"]["values"])), key=members["final"]["values"].__getitem__)]
        path = ctx.api.call("GET", f"/jobs/{best}").get("last_checkpoint")
        if not path:
            raise CliError(node, f"job {best} has no checkpoint", f"see convoy jobs status {best}")
        return path
    return node


# --- figures -----------------------------------------------------------------------------------------------------


@dataclass
class Plan:
    """One experiment file's sweep at a scale: its request, its ledger, its grid points and, after training, the
    state of each point its ledger lacks (failed, stopped, …)."""

    label: str
    body: dict[str, Any]
    pack: int
    ledger: Ledger
    points: list[dict[str, Any]]
    tuning: bool = False
    others: dict[str, str] = field(default_factory=dict)


def training_minutes(ledgers: list[Ledger]) -> float:
    """The training time of the ledgers' runs: each population's learner wall time (resumes and demonstration
    starts included), summed. Kept per run, it survives a study stopped and resumed over days, where the command's
    own wall time does not (populations side by side each count theirs)."""
    walls: dict[tuple[str, str], float] = {}
    for ledger in ledgers:
        for run in ledger.runs.values():
            if run.get("wall_s") is not None:
                key = (str(ledger.path), run["population"])
                walls[key] = max(walls.get(key, 0.0), float(run["wall_s"]))
    return sum(walls.values()) / 60


class Context:
    """What every figure needs: the service, the scale, where results go, and the figure files."""

    def __init__(
        self, api: Api, scale: str, files: dict[str, Any], docs: Path, work: Path, pack: int | None = None
    ) -> None:
        self.api, self.scale, self.files, self.docs, self.work = api, scale, files, docs, work
        self.pack = pack  # seeds per population instead of the files' (what runs measure does not change)
        self.current = ""
        self._summaries: dict[str, list[dict[str, Any]]] = {}
        self.tuning: dict[str, dict[str, dict[str, Any]]] = {}  # per figure, per algorithm: tried and chosen
        self.ledgers: dict[str, list[Ledger]] = {}  # each figure's, tuning included: its training time

    def sweep_summaries(self, fig: str) -> list[dict[str, Any]]:
        """Every group of figure ``fig``'s sweeps, in file order, summarised from its ledgers after the runs they
        lack were trained (or reused), each algorithm at the settings its tuning chose (when the figure tunes at
        this scale)."""
        if fig not in self._summaries:
            chosen = self.tuned(fig)
            plans = [
                self.plan(
                    fig, path, with_settings(resolve_links(sweep_body(data, self.scale, where=str(path)), self), chosen)
                )
                for path, data in self.files[fig]
                if data["figure"].get("kind", "sweep") == "sweep" and not skipped(data, self.scale)
            ]
            self.train(fig, plans)
            self._summaries[fig] = [g for plan in plans for g in self.groups(fig, plan)]
        return self._summaries[fig]

    def measured(self, fig: str, path: Path, body: dict[str, Any], tuning: bool = False) -> list[dict[str, Any]]:
        """The groups of one experiment file's sweep (or of its tuning sweep), its ledger's missing runs trained."""
        plan = self.plan(fig, path, body, tuning)
        self.train(fig, [plan])
        return self.groups(fig, plan)

    def plan(self, fig: str, path: Path, body: dict[str, Any], tuning: bool = False) -> Plan:
        """One experiment file's sweep at this scale with its ledger (runs measured under another request set
        aside)."""
        from convoy.api.sweeps import expand

        name = f"{path.stem}-tuning" if tuning else path.stem
        label = f"{fig} [{self.scale}] {path.name}{' tuning' * tuning}"
        if self.pack is not None:
            body = {**body, "pack": self.pack}
        spec = normal(body)
        if spec is None:
            raise CliError(label, "the sweep request does not validate", "check the experiment file")
        ledger, note = Ledger.open(self.docs / "ledger" / self.scale / f"{name}.json", spec)
        if note:
            plain(out, f"{label}: {note}")
        points = [job.point for job in expand(build_config(SweepSubmit, **spec))]
        held = sum(ledger.has(p) for p in points)
        if held == len(points):
            plain(out, f"{label}: all {len(points)} runs measured ({ledger.path}); nothing to train")
        elif held:
            plain(out, f"{label}: {held} of {len(points)} runs measured already ({ledger.path})")
        return Plan(label, {**body, "exclude": []}, int(spec["pack"]), ledger, points, tuning)

    def train(self, fig: str, plans: list[Plan]) -> None:
        """The runs the plans' ledgers lack, trained through the service wave by wave of seeds (``seed_waves``),
        all waves submitted at once; each run recorded in its ledger as its job completes."""
        size = self.pack or min((p.pack for p in plans), default=1)
        started: list[tuple[dict[str, Any], Harvest]] = []
        owners: list[Plan] = []
        for i, seeds in enumerate(seed_waves([p.body for p in plans], size)):
            for plan in plans:
                body = wave_body(plan.body, seeds, first=i == 0)
                if body is None:
                    continue
                wave = body["grid"].get("seed")
                points = [p for p in plan.points if wave is None or p["seed"] in wave]
                if all(plan.ledger.has(p) for p in points):
                    continue
                body = {**body, "exclude": [p for p in points if plan.ledger.has(p)]}
                harvest = functools.partial(self.harvest, fig, plan.ledger, score=not plan.tuning)
                started.append((start_sweep(self.api, body, plan.label), harvest))
                owners.append(plan)
        for sweep in stale_sweeps(self.api.call("GET", "/sweeps")["sweeps"], plans, [s for s, _ in started]):
            plain(out, f"{fig} [{self.scale}]: sweep {sweep['id']} of {sweep['spec']['name']} runs under a request "
                       f"this command no longer makes (its file changed) and takes the service's slots: "
                       f"`convoy sweep stop {sweep['id']}`")  # fmt: skip
        if not started:
            return
        followed = {point_key(m["point"]) for sweep, _ in started for m in sweep["jobs"]}  # a continued sweep's too
        held = [plan.ledger.runs[k] for plan in plans for p in plan.points
                if (k := point_key(p)) not in followed and plan.ledger.has(p)]  # fmt: skip
        before = (len(held), sum(int(run.get("env_steps", 0)) for run in held))
        ended = follow_sweeps(self.api, started, f"{fig} [{self.scale}]", before)
        for plan, sweep in zip(owners, ended, strict=True):
            plan.others.update({point_key(m["point"]): m["state"] for m in sweep["jobs"]
                                if not plan.ledger.has(m["point"]) and m["state"] != "deleted"})  # fmt: skip

    def groups(self, fig: str, plan: Plan) -> list[dict[str, Any]]:
        """The plan's groups summarised from its ledger (its sweeps' time counted in its figure's)."""
        self.ledgers.setdefault(fig, []).append(plan.ledger)
        groups = plan.ledger.groups(plan.points, plan.others)
        return [{**g, "ledger": plan.ledger, "sweep": str(plan.ledger.path)} for g in groups]

    def harvest(self, fig: str, ledger: Ledger, member: dict[str, Any], score: bool = True) -> None:
        """Record a completed job in ``ledger`` (once): its greedy curve and final evaluation, the references it
        measured, its population's wall time and, when ``score``, its last and best policies on the figure's
        held-out episodes and Table 1's analysis of its last checkpoint where an analysis figure reads its group
        at this scale."""
        from convoy.analysis.evaluation import HELD_OUT_SEED
        from convoy.services.training import score_checkpoint

        point, job_id = member["point"], member["id"]
        if ledger.has(point):
            return
        job = self.api.call("GET", f"/jobs/{job_id}")
        rows = self.api.call("GET", f"/jobs/{job_id}/metrics", params={"names": "eval_return,wall_s"})["rows"]
        kept = [{k: r[k] for k in ("env_steps", "eval_return", "wall_s") if k in r} for r in rows
                if isinstance(r.get("eval_return"), int | float) and math.isfinite(r["eval_return"])]  # fmt: skip
        if rows and (not kept or kept[-1]["env_steps"] != rows[-1].get("env_steps")):
            kept.append({k: rows[-1][k] for k in ("env_steps", "wall_s") if k in rows[-1]})  # the run's end
        final = job.get("final") or {}
        refs = {
            name: float(pair[0])
            for name, pair in (final.get("references") or {}).items()
            if pair and pair[0] is not None
        }
        run: dict[str, Any] = {
            "job": job_id,
            "population": job.get("population") or job_id,
            "env": job["env"],
            "env_steps": job["progress"]["env_steps"],
            "final": final,
            "references": refs,
            "rows": kept,
            "env_params": job["config"].get("env_params") or {},
            "compiled": bool((job["config"].get("algo_params") or {}).get("compile")),  # its wall time's context
            "wall_s": next((r["wall_s"] for r in reversed(rows) if r.get("wall_s") is not None), None),
        }
        episodes = self.held_out_episodes(fig) if score else 0
        if episodes > 0:
            plain(out, f"{fig} [{self.scale}]: {job_id}: last and best policies on {episodes} held-out episodes")
            scores = {}
            for key, name in (("last", "checkpoint.pt"), ("best", "best.pt")):
                path = self.checkpoint(job_id, name)
                scores[key] = None if path is None else score_checkpoint(path, episodes)
            run["held_out"] = {"episodes": episodes, "seed": HELD_OUT_SEED, **scores}
        opts = self.analysis_opts(fig, group_name(point)) if score else None
        if opts is not None:
            run["analysis"] = self.analyse(fig, job_id, opts)
        ledger.record(point, run)

    def held_out_episodes(self, fig: str) -> int:
        """How many held-out episodes re-score each run's last and best policies (0: none)."""
        data = self.files[fig][0][1]
        scale = scale_table(data, self.scale)
        return int(scale.get("held_out_episodes", data["figure"].get("held_out_episodes", 100)))

    def analysis_opts(self, fig: str, group: str) -> dict[str, Any] | None:
        """The settings of the analysis figure (Table 1) that reads ``fig``'s group ``group`` at this scale, or
        None when none does."""
        for files in self.files.values():
            meta = files[0][1]["figure"]
            opts = (meta.get("scales") or {}).get(self.scale)
            if meta.get("kind") != "analysis" or meta.get("source") != fig or opts is None:
                continue
            if group in (meta["group"], *opts.get("also", [])):
                return opts
        return None

    def analyse(self, fig: str, job_id: str, opts: dict[str, Any]) -> dict[str, Any] | None:
        """Table 1's figures of job ``job_id``'s last checkpoint (as the ledger keeps them), None without one."""
        from convoy.algos.checkpoint import load_checkpoint
        from convoy.analysis.recording import analyze
        from convoy.services.training import make_env

        path = self.checkpoint(job_id, "checkpoint.pt")
        if path is None:
            return None
        algo, job, _ = load_checkpoint(path, device="cpu")
        env = make_env(job, int(opts.get("num_envs", 256)))
        try:
            steps = -(-int(opts["samples"]) // env.num_envs)
            plain(out, f"{fig} [{self.scale}]: analysing {job_id} ({steps * env.num_envs:,} samples)")
            result = analyze(algo, env, job.env, steps, int(opts["episodes"]), int(opts.get("seed", 12345)))
        finally:
            env.close()
        return {"opts": analysis_key(opts), "title": result.title, "figures": [asdict(f) for f in result.figures]}

    def checkpoint(self, job_id: str, name: str) -> Path | None:
        """Job ``job_id``'s ``name`` (``checkpoint.pt``, ``best.pt``) fetched from the service once, or None when it
        has none (a job that never evaluated has no best.pt)."""
        path = self.work / "checkpoints" / f"{job_id}-{name}"
        if not path.is_file():
            resp = self.api.client.get(f"/jobs/{job_id}/checkpoints/{name}")
            if resp.status_code != 200:
                return None
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(resp.content)
        return path

    def tuned(self, fig: str) -> dict[str, dict[str, Any]]:
        """Per algorithm of the figure, the settings of ``[figure.tuning]``'s grid with the highest mean final
        return on its validation seeds (the figure's own seeds are fresh); {} when the figure does not tune at
        this scale. Every algorithm gets the same grid, so none is better tuned than another."""
        path, data = self.files[fig][0]
        tuning = data["figure"].get("tuning")
        if not tuning or self.scale not in tuning.get("scales", SCALES):
            return {}
        if fig not in self.tuning:
            body = tuning_body(resolve_links(sweep_body(data, self.scale, where=str(path)), self), tuning)
            self.tuning[fig] = choose_settings(self.measured(fig, path, body, tuning=True), list(tuning["grid"]))
        return {algo: t["chosen"] for algo, t in self.tuning[fig].items()}


def tuning_body(body: dict[str, Any], tuning: dict[str, Any]) -> dict[str, Any]:
    """The tuning sweep of a figure's first file: its algorithms × the tuning grid × the validation seeds."""
    algos = body["grid"].get("algo") or [body["base"].get("algo", "idqn")]
    grid = {"algo": algos, **tuning["grid"], "seed": tuning["seeds"]}
    return {**body, "name": f"{body.get('name', 'figure')}-tuning", "grid": grid}


def choose_settings(groups: list[dict[str, Any]], axes: list[str]) -> dict[str, dict[str, Any]]:
    """Per algorithm: every tried setting's mean final return and the best one (``chosen``, as algo_params)."""
    out: dict[str, dict[str, Any]] = {}
    for g in groups:
        mean = g["final"]["mean"]
        setting = {axis.removeprefix("algo_params."): g["point"][axis] for axis in axes}
        entry = out.setdefault(g["point"]["algo"], {"tried": [], "chosen": None, "best": -math.inf})
        entry["tried"].append({"settings": setting, "final": mean})
        if mean is not None and mean > entry["best"]:
            entry["best"], entry["chosen"] = mean, setting
    for algo, entry in out.items():
        if entry["chosen"] is None:
            raise CliError("figure.tuning", f"no tuning job of {algo} completed", "look at the tuning sweep's jobs")
        del entry["best"]
    return out


def with_settings(body: dict[str, Any], chosen: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``body`` with each tuned algorithm's chosen settings in its ``[algos.NAME]`` table (a grid axis still
    wins: a control that varies one of them keeps its values)."""
    if not chosen:
        return body
    algos = dict(body.get("algos") or {})
    for algo, settings in chosen.items():
        algos[algo] = {**algos.get(algo, {}), **settings}
    return {**body, "algos": algos}


def held_out_references(ctx: Context, groups: list[dict[str, Any]], episodes: int) -> dict[str, float]:
    """The env's reference policies (planners, the best constant, the tuned driver, random) on the held-out episodes
    the groups' policies are re-scored on (in the re-scoring's rounds of ``SCORING_ENVS`` envs), for the first
    group's env; {} where the env has none."""
    from convoy.analysis.evaluation import HELD_OUT_SEED, SCORING_ENVS
    from convoy.envs.registry import env_entry

    run = next((r for g in groups for r in g["runs"]), None)
    if run is None:
        return {}
    table = env_entry(run["env"]).references
    if table is None:
        return {}
    plain(out, f"{ctx.current} [{ctx.scale}]: the reference policies on the same {episodes} held-out episodes")
    refs = table(run.get("env_params") or {}, episodes, HELD_OUT_SEED, round_envs=SCORING_ENVS)
    return {name: float(mean) for name, (mean, _) in refs.items()}


def sweep_figure(ctx: Context, fig: str, meta: dict[str, Any]) -> dict[str, Any]:
    from convoy.analysis.curves import plot_final_by, plot_groups

    groups = ctx.sweep_summaries(fig)
    episodes = ctx.held_out_episodes(fig)
    held_refs = held_out_references(ctx, groups, episodes) if episodes > 0 else {}
    refs: dict[str, Any] = next(
        (g["references"] for g in groups if g["references"]), {}
    )  # the first group that measured them
    png = ctx.docs / f"{fig}.png"
    if meta.get("plot") == "final_by":
        plot_final_by(groups, png, meta["title"], meta["x"], meta["lines"], xlabel=meta.get("xlabel", meta["x"]),
                      ylabel=meta.get("ylabel", "final greedy return"))  # fmt: skip
    else:
        shown = {k: v for k, v in refs.items() if k != "random" or len(refs) == 1} if refs else {}
        plot_groups(groups, png, f"{meta['title']} ({ctx.scale})", references=shown or refs,
                    xlabel=meta.get("xlabel", "env steps"), ylabel=meta.get("ylabel", "greedy return"))  # fmt: skip
    extra = {"references": refs, **({"held_out_references": held_refs} if held_refs else {})}
    return {"groups": groups, "references": refs, "png": png.name, "extra": extra}


def benchmark_figure(ctx: Context, fig: str, meta: dict[str, Any]) -> dict[str, Any]:
    """Run the figure's benchmark script here (``command`` at the scale) and read its fitted exponents."""
    args = [str(a) for a in meta["scales"][ctx.scale]["command"]]
    result, png = ctx.work / f"{fig}.json", ctx.docs / f"{fig}.png"
    cmd = [sys.executable, *args, "--json", str(result), "--plot", str(png)]
    plain(out, f"{fig} [{ctx.scale}]: {' '.join(cmd[1:])}")
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    data = json.loads(result.read_text())
    exponents = {name: {"k": f["exponent_upper"], "ci": f["exponent_upper_ci"]} for name, f in data["fits"].items()}
    return {"groups": [], "references": {}, "png": png.name, "extra": {"exponents": exponents}, "benchmark": data}


def analysis_figure(ctx: Context, fig: str, meta: dict[str, Any]) -> dict[str, Any]:
    """Table 1: every last checkpoint of another figure's group analysed (``source``, ``group``; and at a scale
    whose table names them, its ``also`` groups, e.g. the channel-cut twins), each metric collected over seeds."""
    from convoy.analysis.comm_metrics import MetricFigure, plot_figures

    opts = meta["scales"][ctx.scale]
    summaries = {g["group"]: g for g in ctx.sweep_summaries(meta["source"])}
    names: dict[str, str] = {}
    by_group: dict[str, dict[str, dict[str, list[Any]]]] = {}
    last = None
    for name in [meta["group"], *opts.get("also", [])]:
        if name not in summaries:
            raise CliError("figure.group", f"{meta['source']} has no group {name!r}", "fix the table1 file")
        by_group[name], analysed = analyse_group(ctx, summaries[name], opts, names)
        last = last or analysed
    png = ctx.docs / f"{fig}.png"
    if last is not None:
        figures = [MetricFigure(**f) for f in last["figures"]]
        plot_figures(figures, png, title=f"{last['title']} (last seed analysed)")
    first = by_group[meta["group"]]
    return {"groups": [summaries[g] for g in by_group], "references": {}, "png": png.name if last else None,
            "extra": {"analysis": first, "analysis_groups": by_group}, "analysis_names": names}  # fmt: skip


def analyse_group(
    ctx: Context, group: dict[str, Any], opts: dict[str, Any], names: dict[str, str]
) -> tuple[dict[str, dict[str, list[Any]]], dict[str, Any] | None]:
    """Each metric's values (and shuffled baselines) over the group's runs, and the last run's analysis: as the
    ledger holds them, analysed now (and recorded) where a run was measured under other settings and its
    checkpoint is still on the service."""
    ledger: Ledger = group["ledger"]
    analyses = []
    for run in group["runs"]:
        analysis = run.get("analysis")
        if analysis is None or analysis["opts"] != analysis_key(opts):
            analysis = ctx.analyse(ctx.current, run["job"], opts)
            if analysis is None:
                plain(out, f"{ctx.current} [{ctx.scale}]: {run['job']} of {group['group']} has no analysis at these "
                      "settings and no checkpoint on this service: left out")  # fmt: skip
                continue
            ledger.record(run["point"], {**{k: v for k, v in run.items() if k != "point"}, "analysis": analysis})
        analyses.append(analysis)
    figures, keys = metric_values(analyses)
    names.update(keys)
    return figures, analyses[-1] if analyses else None


RECORDED = (
    "group",
    "jobs",
    "states",
    "final",
    "iqm",
    "auc",
    "held_out",
    "sweep",
    "references",
    "wall_s",
    "clone_unknown",
    "change",
)  # per group


def run_figure(ctx: Context, fig: str) -> dict[str, Any]:
    ctx.current = fig
    meta = ctx.files[fig][0][1]["figure"]
    kind = meta.get("kind", "sweep")
    t0 = time.monotonic()
    result = {"sweep": sweep_figure, "benchmark": benchmark_figure, "analysis": analysis_figure}[kind](ctx, fig, meta)
    groups = result["groups"]
    scales = [d.get("scales") or d["figure"].get("scales") or {} for _, d in ctx.files[fig]]
    scale_notes = [s.get(ctx.scale, {}).get("note", "") for s in scales]
    on_treadmill = any(d.get("base", {}).get("env") == "treadmill" for _, d in ctx.files[fig])
    record = {
        "id": fig,
        "title": meta["title"],
        **({"treadmill_rules": TREADMILL_RULES} if on_treadmill else {}),
        "paper": meta.get("paper", ""),
        "scale": ctx.scale,
        "note": " ".join(dict.fromkeys(n for n in scale_notes if n)) or meta.get("note", ""),
        "files": [str(p) for p, _ in ctx.files[fig]],
        "command": f"convoy reproduce {fig} --scale {ctx.scale}",
        **minutes(ctx, fig, kind, (time.monotonic() - t0) / 60),
        "groups": [{k: g[k] for k in RECORDED if k in g} for g in result["groups"]],
        "references": result["references"],
        **{k: result["extra"][k] for k in ("held_out_references",) if result["extra"].get(k)},
        **judged(meta, groups, result["extra"], ctx.scale),
        "png": result["png"],
    }
    if fig in ctx.tuning:
        record["tuning"] = ctx.tuning[fig]
    if "analysis_names" in result:
        record["analysis"] = {
            k: {"name": result["analysis_names"][k], **v} for k, v in result["extra"]["analysis"].items()
        }
        if len(result["extra"]["analysis_groups"]) > 1:  # the figures of every analysed group, first included
            record["analysis_groups"] = result["extra"]["analysis_groups"]
    if "benchmark" in result:
        record["exponents"] = result["extra"]["exponents"]
    ctx.docs.mkdir(parents=True, exist_ok=True)
    (ctx.docs / f"{fig}.json").write_text(json.dumps(record, indent=2) + "\n")
    plain(out, f"{fig} [{ctx.scale}]: {record['verdict']} — wrote {ctx.docs / (fig + '.json')}")
    return record


def minutes(ctx: Context, fig: str, kind: str, elapsed: float) -> dict[str, Any]:
    """A record's ``minutes`` and what they measure: a sweep figure's training (``training_minutes``), another
    figure's wall time here (a benchmark's run, an analysis)."""
    if kind == "sweep":
        return {"minutes": round(training_minutes(ctx.ledgers.get(fig, [])), 1),
                "minutes_of": "training, its populations' learners summed"}  # fmt: skip
    shown = "wall time here" + ", besides the analyses made as its source's runs completed" * (kind == "analysis")
    return {"minutes": round(elapsed, 1), "minutes_of": shown}


def judged(meta: dict[str, Any], groups: list[dict[str, Any]], extra: dict[str, Any], scale: str) -> dict[str, Any]:
    """A record's ``verdicts`` and ``verdict``: the figure's claims at ``scale`` (a claim's ``scales``, when it
    names them: a control run at some scales only) Holm-corrected together, on its groups and ``extra`` figures
    (references, exponents, analysis)."""
    claims = [c for c in meta.get("claims", []) if scale in c.get("scales", SCALES)]
    groups, extra, on = judged_returns(groups, extra)
    verdicts = judge_figure(claims, {g["group"]: g for g in groups}, extra)
    return {"verdicts": [v.__dict__ for v in verdicts], "verdict": figure_verdict(verdicts), "judged_on": on}


def rejudge(files: dict[str, Any], docs: Path, fig: str) -> dict[str, Any]:
    """Figure ``fig``'s stored record with its verdicts judged again from its stored measurements."""
    path = docs / f"{fig}.json"
    if not path.is_file():
        raise ConfigError("--rejudge", f"no stored record {path}: run `convoy reproduce {fig}` first")
    record = json.loads(path.read_text())
    keys = ("references", "held_out_references", "exponents", "analysis", "analysis_groups")
    extra = {key: record.get(key) or {} for key in keys}
    record.update(judged(files[fig][0][1]["figure"], record["groups"], extra, record["scale"]))
    path.write_text(json.dumps(record, indent=2) + "\n")
    return record


# --- the command -------------------------------------------------------------------------------------------------


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def cmd_reproduce(args: argparse.Namespace) -> int:
    """Run the paper's figures as sweeps and write docs/reproduction.md.

    Run each FIGURE (default: all, in the order fig3 fig4a fig4b fig5 fig6 fig7 fig8 table1) at --scale through a
    job service: a local `convoy serve` on --data unless --service URL, follow its sweeps to the end, check the
    paper's claims (one-sided t-tests over seeds, Holm-corrected per figure) and write --docs/FIGURE.json and
    .png, then render --page from every figure there. A sweep already in the service with the same request is
    reused, so the command continues after an interruption (Ctrl-C stops the running sweep; the same command
    resumes it).
    """
    signal.signal(signal.SIGTERM, _interrupt)  # `kill` stops the running sweep as Ctrl-C does
    folder = Path(args.experiments)
    if not folder.is_dir():
        raise ConfigError("--experiments", f"{folder} is not a folder; run from the repository root or name it")
    files = figure_files(folder)
    wanted = args.figures or [f for f in FIGURES if f in files]
    for fig in wanted:
        if fig not in files:
            raise ConfigError("FIGURE", f"no experiment file for {fig!r}; known: {', '.join(sorted(files))}")
    docs, page, work = Path(args.docs), Path(args.page), Path(args.data).resolve() / args.scale
    if args.pack is not None and not 1 <= args.pack <= MAX_POPULATION:
        raise ConfigError("--pack", f"{args.pack} seeds per population; give 1 to {MAX_POPULATION}")
    if args.rejudge:
        for fig in wanted:
            record = rejudge(files, docs, fig)
            plain(out, f"{fig}: {record['verdict']} — rewrote {docs / (fig + '.json')}")
        render(docs, page, files)
        plain(out, f"wrote {page}")
        return 0
    with contextlib.ExitStack() as stack:
        if args.service:
            url, token = args.service, args.token or os.environ.get("CONVOY_API_TOKEN")
        else:
            url, token = stack.enter_context(local_service(work / "service", args.max_processes))
        api = stack.enter_context(Api(url, token))
        ctx = Context(api, args.scale, files, docs, work, pack=args.pack)
        try:
            for fig in wanted:
                run_figure(ctx, fig)
        except CliError as exc:
            Console(stderr=True).print(f"[bold red]error:[/] {exc.line()}", highlight=False, soft_wrap=True)
            return exc.code
        finally:
            render(docs, page, files)
            plain(out, f"wrote {page}")
    return 0


def add_reproduce_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "reproduce", cmd_reproduce)
    p.add_argument("figures", nargs="*", metavar="FIGURE", help=f"figures to run: {', '.join(FIGURES)} (default all)")
    p.add_argument("--scale", choices=SCALES, default="quick", help="quick (minutes on 2 CPU cores), mid (≥ 10× "
                   "quick's steps; for fig3 and table1 the budget their question needs, days on 2 cores; each "
                   "file's note gives its wall time) or paper (the paper's budgets); default: quick")  # fmt: skip
    p.add_argument("--service", metavar="URL", help="a running `convoy serve` (default: start a local one)")
    p.add_argument("--token", help="its bearer token (default: $CONVOY_API_TOKEN)")
    p.add_argument(
        "--max-processes",
        type=int,
        default=3 * (os.cpu_count() or 1),
        metavar="N",
        help="process budget of the local service (a job takes actors + 2; default: 3 × CPU count, one "
        "single-actor job per core: its learner computes on one torch thread, its host and actor mostly wait)",
    )
    p.add_argument("--pack", type=int, metavar="N", help="seeds per population job instead of each experiment "
                   "file's `pack` (smaller populations finish sooner on a slow machine; the ledger's runs still "
                   "count: packing does not change what a run measures)")  # fmt: skip
    p.add_argument(
        "--experiments", default="experiments", metavar="DIR", help="the figure files (default: %(default)s)"
    )
    p.add_argument("--data", default="runs/reproduce", metavar="DIR", help="the local service's data and checkpoints "
                   "analysed, per scale (default: %(default)s)")  # fmt: skip
    p.add_argument("--docs", default="docs/reproduction", metavar="DIR", help="per-figure JSON and PNG "
                   "(default: %(default)s)")  # fmt: skip
    p.add_argument("--page", default="docs/reproduction.md", metavar="PATH", help="the page (default: %(default)s)")
    p.add_argument("--rejudge", action="store_true", help="run nothing: judge the figures' stored measurements "
                   "(--docs/FIGURE.json) again with the current claims, then render --page")  # fmt: skip
