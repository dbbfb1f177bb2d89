"""MA-MeSN against independent DQN on speaker-listener, both trained in the same run, against the known bounds.

The task (appendix B.2): the speaker sees which of three landmarks is the goal, the listener sees the landmarks but
not the goal, and only the speaker's 2-bit message can tell it. Per-agent returns over 25-step episodes have two
reference points measured with scripted listeners (``../shared/docs/zenoh-notes.md``): **−16.0** is the best a
listener can do without communication (head for the landmarks' centre) and **−7.7** is an oracle listener that knows
the goal. Independent DQN cannot beat −16 (its speaker has no channel); a communicating learner should land between
−16 and −8. The issue's target: MA-MeSN better than −12.

Both algorithms use the paper's particle-env settings (one hidden layer of 256, no parameter sharing for these
heterogeneous agents, 2-bit messages, batch 64, double Q) and the same env-step budget, seeds and evaluation
(greedy, ``--eval-episodes`` fresh episodes). Two settings differ from the defaults, for both algorithms alike,
because they reach the communicating regime within this machine's minutes instead of the paper's 7M steps: Adam 1e-3
instead of 5e-4 and a replay ratio of 8 (an update per 8 new transitions). MA-MeSN's messages use the env's default
deterministic straight-through estimator (``gumbel_noise = 0``): appendix B.2 fed the speaker's *softmax* to the
listener rather than a sample; with sampled messages (``gumbel_noise=1``) MA-MeSN plateaued at
about −12.5 in our runs, because the listener keeps training on the speaker's coin flips. The script prints a table
and writes a PNG of the training curves with the two bounds; ``--json`` saves the figures. ``--quick`` is a smoke
run (numbers meaningless).

Run: ``python benchmarks/speaker_listener.py`` (about 8 minutes on 2 cores with the defaults).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.config import job_config  # noqa: E402
from convoy.output import pyplot, save_figure  # noqa: E402
from convoy.services.training import run_inprocess  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402

NO_COMM, ORACLE, TARGET = -16.0, -7.7, -12.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--steps", type=int, default=300_000, help="env steps per run (default %(default)s)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="seeds (default %(default)s)")
    p.add_argument("--algos", nargs="+", default=["ma-mesn", "idqn"], help="algorithms (default %(default)s)")
    p.add_argument("--num-envs", type=int, default=16, help="envs stepped together (default %(default)s)")
    p.add_argument("--eval-episodes", type=int, default=200, help="greedy episodes per run (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="a smoke run of a few seconds")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--plot", metavar="PATH", default="runs/bench/speaker_listener.png", help="PNG of the curves")
    args = p.parse_args(argv)
    if args.quick:
        args.steps, args.eval_episodes = 4_000, 10
    console = Console()
    hp = {"learning_starts": 2_000 if not args.quick else 200, "replay_ratio": 8.0, "lr": 1e-3}
    runs: list[dict] = []
    for algo in args.algos:
        for seed in args.seeds:
            job = job_config(
                algo=algo,
                env="speaker-listener",
                algo_params=hp,
                steps=args.steps,
                num_envs=args.num_envs,
                seed=seed,
                eval_episodes=args.eval_episodes,
                log_every=max(args.steps // 25, 1),
            )
            t0 = time.perf_counter()
            res = run_inprocess(job, out_dir=None, progress=not args.quick)
            runs.append(
                {
                    "algo": algo,
                    "seed": seed,
                    "eval_return": res.eval_return,
                    "eval_ci95": res.eval_ci95,
                    "random_return": res.random_return,
                    "wall_s": time.perf_counter() - t0,
                    "env_steps_per_s": res.env_steps_per_s,
                    "curve": [(r["env_steps"], r["return"]) for r in res.rows],
                }
            )
            console.print(f"{algo} seed {seed}: greedy return {res.eval_return:.2f} ± {res.eval_ci95:.2f}")
    table = Table(title=f"speaker-listener, {args.steps:,} env steps per run, per-agent return (higher is better)")
    for col in ("algorithm", "greedy return (mean over seeds)", "± 95 % CI", "vs no-comm −16", "vs oracle −7.7"):
        table.add_column(col, justify="right")
    summary = {}
    for algo in args.algos:
        vals = np.array([r["eval_return"] for r in runs if r["algo"] == algo])
        one_seed_ci = next(r["eval_ci95"] for r in runs if r["algo"] == algo)  # across its evaluation episodes
        ci = ci95_half(vals, single=one_seed_ci)  # across seeds when there are several
        m = float(vals.mean())
        summary[algo] = {"mean": m, "ci95": ci}
        table.add_row(algo, f"{m:.2f}", f"{ci:.2f}", f"{m - NO_COMM:+.2f}", f"{m - ORACLE:+.2f}")
    rand = float(np.mean([r["random_return"] for r in runs]))
    table.add_row("random policy", f"{rand:.2f}", "", f"{rand - NO_COMM:+.2f}", f"{rand - ORACLE:+.2f}")
    console.print(table)
    if "ma-mesn" in summary:
        m = summary["ma-mesn"]["mean"]
        verdict = "reached" if m > TARGET else "NOT reached"
        console.print(f"target MA-MeSN better than {TARGET}: {verdict} ({m:.2f})")
    _plot(runs, Path(args.plot))
    console.print(f"wrote {args.plot}")
    if args.json:
        write_json(args.json, {"runs": runs, "summary": summary, "random": rand})
    return 0


def _plot(runs: list[dict], path: Path) -> None:
    plt = pyplot()

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4))
    for r in runs:
        xs, ys = zip(*r["curve"], strict=True) if r["curve"] else ((), ())
        ax.plot(xs, ys, label=f"{r['algo']} seed {r['seed']} (greedy {r['eval_return']:.1f})")
    ax.axhline(NO_COMM, ls="--", color="grey", label="best without communication (−16)")
    ax.axhline(ORACLE, ls=":", color="green", label="oracle listener (−7.7)")
    ax.axhline(TARGET, ls="-.", color="orange", label="target (−12)")
    ax.set_xlabel("env steps")
    ax.set_ylabel("training return per agent (ε-greedy)")
    ax.set_title("speaker-listener")
    ax.legend(fontsize=7)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
