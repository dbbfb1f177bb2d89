"""Can the learner's network drive like the planner of its information? DAgger of a planner into it.

Why: the own-sensor learner stops at ~0.7 × the private planner under every change to its training tried. Two
causes look alike in a return: the network, reading the observation as it does (the entity encoder, the widths, the
agent id), cannot represent a planner-like policy; or it can, and Q-learning does not find it. Imitation separates
them: the same network, built by the same job config as the learner (``--preset charger`` and any ``--hp``), is
trained to reproduce the planner's action in every state it visits (DAgger, Ross et al. 2011: the first round the
planner drives, later rounds the student drives ε-greedily (with probability ``0.5^k`` the planner instead) and the
planner labels what the student's own mistakes lead to), then scored greedily on the held-out episodes
``benchmarks/learner_scores.py`` scores learners on, beside the teacher on the same episodes. A clone near the
teacher means the gap is the learning, not the network.

Run from the repository root: ``python benchmarks/treadmill_imitation.py`` (the private planner into the own
learner's network on the charger rules; ~25 min on one core); ``--teacher team-planner --set team_sightings=true``
clones the team planner into the told learner's network; ``--json`` saves the figures.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, cast

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.envs.batched import StepResult  # noqa: E402
from convoy.envs.treadmill.config import N_ACTIONS  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402

TUNING_SEED = 1  # the episodes the student learns on; it is scored on HELD_OUT_SEED's


class Dagger:
    """A rollout policy that records every running env's observation and the teacher's action there, and plays the
    teacher's action with probability ``beta`` per env and step, else the student's (ε-greedy)."""

    def __init__(self, teacher: Any, student: Any, beta: float, epsilon: float, num_envs: int, seed: int) -> None:
        self.teacher, self.student, self.beta, self.epsilon = teacher, student, beta, epsilon
        self.rng = np.random.default_rng(seed)
        self.running = np.ones(num_envs, bool)
        self.obs: list[np.ndarray] = []
        self.labels: list[np.ndarray] = []

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        label = self.teacher(obs)
        self.obs.append(obs[self.running].copy())
        self.labels.append(label[self.running].copy())
        if self.beta >= 1.0:
            return label
        acted = self.student(obs)
        explore = self.rng.random(size=acted.shape) < self.epsilon
        acted = np.where(explore, self.rng.integers(0, N_ACTIONS, acted.shape), acted)
        teach = self.rng.random(size=(len(obs), 1)) < self.beta
        return np.where(teach, label, acted)

    def after_step(self, res: StepResult) -> None:
        self.running &= ~res.done


def train(agent: Any, obs: np.ndarray, labels: np.ndarray, args: Any) -> float:
    """``args.epochs`` passes of cross-entropy between every run's outputs and the teacher's actions (each run of
    the population learns from all the states); the last pass's accuracy over runs."""
    net, runs = agent.online["q"], agent.runs
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    x_all = torch.as_tensor(obs, dtype=torch.float32)
    y_all = torch.as_tensor(labels, dtype=torch.int64)
    gen = torch.Generator().manual_seed(0)
    correct = total = 0
    for _ in range(args.epochs):
        correct = total = 0
        order = torch.randperm(len(x_all), generator=gen)
        for i in range(0, len(order), args.batch):
            idx = order[i : i + args.batch]
            x, y = x_all[idx].to(agent.device), y_all[idx].to(agent.device).expand(runs, -1, -1)
            logits = net(agent.features(x.expand(runs, *x.shape)))  # [R, b, N, A]
            loss = F.cross_entropy(logits.flatten(0, -2), y.flatten()) * runs  # each run's mean, summed over runs
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
            opt.step()
            correct += int((logits.argmax(-1) == y).sum())
            total += y.numel()
    for nets in (agent.target, agent.average):  # the clone is also what Q-learning bootstraps from and is judged by
        if nets is not None:
            nets.load_state_dict(agent.online.state_dict())
    return correct / max(total, 1)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--teacher", default="private-planner", help="reference policy to clone (default %(default)s)")
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
        help="one clone per seed (its own initial weights), trained on the same states (default 0)",
    )
    p.add_argument("--rounds", type=int, default=8, help="DAgger rounds (default %(default)s)")
    p.add_argument("--episodes", type=int, default=128, help="tuning episodes played per round (default %(default)s)")
    p.add_argument("--epsilon", type=float, default=0.05, help="the student's exploration (default %(default)s)")
    p.add_argument("--epochs", type=int, default=4, help="passes over all data after each round (default %(default)s)")
    p.add_argument("--batch", type=int, default=256, help="env steps per gradient step (default %(default)s)")
    p.add_argument("--lr", type=float, default=5e-4, help="Adam learning rate (default %(default)s)")
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
    from convoy.algos.idqn import IndependentDQN
    from convoy.analysis.evaluation import HELD_OUT_SEED, SCORING_ENVS, evaluate_policy, evaluate_reference
    from convoy.config import job_config
    from convoy.envs.rollout import rollout
    from convoy.envs.treadmill.references import reference_policy
    from convoy.learner.population import PopulationTrainer
    from convoy.learner.runtime import configure_learner
    from convoy.services.training import make_env

    job = job_config(
        algo="idqn", env="treadmill", preset=args.preset, seeds=args.seeds,
        eval_episodes=args.eval_episodes, **({"steps": args.learn} if args.learn else {}),
        env_params=parse_pairs(args.set, "--set"), algo_params=parse_pairs(args.hp, "--hp"),
    )  # fmt: skip
    configure_learner(job.torch_threads)
    runs = len(args.seeds)
    play_env = make_env(job, num_envs=args.episodes * runs)  # run k drives its own share of the envs
    score_env = make_env(job, num_envs=min(args.eval_episodes, SCORING_ENVS))
    agent = cast(IndependentDQN, make_agent(job, play_env.spec, run_configs=[j.algo_config() for j in job.members()]))
    net, device = agent.online["q"], agent.device

    def student(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            x = torch.as_tensor(obs, dtype=torch.float32, device=device).reshape(runs, -1, *obs.shape[1:])
            return net(agent.features(x)).argmax(-1).reshape(obs.shape[:2]).cpu().numpy()

    def held_out() -> list[np.ndarray]:
        return [evaluate_policy(agent.member(k), score_env, args.eval_episodes, HELD_OUT_SEED).returns
                for k in range(runs)]  # fmt: skip

    teacher_returns = evaluate_reference(score_env, args.teacher, args.eval_episodes, HELD_OUT_SEED)
    teacher = float(teacher_returns.mean())
    print(f"{args.teacher} on {args.eval_episodes} held-out episodes: {teacher:.1f} ± {ci95_half(teacher_returns):.1f}")
    obs_all: list[np.ndarray] = []
    labels_all: list[np.ndarray] = []
    rounds = []
    for k in range(args.rounds):
        start = time.perf_counter()
        beta = 0.5**k
        policy = Dagger(
            reference_policy(args.teacher, cast(Any, play_env)), student, beta, args.epsilon, play_env.num_envs, k
        )
        rollout(play_env, policy, seed=TUNING_SEED * 100_000 + k, after_step=policy.after_step)
        obs_all += policy.obs
        labels_all += policy.labels
        obs, labels = np.concatenate(obs_all), np.concatenate(labels_all)
        accuracy = train(agent, obs, labels, args)
        means = np.array([r.mean() for r in held_out()])
        row = {
            "round": k, "beta": beta, "states": len(obs), "train_accuracy": accuracy, "held_out": means.tolist(),
            "mean": float(means.mean()), "ci95": ci95_half(means) if runs > 1 else None,
            "of_teacher": float(means.mean()) / teacher, "seconds": time.perf_counter() - start,
        }  # fmt: skip
        rounds.append(row)
        spread = f" ± {row['ci95']:.1f} over {runs} clones" if runs > 1 else ""
        print(
            f"round {k}: β {beta:.3f}, {len(obs):,} states, accuracy {accuracy:.3f}, held out "
            f"{row['mean']:.1f}{spread} = {row['of_teacher']:.2f} × the teacher ({row['seconds']:.0f} s)",
            flush=True,
        )
    figures: dict[str, Any] = {
        "teacher": args.teacher, "teacher_held_out": teacher, "teacher_ci95": ci95_half(teacher_returns),
        "job": job.model_dump(mode="json"), "settings": vars(args), "rounds": rounds,
    }  # fmt: skip
    if args.learn:
        out = Path(args.out)
        env = make_env(job, job.num_envs * runs)
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
