"""Every learner on the default treadmill at one budget, over seeds, beside the reference policies.

The paper's Fig. 3 question — do communicating learners drive better than independent ones? — asked on Convoy's
treadmill. Each (algorithm, seed) is a ``convoy train --inprocess`` run of ``--steps`` env steps with the
treadmill's default hyper-parameters (``convoy/config.py`` ``ENV_DEFAULTS``), written to ``--out/ALGO-sSEED/``;
``--jobs`` runs go side by side (one core each). For every run the table reports

* **final**: the greedy return of the last policy (the trainer's final evaluation, ``eval_episodes`` episodes);
* **best.pt, held out**: the policy of the best point of the greedy curve, re-evaluated on ``--episodes`` episodes
  of *other* seeds than the ones it was chosen on (choosing and scoring on the same episodes would flatter it).

Each cell is the mean over seeds with its 95 % CI over seeds (t-distribution). Beside them: random, the best
constant action, the scripted driver, and the team-/full-information drivers (``benchmarks/treadmill_references.py``,
same ``--episodes``). An algorithm name may carry variants after ``+``: ``idqn+full-information`` trains on the
treadmill's ``full_information`` observations (every car's offset and who is an adversary: more than any
message can tell, since it includes cars nobody observes), ``idqn+team-observations`` trains on each
agent's observation with its teammates' observations appended (what lossless messages could carry: the bound on
what MA-MeSN's messages can add to independent DQN), ``idqn+team-sightings`` is told, in its own frame and with
an adversary flag, every car some agent observes (perfectly decoded messages), ``idqn+hierarchical`` is
hierarchical DQN (``--hierarchical``), ``ma-mesn+gumbel`` sends the paper's sampled Gumbel-softmax bits
(``gumbel_noise=1``) instead of the treadmill's deterministic ones. ``--set NAME=VALUE`` changes a treadmill rule for
every run and the references. For MA-MeSN and MA-BoN (any ``--analyze`` algorithm) the best and the last
checkpoints also get ``convoy analyze``'s figures: message entropy, instantaneous coordination beside its shuffled
baseline, and the return with white noise in place of the messages.

Run: ``python benchmarks/treadmill_learning.py --seeds 0 1 2 3 4 --steps 400000`` (see docs/benchmarks.md for
the wall time per run); ``--json`` saves every figure.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.envs.treadmill.config import TreadmillConfig  # noqa: E402
from convoy.envs.treadmill.references import best_constant, evaluate_references  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402

HELD_OUT_SEED = 50_000  # best.pt is chosen on seed + 10,000 (learner.runlog.EVAL_SEED_OFFSET); scored here


def ci_over_seeds(values: list[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95 % t-interval over seeds (0 for one seed)."""
    x = np.asarray(values, dtype=np.float64)
    return float(x.mean()), ci95_half(x, single=0.0)


VARIANTS = {
    "full-information": ["--set", "full_information=true"],
    "team-observations": ["--set", "team_observations=true"],
    "team-sightings": ["--set", "team_sightings=true"],
    "hierarchical": ["--hierarchical"],
    # the paper's sampled Gumbel-softmax messages in place of the treadmill's deterministic straight-through bits
    "gumbel": ["--hp", "gumbel_noise=1"],
}


def variant_flags(name: str) -> tuple[str, list[str]]:
    """``ALGO+VARIANT+…`` → (ALGO, the ``convoy train`` flags of its variants)."""
    algo, *variants = name.split("+")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"--algos: unknown variant {unknown[0]!r} of {algo}; choose from {', '.join(VARIANTS)}")
    return algo, [flag for v in variants for flag in VARIANTS[v]]


