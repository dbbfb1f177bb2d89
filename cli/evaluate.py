"""``convoy eval`` and ``convoy analyze``: measure a trained checkpoint — its return under a chosen message source
or channel, and the emergent-communication figures of the paper's Table 1."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console

from convoy.cli.args import add_command
from convoy.config import MESSAGE_SOURCES
from convoy.validation import ConfigError

console = Console()

CHANNEL_HELP = (
    "put a lossy channel between senders and receivers, e.g. drop=0.3,flip=0.01 (keys: drop, flip, latency=0|1); "
    "memory-module algorithms (-mm) replace lost messages with their predictions, the others hear zeros"
)


def load(path: str, device: str) -> tuple[Any, Any, dict[str, Any]]:
    """(algorithm, job, counters) of a checkpoint; a bad file is a CheckpointError that says what to do."""
    from convoy.algos.checkpoint import load_checkpoint

    if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
        raise ConfigError("--device", f"unknown device {device!r}; use auto, cpu, cuda or cuda:N")

    return load_checkpoint(path, device=device)


def cmd_eval(args: argparse.Namespace) -> int:
    """Evaluate a checkpoint's greedy policy (message source, channel, GIF).

    Play EPISODES greedy episodes of a checkpoint's policy and print the mean return with its 95 % confidence
    interval, next to the random policy's. --messages and --channel probe the communication: messages shuffled
    across envs or each sender's modal message (in distribution: real messages, no content), all-zero messages (a
    cut channel), white noise in place of messages, the memory module's predictions (no channel, -mm algorithms),
    or a lossy channel. A probe also plays the same episodes with the true messages and prints that return and the
    paired difference (probe − true) with its 95 % CI: whether the messages matter.
    """
    from convoy.analysis.evaluation import evaluate_policy, evaluate_random, parse_channel
    from convoy.services.training import make_env
    from convoy.stats import ci95_half

    if args.episodes < 1:
        raise ConfigError("--episodes", f"must be ≥ 1 (got {args.episodes})")
    if args.channel:
        parse_channel(args.channel)  # a typo fails before the checkpoint is loaded
    algo, job, counters = load(args.checkpoint, args.device)
    if args.gif and job.env != "treadmill":
        raise ConfigError("--gif", f"only the treadmill renders GIFs ({args.checkpoint} was trained on {job.env})")
    console.print(
        f"[bold]{args.checkpoint}[/]: {job.algo}{' (hierarchical)' if job.hierarchical else ''} on {job.env}, "
        f"trained {counters.get('env_steps', 0):,} env steps / {counters.get('updates', 0):,} updates",
        highlight=False,
        soft_wrap=True,
    )
    probe = args.messages != "sent" or bool(args.channel)
    env = make_env(job, min(args.episodes, args.num_envs))
    try:
        result = evaluate_policy(algo, env, args.episodes, seed=args.seed, messages=args.messages, channel=args.channel)
        # a probe answers "do the messages matter?": the true messages on the same episodes, and the paired difference
        true = evaluate_policy(algo, env, args.episodes, seed=args.seed) if probe else None
        rand = evaluate_random(env, args.episodes, seed=args.seed)
    finally:
        env.close()
    diff = result.returns - true.returns if true is not None else None
    if true is not None and diff is not None:
        console.print(f"true messages:  {true.describe()}", highlight=False, soft_wrap=True)
        paired = f"{diff.mean():+.3f} ± {ci95_half(diff, single=0.0):.3f}"
        console.print(f"greedy return:  {result.describe()}; paired vs true messages {paired} (95 % CI, same "
                      "episodes)", highlight=False, soft_wrap=True)  # fmt: skip
    else:
        console.print(f"greedy return:  {result.describe()}", highlight=False, soft_wrap=True)
    console.print(f"random policy:  {rand.mean():.3f} ± {ci95_half(rand, single=0.0):.3f}", highlight=False)
    if args.gif:
        frames = gif_episode(algo, job, args)
        console.print(f"wrote {args.gif} ({frames} frames of one greedy episode)")
    if args.json:
        summary = {
            "checkpoint": args.checkpoint,
            "algo": job.algo,
            "env": job.env,
            "messages": args.messages,
            "channel": args.channel,
            "episodes": args.episodes,
            "mean_return": result.mean,
            "ci95": result.ci95,
            "random_return": float(rand.mean()),
            "returns": result.returns.tolist(),
        }
        if true is not None and diff is not None:  # the same episodes with the true messages, and the paired gap
            summary.update(true_return=true.mean, true_ci95=true.ci95, true_returns=true.returns.tolist(),
                           paired_difference=float(diff.mean()), paired_ci95=ci95_half(diff, single=0.0))  # fmt: skip
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
        console.print(f"wrote {args.json}")
    return 0


def gif_episode(algo: Any, job: Any, args: argparse.Namespace) -> int:
    """Play one greedy treadmill episode (same message source and channel) and write it as a GIF."""

    from convoy.actors.stepping import AgentPolicy
    from convoy.analysis.evaluation import listening, listening_for
    from convoy.envs.rollout import rollout
    from convoy.envs.treadmill import TreadmillEngine, render_frame, write_gif

    cfg = job.env_config()
    env = TreadmillEngine(cfg, 1, autoreset=False)
    policy = AgentPolicy(algo, 1)

    def draw() -> Any:
        return render_frame(env.x[0], env.y[0], env.heading[0], cfg.n_agents, cfg.length, cfg.width)

    with listening(algo, listening_for(algo, args.messages, args.channel, args.seed)):
        result = rollout(env, policy, seed=args.seed, render=draw, after_step=policy.after_step)
    Path(args.gif).parent.mkdir(parents=True, exist_ok=True)
    write_gif(result.frames, args.gif)
    return len(result.frames)


class AnalyzeProgress:
    """What ``convoy analyze`` is doing, on stderr: the recording's samples with an estimate of the time left (its
    first step, then at most every ``every_s``), then each later stage."""

    def __init__(self, num_envs: int, every_s: float = 5.0) -> None:
        self.num_envs, self.every_s = num_envs, every_s
        self.t0 = time.monotonic()
        self.last = -math.inf

    def say(self, what: str) -> None:
        print(f"convoy analyze: {what}", file=sys.stderr, flush=True)

    def __call__(self, done: int, steps: int) -> None:
        now = time.monotonic()
        if now - self.last < self.every_s and done < steps:
            return
        self.last = now
        left = (now - self.t0) / done * (steps - done)
        samples = f"{done * self.num_envs:,} / {steps * self.num_envs:,} samples"
        self.say(f"recording {samples} ({100 * done / steps:.0f} %), ~{duration(left)} left")


def duration(seconds: float) -> str:
    """``seconds`` as ``1h02m``, ``3m05s`` or ``12s``."""
    s = round(seconds)
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    return f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


def cmd_analyze(args: argparse.Namespace) -> int:
    """Emergent-communication metrics of a checkpoint (the paper's Table 1).

    Record the greedy policy's messages and actions and report speaker consistency, instantaneous coordination,
    causal influence of communication (the listeners' actions when they hear another env's messages instead)
    (plug-in mutual information in nats, each next to its shuffled-pairs baseline and per message bit), message
    entropy, the message-input norm and the return with true messages vs messages shuffled across envs, each
    sender's modal message, all-zero messages and white noise, each paired with the true messages (and predicted
    messages for -mm algorithms). Writes table.md, analysis.json, metrics.png and cooccurrence.png.
    """
    from convoy.analysis.recording import analyze, check_analysable
    from convoy.services.training import make_env

    for flag in ("samples", "episodes", "repeats"):
        if getattr(args, flag) < 1:
            raise ConfigError(f"--{flag}", f"must be ≥ 1 (got {getattr(args, flag)})")
    algo, job, _ = load(args.checkpoint, args.device)
    check_analysable(algo)  # refused in one line, before the plan is announced
    out = Path(args.out) if args.out else Path(args.checkpoint).resolve().parent / "analysis"
    env = make_env(job, args.num_envs)
    try:
        steps = -(-args.samples // env.num_envs)
        progress = AnalyzeProgress(env.num_envs)
        progress.say(f"{algo.name} on {job.env}: recording {steps * env.num_envs:,} samples ({steps:,} steps × "
                     f"{env.num_envs} envs), then {args.episodes} episodes per return figure")  # fmt: skip
        result = analyze(algo, env, job.env, steps, args.episodes, args.seed, out_dir=out, repeats=args.repeats,
                         progress=progress, say=progress.say)  # fmt: skip
    finally:
        env.close()
    console.print(result.table(), highlight=False, soft_wrap=True)
    console.print()
    for what, path in result.files.items():
        console.print(f"wrote {path}  ({what})", highlight=False)
    return 0


def add_eval_parsers(sub: argparse._SubParsersAction) -> None:
    ev = add_command(sub, "eval", cmd_eval)
    ev.add_argument("checkpoint", help="a checkpoint.pt written by convoy train")
    ev.add_argument("--episodes", type=int, default=100, help="greedy episodes to play (default: %(default)s)")
    ev.add_argument(
        "--messages",
        choices=MESSAGE_SOURCES,
        default="sent",
        help="what the agents hear: sent (the true messages), shuffled (another env's messages of the step), modal "
        "(each sender's most frequent message so far), fixed (all-zero bits: a cut channel), noise (uniform random "
        "bits) or predicted (the memory module's predictions, no channel: -mm algorithms) (default: %(default)s)",
    )
    ev.add_argument("--channel", metavar="SPEC", help=CHANNEL_HELP)
    ev.add_argument("--gif", metavar="PATH", help="also write an animated GIF of one greedy episode (treadmill)")
    ev.add_argument("--json", metavar="PATH", help="write the figures and every episode's return as JSON")
    ev.add_argument("--seed", type=int, default=12345, help="seed of the evaluation envs (default: %(default)s)")
    ev.add_argument("--num-envs", type=int, default=256, help="envs played at once (default: %(default)s)")
    ev.add_argument("--device", default="auto", help="torch device: auto, cpu or cuda (default: %(default)s)")

    an = add_command(sub, "analyze", cmd_analyze)
    an.add_argument("checkpoint", help="a checkpoint.pt of ma-mesn, ma-bon, ma-mesn-mm or ma-bon-mm")
    an.add_argument(
        "--samples",
        type=int,
        default=204_800,
        help="env steps × envs recorded for the MI figures; plug-in MI is biased upward by about "
        "(symbols − 1)(actions − 1) / 2·samples, so 2-byte messages need ~10⁵ samples before a figure can stand "
        "clear of its shuffled baseline (default: %(default)s)",
    )
    an.add_argument("--episodes", type=int, default=100, help="episodes per return figure (default: %(default)s)")
    an.add_argument("--repeats", type=int, default=20, help="shuffles for each baseline (default: %(default)s)")
    an.add_argument("--out", metavar="DIR", help="where to write the files (default: analysis/ next to the checkpoint)")
    an.add_argument("--seed", type=int, default=12345, help="seed of the envs and shuffles (default: %(default)s)")
    an.add_argument("--num-envs", type=int, default=256, help="envs played at once (default: %(default)s)")
    an.add_argument("--device", default="auto", help="torch device: auto, cpu or cuda (default: %(default)s)")
