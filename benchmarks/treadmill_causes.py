"""How treadmill episodes end: for reference policies and trained checkpoints, the share of episodes survived to
``max_steps`` and of those ended by a collision with an adversary, a collision between teammates, or an agent
leaving the window.

Why: a return says how well a policy drives, not what it still fails at. A learner told what its teammates see may
stop being caught by the chaser yet crash into a teammate or drive off the window instead (that is what it does on
the default rules), which a return alone would hide.

Each env plays its first episode (as ``convoy eval`` scores them). An episode ends by the adversary when an
adversary crashed in its last step (adversaries crash only into agents), else by a teammate when a crashed agent
is still on the window, else by leaving the window.

Run from the repository root: ``python benchmarks/treadmill_causes.py private-driver team-driver
runs/v4/idqn-private/seed-0/checkpoint.pt`` (a reference policy's name or a checkpoint each; 200 episodes, ~10 s
per policy); ``--set`` changes the reference policies' rules (a checkpoint plays its own); ``--json`` saves the
figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.envs.rollout import Policy  # noqa: E402
from convoy.envs.treadmill.config import TreadmillConfig  # noqa: E402
from convoy.envs.treadmill.engine import TreadmillEngine  # noqa: E402
from convoy.stats import ci95_half  # noqa: E402
from convoy.validation import build_config  # noqa: E402

CAUSES = ("survived", "adversary", "teammate", "left the window")


def episode_ends(engine: TreadmillEngine, policy: Policy, seed: int, after_step=None) -> tuple[np.ndarray, np.ndarray]:
    """Each env's first-episode return (mean over agents) and how it ended (an index into ``CAUSES``)."""
    cfg, n = engine.cfg, engine.cfg.n_agents
    obs = engine.reset(seed)
    running = np.ones(engine.num_envs, bool)
    returns = np.zeros(engine.num_envs)
    cause = np.zeros(engine.num_envs, np.int64)
    while running.any():
        res = engine.step(policy(obs))
        if after_step is not None:
            after_step(res)
        returns[running] += res.reward[running].mean(axis=1)
        ended = running & res.done
        crashed = engine.last_crashed
        outside = (engine.x < 0) | (engine.x >= cfg.length) | (engine.y < 0) | (engine.y >= cfg.width)
        on_window = (crashed[:, :n] & ~outside[:, :n]).any(axis=1)
        how = np.where(crashed[:, n:].any(axis=1), 1, np.where(on_window, 2, 3))
        cause[ended] = np.where(res.truncated[ended], 0, how[ended])
        running &= ~res.done
        obs = res.obs
    return returns, cause


def play(what: str, episodes: int, seed: int, sets: dict[str, object]) -> tuple[np.ndarray, np.ndarray]:
    """A reference policy by name (on the defaults with ``sets``) or a checkpoint (on its own rules)."""
    if Path(what).suffix == ".pt":
        from convoy.actors.stepping import AgentPolicy
        from convoy.algos.checkpoint import load_checkpoint

        algo, job, _ = load_checkpoint(what, device="cpu")
        cfg = job.env_config()
        if not isinstance(cfg, TreadmillConfig):
            raise SystemExit(f"{what}: trained on {job.env}, not the treadmill")
        engine = TreadmillEngine(cfg, episodes, autoreset=False)
        agent = AgentPolicy(algo, episodes)
        return episode_ends(engine, agent, seed, agent.after_step)
    from convoy.envs.treadmill.references import reference_policy

    engine = TreadmillEngine(build_config(TreadmillConfig, **sets), episodes, autoreset=False)
    return episode_ends(engine, reference_policy(what, engine, seed), seed)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policies", nargs="+", metavar="POLICY", help="a reference policy's name or a checkpoint.pt")
    p.add_argument("--episodes", type=int, default=200, help="episodes per policy (default %(default)s)")
    p.add_argument("--seed", type=int, default=777, help="episode seed (default %(default)s, convoy eval's held out)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="rules of the reference policies, repeatable")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = p.parse_args(argv)
    sets = parse_pairs(args.set, "--set")
    table = Table(title=f"how {args.episodes} treadmill episodes end (seed {args.seed})")
    table.add_column("policy", overflow="fold")
    for col in ("return (95 % CI)", *CAUSES):
        table.add_column(col, justify="right")
    figures = {}
    for what in args.policies:
        returns, cause = play(what, args.episodes, args.seed, sets)
        shares = np.bincount(cause, minlength=len(CAUSES)) / len(cause)
        share = dict(zip(CAUSES, shares.tolist(), strict=True))
        figures[what] = {"return": float(returns.mean()), "ci95": ci95_half(returns), **share}
        table.add_row(what, f"{returns.mean():.1f} ± {ci95_half(returns):.1f}", *(f"{s:.0%}" for s in shares))
    Console().print(table)
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
