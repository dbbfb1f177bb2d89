"""The treadmill's reference policies: what no learner may be judged without.

Plays ``--episodes`` episodes (default 500, the same env seeds for every policy) of random, each of the 9 constant
actions, the scripted driver on private observations, the team-information driver (also told where every adversary
is that some agent observes: what perfectly decoded messages could carry) and the full-information driver (every
car's position and who is an adversary), and prints each with its 95 % CI. Then the two properties the treadmill is
built for (``docs/treadmill.md``):

* open loop does not pay: best constant action ÷ scripted driver (goal ≤ 0.5);
* information pays: full-information ÷ scripted, the value of information (goal ≥ 1.3, CIs apart);

and who observes an adversary that is close to an agent: the agent, only a teammate (what messages can add), nobody.

It plays the planners too (``envs.treadmill.planner``, the strongest reference at each information level).

Run: ``python benchmarks/treadmill_references.py`` (about 3 minutes, most of it the planners); ``--set KEY=VALUE``
tries other rules.
``--search`` runs the searched and tuned references instead (``benchmarks/treadmill_search.py``: open-loop search,
tuned private / team / 16-bit team drivers, paired ratios; the arguments after ``--search`` go to it, e.g.
``--search``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.envs.treadmill import TreadmillConfig  # noqa: E402
from convoy.envs.treadmill.references import best_constant, evaluate_references, who_sees_the_threat  # noqa: E402
from convoy.validation import build_config  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--search" in argv:
        from benchmarks.treadmill_search import main as search

        return search([a for a in argv if a != "--search"])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=500, help="episodes per policy (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="env seed (default %(default)s)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="treadmill parameter, repeatable")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--search", action="store_true", help="run benchmarks/treadmill_search.py with the other arguments")
    args = p.parse_args(argv)
    cfg = build_config(TreadmillConfig, **parse_pairs(args.set, "--set"))
    results = evaluate_references(cfg, args.episodes, args.seed)
    figures = {
        name: dict(zip(("mean", "ci95"), r.ci95(), strict=True))
        | {"crashed": float(r.terminated.mean()), "length": float(r.lengths.mean())}
        for name, r in results.items()
    }
    console = Console()
    table = Table(title=f"treadmill references: {args.episodes} episodes each, seed {args.seed}")
    for col in ("policy", "return per agent (95 % CI)", "crashed", "mean length"):
        table.add_column(col, justify="left" if col == "policy" else "right")
    for name, f in figures.items():
        table.add_row(name, f"{f['mean']:.1f} ± {f['ci95']:.1f}", f"{f['crashed']:.0%}", f"{f['length']:.0f}")
    console.print(table)
    const = best_constant(results)
    c, s, full = figures[const], figures["scripted"], figures["full-information"]
    open_loop = c["mean"] / s["mean"]
    value = full["mean"] / s["mean"]
    reachable = figures["team-information"]["mean"] / s["mean"]
    apart = full["mean"] - full["ci95"] > s["mean"] + s["ci95"]
    console.print(f"best constant action: {const}; best constant ÷ scripted = {open_loop:.2f} (goal ≤ 0.5)")
    console.print(
        f"value of information: full-information ÷ scripted = {value:.2f} (goal ≥ 1.3), "
        f"CIs {'apart' if apart else 'OVERLAP'}; reachable by messages: team-information ÷ scripted = {reachable:.2f}"
    )
    seen = who_sees_the_threat(cfg, seed=args.seed)
    console.print(
        f"an adversary within the scripted driver's danger distance (scripted driving, 256 envs × 400 steps): the "
        f"agent observes it {seen['own']:.0%}, only a teammate does {seen['only_teammate']:.0%} (what messages can "
        f"add), nobody does {seen['nobody']:.0%}"
    )
    if args.json:
        summary = {"config": cfg.model_dump(), "episodes": args.episodes, "seed": args.seed, "policies": figures}
        summary |= {"best_constant": const, "constant_over_scripted": open_loop, "value_of_information": value}
        summary |= {"team_over_scripted": reachable, "who_sees_the_threat": seen}
        write_json(args.json, summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
