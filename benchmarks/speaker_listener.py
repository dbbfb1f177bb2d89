"""MA-MeSN against independent DQN on speaker-listener, on several seeds, against the known bounds.

The task (appendix B.2): the speaker sees which of three landmarks is the goal, the listener sees the landmarks but
not the goal, and only the speaker's 2-bit message can tell it. Per-agent returns over 25-step episodes have two
reference points measured with scripted listeners (``../shared/docs/zenoh-notes.md``): **−16.0** is the best a
listener can do without communication (head for the landmarks' centre) and **−7.7** is an oracle listener that knows
the goal. Independent DQN cannot beat −16 (its speaker has no channel); a communicating learner should land between
−16 and −8. The target: MA-MeSN better than −10, the mean over seeds.

Every algorithm uses the paper's particle-env settings (one hidden layer of 256, no parameter sharing for these
heterogeneous agents, 2-bit messages, batch 64, double Q) and the same env-step budget, seeds and evaluation
(greedy, ``--eval-episodes`` fresh episodes). Two settings differ from the defaults, for all alike, because they reach
the communicating regime within this machine's minutes instead of the paper's 7M steps: Adam 1e-3 instead of 5e-4 and
a replay ratio of 8 (an update per 8 new transitions). MA-MeSN's messages use the env's default deterministic
straight-through estimator (``gumbel_noise = 0``): appendix B.2 fed the speaker's *softmax* to the listener rather
than a sample; with sampled messages (``gumbel_noise=1``) MA-MeSN plateaued at about −12.5 in our runs, because the
listener keeps training on the speaker's coin flips.

``ma-mesn+ps`` is MA-MeSN with Eccles et al.'s positive signalling (``signalling_coef=0.1``: the loss also rewards
I(speaker's observation; message)). The paper's MA-MeSN forms a full protocol on about two seeds in three within 300 k
steps; on the third it stays between the two bounds (≈ −10.5 to −14.5: the speaker tells only some goals apart).
Rewarding a message that varies with what the speaker sees forms it on every seed tried (docs/benchmarks.md).

The script prints a table (mean over seeds, each seed) and writes a PNG of the training curves with the bounds;
``--json`` saves the figures and ``--load`` reports saved ones again (runs split over processes, one table).
``--quick`` is a smoke run of the first seed (numbers meaningless).

Run: ``python benchmarks/speaker_listener.py`` (9 runs of ~5 minutes on one core each; split ``--algos`` over two
processes and ``--load`` their JSON files for one table).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.config import ALGORITHMS, job_config  # noqa: E402
from convoy.output import pyplot, save_figure  # noqa: E402
from convoy.services.training import run_inprocess  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402

NO_COMM, ORACLE, TARGET = -16.0, -7.7, -10.0
# what --algos names: (algorithm, its settings over the script's); "+ps" adds Eccles et al.'s positive signalling
VARIANTS: dict[str, tuple[str, dict[str, float]]] = {
    "ma-mesn": ("ma-mesn", {}),
    "ma-mesn+ps": ("ma-mesn", {"signalling_coef": 0.1}),
    "idqn": ("idqn", {}),
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--steps", type=int, default=300_000, help="env steps per run (default %(default)s)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds (default %(default)s)")
    p.add_argument("--algos", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
                   help="algorithms; ma-mesn+ps: MA-MeSN, positive signalling 0.1 (default %(default)s)")  # fmt: skip
    p.add_argument("--num-envs", type=int, default=16, help="envs stepped together (default %(default)s)")
    p.add_argument("--eval-episodes", type=int, default=200, help="greedy episodes per run (default %(default)s)")
    p.add_argument("--hp", action="append", default=[], metavar="KEY=VALUE",
                   help="an algorithm setting over the script's, where the algorithm has it (repeatable)")  # fmt: skip
    p.add_argument("--load", nargs="+", metavar="JSON", help="report the runs of these --json files; no training")
    p.add_argument("--quick", action="store_true", help="a smoke run of a few seconds")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--plot", metavar="PATH", default="runs/bench/speaker_listener.png", help="PNG of the curves")
    args = p.parse_args(argv)
    if args.quick:
        args.steps, args.eval_episodes, args.seeds = 4_000, 10, args.seeds[:1]
    extra = parse_pairs(args.hp, "--hp")
    known = {k for a in args.algos for k in ALGORITHMS[VARIANTS[a][0]].config.model_fields}
    if unknown := [k for k in extra if k not in known]:
        p.error(f"--hp {unknown[0]}: no algorithm of --algos has that setting (see `convoy train --help`)")
    console = Console()
    if args.load:
        runs = [run for path in args.load for run in json.loads(Path(path).read_text())["runs"]]
    else:
        runs = [_train(name, seed, args, extra, console) for name in args.algos for seed in args.seeds]
    _report(runs, args, console)
    return 0


def _train(name: str, seed: int, args: argparse.Namespace, extra: dict, console: Console) -> dict:
    """One run of --algos' ``name``: its greedy evaluation and training curve."""
    algo, own = VARIANTS[name]
    hp = {"learning_starts": 2_000 if not args.quick else 200, "replay_ratio": 8.0, "lr": 1e-3, **own}
    fields = ALGORITHMS[algo].config.model_fields
    job = job_config(
        algo=algo,
        env="speaker-listener",
        algo_params={**hp, **{k: v for k, v in extra.items() if k in fields}},
        steps=args.steps,
        num_envs=args.num_envs,
        seed=seed,
        eval_episodes=args.eval_episodes,
        log_every=max(args.steps // 25, 1),
    )
    t0 = time.perf_counter()
    res = run_inprocess(job, out_dir=None, progress=not args.quick)
    console.print(f"{name} seed {seed}: greedy return {res.eval_return:.2f} ± {res.eval_ci95:.2f}")
    return {
        "algo": name,
        "seed": seed,
        "eval_return": res.eval_return,
        "eval_ci95": res.eval_ci95,
        "random_return": res.random_return,
        "wall_s": time.perf_counter() - t0,
        "env_steps_per_s": res.env_steps_per_s,
        "curve": [(r["env_steps"], r["return"]) for r in res.rows],
    }


def _report(runs: list[dict], args: argparse.Namespace, console: Console) -> None:
    """The table (mean over seeds, each seed, the bounds), the verdicts, the PNG and the JSON."""
    steps = max((r["curve"][-1][0] for r in runs if r["curve"]), default=args.steps)
    table = Table(title=f"speaker-listener, {steps:,} env steps per run, per-agent return (higher is better)")
    for col in ("algorithm", "greedy return (seeds' mean)", "± 95 % CI", "per seed", "vs no-comm −16", "vs oracle"):
        table.add_column(col, justify="right")
    summary = {}
    for name in dict.fromkeys(r["algo"] for r in runs):
        mine = sorted((r for r in runs if r["algo"] == name), key=lambda r: r["seed"])
        vals = np.array([r["eval_return"] for r in mine])
        ci = ci95_half(vals, single=mine[0]["eval_ci95"])  # across seeds; one seed: across its episodes
        m = float(vals.mean())
        summary[name] = {"mean": m, "ci95": ci, "seeds": [r["seed"] for r in mine], "per_seed": vals.tolist()}
        per_seed = " ".join(f"{v:.2f}" for v in vals)
        table.add_row(name, f"{m:.2f}", f"{ci:.2f}", per_seed, f"{m - NO_COMM:+.2f}", f"{m - ORACLE:+.2f}")
    rand = float(np.mean([r["random_return"] for r in runs]))
    table.add_row("random policy", f"{rand:.2f}", "", "", f"{rand - NO_COMM:+.2f}", f"{rand - ORACLE:+.2f}")
    console.print(table)
    for name in (n for n in summary if n.startswith("ma-mesn")):
        m = summary[name]["mean"]
        verdict = "reached" if m > TARGET else "NOT reached"
        console.print(f"target {name} better than {TARGET} (mean over seeds): {verdict} ({m:.2f})")
    _plot(runs, Path(args.plot))
    console.print(f"wrote {args.plot}")
    if args.json:
        write_json(args.json, {"runs": runs, "summary": summary, "random": rand})


def _plot(runs: list[dict], path: Path) -> None:
    """Training curves, one colour per algorithm and one line per seed, with the bounds."""
    plt = pyplot()

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4))
    colours = {name: f"C{i}" for i, name in enumerate(dict.fromkeys(r["algo"] for r in runs))}
    for r in runs:
        xs, ys = zip(*r["curve"], strict=True) if r["curve"] else ((), ())
        label = f"{r['algo']} seed {r['seed']} (greedy {r['eval_return']:.1f})"
        ax.plot(xs, ys, color=colours[r["algo"]], alpha=0.8, lw=1.2, label=label)
    ax.axhline(NO_COMM, ls="--", color="grey", label=f"best without communication ({NO_COMM:g})")
    ax.axhline(ORACLE, ls=":", color="green", label=f"oracle listener ({ORACLE:g})")
    ax.axhline(TARGET, ls="-.", color="orange", label=f"target ({TARGET:g})")
    ax.set_xlabel("env steps")
    ax.set_ylabel("training return per agent (ε-greedy)")
    ax.set_title("speaker-listener")
    ax.legend(fontsize=6, ncol=2)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
