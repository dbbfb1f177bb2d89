"""``convoy train``: the command that trains an algorithm — distributed (actors + learner over Zenoh) by default,
in one process with ``--inprocess``."""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from convoy.cli.args import (
    add_command,
    add_limit_flags,
    add_model_flags,
    env_params,
    given,
    limits_from_args,
    parse_pairs,
)
from convoy.cli.rundir import LAUNCH, claim, discard_unstarted, free_default
from convoy.config import (
    ALGORITHMS,
    JOB_FIELDS,
    AlgoConfig,
    DemonstrationFields,
    JobConfig,
    env_default_note,
    job_config,
)
from convoy.validation import ConfigError

console = Console()


def read_config_file(path: str) -> dict[str, Any]:
    """A JobConfig as JSON or TOML (by extension)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError("--config", f"no such file {path!r}; pass a JSON or TOML job file")
    try:
        data = tomllib.loads(p.read_text()) if p.suffix == ".toml" else json.loads(p.read_text())
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(
            "--config", f"{path}: not valid {'TOML' if p.suffix == '.toml' else 'JSON'} ({exc})"
        ) from None
    if not isinstance(data, dict):
        raise ConfigError("--config", f"{path}: expected a table/object of JobConfig fields")
    return data


def job_from_args(args: argparse.Namespace) -> JobConfig:
    """Config file first, then every flag given on the command line on top of it."""
    values: dict[str, Any] = read_config_file(args.config) if args.config else {}
    values.update(given(args, (*JOB_FLAGS, "seeds", "loggers", "device", "torch_threads", "checkpoint_every")))
    with_runtime_flags(values, args)
    values["env_params"] = env_params(args, values.get("env_params"))
    values["algo_params"] = {**values.get("algo_params", {}), **parse_pairs(args.hp, "--hp")}
    return job_config(**values)


def cmd_train(args: argparse.Namespace) -> int:
    """Train an algorithm on an environment.

    Train ALGO on ENV: batched envs and learner updates, a progress bar, then a summary table. Writes
    metrics.jsonl/metrics.csv (one row per --log-every steps), curve.png, checkpoint.pt and summary.json under
    --out.
    """
    from convoy.services.procs import JobRefused

    job = resumed_job(args) if args.resume else job_from_args(args)
    limits_from_args(args).check(job, "convoy train")
    check_job_inputs(job)  # before --out is made: a refused input leaves no folder that looks like a run
    if args.resume:
        out = Path(args.resume)
        args.inprocess = resumed_inprocess(args, out)
    else:
        out = Path(args.out) if args.out else free_default(Path("runs") / f"{job.algo}-{job.env}")
    made = not out.exists()
    run_dir = claim(out, overwrite=args.overwrite, resume=bool(args.resume))
    try:
        (out / LAUNCH).write_text(json.dumps({"inprocess": bool(args.inprocess)}) + "\n")
        return _train(args, job, out)
    except (ConfigError, JobRefused):  # refused once under way: before a checkpoint, nothing stays that reads as a run
        run_dir.release()
        if not args.resume:
            discard_unstarted(out, made)
        raise
    finally:
        run_dir.release()


def check_job_inputs(job: JobConfig) -> None:
    """What the job names outside its flags, tried before any folder is made: the files it reads (a CoDBC teacher
    checkpoint) and the trackers it logs to (``--logger``), each a ConfigError that names it."""
    from convoy.algos.inputs import check_inputs
    from convoy.learner.trackers import check_loggers

    check_inputs(job)
    check_loggers(job.loggers)


def resumed_inprocess(args: argparse.Namespace, out: Path) -> bool:
    """Whether ``--resume`` goes on in this process: as the run was started, unless ``--inprocess`` or ``--actors``
    says otherwise — a run's data should not change how it is collected half-way without the user asking."""
    if args.inprocess or args.actors is not None or not (out / LAUNCH).is_file():
        return bool(args.inprocess)
    try:
        started_inprocess = json.loads((out / LAUNCH).read_text())["inprocess"]
        if not isinstance(started_inprocess, bool):
            raise TypeError(f"inprocess is {started_inprocess!r}, not true or false")
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError("--resume", f"{out / LAUNCH} (how the run was started) is unreadable ({exc}); say how "
                          "to go on with --inprocess or --actors N") from None  # fmt: skip
    if started_inprocess:
        console.print(f"{out} was started with --inprocess: going on in this process (--actors N moves it to actors)")
    return started_inprocess


RESUME_FLAGS = ("steps", "device", "torch_threads", "loggers", "checkpoint_every")  # what may change when a run goes on
RESUME_HP = ("compile",)  # how the update runs, not what it computes: a long run may go on captured


