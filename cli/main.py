"""The ``convoy`` command line. Errors in user input are printed as one line, never as a traceback."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from convoy.algos.errors import CheckpointError
from convoy.cli.args import add_command, env_params, in_flag_words
from convoy.envs import ENVS, make_batched
from convoy.envs.registry import env_entry
from convoy.envs.rollout import RolloutResult, random_policy, rollout
from convoy.envs.treadmill.references import REFERENCES
from convoy.output import save_figure
from convoy.protocol.reports import setup_logging
from convoy.services.procs import JobFailed
from convoy.validation import ConfigError, build_config

console = Console()
err_console = Console(stderr=True)


def describe(params: dict[str, dict[str, Any]], names: list[str] | None = None) -> str:
    """One line per parameter (``convoy.catalog``): default, allowed range, meaning."""
    lines = []
    for field in names or params:
        p = params[field]
        extra = f", {p['range']}" if p["range"] else ""
        lines.append(f"  {field} (default {p['default']!r}{extra}): {p['description']}")
    return "\n".join(lines)


def describe_params(name: str) -> str:
    """One line per parameter of env ``name``: default, allowed range, meaning (from its pydantic model)."""
    from convoy.catalog import parameters

    return describe(parameters(ENVS[name].config()))


def cmd_algos(args: argparse.Namespace) -> int:
    """List the algorithms.

    List the algorithms and, with --params, their hyper-parameters (--hp KEY=VALUE) with defaults, ranges and the
    values each env sets; --json prints the same as GET /algos.
    """
    from convoy.catalog import algos

    table_ = algos()
    if args.json:
        print(json.dumps(table_, indent=2))
        return 0
    table = Table(title="Convoy algorithms")
    table.add_column("name")
    table.add_column("what it is")
    for name, entry in table_.items():
        table.add_row(name, entry["summary"])
    console.print(table)
    if not args.params:
        console.print("Each algorithm's hyper-parameters, defaults, ranges and env defaults: convoy algos --params")
        return 0
    common = list(next(iter(table_.values()))["params"])
    common = [k for k in common if all(k in e["params"] for e in table_.values())]
    console.print(f"\n[bold]every algorithm[/] (--hp KEY=VALUE):\n{describe(table_['idqn']['params'], common)}",
                  highlight=False, soft_wrap=True)  # fmt: skip
    for name, entry in table_.items():
        own = describe(entry["params"], entry["own"]) if entry["own"] else "  (none of its own)"
        set_by = "; ".join(f"{env}: " + ", ".join(f"{k}={v}" for k, v in d.items())
                           for env, d in entry["env_defaults"].items() if d)  # fmt: skip
        console.print(f"\n[bold]{name}[/] — its own:\n{own}\n  env defaults: {set_by}", highlight=False,
                      soft_wrap=True)  # fmt: skip
    return 0


def cmd_env_list(args: argparse.Namespace) -> int:
    """List the environments.

    List the environments and, with --params, their parameters.
    """
    table = Table(title="Convoy environments")
    table.add_column("name")
    table.add_column("what it is")
    for name, entry in ENVS.items():
        table.add_row(name, entry.summary)
    console.print(table)
    if args.params:
        for name in ENVS:
            text = f"\n[bold]{name}[/] parameters (--set KEY=VALUE):\n{describe_params(name)}"
            console.print(text, highlight=False, soft_wrap=True)
    else:
        console.print("Each env's parameters, defaults and ranges: convoy env list --params")
    return 0


def cmd_env_rollout(args: argparse.Namespace) -> int:
    """Play episodes with a reference policy (random, constant, scripted, full-information) and summarise.

    Play EPISODES episodes (all in one batch) and print a per-episode table with the mean return and its 95 %
    confidence interval. Optionally write a GIF of episode 0 (treadmill), a JSON summary and a PNG of the
    returns.
    """
    if args.episodes < 1:
        raise ConfigError("--episodes", f"must be ≥ 1 (got {args.episodes})")
    is_treadmill = env_entry(args.env) is ENVS["treadmill"]  # also rejects unknown names first
    params = env_params(args)
    if args.policy != "random" and not is_treadmill:
        raise ConfigError("--policy", f"the {args.policy} policy drives the treadmill only; use --policy random")
    if args.gif and not is_treadmill:
        raise ConfigError("--gif", "only the treadmill renders GIFs so far; drop --gif")
    render = None
    if is_treadmill:
        from convoy.envs.treadmill import TreadmillConfig, TreadmillEngine, reference_policy, render_frame

        cfg = build_config(TreadmillConfig, **params)
        env = TreadmillEngine(cfg, args.episodes, autoreset=False)  # keeps each episode's last frame for the GIF
        if args.gif:
            render = lambda: render_frame(env.x[0], env.y[0], env.heading[0], cfg.n_agents, cfg.length, cfg.width)  # noqa: E731
    else:
        env = make_batched(args.env, args.episodes, **params)  # type: ignore[assignment]  # not a treadmill: no GIF
    policy = reference_policy(args.policy, env, args.seed) if is_treadmill else random_policy(env.spec, args.seed)
    result = rollout(env, policy, seed=args.seed, render=render)
    _print_rollout(args, env.spec.agent_ids, result)
    if args.gif:
        from convoy.envs.treadmill import write_gif

        Path(args.gif).parent.mkdir(parents=True, exist_ok=True)
        write_gif(result.frames, args.gif)
        console.print(f"wrote {args.gif} ({len(result.frames)} frames of episode 0)")
    if args.summary:
        _write_summary(args, params, result)
    if args.plot:
        _plot_returns(args, env.spec.agent_ids, result)
    return 0


def _print_rollout(args: argparse.Namespace, agent_ids: tuple[str, ...], result: RolloutResult) -> None:
    table = Table(title=f"{args.env}: {args.episodes} episodes, {args.policy} policy, seed {args.seed}")
    table.add_column("episode", justify="right")
    table.add_column("steps", justify="right")
    table.add_column("ended by")
    table.add_column("mean return", justify="right")
    for aid in agent_ids:
        table.add_column(aid, justify="right")
    shown = min(len(result.lengths), args.show)
    for i in range(shown):
        ended = "crash/terminal" if result.terminated[i] else "time limit"
        row = [str(i), str(result.lengths[i]), ended, f"{result.mean_return[i]:.2f}"]
        table.add_row(*row, *(f"{v:.2f}" for v in result.returns[i]))
    console.print(table)
    if shown < len(result.lengths):
        console.print(f"({len(result.lengths) - shown} more episodes not shown; --show N to list them)")
    mean, half = result.ci95()
    console.print(
        f"mean return {mean:.2f} ± {half:.2f} (95 % CI) | mean length {result.lengths.mean():.1f} | "
        f"terminated {result.terminated.mean():.0%} | {result.env_steps_per_s:,.0f} env-steps/s",
        soft_wrap=True,
    )


def _write_summary(args: argparse.Namespace, params: dict[str, Any], result: RolloutResult) -> None:
    mean, half = result.ci95()
    summary = {
        "env": args.env,
        "params": params,
        "policy": args.policy,
        "seed": args.seed,
        "episodes": len(result.lengths),
        "mean_return": mean,
        "ci95": half,
        "mean_length": float(result.lengths.mean()),
        "terminated_fraction": float(result.terminated.mean()),
        "env_steps_per_s": result.env_steps_per_s,
        "episode_returns": result.returns.round(4).tolist(),
        "episode_lengths": result.lengths.tolist(),
    }
    Path(args.summary).parent.mkdir(parents=True, exist_ok=True)
    Path(args.summary).write_text(json.dumps(summary, indent=2))
    console.print(f"wrote {args.summary}")


def _plot_returns(args: argparse.Namespace, agent_ids: tuple[str, ...], result: RolloutResult) -> None:
    from convoy.output import pyplot

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(8, 4))
    episodes = np.arange(len(result.lengths))
    width = 0.8 / len(agent_ids)
    for i, aid in enumerate(agent_ids):
        ax.bar(episodes + i * width, result.returns[:, i], width, label=aid)
    mean, half = result.ci95()
    ax.axhline(mean, color="k", lw=1, ls="--", label=f"mean {mean:.1f} ± {half:.1f}")
    ax.set_xlabel("episode")
    ax.set_ylabel("return")
    ax.set_title(f"{args.env}, {args.policy} policy")
    ax.set_xticks(episodes + 0.4 - width / 2, [str(e) for e in episodes], fontsize=7)
    ax.legend(fontsize=8, ncol=len(agent_ids) + 1, loc="upper center", bbox_to_anchor=(0.5, -0.15))
    save_figure(fig, args.plot, dpi=100)
    console.print(f"wrote {args.plot}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="convoy",
        description="Convoy: train cooperating, communicating agents (treadmill highway, particle envs).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    env = sub.add_parser("env", help="inspect and run environments", description="Inspect and run environments.")
    env_sub = env.add_subparsers(dest="env_command", required=True, metavar="ENV_COMMAND")

    lst = add_command(env_sub, "list", cmd_env_list)
    lst.add_argument("--params", action="store_true", help="also list every parameter with its default and range")
    alg = add_command(sub, "algos", cmd_algos)
    alg.add_argument("--params", action="store_true", help="also list every hyper-parameter and the env defaults")
    alg.add_argument("--json", action="store_true", help="print the catalogue as JSON (what GET /algos returns)")

    ro = add_command(
        env_sub,
        "rollout",
        cmd_env_rollout,
        epilog="treadmill parameters for --set (see docs/treadmill.md; other envs: convoy env list --params):\n"
        + describe_params("treadmill"),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ro.add_argument("--env", default="treadmill", help=f"environment: {', '.join(ENVS)} (default: %(default)s)")
    ro.add_argument("--agents", type=int, help="treadmill: cooperative cars (n_agents, default 3)")
    ro.add_argument("--adversaries", type=int, help="treadmill: adversary cars (n_adversaries, default 1)")
    ro.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="any env parameter, repeatable, e.g. --set aggression=0.9 --set max_steps=100 (listed below)",
    )
    ro.add_argument("--episodes", type=int, default=5, help="episodes to play (default: %(default)s)")
    ro.add_argument(
        "--policy",
        choices=REFERENCES,
        default="scripted",
        metavar="POLICY",
        help="who drives the agents: random; constant-0 … constant-8 (one action throughout); scripted (private "
        "observations); team-information (also told of every adversary some agent observes); full-information "
        "(knows every car and which are adversaries); private-driver, team-driver, team16-driver (the tuned "
        "reactive driver on its own sensor, told its teammates' observations, told a 16-bit code per teammate); "
        "private-planner, team16-planner, team-planner, full-planner (the tuned model-predictive driver on its own "
        "sensor, told a 16-bit word per teammate, told its teammates' observations, told every car: the strongest "
        "references); drivers and planners play the parameters tuned on the charger rules (--set adversary_speed=7 "
        "--set adversary_steer_speed=3 --set adversary_stealth=true) there, else those tuned on the defaults; all "
        "but random are treadmill-only (default: %(default)s)",
    )
    ro.add_argument(
        "--seed", type=int, default=0, help="seed of the envs and of the random policy (default: %(default)s)"
    )
    ro.add_argument("--gif", metavar="PATH", help="write an animated GIF of episode 0 (treadmill)")
    ro.add_argument("--summary", metavar="PATH", help="write the figures as JSON")
    ro.add_argument("--plot", metavar="PATH", help="write a PNG bar chart of each agent's return per episode")
    ro.add_argument("--show", type=int, default=20, help="episodes listed in the table (default: %(default)s)")

    from convoy.cli.compare import add_compare_parser
    from convoy.cli.evaluate import add_eval_parsers
    from convoy.cli.jobs import add_jobs_parser
    from convoy.cli.reproduce import add_reproduce_parser
    from convoy.cli.roles import add_role_parsers
    from convoy.cli.serve import add_serve_parser
    from convoy.cli.sweep import add_sweep_parser
    from convoy.cli.train import add_train_parser

    add_train_parser(sub)
    add_eval_parsers(sub)
    add_compare_parser(sub)
    add_serve_parser(sub)
    add_jobs_parser(sub)
    add_sweep_parser(sub)
    add_reproduce_parser(sub)
    add_role_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    setup_logging()  # the runtime's log lines to stdout; `convoy serve` and `convoy host` add their own
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, ValidationError, CheckpointError) as exc:
        if isinstance(exc, ConfigError):  # in the words the user typed: --steps, --hp lr, not the field's name
            exc = in_flag_words(exc, args)
        err_console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        return 2
    except JobFailed as exc:
        err_console.print(f"[bold red]job failed:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        return 1
    except FloatingPointError as exc:  # the in-process trainer's NetworkAgent.update gave up on non-finite losses
        err_console.print(
            f"[bold red]job failed:[/] training diverged: {escape(str(exc))}", highlight=False, soft_wrap=True
        )
        return 1
    except KeyboardInterrupt:
        err_console.print("interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
