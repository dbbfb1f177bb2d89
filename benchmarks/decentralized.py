"""Decentralised execution on the treadmill (the paper's section 6.4): MA-MeSN-MM with no channel against
independent DQN, DQN with stabilised experience replay and CoDBC, plus a channel-robustness table.

What runs, per seed, in one process each (the in-process trainer; same env, network sizes, env-step budget):

1. **MA-MeSN-MM** — centralised MA-MeSN training with the memory modules trained in parallel. Its curve is the
   *decentralised* policy: every ``--eval-every`` steps a greedy evaluation with ``messages=predicted`` (no channel
   at all, each agent's memory module supplies the messages).
2. **Independent DQN** and **DQN + SER** — decentralised by construction; curves are greedy evaluations too.
3. **CoDBC** — behaviour cloning of the MA-MeSN policy trained in step 1 (its checkpoint, heard with true
   messages, is the teacher), for the same budget. It can only start after step 1 (the paper's objection), so its
   curve is drawn shifted right by the teacher's training steps.

The table gives each method's final greedy return with no channel (``--final-episodes`` episodes per seed) and the
mean of its last three curve points (less sensitive to where a DQN's greedy policy happens to oscillate at the last
step), each as mean ± 95 % CI over seeds (Student t), and the env-steps each needed in total.

The channel table evaluates the trained MA-MeSN-MM checkpoints as the packet-drop probability goes 0 → 0.5 → 1.0:
the same policy hearing zeros for lost messages (plain MA-MeSN: the memory module's parameters are separate and its
loss is detached, so training it does not change the centralised networks) against hearing its memory module's
prediction for them (MA-MeSN-MM).

The env is a small treadmill (3 agents + 1 adversary on a 30 × 12 road, 50-step episodes) and the networks are one
hidden layer of 64 units, so that 5 seeds × 4 methods fit in a few minutes on 2 cores; the paper's runs are far
longer. ``--quick`` is a smoke run (numbers meaningless). Writes a PNG of the curves and, with ``--json``, every
figure.

Run: ``python benchmarks/decentralized.py`` (about 5 minutes on 2 cores with the defaults).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Literal

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.algos.agent import make_agent  # noqa: E402
from convoy.algos.checkpoint import load_checkpoint  # noqa: E402
from convoy.algos.listening import Source  # noqa: E402
from convoy.analysis.evaluation import evaluate_policy  # noqa: E402
from convoy.config import JobConfig, job_config  # noqa: E402
from convoy.learner.inprocess import Trainer  # noqa: E402
from convoy.learner.runtime import configure_learner  # noqa: E402
from convoy.output import pyplot, save_figure  # noqa: E402
from convoy.services.training import make_env  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402

TREADMILL = {"n_agents": 3, "n_adversaries": 1, "length": 30, "width": 12, "max_steps": 50}
HP = {"hidden": (64,), "learning_starts": 500, "replay_ratio": 4.0, "target_update": 100, "gamma": 0.95, "lr": 1e-3}
MEMORY_HP = {"memory_window": 8, "memory_hidden": 64}
METHODS = ("ma-mesn-mm", "idqn", "dqn-ser", "codbc")
LABELS = {
    "ma-mesn-mm": "MA-MeSN-MM (no channel)",
    "idqn": "independent DQN",
    "dqn-ser": "DQN + SER",
    "codbc": "CoDBC (after MA-MeSN)",
}
DROPS = (0.0, 0.5, 1.0)


def t_ci95(values: np.ndarray) -> float:
    """Half-width of the 95 % Student-t interval of the mean (0 for one value)."""
    return ci95_half(values, single=0.0)


def train(job: JobConfig, out_dir: Path, eval_episodes: int, messages: Source) -> tuple[list[tuple[int, float]], Any]:
    """Train ``job`` in-process with a greedy evaluation (hearing ``messages``) at every metric row."""
    configure_learner(job.torch_threads)
    env, eval_env = make_env(job), make_env(job, min(eval_episodes, 256))
    algo = make_agent(job, env.spec)
    curve: list[tuple[int, float]] = []

    def on_row(steps: int) -> dict[str, float]:
        ret = evaluate_policy(algo, eval_env, eval_episodes, seed=job.seed + 777, messages=messages).mean
        curve.append((steps, ret))
        return {"eval_return": ret}

    try:
        Trainer(job, env, algo, out_dir=out_dir, progress=False, on_row=on_row).run()
    finally:
        env.close()
        eval_env.close()
    return curve, algo


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--steps", type=int, default=30_000, help="env steps per run (default %(default)s)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="seeds (default %(default)s)")
    p.add_argument("--num-envs", type=int, default=16, help="envs stepped together (default %(default)s)")
    p.add_argument("--eval-every", type=int, default=5_000, help="env steps between curve points (default %(default)s)")
    p.add_argument(
        "--eval-episodes", type=int, default=64, help="greedy episodes per curve point (default %(default)s)"
    )
    p.add_argument(
        "--final-episodes", type=int, default=200, help="greedy episodes per final figure (default %(default)s)"
    )
    p.add_argument("--quick", action="store_true", help="a smoke run of a few seconds")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--plot", metavar="PATH", default="runs/bench/decentralized.png", help="PNG of the curves")
    p.add_argument("--out", metavar="DIR", help="keep the runs (checkpoints, metrics) here; default a temp dir")
    args = p.parse_args(argv)
    if args.quick:
        args.steps, args.eval_every, args.eval_episodes, args.final_episodes = 1_500, 500, 8, 8
        args.seeds = args.seeds[:2]
    console = Console(width=120)
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="convoy-decentralized-"))
    hp = dict(HP, learning_starts=200) if args.quick else HP
    runs: list[dict[str, Any]] = []
    channel_rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    for seed in args.seeds:
        mm_ckpt = root / f"ma-mesn-mm-{seed}" / "checkpoint.pt"
        for method in METHODS:
            params = dict(hp)
            if method == "ma-mesn-mm":
                params.update(MEMORY_HP)
            if method == "codbc":
                params["teacher"] = str(mm_ckpt)
            job = job_config(
                algo=method,
                env="treadmill",
                env_params=TREADMILL,
                algo_params=params,
                steps=args.steps,
                num_envs=args.num_envs,
                seed=seed,
                eval_episodes=0,
                log_every=args.eval_every,
                checkpoint_every=10**9,
            )
            heard: Source = "predicted" if method == "ma-mesn-mm" else "sent"
            t0 = time.perf_counter()
            curve, algo = train(job, root / f"{method}-{seed}", args.eval_episodes, heard)
            wall = time.perf_counter() - t0
            final_env = make_env(job, min(args.final_episodes, 256))
            final = evaluate_policy(algo, final_env, args.final_episodes, seed=10_000 + seed, messages=heard)
            random = evaluate_policy(algo, final_env, args.final_episodes, seed=10_000 + seed, epsilon=1.0)
            offset = args.steps if method == "codbc" else 0  # CoDBC starts once its teacher is trained
            runs.append(
                {
                    "method": method,
                    "seed": seed,
                    "final_return": final.mean,
                    "final_ci95": final.ci95,
                    "random_return": random.mean,
                    "total_env_steps": args.steps + offset,
                    "wall_s": wall,
                    "curve": [(s + offset, r) for s, r in curve],
                }
            )
            console.print(
                f"seed {seed} {LABELS[method]:<26} greedy return {final.mean:7.2f} ± {final.ci95:.2f} "
                f"(random {random.mean:.2f}; trained in {wall:.1f} s)",
                highlight=False,
            )
            if method == "ma-mesn-mm":
                channel_rows.extend(channel_robustness(mm_ckpt, job, args.final_episodes, seed))
            final_env.close()
    summary = report(console, runs, channel_rows, args)
    plot(runs, Path(args.plot), args)
    console.print(f"wrote {args.plot} (total {time.perf_counter() - t_start:.0f} s)")
    if args.json:
        data: dict[str, Any] = {
            "settings": {"treadmill": TREADMILL, "hp": hp, "steps": args.steps, "seeds": args.seeds}
        }
        data.update(runs=runs, channel=channel_rows, summary=summary)
        write_json(args.json, data)
    return 0


def channel_robustness(ckpt: Path, job: JobConfig, episodes: int, seed: int) -> list[dict[str, Any]]:
    """The trained MA-MeSN-MM as the drop probability rises: lost messages heard as zeros vs as predictions."""
    algo, _, _ = load_checkpoint(ckpt)
    env = make_env(job, min(episodes, 256))
    rows = []
    try:
        for drop in DROPS:
            fills: tuple[tuple[Literal["zeros", "predicted"], str], ...] = (
                ("zeros", "ma-mesn"),
                ("predicted", "ma-mesn-mm"),
            )
            for fill, label in fills:
                res = evaluate_policy(
                    algo,
                    env,
                    episodes,
                    seed=20_000 + seed,
                    channel=f"drop={drop}",
                    fill_lost=fill,
                )
                rows.append({"seed": seed, "drop": drop, "method": label, "return": res.mean})
    finally:
        env.close()
    return rows


def report(console: Console, runs: list[dict], channel_rows: list[dict], args: argparse.Namespace) -> dict:
    n = len(args.seeds)
    table = Table(title=f"Decentralised execution on a small treadmill, {args.steps:,} env steps per run, {n} seeds")
    cols = ("method", "final greedy return", "± 95 % CI", "last-3-points mean", "± 95 % CI", "env steps", "train s")
    for col in cols:
        table.add_column(col, justify="right")
    summary: dict[str, Any] = {}
    for method in METHODS:
        mine = [r for r in runs if r["method"] == method]
        vals = np.array([r["final_return"] for r in mine])
        late = np.array([np.mean([y for _, y in r["curve"][-3:]]) for r in mine])
        m, ci = float(vals.mean()), t_ci95(vals)
        summary[method] = {
            "mean": m,
            "ci95": ci,
            "per_seed": vals.tolist(),
            "late_mean": float(late.mean()),
            "late_ci95": t_ci95(late),
        }
        wall = np.mean([r["wall_s"] for r in mine])
        table.add_row(
            LABELS[method],
            f"{m:.2f}",
            f"{ci:.2f}",
            f"{late.mean():.2f}",
            f"{t_ci95(late):.2f}",
            f"{mine[0]['total_env_steps']:,}",
            f"{wall:.1f}",
        )
    rand = float(np.mean([r["random_return"] for r in runs]))
    summary["random"] = rand
    table.add_row("random policy", f"{rand:.2f}", "", "", "", "", "")
    console.print(table)
    ch = Table(title="Channel robustness: the trained MA-MeSN policy as messages are dropped (mean over seeds)")
    ch.add_column("drop probability", justify="right")
    ch.add_column("MA-MeSN, lost → zeros", justify="right")
    ch.add_column("MA-MeSN-MM, lost → predicted", justify="right")
    ch.add_column("MM − MeSN (paired by seed)", justify="right")
    summary["channel"] = {}
    for drop in DROPS:
        cells, per = [], {}
        for method in ("ma-mesn", "ma-mesn-mm"):
            rows = sorted(
                (r for r in channel_rows if r["drop"] == drop and r["method"] == method), key=lambda r: r["seed"]
            )
            per[method] = vals = np.array([r["return"] for r in rows])
            cells.append(f"{vals.mean():.2f} ± {t_ci95(vals):.2f}")
            summary["channel"][f"{method}@{drop}"] = float(vals.mean())
        diff = per["ma-mesn-mm"] - per["ma-mesn"]
        ch.add_row(f"{drop:.1f}", *cells, f"{diff.mean():+.2f} ± {t_ci95(diff):.2f}")
    console.print(ch)
    return summary


def plot(runs: list[dict], path: Path, args: argparse.Namespace) -> None:
    plt = pyplot()

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for i, method in enumerate(METHODS):
        curves = [r["curve"] for r in runs if r["method"] == method and r["curve"]]
        if not curves:
            continue
        length = min(len(c) for c in curves)
        xs = np.array([x for x, _ in curves[0][:length]])
        ys = np.array([[y for _, y in c[:length]] for c in curves])
        mean = ys.mean(axis=0)
        half = np.array([t_ci95(ys[:, j]) for j in range(length)])
        colour = f"C{i}"
        ax.plot(xs, mean, color=colour, label=LABELS[method])
        ax.fill_between(xs, mean - half, mean + half, color=colour, alpha=0.18)
    rand = float(np.mean([r["random_return"] for r in runs]))
    ax.axhline(rand, ls="--", color="grey", label=f"random policy ({rand:.1f})")
    ax.axvline(args.steps, ls=":", color="C3", alpha=0.6)
    ax.set_xlabel("env steps (CoDBC: after its MA-MeSN teacher's)")
    ax.set_ylabel("greedy return per agent, no channel")
    ax.set_title(f"Decentralised execution, small treadmill (mean ± 95 % CI over {len(args.seeds)} seeds)")
    ax.legend(fontsize=8)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