def resumed_job(args: argparse.Namespace) -> JobConfig:
    """The job of the run in ``--resume DIR`` (its ``job.json``), with the few flags a run may change as it goes on."""
    path = Path(args.resume) / "job.json"
    if not path.is_file():
        raise ConfigError("--resume", f"{path.parent} has no job.json, the run's config: give the run's folder (Convoy "
                          "writes job.json there), or train it again with its flags and --overwrite")  # fmt: skip
    other = [f for f in (*JOB_FLAGS, "seeds") if getattr(args, f) is not None and f not in RESUME_FLAGS]
    hp = parse_pairs(args.hp, "--hp")
    other += [f"--hp {key}" for key in hp if key not in RESUME_HP]
    fixed = (("--set", args.set), ("--config", args.config), ("--out", args.out), ("--agents", args.agents),
             ("--adversaries", args.adversaries))  # fmt: skip
    other += [flag for flag, value in fixed if value]
    if other:
        raise ConfigError("--resume", f"goes on with the run's own job ({path}); {', '.join(other)} cannot change "
                          "(only --steps, --device, --threads, --checkpoint-every, --actors, --runtime and --hp "
                          "compile)")  # fmt: skip
    values = json.loads(path.read_text())
    values.update(given(args, RESUME_FLAGS))
    values["algo_params"] = {**values.get("algo_params", {}), **hp}
    job = job_config(**with_runtime_flags(values, args))
    unsaved = [str(d) for d in job.member_dirs(path.parent) if not (d / "checkpoint.pt").is_file()]
    if unsaved:  # before job.json is written again: a refused resume changes nothing
        raise ConfigError("--resume", f"{', '.join(unsaved)} has no checkpoint.pt to go on from (the run stopped "
                          f"before its first, every {job.checkpoint_every:,} steps): train it again with "
                          f"`convoy train --config {path} --out {path.parent} --overwrite`")  # fmt: skip
    return job