def train(name: str, seed: int, args: argparse.Namespace) -> dict:
    """One ``convoy train --inprocess`` run in its own process (one torch thread); its summary."""
    algo, flags = variant_flags(name)
    out = Path(args.out).resolve() / f"{name}-s{seed}"  # the user's --out, wherever the runs start
    cmd = [sys.executable, "-m", "convoy.cli", "train", "--inprocess", "--algo", algo,
           "--steps", str(args.steps), "--seed", str(seed), "--out", str(out), "--overwrite", "--no-progress",
           "--eval-every", str(args.eval_every)]  # fmt: skip
    cmd += ["--eval-episodes", str(args.eval_episodes)] if args.eval_episodes else []
    cmd += flags
    for hp in args.hp or []:
        cmd += ["--hp", hp]
    for rule in args.set or []:
        cmd += ["--set", rule]
    log = out.with_suffix(".log")
    if args.reuse and (out / "summary.json").exists() and (out / "best.pt").exists():
        summary = json.loads((out / "summary.json").read_text())
        if summary.get("env_steps", 0) >= args.steps:
            return {**summary, "algo": name, "seed": seed, "out": str(out), "wall_s": summary["wall_s"]}
    t0 = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as fh:
        subprocess.run(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, check=True)
    summary = json.loads((out / "summary.json").read_text())
    return {**summary, "algo": name, "seed": seed, "out": str(out), "wall_s": time.perf_counter() - t0}


