"""How treadmill episodes end: for reference policies and trained checkpoints, the share of episodes survived to
``max_steps`` and of those ended by a collision with an adversary, a collision between teammates, or an agent
leaving the window (out of the front, out of the back, off a side). For a checkpoint also what its Q-function
believed, at the last act of an agent that then left the window, about the best action's value there.

Why: a return says how well a policy drives, not what it still fails at. A learner told what its teammates see may
stop being caught by the chaser yet crash into a teammate or drive off the window instead (that is what it does on
the default rules), which a return alone would hide.

Each env plays its first episode (as ``convoy eval`` scores them). An episode ends by the adversary when an
adversary crashed in its last step (adversaries crash only into agents), else by a teammate when a crashed agent
is still on the window, else by leaving the window: out of the front when a crashed agent is past the front, else
out of the back, else off a side.

The belief before leaving: a car that drives out of the front at top speed could not stop in its last step or two,
so a Q-function that knew the window's edge would value those states near −crash_penalty; one that never saw the
front (random play never gets there against the belt) values them like any empty road.

Run from the repository root: ``python benchmarks/treadmill_causes.py private-driver team-driver
runs/v4/idqn-private/seed-0/checkpoint.pt`` (a reference policy's name or a checkpoint each; 200 episodes, ~10 s
per policy; ``LABEL=A.pt,B.pt`` pools a population's seeds on the same episodes); ``--set`` changes the reference
policies' rules (a checkpoint plays its own); ``--json`` saves the figures.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.envs.batched import StepResult  # noqa: E402
from convoy.envs.rollout import Policy  # noqa: E402
from convoy.envs.treadmill.config import TreadmillConfig  # noqa: E402
from convoy.envs.treadmill.engine import TreadmillEngine  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402
from convoy.validation import build_config  # noqa: E402

CAUSES = ("survived", "adversary", "teammate", "out the front", "out the back", "off a side")
LEFT = CAUSES[3:]


class Ends(NamedTuple):
    """Per env: the first episode's return (mean over agents), how it ended (an index into ``CAUSES``), for an
    episode that an agent ended by leaving the window the max Q the policy gave that agent at its last act (NaN
    otherwise, or without a Q-function), and the steps it lasted (how long a policy survives, apart from what it
    earns per step: a discounted learner may trade the one for the other)."""

    returns: np.ndarray
    cause: np.ndarray
    belief: np.ndarray
    steps: np.ndarray


def episode_ends(
    engine: TreadmillEngine,
    policy: Policy,
    seed: int,
    after_step: Callable[[StepResult], None] | None = None,
    max_q: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Ends:
    """Each env's first episode played to its end; ``max_q(obs)`` (``[E, N]``) reads the policy's beliefs."""
    cfg, n = engine.cfg, engine.cfg.n_agents
    obs = engine.reset(seed)
    running = np.ones(engine.num_envs, bool)
    returns = np.zeros(engine.num_envs)
    cause = np.zeros(engine.num_envs, np.int64)
    belief = np.full(engine.num_envs, np.nan)
    steps = np.zeros(engine.num_envs, np.int64)
    while running.any():
        q = None if max_q is None else max_q(obs)
        res = engine.step(policy(obs))
        if after_step is not None:
            after_step(res)
        returns[running] += res.reward[running].mean(axis=1)
        steps += running
        ended = running & res.done & ~res.truncated
        crashed = engine.last_crashed[:, :n]
        x, y = engine.x[:, :n], engine.y[:, :n]
        front, back = crashed & (x >= cfg.length), crashed & (x < 0)
        side = crashed & ((y < 0) | (y >= cfg.width)) & ~front & ~back
        left = front | back | side
        how = np.select(
            [
                engine.last_crashed[:, n:].any(axis=1),
                (crashed & ~left).any(axis=1),
                front.any(axis=1),
                back.any(axis=1),
            ],
            [1, 2, 3, 4],
            5,
        )
        cause[ended] = how[ended]
        if q is not None:
            leaving = ended & (how >= 3)
            belief[leaving] = (q * left).sum(axis=1)[leaving] / left.sum(axis=1)[leaving]
        running &= ~res.done
        obs = res.obs
    return Ends(returns, cause, belief, steps)


def play(what: str, episodes: int, seed: int, sets: dict[str, object]) -> Ends:
    """A reference policy by name (on the defaults with ``sets``) or a checkpoint (on its own rules)."""
    if Path(what).suffix == ".pt":
        from convoy.actors.stepping import AgentPolicy
        from convoy.algos.algorithm import NetworkAgent
        from convoy.algos.checkpoint import load_checkpoint

        algo, job, _ = load_checkpoint(what, device="cpu")
        cfg = job.env_config()
        if not isinstance(cfg, TreadmillConfig):
            raise SystemExit(f"{what}: trained on {job.env}, not the treadmill")
        engine = TreadmillEngine(cfg, episodes, autoreset=False)
        agent = AgentPolicy(algo, episodes)

        def max_q(obs: np.ndarray) -> np.ndarray:  # what the greedy pass believes, before the act that uses it
            with torch.no_grad():
                q, _, _ = algo.greedy_q(torch.as_tensor(obs, dtype=torch.float32)[None], agent.state)  # R = 1
            return q[0].max(dim=-1).values.cpu().numpy()

        beliefs = max_q if isinstance(algo, NetworkAgent) else None  # a hierarchy's values are per option
        return episode_ends(engine, agent, seed, agent.after_step, beliefs)
    from convoy.envs.treadmill.references import reference_policy

    engine = TreadmillEngine(build_config(TreadmillConfig, **sets), episodes, autoreset=False)
    return episode_ends(engine, reference_policy(what, engine, seed), seed)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "policies",
        nargs="+",
        metavar="[LABEL=]POLICY",
        help="a reference policy's name, a checkpoint.pt or several comma-separated (a population's seeds: each "
        "plays the same episodes, their ends pooled), optionally named LABEL in the table and the JSON",
    )
    p.add_argument("--episodes", type=int, default=200, help="episodes per policy (default %(default)s)")
    p.add_argument("--seed", type=int, default=777, help="episode seed (default %(default)s, convoy eval's held out)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="rules of the reference policies, repeatable")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = p.parse_args(argv)
    sets = parse_pairs(args.set, "--set")
    table = Table(title=f"how {args.episodes} treadmill episodes end (seed {args.seed})")
    table.add_column("policy", overflow="fold")
    for col in ("return (95 % CI)", *CAUSES, "max Q before leaving", "steps", "return per step"):
        table.add_column(col, justify="right")
    figures = {}
    for arg in args.policies:
        label, _, what = arg.rpartition("=")
        label = label or what
        parts = []  # several checkpoints (a population's seeds) play the same episodes, their ends pooled
        for one in what.split(","):
            try:
                parts.append(play(one, args.episodes, args.seed, sets))
            except ValueError as exc:  # a checkpoint it cannot use (CheckpointError), an unknown policy or rule
                raise SystemExit(f"error: {one}: {exc}") from None
        ends = Ends(*(np.concatenate(field) for field in zip(*parts, strict=True)))
        shares = np.bincount(ends.cause, minlength=len(CAUSES)) / len(ends.cause)
        share = dict(zip(CAUSES, shares.tolist(), strict=True))
        believed = ends.belief[np.isfinite(ends.belief)]
        q = float(believed.mean()) if believed.size else None
        r = ends.returns
        figures[label] = {"policy": what, "return": float(r.mean()), "ci95": ci95_half(r), **share}
        figures[label]["max_q_before_leaving"] = q
        steps, rate = float(ends.steps.mean()), float(r.sum() / ends.steps.sum())  # pooled over the episodes
        figures[label] |= {"steps": steps, "return_per_step": rate}
        cells = (f"{s:.0%}" for s in shares)
        table.add_row(label, f"{r.mean():.1f} ± {ci95_half(r):.1f}", *cells, "—" if q is None else f"{q:.1f}",
                      f"{steps:.0f}", f"{rate:.3f}")  # fmt: skip
    Console().print(table)
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