def with_runtime_flags(values: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """``values`` with ``--runtime KEY=VALUE`` and ``--actors`` merged into its runtime table."""
    values["runtime"] = {**values.get("runtime", {}), **parse_pairs(args.runtime, "--runtime")}
    if args.actors is not None:
        values["runtime"]["actors"] = args.actors
    return values


def _train(args: argparse.Namespace, job: JobConfig, out: Path) -> int:
    """The job's runs (one, or a population's: each in ``out/seed-N``), in this process or with actors; then one
    run's table of figures, or a population's table of its runs."""
    from convoy.services.procs import JobFailed
    from convoy.services.training import run_distributed, run_population

    seeds, dirs = job.run_seeds(), job.member_dirs(out)
    env = f"[bold]{job.algo}[/] on [bold]{job.env}[/]{' ' + str(job.env_params) if job.env_params else ''}"
    per_actor = "" if args.inprocess else " per actor"
    if len(seeds) == 1:
        where = "in this process" if args.inprocess else f"{job.runtime.actors} actor processes + a learner (Zenoh)"
        head = (f"{env}: {job.steps:,} env steps, {job.num_envs} envs{per_actor}, hidden {job.algo_config().hidden}, "
                f"seed {job.seed}, {where} → {out}/")  # fmt: skip
    else:
        where = "one population in this process" if args.inprocess else (
            f"{job.runtime.actors} actor processes stepping every run's envs + one learner (Zenoh)")  # fmt: skip
        head = (f"{env}: {len(seeds)} runs (seeds {' '.join(map(str, seeds))}) × {job.steps:,} env steps, "
                f"{job.num_envs} envs each{per_actor}, hidden {job.algo_config().hidden}, {where} → "
                f"{out}/seed-N/")  # fmt: skip
    cfg = job.algo_config()
    if isinstance(cfg, DemonstrationFields) and cfg.demonstrator and not args.resume:
        head += (f"\nfirst cloned from {cfg.demonstrator} (DAgger, {cfg.demo_rounds} rounds of {cfg.demo_episodes} "
                 "episodes per run): a few minutes per round")  # fmt: skip
    console.print(head, highlight=False, soft_wrap=True)
    out.mkdir(parents=True, exist_ok=True)  # the job's own config (each run writes its own): for --resume
    job.write(out / "job.json")
    if args.inprocess:
        trained = run_population(job.members(), dirs, not args.no_progress, root=out, resume=bool(args.resume))
        results = [r.as_dict() for r in trained]
    else:
        results = run_distributed(job, out, progress=not args.no_progress, job_id=args.job_id, stop_on_sigterm=True)
        if not results:
            saved = f"{out}/checkpoint.pt holds" if len(dirs) == 1 else f"{out}/seed-N/checkpoint.pt hold"
            raise JobFailed(f"the learner stopped before the job finished; {saved} its progress")
    if len(results) == 1:
        _show_run(job, results[0], out)
    else:
        _show_runs(job, results, dirs)
    return 0


def _show_runs(job: JobConfig, results: list[dict[str, Any]], dirs: list[Path]) -> None:
    """A population's runs, one row each, and their mean."""
    from convoy.stats import ci95_half

    table = Table(title=f"{job.algo} on {job.env}: {len(results)} runs")
    for col in ("seed", "greedy return (95 % CI)", "best greedy point (step)", "ε-greedy return (last 10 %)"):
        table.add_column(col, justify="right")
    for s, r in zip(job.run_seeds(), results, strict=True):
        best = f"{r['best_eval_return']:.3f} ({r['best_eval_step']:,})" if r["best_eval_step"] >= 0 else "–"
        table.add_row(str(s), f"{r['eval_return']:.3f} ± {r['eval_ci95']:.3f}", best, f"{r['final_return']:.3f}")
    finals = [r["eval_return"] for r in results]
    table.add_row(
        "[bold]mean over seeds[/]", f"{sum(finals) / len(finals):.3f} ± {ci95_half(np.asarray(finals)):.3f}", "", ""
    )
    console.print(table)
    wall = results[0]["wall_s"]
    steps = sum(r["env_steps"] for r in results)
    console.print(f"{steps:,} env steps in {wall:.1f} s: {steps / max(wall, 1e-9):,.0f} env steps/s over all runs")
    console.print(f"wrote {', '.join(str(d) for d in dirs)} (metrics, curve.png, checkpoint.pt, summary.json each)")


def _show_run(job: JobConfig, s: dict[str, Any], out: Path) -> None:
    """One run's figures, and a warning when its messages carry nothing."""
    table = Table(title=f"{job.algo} on {job.env}")
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_row("env steps", f"{s['env_steps']:,}")
    table.add_row("episodes", f"{s['episodes']:,}")
    table.add_row("updates", f"{s['updates']:,}")
    table.add_row("wall time", f"{s['wall_s']:.1f} s")
    table.add_row("env steps/s", f"{s['env_steps'] / max(s['wall_s'], 1e-9):,.0f}")
    table.add_row("updates/s", f"{s['updates'] / max(s['wall_s'], 1e-9):,.1f}")
    table.add_row("ε-greedy training return (last 10 % of episodes)", f"{s['final_return']:.3f}")
    greedy = f"{s['eval_return']:.3f} ± {s['eval_ci95']:.3f}"
    table.add_row(f"[bold]greedy return[/] ({job.eval_episodes} episodes, 95 % CI)", greedy)
    if s.get("best_eval_step", -1) >= 0:
        table.add_row(f"best greedy point (step {s['best_eval_step']:,}, best.pt)", f"{s['best_eval_return']:.3f}")
    for name, (mean, ci) in (s.get("references") or {"random": [s["random_return"], float("nan")]}).items():
        table.add_row(f"reference: {name}", f"{mean:.3f} ± {ci:.3f}")
    if "dropped" in s:
        table.add_row("messages dropped (corrupt / foreign)", f"{s['dropped']:,}")
    console.print(table)
    best = ", best.pt" if s.get("best_eval_step", -1) >= 0 else ""
    console.print(f"wrote {out}/metrics.jsonl, metrics.csv, curve.png, checkpoint.pt{best}, summary.json")
    warn_constant_messages(out / "checkpoint.pt")


def warn_constant_messages(checkpoint: Path, steps: int = 100, envs: int = 16) -> float | None:
    """Say so when a trained policy sends one message whatever it sees: its messages carry nothing, and a probe
    of them (``--messages noise``, ``convoy analyze``) says nothing about communication. The entropy in nats of
    the messages of ``steps`` greedy steps of ``envs`` envs (None for algorithms without discrete messages)."""
    from convoy.algos.checkpoint import load_checkpoint
    from convoy.algos.listening import HearsMessages
    from convoy.analysis.comm_metrics import entropy, symbols
    from convoy.analysis.recording import record
    from convoy.services.training import make_env

    algo, job, _ = load_checkpoint(checkpoint, device="cpu")
    if not isinstance(algo, HearsMessages):
        return None
    env = make_env(job, envs)
    try:
        sent = symbols(record(algo, env, steps, seed=job.seed + 20_000).messages)  # [T, B, N]
    finally:
        env.close()
    h = entropy(sent.reshape(-1))
    if h < 0.01:
        console.print(
            f"[bold yellow]warning:[/] every message this policy sent in {steps * envs:,} greedy steps was the same "
            f"(entropy {h:.3f} nats): its messages carry nothing, so probing them (convoy eval --messages noise, "
            "convoy analyze) says nothing about communication. Longer training, or --hp signalling_coef, changes "
            "that.",
            highlight=False,
        )
    return h


def _algo_epilog() -> str:
    lines = ["algorithms (--algo):"]
    lines += [f"  {name:9} {ALGORITHMS[name].summary}" for name in ALGORITHMS]
    lines.append("\nhyper-parameters (--hp KEY=VALUE; the algorithms that have a field in parentheses):")
    for name, info in AlgoConfig.model_fields.items():
        lines.append(f"  {name} (default {info.default!r}{env_default_note(name)}): {info.description}")
    extras: dict[str, list[str]] = {}
    for algo, model in ((n, a.config) for n, a in ALGORITHMS.items()):
        for name in model.model_fields:
            if name not in AlgoConfig.model_fields:
                extras.setdefault(name, []).append(algo)
    for name, algos in extras.items():
        info = ALGORITHMS[algos[0]].config.model_fields[name]
        note = env_default_note(name)
        lines.append(f"  {name} ({', '.join(algos)}; default {info.default!r}{note}): {info.description}")
    lines.append("\nenv parameters (--set KEY=VALUE): convoy env list --params")
    return "\n".join(lines)


def add_train_parser(sub: argparse._SubParsersAction) -> None:
    tr = add_command(
        sub, "train", cmd_train, epilog=_algo_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter
    )
    tr.add_argument(
        "--inprocess", action="store_true", help="run envs and learner in this one process (the reference baseline)"
    )
    tr.add_argument("--job-id", help="Zenoh job id (default: the --out directory's name + a random suffix)")
    add_job_arguments(tr)
    tr.add_argument(
        "--out",
        metavar="DIR",
        help="output directory, one run each (default runs/ALGO-ENV, or runs/ALGO-ENV-2, -3, … when that holds a run)",
    )
    tr.add_argument("--overwrite", action="store_true", help="replace the run already in --out")
    tr.add_argument(
        "--resume",
        metavar="DIR",
        help="go on with the run in DIR (its job.json, checkpoint and replay) up to its steps, or to a new --steps; "
        "the way it was started (in this process or with actors); only --steps, --device, --threads, --actors, "
        "--runtime and --hp compile=true|false may change",
    )
    tr.add_argument("--no-progress", action="store_true", help="no progress bar (for logs)")
    add_limit_flags(tr)


def add_job_arguments(tr: argparse.ArgumentParser) -> None:
    """The flags that build a JobConfig (``job_from_args``): shared by train and the single-role commands."""
    add_job_flags(tr)
    add_model_flags(
        tr, JobConfig, ("seeds", "device", "torch_threads", "checkpoint_every"), flags={"torch_threads": "--threads"}
    )
    tr.add_argument(
        "--logger",
        dest="loggers",
        action="append",
        choices=("wandb", "mlflow"),
        help="also send metrics and the summary to this tracker (repeatable; every run writes TensorBoard files to "
        "RUN/tb/); each an optional extra: pip install 'convoy[wandb]'",
    )
    tr.add_argument("--config", metavar="FILE", help="job config as JSON or TOML; flags override its values")


JOB_FLAGS = JOB_FIELDS  # one list with the sweep grid's job fields (convoy/config.py)


def add_job_flags(tr: argparse.ArgumentParser) -> None:
    """What to train, on what, for how long: the job flags of ``convoy train`` and ``convoy jobs submit`` alike,
    made from JobConfig's fields (type, description, default), plus the maps (``--set``, ``--hp``, ``--runtime``)."""
    tr.add_argument("--actors", type=int, help="actor processes (default 2; distributed runs only)")
    add_model_flags(tr, JobConfig, JOB_FLAGS)
    tr.add_argument("--agents", type=int, help="treadmill: cooperative cars (n_agents)")
    tr.add_argument("--adversaries", type=int, help="treadmill: adversary cars (n_adversaries)")
    tr.add_argument("--set", action="append", metavar="KEY=VALUE", help="env parameter, repeatable")
    tr.add_argument("--hp", action="append", metavar="KEY=VALUE", help="algorithm hyper-parameter, repeatable")
    tr.add_argument(
        "--runtime",
        action="append",
        metavar="KEY=VALUE",
        help="distributed runtime setting, repeatable (e.g. actor_max_restarts=500; all: docs/training.md)",
    )