def held_out(run: dict, episodes: int, analyze: bool, samples: int) -> dict:
    """best.pt's greedy return on held-out seeds; for communicating algorithms the analysis of best.pt and of the
    last checkpoint (best.pt is picked on the greedy curve, which can favour a policy that ignores its messages)."""
    from convoy.algos.checkpoint import load_checkpoint
    from convoy.analysis.evaluation import evaluate_policy
    from convoy.analysis.recording import analyze as analyze_policy
    from convoy.services.training import make_env

    out: dict = {}
    checkpoints = (("best.pt", "analysis"), ("checkpoint.pt", "analysis_last"))
    for name, key in checkpoints if analyze else checkpoints[:1]:  # the last checkpoint only to analyse it
        algo, job, _ = load_checkpoint(Path(run["out"]) / name, device="cpu")
        env = make_env(job, min(episodes, 256))
        try:
            if name == "best.pt":
                res = evaluate_policy(algo, env, episodes, seed=HELD_OUT_SEED)
                out.update(best_held_out=res.mean, best_held_out_ci95=res.ci95)
            if analyze:
                steps = -(-samples // env.num_envs)
                figures = analyze_policy(algo, env, job.env, steps, episodes, seed=HELD_OUT_SEED).figures
                out[key] = {f.key: {"value": f.value, "shuffled": f.shuffled} for f in figures}
        finally:
            env.close()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument(
        "--algos",
        nargs="+",
        default=[
            "ma-mesn",
            "idqn",
            "ma-bon",
            "ims",
            "dial",
            "idqn+hierarchical",
            "idqn+team-observations",
            "idqn+full-information",
        ],
        help="algorithms, each optionally ALGO+VARIANT (full-information, team-observations, team-sightings, "
        "hierarchical, gumbel) (default %(default)s)",
    )
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="(default %(default)s)")
    p.add_argument("--steps", type=int, default=400_000, help="env steps per run (default %(default)s)")
    p.add_argument(
        "--eval-every", type=int, default=20_000, help="env steps between curve points (default %(default)s)"
    )
    p.add_argument("--episodes", type=int, default=500, help="held-out and reference episodes (default %(default)s)")
    p.add_argument("--eval-episodes", type=int, help="episodes of each curve point (default: convoy train's)")
    p.add_argument("--hp", action="append", metavar="KEY=VALUE", help="hyper-parameter for every run, repeatable")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="treadmill rule for every run, repeatable")
    p.add_argument("--jobs", type=int, default=2, help="runs side by side (default %(default)s)")
    p.add_argument("--analyze", nargs="*", default=["ma-mesn", "ma-bon"], help="algorithms to analyse")
    p.add_argument(
        "--analysis-samples",
        type=int,
        default=204_800,
        help="agent-steps recorded for the MI figures, as `convoy analyze --samples` (default %(default)s)",
    )
    p.add_argument("--out", default="runs/bench/treadmill", help="run directories (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="also write every figure as JSON")
    p.add_argument(
        "--reuse", action="store_true", help="keep finished runs of ≥ --steps already in --out instead of re-training"
    )
    args = p.parse_args(argv)
    console = Console()

    for name in args.algos:
        variant_flags(name)  # fail on a bad name before any run starts
    grid = [(a, s) for a in args.algos for s in args.seeds]
    with ThreadPoolExecutor(args.jobs) as pool:
        runs = list(pool.map(lambda job: train(*job, args), grid))
    for run in runs:
        run.update(held_out(run, args.episodes, run["algo"] in args.analyze, args.analysis_samples))
        console.print(
            f"{run['algo']} seed {run['seed']}: final {run['eval_return']:.1f}, best.pt held out "
            f"{run['best_held_out']:.1f} ({run['wall_s'] / 60:.1f} min)"
        )
    rules = dict(rule.split("=", 1) for rule in args.set or [])
    refs = evaluate_references(TreadmillConfig(**rules), args.episodes, seed=HELD_OUT_SEED)
    const = best_constant(refs)

    table = Table(
        title=f"treadmill ({' '.join(args.set or []) or 'default'}), {args.steps:,} env steps per run, "
        f"{len(args.seeds)} seeds, greedy return"
    )
    for col in ("policy", "final (95 % CI over seeds)", "best.pt held out (95 % CI)", "min/run"):
        table.add_column(col, justify="right")
    summary: dict[str, dict] = {}
    for algo in args.algos:
        mine = [r for r in runs if r["algo"] == algo]
        final = ci_over_seeds([r["eval_return"] for r in mine])
        best = ci_over_seeds([r["best_held_out"] for r in mine])
        minutes = float(np.mean([r["wall_s"] for r in mine]) / 60)
        summary[algo] = {"final": final, "best_held_out": best, "minutes": minutes}
        table.add_row(algo, f"{final[0]:.1f} ± {final[1]:.1f}", f"{best[0]:.1f} ± {best[1]:.1f}", f"{minutes:.1f}")
    for name in ("random", const, "scripted", "private-driver", "team-driver", "team-information", "full-information"):
        mean, ci = refs[name].ci95()
        summary[name] = {"reference": (mean, ci)}
        table.add_row(f"reference: {name}", f"{mean:.1f} ± {ci:.1f} (episodes)", "", "")
    console.print(table)
    for algo in args.analyze:
        for key, which in (("analysis", "best.pt"), ("analysis_last", "last checkpoint")):
            mine = [r for r in runs if r["algo"] == algo and key in r]
            if not mine:
                continue
            fig = {k: ci_over_seeds([r[key][k]["value"] for r in mine]) for k in mine[0][key]}
            shuf = ci_over_seeds([r[key]["instantaneous_coordination"]["shuffled"] or 0.0 for r in mine])
            summary[algo][key] = {**fig, "instantaneous_coordination_shuffled": shuf}
            console.print(
                f"{algo} {which} analysis ({len(mine)} seeds, 95 % CI over seeds): message entropy "
                f"{fig['message_entropy'][0]:.2f} ± {fig['message_entropy'][1]:.2f} nats; IC "
                f"{fig['instantaneous_coordination'][0]:.4f} ± {fig['instantaneous_coordination'][1]:.4f} vs "
                f"shuffled {shuf[0]:.4f} ± {shuf[1]:.4f}; return with true messages {fig['return_sent'][0]:.1f} ± "
                f"{fig['return_sent'][1]:.1f} vs white noise {fig['return_noise'][0]:.1f} ± "
                f"{fig['return_noise'][1]:.1f}"
            )
            for r in mine:
                a, ic = r[key], r[key]["instantaneous_coordination"]
                console.print(
                    f"  seed {r['seed']}: entropy {a['message_entropy']['value']:.2f}, IC "
                    f"{ic['value']:.4f} vs {ic['shuffled'] if ic['shuffled'] is not None else float('nan'):.4f}"
                    f", return {a['return_sent']['value']:.1f} vs white noise {a['return_noise']['value']:.1f}"
                )
    if args.json:
        write_json(args.json, {"runs": runs, "summary": summary})
    return 0


if __name__ == "__main__":
    sys.exit(main())
