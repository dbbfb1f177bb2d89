"""Can the learner's network drive like the planner of its information? DAgger of a planner into it.

Why: the own-sensor learner stops at ~0.7 × the private planner under every change to its training tried. Two
causes look alike in a return: the network, reading the observation as it does (the entity encoder, the widths, the
agent id), cannot represent a planner-like policy; or it can, and Q-learning does not find it. Imitation separates
them: the same network, built by the same job config as the learner (``--preset charger`` and any ``--hp``), is
trained to reproduce the planner's action in every state it visits (DAgger, Ross et al. 2011: the first round the
planner drives, later rounds the student drives ε-greedily (with probability ``0.5^k`` the planner instead) and the
planner labels what the student's own mistakes lead to; ``learner/imitation.py``, what ``--hp demonstrator=NAME``
runs before a job's Q-learning), each round's clones scored greedily on the held-out episodes
``benchmarks/learner_scores.py`` scores learners on, beside the teacher on the same episodes. A clone near the
teacher means the gap is the learning, not the network.

Run from the repository root: ``python benchmarks/treadmill_imitation.py`` (the private planner into the own
learner's network on the charger rules; ~25 min on one core); ``--teacher team-planner --set team_sightings=true``
clones the team planner into the told learner's network; ``--json`` saves the figures.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.cli.rundir import LAUNCH  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--teacher", default="private-planner", help="reference policy to clone (default %(default)s)")
    p.add_argument(
        "--algo",
        default="idqn",
        help="the learner whose network clones (idqn, dqn-ser, ma-mesn, ma-bon: these through their channel) "
        "(default %(default)s)",
    )
    p.add_argument("--preset", default="charger", help="job preset: rules and network (default %(default)s)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="env rule, as convoy train's")
    p.add_argument(
        "--hp",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="learner setting, as convoy train's (the network, and --learn's Q-learning)",
    )
    p.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[0],
        help="one clone per seed (its own initial weights and its own share of the envs) (default 0)",
    )
    p.add_argument("--rounds", type=int, default=8, help="DAgger rounds (default %(default)s)")
    p.add_argument(
        "--episodes", type=int, default=128, help="tuning episodes each clone plays per round (default %(default)s)"
    )
    p.add_argument("--epochs", type=int, default=4, help="passes over all data after each round (default %(default)s)")
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=200,
        help="held-out episodes per score, and --learn's evaluations (default %(default)s)",
    )
    p.add_argument(
        "--learn",
        type=int,
        default=0,
        metavar="STEPS",
        help="then Q-learn from the clones for STEPS env steps with the job's recipe, as convoy train does "
        "(online, target and judged weights start at the clone): does Q-learning keep a planner-level "
        "policy? (default 0: no)",
    )
    p.add_argument(
        "--out",
        default="runs/imitation/learn",
        help="--learn's run folder, DIR/seed-N as convoy train's (default %(default)s)",
    )
    p.add_argument("--json", default=None, help="write the figures here")
    args = p.parse_args(argv)

    from convoy.algos.agent import make_agent
    from convoy.algos.checkpoint import REPLAY_FILE
    from convoy.analysis.evaluation import HELD_OUT_SEED, SCORING_ENVS, evaluate_policy, evaluate_reference
    from convoy.config import job_config
    from convoy.learner.core import print_line
    from convoy.learner.imitation import demonstration_start
    from convoy.learner.population import PopulationTrainer
    from convoy.learner.runtime import configure_learner
    from convoy.services.training import make_env

    demo = {"demonstrator": args.teacher, "demo_rounds": args.rounds, "demo_episodes": args.episodes,
            "demo_epochs": args.epochs}  # fmt: skip
    job = job_config(
        algo=args.algo, env="treadmill", preset=args.preset, seeds=args.seeds,
        eval_episodes=args.eval_episodes, **({"steps": args.learn} if args.learn else {}),
        env_params=parse_pairs(args.set, "--set"), algo_params={**parse_pairs(args.hp, "--hp"), **demo},
    )  # fmt: skip
    configure_learner(job.torch_threads)
    runs = len(args.seeds)
    score_env = make_env(job, num_envs=min(args.eval_episodes, SCORING_ENVS))
    agent = make_agent(job, score_env.spec, run_configs=[j.algo_config() for j in job.members()])

    def held_out() -> list[np.ndarray]:
        return [evaluate_policy(agent.member(k), score_env, args.eval_episodes, HELD_OUT_SEED).returns
                for k in range(runs)]  # fmt: skip

    teacher_returns = evaluate_reference(score_env, args.teacher, args.eval_episodes, HELD_OUT_SEED)
    teacher = float(teacher_returns.mean())
    print(f"{args.teacher} on {args.eval_episodes} held-out episodes: {teacher:.1f} ± {ci95_half(teacher_returns):.1f}")
    rounds = []

    def score(per_run: list[dict[str, Any]]) -> None:
        means = np.array([r.mean() for r in held_out()])
        row = {
            "round": per_run[0]["round"], "beta": per_run[0]["beta"],
            "states": int(np.mean([r["states"] for r in per_run])),
            "train_accuracy": float(np.mean([r["accuracy"] for r in per_run])), "held_out": means.tolist(),
            "mean": float(means.mean()), "ci95": ci95_half(means) if runs > 1 else None,
            "of_teacher": float(means.mean()) / teacher,
        }  # fmt: skip
        rounds.append(row)
        spread = f" ± {row['ci95']:.1f} over {runs} clones" if runs > 1 else ""
        print(f"  held out {row['mean']:.1f}{spread} = {row['of_teacher']:.2f} × the teacher", flush=True)

    demonstration_start(agent, job, print_line, after_round=score)
    figures: dict[str, Any] = {
        "teacher": args.teacher, "teacher_held_out": teacher, "teacher_ci95": ci95_half(teacher_returns),
        "job": job.model_dump(mode="json"), "settings": vars(args), "rounds": rounds,
    }  # fmt: skip
    if args.learn:
        out = Path(args.out)
        env = make_env(job, job.num_envs * runs)
        out.mkdir(parents=True, exist_ok=True)  # a run folder as convoy train's: `convoy train --resume OUT` goes on
        job.write(out / "job.json")
        (out / LAUNCH).write_text(json.dumps({"inprocess": True}) + "\n")
        trainer = PopulationTrainer(job.members(), env, agent, lambda n: make_env(job, n), job.member_dirs(out),
                                    replay=out / REPLAY_FILE)  # fmt: skip
        results = trainer.run()
        means = np.array([r.mean() for r in held_out()])
        figures["learned"] = {"steps": args.learn, "out": str(out), "held_out": means.tolist(),
                              "mean": float(means.mean()), "of_teacher": float(means.mean()) / teacher}  # fmt: skip
        print(f"after {args.learn:,} steps of Q-learning: held out {means.mean():.1f} "
              f"= {means.mean() / teacher:.2f} × the teacher; the runs: {out}/seed-N ({len(results)})")  # fmt: skip
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
